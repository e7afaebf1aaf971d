#!/usr/bin/env bash
# Several MAML runs at once on the device machine, each pinned to CORES cores; SIGTERM after RUN_S seconds (each run
# saves after its iteration in flight), SIGKILL HARD_S seconds later; run folders (checkpoints, csv) and logs are
# tarred to $OUT/runs.tgz, the machine to $OUT/machine.txt.
# Usage, from the project root:
#   ENV=point_nav RUNS="oracle:0 oracle:1" ITERATIONS=100 EVERY=10 CORES=5 RUN_S=480 DEVICE=cuda \
#     EXTRA="cudagraphs=true" bash scripts/device/maml_runs_at_once.sh
# RUNS: proposal:seed pairs (proposal as recipes/maml.py takes it); a run's folder is <name>_seed<seed>, with name
# oracle or uml_<proposal>.
set -u
ENV=${ENV:?}; RUNS=${RUNS:?}; ITERATIONS=${ITERATIONS:?}; EVERY=${EVERY:-10}; CORES=${CORES:-3}
DEVICE=${DEVICE:-cuda}; RUN_S=${RUN_S:-380}; HARD_S=${HARD_S:-100}; EXTRA=${EXTRA:-}
OUT=${OUT:-/tmp/maml_out}; mkdir -p "$OUT"; W=${W:-/tmp/maml_runs}; mkdir -p "$W"
export PYTHONUNBUFFERED=1 WANDB_MODE=disabled
{ date -u; nproc; lscpu | grep "Model name"; nvidia-smi --query-gpu=name,memory.total --format=csv 2>/dev/null; git log -1 --format=%H 2>/dev/null; python3 -c "import torch,torchrl,mujoco; print(torch.__version__, torchrl.__version__, mujoco.__version__)"; } > "$OUT/machine.txt" 2>&1
cat "$OUT/machine.txt"
i=0; pids=()
for run in $RUNS; do
  p=${run%%:*}; s=${run##*:}; name=$([ "$p" = oracle ] && echo oracle || echo "uml_$p")
  pin=""; [ "$(nproc)" -ge $((CORES * (i + 1))) ] && pin="taskset -c $((CORES * i))-$((CORES * i + CORES - 1))"
  $pin python3 recipes/maml.py env.name=$ENV proposal=$p seed=$s iterations=$ITERATIONS device=$DEVICE \
    num_threads=1 trpo.hvp=analytic checkpoint.every=$EVERY logger.backend=csv progress=false \
    output_dir=$W/${name}_seed$s $EXTRA > "$W/${name}_seed$s.log" 2>&1 &
  pids+=($!); i=$((i + 1))
done
alive_any() { for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && return 0; done; return 1; }
t0=$(date +%s)
while [ $(( $(date +%s) - t0 )) -lt "$RUN_S" ] && alive_any; do sleep 5; done
echo "SIGTERM at $(( $(date +%s) - t0 )) s"; for p in "${pids[@]}"; do kill -TERM "$p" 2>/dev/null; done
t1=$(date +%s)
while [ $(( $(date +%s) - t1 )) -lt "$HARD_S" ] && alive_any; do sleep 2; done
echo "all stopped $(( $(date +%s) - t0 )) s after the start"; for p in "${pids[@]}"; do kill -KILL "$p" 2>/dev/null; done
nvidia-smi 2>/dev/null | head -20 >> "$OUT/machine.txt"
for f in "$W"/*.log; do echo "== $f"; tail -3 "$f"; done
(cd "$W" && find . -name "*.safetensors" | sort; rm -rf -- */hydra */run.lock)
tar -czf "$OUT/runs.tgz" -C "$W" .
ls -la "$OUT"
