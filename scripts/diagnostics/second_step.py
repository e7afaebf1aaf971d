"""Meta-test a MAML initialisation at k = 0 … K under each SGD schedule and each way of sampling a batch, to tell
whether a poor second step comes from the update itself or from the batch it is computed on.

    python scripts/diagnostics/second_step.py --run outputs/maml/point_nav/oracle/seed1 --steps 3 \
        --schedules constant reference --env-steps none 4000

A diagnostic, not a method. The update is the MAML reference code's test-time VPG step (``tests/
test_reference_update.py`` checks it against a transcription of cbfinn/maml_rl's ``vpg.py``, ``process_samples``
and ``LinearFeatureBaseline`` on one recorded batch). What the reference does differently is how many episodes a
batch holds: ``test_maml_point.py`` samples ``batch_size=4000`` env steps per goal, so where point_nav episodes end
early at the goal (which an adapted policy does) the batch holds more of them than 40. ``--env-steps none`` is the
protocol (``--trajectories`` per task and step); ``--env-steps S`` is the reference's sampler
(``protocol.env_steps``, :func:`umrl.rollout.collect_env_steps`).

Every (schedule, sampling) pair adapts the init at ``--run`` (a MAML run directory or checkpoint) on the env's first
``--num-tasks`` evaluation tasks, SGD at the checkpoint's inner lr ``α``, with the same meta-test seed. Printed, one
markdown row per pair and ``k``: the mean return over tasks and its standard error, the worst task's return, the
share of tasks below ``--collapse`` (default -50), the mean number of episodes per task's batch and their mean
length, and the mean log-std the batch was collected with (what the adaptation made of the init's). ``--log-std`` replaces the init's learned log-std (a diagnostic of the action noise's part, as
``scripts/diagnostics/action_noise.py``).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from umrl.checkpoints import load_maml_policy
from umrl.envs.tasks import get_task_family
from umrl.metatest import AdaptationConfig
from umrl.metatest.protocol import SGD_SCHEDULES, TaskAdapter, make_eval_env
from umrl.modules import policy_log_std
from umrl.modules.policy import std_is_fixed
from umrl.objectives.policy_gradient import episode_lengths, episode_mean
from umrl.rng import seed_everything

HEADER = ("| schedule | batch | k | mean return ± s.e. | worst task | tasks < {collapse:g} | episodes per batch "
          "| episode length | log σ |\n|---|---|---|---|---|---|---|---|---|")


def adapt(path: str, *, env_name: str, tasks: torch.Tensor, seed: int, config: AdaptationConfig,
          log_std: float | None = None) -> dict:
    """Adapt the init at ``path`` as the suite's MAML cells do (its log-std set to ``log_std`` unless None);
    returns ``returns`` ``[K + 1, T]``, ``episodes``, ``lengths`` and ``log_std`` ``[K + 1, T]`` (episodes in each
    task's batch, their mean length, the policy's log-std that collected it, averaged over action dims)."""
    policy, inner_lr = load_maml_policy(path)
    if log_std is not None:
        with torch.no_grad():
            policy_log_std(policy).fill_(log_std)
    seed_everything(seed)
    env = make_eval_env(env_name, tasks, config.num_trajectories, seed=seed, horizon=config.horizon)
    adapter = TaskAdapter(policy, env, tasks.shape[0], optimizer="sgd", lr=inner_lr, config=config)
    episodes, lengths, log_std = [], [], []

    def record(step: int, batch) -> None:
        episodes.append(batch["mask"].any(-1).sum(-1))
        lengths.append(episode_mean(episode_lengths(batch).float(), batch))
        log_std.append(batch["scale"][:, 0, 0].log().mean(-1))  # state-independent: any step's

    returns = adapter.run(record)
    env.close()
    return {"returns": returns.numpy(), "episodes": torch.stack(episodes).numpy(),
            "lengths": torch.stack(lengths).numpy(), "log_std": torch.stack(log_std).numpy()}


def rows(schedule: str, sampling: str, result: dict, collapse: float) -> list[str]:
    """The markdown rows of one (schedule, sampling) pair, one per ``k``."""
    out = []
    for k, returns in enumerate(result["returns"]):
        se = returns.std(ddof=1) / np.sqrt(len(returns))
        out.append(f"| {schedule} | {sampling} | {k} | {returns.mean():.1f} ± {se:.1f} | {returns.min():.1f} | "
                   f"{(returns < collapse).mean():.0%} | {result['episodes'][k].mean():.1f} | "
                   f"{result['lengths'][k].mean():.1f} | {result['log_std'][k].mean():.2f} |")
    return out


def env_steps_arg(text: str) -> int | None:
    if text.lower() in ("none", "null"):
        return None
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"got {text}; expected none or an integer >= 1")
    return value


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", required=True, help="a MAML run directory or checkpoint")
    parser.add_argument("--steps", type=int, default=3, help="K: updates; returns at k = 0 … K")
    parser.add_argument("--schedules", nargs="+", choices=SGD_SCHEDULES[:2], default=["constant", "reference"])
    parser.add_argument("--env-steps", nargs="+", type=env_steps_arg, default=[None, 4000], metavar="S",
                        help="none: --trajectories per task and step; S: the first episodes up to S env steps")
    parser.add_argument("--env", default="point_nav")
    parser.add_argument("--num-tasks", type=int, default=40)
    parser.add_argument("--trajectories", type=int, default=40, help="per task and step (per round with S)")
    parser.add_argument("--seed", type=int, default=0, help="meta-test seed")
    parser.add_argument("--collapse", type=float, default=-50.0, help="a task's return counted as collapsed below")
    parser.add_argument("--log-std", type=float, default=None,
                        help="replace the init's learned log-std by this value (as scripts/diagnostics/action_noise.py)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    tasks = get_task_family(args.env).eval_tasks(args.num_tasks)
    policy = load_maml_policy(args.run)[0]
    saved, kind = policy_log_std(policy).mean().item(), "fixed" if std_is_fixed(policy) else "learned"
    print(f"init {args.run}: {kind} log-std {saved:.2f}" + ("" if args.log_std is None else
                                                          f", replaced by {args.log_std:g}"), flush=True)
    print(HEADER.format(collapse=args.collapse), flush=True)
    for schedule in args.schedules:
        for env_steps in args.env_steps:
            start = time.perf_counter()
            config = AdaptationConfig(num_steps=args.steps, num_trajectories=args.trajectories,
                                      sgd_schedule=schedule, env_steps=env_steps)
            result = adapt(args.run, env_name=args.env, tasks=tasks, seed=args.seed, config=config,
                           log_std=args.log_std)
            sampling = f"{args.trajectories} trajectories" if env_steps is None else f"{env_steps} env steps"
            print("\n".join(rows(schedule, sampling, result, args.collapse)), flush=True)
            print(f"<!-- {schedule}, {sampling}: {time.perf_counter() - start:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
