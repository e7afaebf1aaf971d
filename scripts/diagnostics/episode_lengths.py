"""How long meta-test episodes last: replays suite cells and prints the episode lengths behind their returns.

    python scripts/diagnostics/episode_lengths.py outputs/suite/quick/cells/ant/*/seed0-*.json --stand-still
    python scripts/diagnostics/episode_lengths.py CELL.json --steps 0 5 10

Where an env ends episodes early (ant: gymnasium's Ant-v5 ends one when the torso height leaves [0.2, 1.0];
point_nav: when the goal is reached), a return sums a different number of steps for each policy, and with rewards
below zero per step a shorter episode scores higher. The suite's ``results.csv`` records each cell's mean episode
``length`` (and ``summary.md`` shows it where episodes end early); this script tells more, for any cell, including
cells written before that column: the reward per step, how episodes end, and a policy that does not move.

Each cell JSON (written by ``umrl.metatest.run_cell`` beside its CSV) is replayed with its own method, checkpoint,
seed, learning rate and protocol through ``umrl.metatest.meta_test``, so the episodes are the cell's own: the
replayed mean returns are compared with those the cell recorded (``match`` column: the largest difference; the suite
runs cells on one torch thread, as ``--threads`` does by default). Printed per cell and adaptation step ``k``: the
mean return, the mean episode length, the fraction of episodes the env terminated (not the horizon's truncation),
the mean reward per step, on ant the fraction terminated by a jump (the torso above the healthy range), and the mean
end error: how far each episode ended from its task (final x-y to the goal; half_cheetah: mean velocity to the
target), whatever the reward's shaping.
``--stand-still`` adds, per env and seed, zero actions on the same tasks (no adaptation); ``--maml-checkpoints`` adds
MAML checkpoints' policies there at k = 0 (for instance the ones a run kept along meta-training).
"""
from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import torch
from tensordict import TensorDictBase

from umrl.checkpoints import load_maml_policy
from umrl.envs import get_env_spec
from umrl.envs.builtin import ANT
from umrl.envs.mujoco_batched import AntBatchedEnv
from umrl.envs.tasks import get_task_family
from umrl.metatest import AdaptationConfig, CellSpec, load_initialisation, meta_test
from umrl.metatest.protocol import make_eval_env
from umrl.metatest.provenance import resolve_recorded_path
from umrl.objectives.policy_gradient import episode_lengths, episode_returns
from umrl.rng import seed_everything
from umrl.rollout import collect
from umrl.skill_coverage import final_states
from umrl.trajectories import trajectory_mask

#: ant's observation starts at qpos[2], the torso height (x-y are excluded)
ANT_TORSO_Z = 0
HEADER = (f"{'cell':<36}{'k':>4}{'return':>10}{'length':>8}{'terminated':>12}{'reward/step':>13}"
          f"{'jumped':>8}{'end error':>11}{'match':>10}")


def episode_stats(batch: TensorDictBase, env_name: str) -> dict[str, float]:
    """Means over a ``[T, N, H]`` batch's first episodes: return, length, fraction terminated, reward per step,
    (Ant, else NaN) the fraction terminated by a jump, and the end error: the distance between the episode's
    coverage point (final x-y, or mean forward velocity: :func:`umrl.skill_coverage.final_states`) and its task,
    which does not depend on how the reward is shaped."""
    returns, length = episode_returns(batch), episode_lengths(batch).float()
    episodes = batch.reshape(-1, batch.shape[-1])  # [T * N, H]
    end_error = (final_states(episodes, env_name)["end_point"] - episodes["task"][:, 0]).norm(dim=-1)
    # the step where the env ended a first episode
    terminated = batch["next", "terminated"].squeeze(-1) & trajectory_mask(batch["next", "done"])
    stats = {"return": returns.mean().item(), "length": length.mean().item(),
             "terminated": terminated.any(-1).float().mean().item(),
             "reward/step": (returns.sum() / length.sum()).item(), "jumped": float("nan"),
             "end error": end_error.mean().item()}
    if get_env_spec(env_name).make is ANT.make:  # the Ant CMP, whatever its task reward
        above = batch["next", "observation"][..., ANT_TORSO_Z] > AntBatchedEnv.HEALTHY_Z_RANGE[1]
        stats["jumped"] = (terminated & above).any(-1).float().mean().item()
    return stats


def row(label: str, k: int, stats: dict[str, float], match: str = "") -> str:
    jumped = "" if stats["jumped"] != stats["jumped"] else f"{stats['jumped']:.2f}"  # NaN: not ant
    return (f"{label:<36}{k:>4}{stats['return']:>10.1f}{stats['length']:>8.1f}{stats['terminated']:>12.2f}"
            f"{stats['reward/step']:>13.3f}{jumped:>8}{stats['end error']:>11.3f}{match:>10}")


