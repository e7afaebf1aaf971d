"""Meta-test MAML initialisations with their action noise replaced: how much of a step's effect is the init's σ?

    python scripts/diagnostics/action_noise.py --log-std saved -1.5 -2.0 --steps 5 \
        --run "paper=results/point_nav/uml_diayn_paper/seed{seed}" \
        --run "10 %=results/point_nav/uml_diayn_trained_paper_batch/seed{seed}"

The runs named here left the tree (results/README.md lists them); bring them back first:
``git checkout bbe1d9b -- results/point_nav/uml_diayn_paper results/point_nav/uml_diayn_trained_paper_batch``.

A diagnostic, not a method: every run's policy (a MAML checkpoint, ``{seed}`` filled with each ``--seeds``) is
adapted as the suite's MAML cells are (:func:`umrl.metatest.meta_test`, SGD at the checkpoint's inner lr, the chosen
``--schedule``, the env's first ``--num-tasks`` evaluation tasks, meta-test seed = the run's seed), once with its own
learned log-std (``saved``) and once with every action dimension's log-std set to each given value, the mean network
untouched. The score-function gradient of a Gaussian policy scales like 1/σ², so an init that ends meta-training
with a small σ takes larger steps in action space at the same lr; swapping σ between inits tests whether that, rather
than the mean network, decides where the adapted policy lands.

Printed per run and log-std: the saved log-std (mean over dimensions and seeds), the IQM return over tasks × seeds at
every step ``k = 0 … K``, and the IQM [95 % bootstrap CI] of the AUC over ``k = 0 … K``.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from umrl.checkpoints import load_maml_policy
from umrl.checkpoints.labels import labelled_path
from umrl.envs.tasks import get_task_family
from umrl.metatest import AdaptationConfig, Initialisation, meta_test
from umrl.metatest.protocol import SGD_SCHEDULES
from umrl.metatest.stats import auc, bootstrap_ci, iqm
from umrl.modules import policy_log_std
from umrl.process import tune_process


def adapt(path: str, log_std: float | None, *, env: str, tasks: torch.Tensor, seed: int,
          config: AdaptationConfig) -> tuple[float, np.ndarray]:
    """(saved log-std mean, returns ``[K + 1, T]``) of the MAML init at ``path``, its log-std set to ``log_std``."""
    policy, inner_lr = load_maml_policy(path)
    parameter = policy_log_std(policy)
    saved = parameter.mean().item()
    if log_std is not None:
        with torch.no_grad():
            parameter.fill_(log_std)
    returns, _ = meta_test(Initialisation(policy, "sgd", lr=inner_lr), env, tasks, lr=inner_lr, seed=seed,
                           config=config, skill_trajectories=1)
    return saved, returns.numpy()


def parse_log_std(value: str) -> float | None:
    return None if value == "saved" else float(value)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", required=True, type=labelled_path, metavar="LABEL=PATH",
                        help="a MAML run directory or checkpoint; {seed} is replaced by each seed")
    parser.add_argument("--log-std", nargs="+", type=parse_log_std, default=[None], metavar="saved|VALUE")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--env", default="point_nav")
    parser.add_argument("--steps", type=int, default=5, help="K adaptation steps")
    parser.add_argument("--num-tasks", type=int, default=20)
    parser.add_argument("--trajectories", type=int, default=20, help="per task and step (the quick profile's 20)")
    parser.add_argument("--schedule", choices=SGD_SCHEDULES, default="reference")
    parser.add_argument("--later-factor", type=float, default=0.5,
                        help="the swept schedule's factor of the inner lr after the first step (not swept here)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    tune_process()
    try:
        config = AdaptationConfig(num_steps=args.steps, num_trajectories=args.trajectories,
                                  sgd_schedule=args.schedule, sgd_later_factor=args.later_factor)
    except ValueError as error:
        parser.error(str(error))
    tasks = get_task_family(args.env).eval_tasks(args.num_tasks)
    steps = "".join(f"{f'k={k}':>9}" for k in range(args.steps + 1))
    print(f"{'run':<16}{'log-std':>9}{'saved':>8}{steps}  AUC k <= {args.steps} IQM [95 % CI]", flush=True)
    for label, path in args.run:
        for log_std in args.log_std:
            saved, returns = zip(*(adapt(path.format(seed=seed), log_std, env=args.env, tasks=tasks, seed=seed,
                                         config=config) for seed in args.seeds), strict=True)
            returns = np.concatenate(returns, axis=1)  # [K + 1, T * seeds]
            areas = auc(returns.T)
            low, high = bootstrap_ci(areas, iqm)
            used = "saved" if log_std is None else f"{log_std:.2f}"
            per_step = "".join(f"{value:>9.1f}" for value in iqm(returns, axis=1))
            print(f"{label:<16}{used:>9}{np.mean(saved):>8.2f}{per_step}  {iqm(areas):.1f} [{low:.1f}, {high:.1f}]",
                  flush=True)


if __name__ == "__main__":
    main()
