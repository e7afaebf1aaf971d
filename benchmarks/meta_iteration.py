"""Seconds per MAML meta-iteration, split into collection and learning, against the learning step's arithmetic floor.

    python benchmarks/meta_iteration.py --preset reference           # point_nav 40 tasks x 20 x 100, 2x100, lr 0.5
    python benchmarks/meta_iteration.py --preset paper               # point_nav 50 x 40 x 100, 2x300, lr 0.1
    python benchmarks/meta_iteration.py --preset half_cheetah        # 20 x 40 x 100, 2x300
    python benchmarks/meta_iteration.py --preset reference --task-loop batched loop   # variants, interleaved
    python benchmarks/meta_iteration.py --device auto --threads 16 --hvp-fraction 0.1 --repeats 5

One meta-iteration is the MAML recipe's (oracle tasks, Gauss-Newton KL Hessian-vector products through the inner
step), built here from umrl's pieces: pre-update collection with θ and advantages, the inner adaptation (with the
graph the meta-step reuses), post-update collection with every task's adapted parameters ("collect" = both
collections and advantages), then the TRPO meta-step ("learn" = inner adaptation + TRPO step).

The **arithmetic floor** is the learning step's matmul FLOPs (``torch.utils.flop_counter.FlopCounterMode`` over one
untimed warm-up step) divided by the device's matmul rate, measured in the same run (one large ``torch.mm`` at the
configured thread count before every round of iterations, median); ``learn / floor`` is how far the step is from that
bound. Each ``--task-loop`` variant (``batched``: one batched matmul per layer for all tasks; ``loop``: a Python loop
over tasks; ``vmap``) gets its own policy from the same seed, so all variants do the same work; their iterations are
interleaved and the medians of ``--repeats`` runs are printed with same-run ratios. ``--metrics`` prints every
iteration's TRPO numbers in full precision (same seed, same numbers: compare before/after a change).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import statistics

import torch
from torch.utils.flop_counter import FlopCounterMode

from umrl.envs import get_task_family, make_task_env
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.maml import MAMLLoss
from umrl.objectives.policy_gradient import compute_advantages
from umrl.optim.trpo import TRPOStep
from umrl.profiling import device_clock, matmul_rate
from umrl.rollout import collect
from umrl.runtime import seed_everything
from umrl.validation import resolve_device

_KEYS = ("env", "tasks", "trajectories", "horizon", "hidden", "inner_lr")
PRESETS = {name: dict(zip(_KEYS, values)) for name, values in {
    "reference": ("point_nav", 40, 20, 100, (100, 100), 0.5),
    "paper": ("point_nav", 50, 40, 100, (300, 300), 0.1),
    "half_cheetah": ("half_cheetah", 20, 40, 100, (300, 300), 0.1),
}.items()}
TASK_LOOP = {"batched": None, "loop": True, "vmap": False}


class Variant:
    """One policy/loss/TRPO triple and its meta-iterations (the recipe's, oracle proposal)."""

    def __init__(self, args, device: torch.device, task_loop: bool | None):
        self.args, self.device = args, device
        self.generator = seed_everything(args.seed)  # same init, tasks and data for every variant
        self.family = get_task_family(args.env)
        n = args.trajectories
        tasks = self.family.sample(args.tasks, torch.Generator().manual_seed(args.seed))
        self.env = make_task_env(args.env, tasks.repeat_interleave(n, 0).to(device), seed=args.seed, horizon=args.horizon,
                                 device=device)
        obs_dim, act_dim = self.env.observation_spec["observation"].shape[-1], self.env.action_spec.shape[-1]
        self.policy = make_gaussian_policy(obs_dim, act_dim, hidden=args.hidden).to(device)
        self.loss = MAMLLoss(self.policy, inner_lr=args.inner_lr, task_loop=task_loop)
        self.trpo = TRPOStep(self.loss.params)
        self.rng_state = torch.get_rng_state()

    def _collect(self, params=None):
        td = collect(self.env, self.policy, num_tasks=self.args.tasks, horizon=self.args.horizon, params=params)
        return compute_advantages(td)

    def iteration(self, flops: FlopCounterMode | None = None) -> dict[str, float]:
        """One meta-iteration; with ``flops`` the learning step runs under that counter."""
        torch.set_rng_state(self.rng_state)  # variants share the global RNG: each continues its own stream
        tasks = self.family.sample(self.args.tasks, self.generator)
        self.env.transform[-1].set_tasks(tasks.repeat_interleave(self.args.trajectories, 0).to(self.device))
        start = device_clock(self.device)
        support = self._collect()
        inner_start = device_clock(self.device)
        with torch.enable_grad(), flops or contextlib.nullcontext():
            adapted = self.loss.adapt(support)
        inner_s = device_clock(self.device) - inner_start
        query = self._collect(adapted.detach())
        collected = device_clock(self.device)
        with flops or contextlib.nullcontext():
            info = self.step(support, query, adapted)
        learned = device_clock(self.device)
        self.rng_state = torch.get_rng_state()
        return {**info, "collect_s": collected - start - inner_s, "learn_s": learned - collected + inner_s}

    def step(self, support, query, adapted) -> dict[str, float]:
        """The TRPO meta-step through the inner step (the recipe's default ``trpo.hvp=gauss_newton``)."""
        loss, fraction, generator = self.loss, self.args.hvp_fraction, self.generator
        with torch.enable_grad():
            initial = loss.objective_and_kl(support, query, phi=adapted)
        return self.trpo(lambda: loss.objective_and_kl(support, query), initial=initial,
                         hvp=lambda: loss.gauss_newton_hvp(support, query, fraction=fraction, generator=generator))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--tasks", type=int, help="override the preset's meta-batch")
    parser.add_argument("--trajectories", type=int, help="override the preset's trajectories per task")
    parser.add_argument("--hvp-fraction", type=float, default=1.0)
    parser.add_argument("--task-loop", nargs="+", default=["batched"], choices=sorted(TASK_LOOP))
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--metrics", action="store_true", help="print each iteration's TRPO numbers in full")
    args = parser.parse_args()
    for key, value in PRESETS[args.preset].items():
        if getattr(args, key, None) is None:
            setattr(args, key, value)
    device = torch.device(resolve_device("--device", args.device))
    torch.set_num_threads(args.threads)

    variants = {name: Variant(args, device, TASK_LOOP[name]) for name in args.task_loop}
    flops = {}
    for name, variant in variants.items():  # warm-up iteration, FLOPs counted (not timed)
        counter = FlopCounterMode(display=False)
        info = variant.iteration(counter)
        flops[name] = counter.get_total_flops()
        if args.metrics:
            print(f"  {name} warm-up: {json.dumps(info)}", flush=True)
    rows = {name: {"collect_s": [], "learn_s": []} for name in variants}
    rates = []
    for _ in range(args.repeats):
        size = 4096 if device.type == "cuda" else 2048
        rates.append(matmul_rate(device, size, size, size))
        for name, variant in variants.items():
            info = variant.iteration()
            rows[name]["collect_s"].append(info["collect_s"])
            rows[name]["learn_s"].append(info["learn_s"])
            print(f"  run {name}: collect {info['collect_s']:.2f}s  learn {info['learn_s']:.2f}s  "
                  f"(backtracks {info['backtracks']:.0f}, kl {info['kl']:.5f})", flush=True)
            if args.metrics:
                print(f"    {json.dumps(info)}", flush=True)
    rate = statistics.median(rates)
    steps = 2 * args.tasks * args.trajectories * args.horizon
    print(f"\n{args.preset}: {args.env} {args.tasks} tasks x {args.trajectories} traj x {args.horizon} steps "
          f"({steps} env steps pre + post), hidden {list(args.hidden)}, inner lr {args.inner_lr}, hvp_fraction "
          f"{args.hvp_fraction}, {device}, {args.threads} thread(s), median of {args.repeats}; matmul rate "
          f"{rate / 1e9:,.1f} GFLOP/s")
    first = None
    for name, row in rows.items():
        collect_s, learn_s = statistics.median(row["collect_s"]), statistics.median(row["learn_s"])
        floor = flops[name] / rate
        first = first or learn_s
        print(f"  {name:8s} collect {collect_s:7.2f} s  learn {learn_s:7.2f} s  learn/collect {learn_s / collect_s:5.2f}"
              f"  floor {floor:6.2f} s ({flops[name] / 1e9:,.0f} GFLOP)  learn/floor {learn_s / floor:5.2f}"
              f"  learn vs {args.task_loop[0]} {learn_s / first:5.2f}x")


if __name__ == "__main__":
    main()
