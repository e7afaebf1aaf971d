"""Seconds per MAML meta-iteration, split into collection and learning, against pure env stepping.

    python benchmarks/meta_iteration.py                          # point_nav, paper settings (50 tasks x 40 x 100)
    python benchmarks/meta_iteration.py --env half_cheetah       # 20 tasks x 40 x 100
    python benchmarks/meta_iteration.py --hvp-fraction 0.1 --repeats 3
    python benchmarks/meta_iteration.py --override maml.task_loop=true   # any recipes/config/maml.yaml key

One meta-iteration is exactly the recipe's (``recipes/maml.py: meta_iteration``, oracle proposal): pre-update and
post-update collection with per-task parameters, advantages included ("collect"); the inner adaptation that gives
the post-update parameters plus the TRPO meta-step with KL Hessian-vector products through the inner step ("learn",
with the inner step also shown alone). "env only" steps the same env for the same number of
steps (2 × T × N × H) with random actions and no policy, in the same process, interleaved with the iterations.
Prints the median of ``--repeats`` runs of each; on a shared machine compare ratios measured in the same run.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "recipes"))
from maml import build, meta_iteration

from umrl.runtime import seed_everything

DEFAULT_TASKS = {"point_nav": 50, "half_cheetah": 20, "ant": 20}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="point_nav", choices=sorted(DEFAULT_TASKS))
    parser.add_argument("--tasks", type=int, default=None, help="meta-batch (default: PROTOCOL.md's 50/20/20)")
    parser.add_argument("--trajectories", type=int, default=40)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--hvp-fraction", type=float, default=1.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--override", action="append", default=[], help="extra maml.yaml override, repeatable")
    args = parser.parse_args()
    tasks = args.tasks or DEFAULT_TASKS[args.env]
    overrides = [f"env.name={args.env}", f"meta_batch_size={tasks}", f"trajectories_per_task={args.trajectories}",
                 f"env.horizon={args.horizon}", f"trpo.hvp_fraction={args.hvp_fraction}", "proposal=oracle",
                 f"num_threads={args.threads}", "logger.backend=none", *args.override]
    with initialize_config_dir(config_dir=str(REPO / "recipes" / "config"), version_base="1.3"):
        cfg = compose("maml", overrides=overrides)
    torch.set_num_threads(args.threads)
    generator = seed_everything(cfg.seed)  # same policy init and data in every run: variants do the same work
    proposal, policy, loss, trpo = build(cfg)
    env = proposal.env
    steps = 2 * env.batch_size.numel() * args.horizon
    rows = {"env_only_s": [], "collect_s": [], "learn_s": [], "inner_s": []}
    for _ in range(args.repeats):
        start = time.perf_counter()
        with torch.no_grad():
            for _ in range(2):
                env.rollout(args.horizon, break_when_any_done=False)
        rows["env_only_s"].append(time.perf_counter() - start)
        metrics = meta_iteration(cfg, proposal, policy, loss, trpo, generator)
        rows["collect_s"].append(metrics["time/collect_s"])
        rows["learn_s"].append(metrics["time/learn_s"])
        rows["inner_s"].append(metrics["time/inner_s"])
        print(f"  run: env only {rows['env_only_s'][-1]:.2f}s  collect {metrics['time/collect_s']:.2f}s  "
              f"learn {metrics['time/learn_s']:.2f}s  (backtracks {metrics['train/backtracks']:.0f}, "
              f"kl {metrics['train/kl']:.4f})", flush=True)
    med = {k: statistics.median(v) for k, v in rows.items()}
    print(f"\n{args.env}: {tasks} tasks x {args.trajectories} traj x {args.horizon} steps = {steps} env steps "
          f"(pre + post), hvp_fraction {args.hvp_fraction}, {args.threads} thread(s), median of {args.repeats}")
    print(f"  env only   {med['env_only_s']:8.2f} s   ({steps / med['env_only_s']:,.0f} steps/s)")
    print(f"  collect    {med['collect_s']:8.2f} s   ({steps / med['collect_s']:,.0f} steps/s, "
          f"{med['collect_s'] / med['env_only_s']:.2f}x env only)")
    print(f"  learn      {med['learn_s']:8.2f} s   ({med['learn_s'] / med['collect_s']:.2f}x collect; inner step "
          f"{med['inner_s']:.2f} s)")
    print(f"  total      {med['collect_s'] + med['learn_s']:8.2f} s per meta-iteration")


if __name__ == "__main__":
    main()
