"""Seconds per MAML meta-iteration, split into collection and learning, against the learning step's arithmetic floor.

    python benchmarks/meta_iteration.py --preset reference           # point_nav 40 tasks x 20 x 100, 2x100, lr 0.5
    python benchmarks/meta_iteration.py --preset paper               # point_nav 50 x 40 x 100, 2x300, lr 0.1
    python benchmarks/meta_iteration.py --preset half_cheetah        # 20 x 40 x 100, 2x300
    python benchmarks/meta_iteration.py --preset reference --task-loop batched loop   # variants, interleaved
    python benchmarks/meta_iteration.py --preset reference --hvp gauss_newton analytic  # autograd vs hand-derived HVP
    python benchmarks/meta_iteration.py --device auto --threads 16 --hvp-fraction 0.1 --repeats 5
    python benchmarks/meta_iteration.py --device cuda --collection eager cudagraphs   # collection replayed from a CUDA graph

One meta-iteration is the MAML recipe's own: ``step()`` of a :class:`umrl.trainers.MAMLTrainer` on the
composed ``umrl/configs/maml.yaml`` with the preset's overrides, oracle tasks (its checkpoint 0 goes to a
temporary folder, removed at the end): pre-update collection with θ and advantages, the inner adaptation (with
the graph the meta-step reuses), post-update collection with every task's adapted parameters ("collect" = both
collections and advantages), then the TRPO meta-step ("learn" = inner adaptation + TRPO step). A second line
splits "learn" into the recipe's ``time/`` parts: the inner adaptation, the surrogate and KL through it, the
search direction (the gradient with the Hessian-vector product set-up, and the conjugate-gradient products)
and the line search, with the median number of trials.

The **arithmetic floor** is the learning step's matmul FLOPs (a ``umrl.profiling.flop_counter`` over each of
its parts in one untimed warm-up step, entered and left by the trainer's ``pre_phase`` / ``post_phase`` hooks
around ``inner_step`` and ``meta_step``) divided by the device's matmul rate, measured in the same run (one
large ``torch.mm`` at the configured thread count before every round of iterations, median); ``learn / floor``
is how far the step is from that bound. Each ``--task-loop`` variant (``batched``: one batched matmul per
layer for all tasks; ``loop``: a Python loop over tasks; ``vmap``), ``--collection`` variant (``eager``:
TorchRL's ``env.rollout``; ``cudagraphs``: the recipe's ``cudagraphs=true``, each rollout replayed from a CUDA
graph, point_nav on CUDA only) and ``--hvp`` variant (the recipe's ``trpo.hvp``: ``gauss_newton`` by autograd,
``analytic`` the same product by hand, with ``batched`` only) gets its own policy from the same seed, so all
variants do the same work; their iterations are interleaved and the medians of ``--repeats`` runs are printed
with same-run ratios. ``--metrics`` prints every iteration's TRPO numbers in full precision (same seed, same
numbers: compare before/after a change). ``--heap release`` runs with glibc's default malloc instead of
keeping freed memory (``umrl.heap``); the header line prints the process's peak resident memory for the
comparison.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import tempfile

import torch
from torch.utils.flop_counter import FlopCounterMode

from umrl.configs.maml import HVP_MODES
from umrl.process import tune_process
from umrl.profiling import flop_counter, matmul_rate
from umrl.rng import rng_state, set_rng_state
from umrl.trainers import MAMLTrainer, compose

PRESETS = {  # recipe overrides (env.horizon stays the recipe's 100)
    "reference": ["env.name=point_nav", "meta_batch_size=40", "trajectories_per_task=20", "policy.hidden=[100,100]",
                  "maml.inner_lr=0.5"],
    "paper": ["env.name=point_nav", "meta_batch_size=50", "trajectories_per_task=40", "policy.hidden=[300,300]",
              "maml.inner_lr=0.1"],
    "half_cheetah": ["env.name=half_cheetah", "meta_batch_size=20", "trajectories_per_task=40",
                     "policy.hidden=[300,300]", "maml.inner_lr=0.1"],
}
TASK_LOOP = {"batched": "null", "loop": "true", "vmap": "false"}
LEARNING_PHASES = ("inner_step", "meta_step")
"""The parts of ``MAMLTrainer.step`` that make its learning step (the query collection runs between them)."""


class Variant:
    """The recipe's trainer for one variant (``overrides`` name its ``output_dir``) and its meta-iterations;
    variants share the global RNGs, so each keeps (and restores) its own streams."""

    def __init__(self, overrides: list[str]):
        self.trainer = MAMLTrainer(compose("maml", overrides))  # seeded as the recipe: same init, tasks, data
        self.cfg, self.proposal = self.trainer.cfg, self.trainer.proposal
        self.rng = rng_state()
        self.counters: list[FlopCounterMode] | None = None
        self.trainer.register_op("pre_phase", self._count_flops)
        self.trainer.register_op("post_phase", self._stop_counting)

    def _count_flops(self, trainer: MAMLTrainer, phase: str) -> None:
        if self.counters is not None and phase in LEARNING_PHASES:
            self.counters.append(flop_counter())  # one per part: a counter entered twice forgets the first
            self.counters[-1].__enter__()

    def _stop_counting(self, trainer: MAMLTrainer, phase: str) -> None:
        if self.counters is not None and phase in LEARNING_PHASES:
            self.counters[-1].__exit__(None, None, None)

    def iteration(self, counters: list[FlopCounterMode] | None = None) -> dict[str, float]:
        """One meta-iteration; with ``counters`` each part of the learning step runs under a new FLOP counter
        appended to it (their sum is the step's FLOPs)."""
        set_rng_state(self.rng)
        self.counters = counters
        try:
            metrics = self.trainer.step()
        finally:
            self.counters = None
        self.rng = rng_state()
        return metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--tasks", type=int, help="override the preset's meta-batch")
    parser.add_argument("--trajectories", type=int, help="override the preset's trajectories per task")
    parser.add_argument("--hvp-fraction", type=float, default=1.0)
    parser.add_argument("--task-loop", nargs="+", default=["batched"], choices=sorted(TASK_LOOP))
    parser.add_argument("--collection", nargs="+", default=["eager"], choices=["eager", "cudagraphs"])
    parser.add_argument("--hvp", nargs="+", default=["gauss_newton"], choices=HVP_MODES)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--metrics", action="store_true", help="print each iteration's TRPO numbers in full")
    parser.add_argument("--heap", default="keep", choices=["keep", "release"],
                        help="keep: freed memory stays in the process for reuse, as the recipes run "
                             "(umrl.heap.keep_freed_memory, via umrl.process.tune_process); release: glibc's default")
    args = parser.parse_args()
    overrides = [*PRESETS[args.preset], "proposal=oracle", "logger.backend=none", f"seed={args.seed}",
                 f"device={args.device}", f"num_threads={args.threads}", f"trpo.hvp_fraction={args.hvp_fraction}"]
    overrides += [f"meta_batch_size={args.tasks}"] * (args.tasks is not None)
    overrides += [f"trajectories_per_task={args.trajectories}"] * (args.trajectories is not None)
    torch.set_num_threads(args.threads)
    heap = "kept" if tune_process(keep_freed_memory=args.heap == "keep")["kept_freed_memory"] else "glibc default"

    scratch = tempfile.TemporaryDirectory(prefix="meta_iteration_")  # the trainers' checkpoint 0
    variants = {
        "/".join([loop] + [part for part, options in ((collection, args.collection), (hvp, args.hvp))
                           if len(options) > 1]):
            Variant([*overrides, f"maml.task_loop={TASK_LOOP[loop]}", f"cudagraphs={collection == 'cudagraphs'}",
                     f"trpo.hvp={hvp}", f"output_dir={scratch.name}/{loop}_{collection}_{hvp}"])
        for loop in args.task_loop for collection in args.collection for hvp in args.hvp
        if hvp != "analytic" or loop == "batched"  # the hand-derived product needs the task-batched MLP
    }
    cfg = next(iter(variants.values())).cfg
    device = torch.device(cfg.device)
    flops = {}
    for name, variant in variants.items():  # warm-up iteration, FLOPs of the learning step counted (not timed)
        counters = []
        info = variant.iteration(counters)
        flops[name] = sum(c.get_total_flops() for c in counters)
        if args.metrics:
            print(f"  {name} warm-up: {json.dumps(info)}", flush=True)
    phases = ("inner_s", "objective_s", "direction_s", "cg_s", "line_search_s")
    rows = {name: {k: [] for k in ("collect_s", "learn_s", *phases, "backtracks")} for name in variants}
    rates = []
    for _ in range(args.repeats):
        size = 4096 if device.type == "cuda" else 2048
        rates.append(matmul_rate(device, size, size, size))
        for name, variant in variants.items():
            info = variant.iteration()
            for key in ("collect_s", "learn_s", *phases):
                rows[name][key].append(info[f"time/{key}"])
            rows[name]["backtracks"].append(info["train/backtracks"])
            print(f"  run {name}: collect {info['time/collect_s']:.2f}s  learn {info['time/learn_s']:.2f}s  "
                  f"(backtracks {info['train/backtracks']:.0f}, kl {info['train/kl']:.5f})", flush=True)
            if args.metrics:
                print(f"    {json.dumps(info)}", flush=True)
    rate = statistics.median(rates)
    proposal = next(iter(variants.values())).proposal
    steps = 2 * proposal.num_tasks * proposal.trajectories_per_task * cfg.env.horizon
    print(f"\n{args.preset}: {cfg.env.name} {proposal.num_tasks} tasks x {proposal.trajectories_per_task} traj x "
          f"{cfg.env.horizon} steps ({steps} env steps pre + post), hidden {list(cfg.policy.hidden)}, inner lr "
          f"{cfg.maml.inner_lr}, hvp_fraction {cfg.trpo.hvp_fraction}, {device}, {args.threads} thread(s), median of "
          f"{args.repeats}; matmul rate {rate / 1e9:,.1f} GFLOP/s; heap {heap}, peak RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
    first = None
    for name, row in rows.items():
        collect_s, learn_s = statistics.median(row["collect_s"]), statistics.median(row["learn_s"])
        floor = flops[name] / rate
        first = first or (name, collect_s, learn_s)
        hvp = variants[name].cfg.trpo.hvp
        print(f"  {name:8s} collect {collect_s:7.2f} s  learn {learn_s:7.2f} s  learn/collect {learn_s / collect_s:5.2f}"
              f"  floor {floor:6.2f} s ({flops[name] / 1e9:,.0f} GFLOP)  learn/floor {learn_s / floor:5.2f}"
              f"  vs {first[0]}: collect {collect_s / first[1]:5.2f}x, learn {learn_s / first[2]:5.2f}x")
        inner, objective, direction, cg, search, trials = (statistics.median(row[k]) for k in (*phases, "backtracks"))
        print(f"  {'':8s} learn = inner {inner:.2f} s + objective {objective:.2f} s + direction {direction:.2f} s "
              f"(gradient and HVP set-up {direction - cg:.2f} s, {cfg.trpo.cg_iters} CG products {cg:.2f} s, "
              f"{hvp} HVP) + line search {search:.2f} s "
              f"({trials:.0f} trials)")
    for variant in variants.values():
        variant.trainer.close()
    scratch.cleanup()


if __name__ == "__main__":
    main()