def num_tasks(path: Path, cell: dict) -> int:
    """The cell's number of evaluation tasks: recorded in its JSON, or (older cells) counted in its CSV."""
    if "num_tasks" in cell:
        return cell["num_tasks"]
    with path.with_suffix(".csv").open() as rows:
        return len({row["task"] for row in csv.DictReader(rows)})


def replay_cell(cell: dict, config: AdaptationConfig, tasks: torch.Tensor, steps: set[int] | None,
                device: str) -> list[str]:
    """Replay ``cell`` (its JSON) on ``tasks`` with its protocol ``config``: one row per adaptation step in
    ``steps``."""
    init = load_initialisation(cell["method"], cell["env"], cell["checkpoint"], seed=cell["seed"], device=device)
    per_step: dict[int, dict[str, float]] = {}

    def observe(k: int, batch: TensorDictBase) -> None:
        per_step[k] = episode_stats(batch, cell["env"])

    returns, _ = meta_test(init, cell["env"], tasks, lr=cell["lr"], seed=cell["seed"], config=config,
                           skill_trajectories=cell.get("skill_trajectories", CellSpec.skill_trajectories),
                           device=device, observe=observe)
    label = f"{cell['env']}/{cell['method']}/seed{cell['seed']}"
    rows = []
    for k, stats in per_step.items():
        if steps is None or k in steps:
            diff = abs(returns[k].mean().item() - cell["mean_return"][k])
            rows.append(row(label, k, stats, f"{diff:.1e}"))
    return rows


def unadapted(policy, env_name: str, seed: int, config: AdaptationConfig, tasks: torch.Tensor) -> dict[str, float]:
    """:func:`episode_stats` of ``policy`` (``None``: zero actions) on ``tasks`` without adaptation (k = 0), seeded
    and rolled out as a cell's first step is."""
    seed_everything(seed)
    env = make_eval_env(env_name, tasks, config.num_trajectories, seed=seed, horizon=config.horizon)
    if policy is None:
        with torch.no_grad():
            batch = env.rollout(config.horizon, policy=lambda td: td.set("action", torch.zeros(env.action_spec.shape)),
                                auto_reset=True, break_when_any_done=False)
        batch = batch.view(len(tasks), config.num_trajectories, config.horizon)
    else:
        batch = collect(env, policy, num_tasks=len(tasks), horizon=config.horizon)
    env.close()
    return episode_stats(batch, env_name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("cells", nargs="+", type=Path, help="cell JSON files (<suite output>/cells/<env>/<method>/)")
    parser.add_argument("--steps", type=int, nargs="*", default=None, help="adaptation steps to print (default: all)")
    parser.add_argument("--stand-still", action="store_true", help="add zero actions per env and seed")
    parser.add_argument("--maml-checkpoints", nargs="*", default=[],
                        help="step_*.safetensors files of MAML runs: their policies at k = 0 on the cells' env, tasks and seed "
                             "(e.g. along meta-training)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the suite's cells use 1)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    missing = [str(p) for p in args.cells if p.suffix != ".json" or not p.is_file()]
    if missing:
        raise SystemExit(f"cells: not cell JSON files: {missing} (expected <suite output>/cells/<env>/<method>/"
                         f"seed<s>-<key>.json)")
    torch.set_num_threads(args.threads)
    steps = None if args.steps is None else set(args.steps)
    print(HEADER)
    baselines = {}
    for path in args.cells:
        cell = json.loads(path.read_text())
        if cell.get("checkpoint"):  # recorded relative to the cell's file
            cell["checkpoint"] = str(resolve_recorded_path(cell["checkpoint"], path))
        config = AdaptationConfig(**cell["protocol"])
        tasks = get_task_family(cell["env"]).eval_tasks(num_tasks(path, cell))
        for line in replay_cell(cell, config, tasks, steps, args.device):
            print(line, flush=True)
        baselines[cell["env"], cell["seed"]] = config, tasks
    for (env_name, seed), (config, tasks) in sorted(baselines.items()):
        if args.stand_still:
            print(row(f"{env_name}/stand_still/seed{seed}", 0, unadapted(None, env_name, seed, config, tasks)),
                  flush=True)
        for path in args.maml_checkpoints:
            label = f"{Path(path).parent.parent.name[:20]}/{Path(path).stem}"
            print(row(label, 0, unadapted(load_maml_policy(path)[0], env_name, seed, config, tasks)), flush=True)


if __name__ == "__main__":
    main()
