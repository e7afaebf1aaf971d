#!/usr/bin/env bash
# Five ant MAML runs at once on the device machine (oracle seeds 1 2, UML-random seeds 0 1 2), 3 cores each,
# learning on DEVICE; SIGTERM after RUN_S seconds (each run saves after its iteration in flight); results to $OUT.
# Usage: DEVICE=cuda RUN_S=380 EXTRA="" bash docs/measurements/2026-12-04-h200/ant_maml_five_runs.sh
set -u
DEVICE=${DEVICE:-cuda}; RUN_S=${RUN_S:-380}; HARD_S=${HARD_S:-100}; EXTRA=${EXTRA:-}
OUT=${OUT:-/tmp/ant_out}; mkdir -p "$OUT"; W=${W:-/tmp/ant_runs}; mkdir -p "$W"
export PYTHONUNBUFFERED=1 WANDB_MODE=disabled
{ date -u; nproc; lscpu | grep "Model name"; nvidia-smi --query-gpu=name,memory.total --format=csv 2>/dev/null; git log -1 --format=%H 2>/dev/null; python3 -c "import torch,torchrl,mujoco; print(torch.__version__, torchrl.__version__, mujoco.__version__)"; } > "$OUT/machine.txt" 2>&1
cat "$OUT/machine.txt"
i=0; pids=()
for run in "oracle 1" "oracle 2" "random 0" "random 1" "random 2"; do
  set -- $run; p=$1; s=$2; name=$([ $p = oracle ] && echo oracle || echo uml_random)
  cores="$((3*i))-$((3*i+2))"
  pin=""; [ $(nproc) -ge 15 ] && pin="taskset -c $cores"
  $pin python3 recipes/maml.py env.name=ant proposal=$p seed=$s iterations=300 device=$DEVICE \
    num_threads=1 trpo.hvp=analytic checkpoint.every=25 logger.backend=csv progress=false \
    output_dir=$W/${name}_seed$s $EXTRA > "$W/${name}_seed$s.log" 2>&1 &
  pids+=($!); i=$((i+1))
done
t0=$(date +%s)
while [ $(( $(date +%s) - t0 )) -lt $RUN_S ]; do sleep 5; alive=0; for p in "${pids[@]}"; do kill -0 $p 2>/dev/null && alive=1; done; [ $alive = 0 ] && break; done
echo "SIGTERM at $(( $(date +%s) - t0 )) s"; for p in "${pids[@]}"; do kill -TERM $p 2>/dev/null; done
t1=$(date +%s)
while [ $(( $(date +%s) - t1 )) -lt $HARD_S ]; do sleep 2; alive=0; for p in "${pids[@]}"; do kill -0 $p 2>/dev/null && alive=1; done; [ $alive = 0 ] && break; done
echo "all stopped $(( $(date +%s) - t0 )) s after the start (alive=$alive)"; for p in "${pids[@]}"; do kill -KILL $p 2>/dev/null; done
nvidia-smi 2>/dev/null | head -20 >> "$OUT/machine.txt"
for f in "$W"/*.log; do echo "== $f"; tail -3 "$f"; done
(cd "$W" && find . -name "*.pt" -o -name "*.safetensors" | sort; rm -rf */hydra */run.lock) 
tar -czf "$OUT/ant_runs.tgz" -C "$W" .
ls -la "$OUT"
