"""Reward maps of point_nav skill discriminators: what UML-random's (and UML-DIAYN's) tasks ask for.

    python scripts/diagnostics/reward_map.py --random-seeds 0 1 2                    # frozen random discriminators
    python scripts/diagnostics/reward_map.py --random-seeds 0 1 2 --init torch      # the previous (torch default) init
    python scripts/diagnostics/reward_map.py --diayn-checkpoint outputs/diayn/point_nav/seed0 --out outputs/reward_map

Random discriminators are built exactly as the UML-random proposal builds them
(``make_discriminator(2, K, hidden, seed=s)``, frozen); a DIAYN checkpoint is read with
``umrl.checkpoints.load_discriminator``. For each discriminator this prints the numbers of
:func:`umrl.reward_map.reward_map_stats` (reward range inside the goal square vs within radius R, fraction of skills
whose best point within R is on its edge, skills most likely somewhere in [-1, 1]², skills owning the evaluation
goals) and writes ``territories_<name>.png`` and ``rays_<name>.png`` under ``--out``. R defaults to the reach of one
episode: horizon x the per-step displacement bound (100 x 0.1 = 10).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from umrl.checkpoints import load_discriminator
from umrl.configs.env_groups import env_defaults
from umrl.envs.point_nav import ACTION_SCALE
from umrl.envs.registry import get_env_spec
from umrl.modules.discriminator import DISCRIMINATOR_INITS, make_discriminator
from umrl.reward_map import plot_rays, plot_territories, reward_map, reward_map_stats

COLUMNS = ("num_skills", "goal_square_range", "disc_range", "disc_min", "disc_max", "edge_fraction",
           "skills_near_origin", "skills_at_eval_goals")


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--random-seeds", type=int, nargs="*", default=[0, 1, 2])
    parser.add_argument("--diayn-checkpoint", nargs="*", default=[], help="DIAYN run dirs or step_*.safetensors files")
    parser.add_argument("--num-skills", type=int, default=None, help="random discriminators (default: the env's)")
    parser.add_argument("--hidden", type=int, nargs="+", default=None,
                        help="random discriminators' widths (default: UML-random's, maml_env/point_nav.yaml)")
    parser.add_argument("--init", default="xavier", choices=DISCRIMINATOR_INITS, help="random discriminators' init")
    parser.add_argument("--radius", type=float, default=None, help="R (default: horizon x 0.1 = 10)")
    parser.add_argument("--resolution", type=int, default=201)
    parser.add_argument("--out", default="outputs/reward_map")
    args = parser.parse_args()
    spec = get_env_spec("point_nav")
    radius = args.radius or spec.horizon * ACTION_SCALE
    eval_goals = spec.eval_tasks()
    defaults = env_defaults("maml", "point_nav")  # UML-random's discriminator
    num_skills = args.num_skills or defaults["default_num_skills"]
    hidden = args.hidden or defaults["discriminator_hidden"]
    discriminators = {
        f"random_{args.init}_seed{seed}": make_discriminator(spec.obs_dim, num_skills, hidden=hidden, seed=seed,
                                                             init=args.init).eval().requires_grad_(False)
        for seed in args.random_seeds
    }
    for path in args.diayn_checkpoint:
        discriminator, _, obs_dim = load_discriminator(path)
        if obs_dim != 2:
            raise SystemExit(f"--diayn-checkpoint {path}: reward maps need a 2-D observation (point_nav), got "
                             f"obs_dim={obs_dim}.")
        discriminators[f"diayn_{Path(path).resolve().name}"] = discriminator
    if not discriminators:
        raise SystemExit("nothing to map: give --random-seeds and/or --diayn-checkpoint.")

    out = Path(args.out)
    print(f"point_nav reward maps: R = {radius:g}, goal square [-0.5, 0.5]², {len(eval_goals)} evaluation goals; "
          "ranges in nats, medians over skills")
    print(f"{'discriminator':<28}" + "".join(f"{c:>21}" for c in COLUMNS))
    for name, discriminator in discriminators.items():
        rmap = reward_map(discriminator, eval_goals, radius=radius, resolution=args.resolution)
        stats = reward_map_stats(rmap)
        print(f"{name:<28}" + "".join(f"{stats[c]:>21.3g}" for c in COLUMNS))
        title = f"{name}: {rmap.num_skills} skills"
        plot_territories(rmap, out / f"territories_{name}.png", title=title)
        plot_rays(rmap, out / f"rays_{name}.png", title=title)
    print(f"figures in {out}/")


if __name__ == "__main__":
    main()
