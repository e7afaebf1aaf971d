"""Where a trained DIAYN run's skills go, at any episode length, next to a random policy.

    python scripts/diagnostics/skill_coverage.py outputs/diayn/half_cheetah/seed0 --horizons 100 1000
    python scripts/diagnostics/skill_coverage.py run_a run_b --episodes 4 --seed 0 --out outputs/skill_coverage

Each checkpoint (a run's output_dir, its ``checkpoints/`` folder or a ``step_*.safetensors``) is read with
``umrl.checkpoints.load_skill_policy`` / ``load_discriminator``. For every horizon, every skill is rolled out
``--episodes`` times (sampled actions, the env's reset noise seeded by ``--seed``) in a fresh env of the run's
``env``, as the recipe's own evaluation does, and a uniformly random policy is rolled out beside it. Printed per row:
the :func:`umrl.skill_coverage.coverage_metrics` (final-state accuracy; centroid spread; ``task_distance_median`` /
``_max``: distance from each held-out evaluation task to the nearest skill centroid) and the range of the skills'
centroids per coordinate (x-y end points, or half_cheetah's mean forward velocity) against the evaluation tasks'.
Figures: ``<out>/<run>_h<horizon>.png``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from umrl.checkpoints import load_diayn_checkpoint, load_discriminator, load_skill_policy
from umrl.checkpoints.folder import resolve_checkpoint
from umrl.envs import get_env_spec, make_env
from umrl.rng import seed_everything
from umrl.skill_coverage import coverage_metrics, evaluate_skills, plot_coverage, skill_centroids
from umrl.transforms.skill import SkillTransform

# coverage_metrics key -> column header
COLUMNS = {"final_state_accuracy": "accuracy", "centroid_pairwise_distance": "centroid dist",
           "within_skill_std": "within std", "task_distance_median": "task dist med",
           "task_distance_max": "task dist max"}
WIDTH = 15


def _ranges(points: torch.Tensor) -> str:
    """``[min, max]`` of each coordinate of ``points`` [N, d]."""
    low, high = points.min(0).values.tolist(), points.max(0).values.tolist()
    return " ".join(f"[{lo:.2f}, {hi:.2f}]" for lo, hi in zip(low, high))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", help="DIAYN run dirs, checkpoints/ folders or step_*.safetensors files")
    parser.add_argument("--horizons", type=int, nargs="+", default=[100])
    parser.add_argument("--episodes", type=int, default=4, help="rollouts per skill")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/skill_coverage")
    args = parser.parse_args()
    if min(args.horizons) < 1 or args.episodes < 1:
        raise SystemExit(f"--horizons and --episodes must be positive, got {args.horizons} and {args.episodes}.")
    torch.set_num_threads(1)  # as the recipes evaluate: one torch thread beside the physics

    files = [resolve_checkpoint(path) for path in args.checkpoints]
    runs = [f"{file.parent.parent.name}_{file.stem}" for file in files]
    run_width = max(len(run) for run in runs) + 2
    print(f"{'run':<{run_width}}{'horizon':>8} {'policy':<8}" + "".join(f"{c:>{WIDTH}}" for c in COLUMNS.values())
          + "  centroid range")
    for path, run in zip(files, runs):
        env_name = load_diayn_checkpoint(path)["meta"]["env"]
        actor, num_skills, _ = load_skill_policy(path)
        discriminator, _, _ = load_discriminator(path)
        spec = get_env_spec(env_name)
        eval_tasks = spec.eval_tasks()
        for horizon in args.horizons:
            results = {}
            for label, policy in (("skills", actor), ("random", None)):
                seed_everything(args.seed)
                env = make_env(env_name, num_skills * args.episodes, seed=args.seed, horizon=horizon)
                env.append_transform(SkillTransform(num_skills))
                results[label] = evaluate_skills(env, policy, env_name=env_name, num_skills=num_skills,
                                                 episodes_per_skill=args.episodes, horizon=horizon)
                env.close()
                metrics = coverage_metrics(results[label], num_skills, discriminator, eval_tasks)
                values = "".join(f"{metrics[c]:>{WIDTH}.3f}" for c in COLUMNS)
                centroids = skill_centroids(results[label]["end_point"].float(), results[label]["skill"], num_skills)
                print(f"{run:<{run_width}}{horizon:>8} {label:<8}{values}  {_ranges(centroids)}")
            figure = plot_coverage(results["skills"]["end_point"], Path(args.out) / f"{run}_h{horizon}.png",
                                   eval_tasks=eval_tasks, skills=results["skills"]["skill"],
                                   baseline=results["random"]["end_point"],
                                   title=f"DIAYN {env_name} ({run}), {num_skills} skills, horizon {horizon}")
            blank = " " * (run_width + 9 + WIDTH * len(COLUMNS))
            print(f"{blank}{'tasks':<8}  {_ranges(eval_tasks)}   figure: {figure}")


if __name__ == "__main__":
    main()
