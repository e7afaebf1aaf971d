"""Scale one meta-test SGD step of MAML initialisations: does a collapse come from the step's size or its direction?

    python benchmarks/step_size.py --step 2 --scales 0 0.125 0.25 0.5 1 \
        --run "full=results/point_nav/uml_diayn_paper/seed{seed}" \
        --run "10 %=results/point_nav/uml_diayn_trained_paper_batch/seed{seed}"

A diagnostic, not a method. Every run's policy (a MAML checkpoint, ``{seed}`` filled with each ``--seeds``) is
adapted as the suite's MAML cells are (:class:`umrl.metatest.protocol.TaskAdapter`: SGD at the checkpoint's inner lr
``α``, the reference schedule, the env's first ``--num-tasks`` evaluation tasks, meta-test seed = the run's seed) up
to the update ``--step`` (1: the first update, from the init; 2: the second, after a reference first step). That
update's gradient ``g`` is then taken at ``c · α`` for every ``c`` of ``--scales`` (the reference schedule takes
``c = 1`` at step 1 and ``c = 0.5`` later), and each result is rolled out with the same random numbers.

If the return falls only for large ``c`` and rises for small ones, the step overshoots (its size is wrong); if it
falls at every ``c > 0``, the direction is.

Printed per run and scale: IQM return over tasks × seeds after the scaled step, the RMS change of the action mean
``|Δμ|`` on the states of the batch the step was computed from (the step's size in action space), and the share of
those states whose new action mean lies outside the action bounds [-1, 1] (where a larger mean moves no faster).
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from umrl.checkpoints import load_maml_policy
from umrl.checkpoints.labels import labelled_path
from umrl.envs.tasks import get_task_family
from umrl.heap import keep_freed_memory
from umrl.metatest import AdaptationConfig
from umrl.metatest.protocol import TaskAdapter, make_eval_env
from umrl.metatest.stats import iqm
from umrl.objectives.policy_gradient import episode_returns
from umrl.runtime import seed_everything


def scaled_step(path: str, *, step: int, scales: list[float], env_name: str, tasks: torch.Tensor, seed: int,
                config: AdaptationConfig) -> dict[str, np.ndarray]:
    """Returns ``[S, T]``, RMS ``|Δμ|`` ``[S]`` and out-of-bounds share ``[S]`` of update ``step`` scaled by each
    of the ``S`` scales, for the init at ``path``."""
    policy, inner_lr = load_maml_policy(path)
    seed_everything(seed)
    env = make_eval_env(env_name, tasks, config.num_trajectories, seed=seed, horizon=config.horizon)
    adapter = TaskAdapter(policy, env, tasks.shape[0], optimizer="sgd", lr=inner_lr, config=config)
    for _ in range(step - 1):
        adapter.step(adapter.collect())
    batch = adapter.collect()
    before = adapter.params.detach().clone()
    adapter.step(batch)  # leaves the update's gradient in each leaf's .grad
    leaves = adapter.optimizer.param_groups[0]["params"]  # the per-task parameters the update moved
    gradients = [p.grad.clone() for p in leaves]
    mask = batch["mask"]
    loc_before = adapter.functional.dist_params(before, batch)["loc"][mask]
    rng_state = torch.get_rng_state()
    out = {"returns": [], "rms_shift": [], "out_of_bounds": []}
    for scale in scales:
        with torch.no_grad():
            adapter.params.update_(before)
            for p, g in zip(leaves, gradients, strict=True):
                p.sub_(scale * inner_lr * g)
            loc = adapter.functional.dist_params(adapter.params, batch)["loc"][mask]
        torch.set_rng_state(rng_state)  # every scale rolls out with the same random numbers
        out["returns"].append(episode_returns(adapter.collect()).mean(-1).numpy())
        out["rms_shift"].append((loc - loc_before).square().sum(-1).mean().sqrt().item())
        out["out_of_bounds"].append((loc.abs() > 1).any(-1).float().mean().item())
    env.close()
    return {key: np.asarray(value) for key, value in out.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", required=True, type=labelled_path, metavar="LABEL=PATH",
                        help="a MAML run directory or checkpoint; {seed} is replaced by each seed")
    parser.add_argument("--step", type=int, choices=(1, 2, 3), default=2, help="the update to scale (1 = first)")
    parser.add_argument("--scales", nargs="+", type=float, default=[0.0, 0.125, 0.25, 0.5, 1.0],
                        metavar="C", help="multiples of the inner lr α to take the update at")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--env", default="point_nav")
    parser.add_argument("--num-tasks", type=int, default=20)
    parser.add_argument("--trajectories", type=int, default=20, help="per task and step (the quick profile's 20)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    if any(scale < 0 for scale in args.scales):
        parser.error(f"--scales: got {args.scales}; expected values >= 0")
    torch.set_num_threads(args.threads)
    keep_freed_memory()
    config = AdaptationConfig(num_steps=args.step, num_trajectories=args.trajectories, sgd_schedule="reference")
    tasks = get_task_family(args.env).eval_tasks(args.num_tasks)
    print(f"update {args.step} taken at c × α; IQM return over tasks × seeds after it, RMS |Δμ| on the batch's "
          "states, share of new means outside [-1, 1]", flush=True)
    print(f"{'run':<16}{'seed':>5}" + "".join(f"{f'c={c:g}':>24}" for c in args.scales), flush=True)
    for label, path in args.run:
        results = [scaled_step(path.format(seed=seed), step=args.step, scales=args.scales, env_name=args.env,
                               tasks=tasks, seed=seed, config=config) for seed in args.seeds]
        rows = [(str(seed), [r]) for seed, r in zip(args.seeds, results, strict=True)] + [("all", results)]
        for seed, group in rows:
            returns = iqm(np.concatenate([r["returns"] for r in group], axis=1), axis=1)
            shift = np.mean([r["rms_shift"] for r in group], axis=0)
            bounds = np.mean([r["out_of_bounds"] for r in group], axis=0)
            cells = "".join(f"{f'{g:.1f} | {s:.2f} | {b:.2f}':>24}" for g, s, b in zip(returns, shift, bounds,
                                                                                          strict=True))
            print(f"{label:<16}{seed:>5}{cells}", flush=True)


if __name__ == "__main__":
    main()
