"""The paper's regret analysis on small deterministic CMPs, computed exactly (CPU, seconds).

    python benchmarks/theory.py                       # table on stdout, figures under outputs/theory
    python benchmarks/theory.py --out docs/theory     # the figures docs/theory.md shows

For each CMP (a chain, a 5x5 grid with walls, a binary tree, a random CMP) and each task proposal (the minimax
uniform marginal, MI-optimal, a frozen random discriminator, hand-designed far goals, each with hard-optimal and
maximum-entropy (a=1) task policies, and random actions), the table gives the worst-case regret of the learner f_pi
that explores with the proposal's task-optimal policies, and its regret (expected hitting time, episodes) on uniform,
skewed and adversarial goal distributions (:func:`umrl.theory.goal_distributions`). A second table does trajectory
matching; figures: the grid marginals per proposal, and worst-case regret against the number of latents |Z|, whose
table closes the output (MI in nats).
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from umrl.theory import (
    chain,
    compare_proposals,
    enumerate_trajectories,
    goal_distributions,
    grid,
    maximise_trajectory_information,
    optimal_marginal,
    random_cmp,
    reachable_at,
    regret,
    regret_against_latents,
    terminal_marginal,
    trajectory_probabilities,
    tree,
    uniform_policy,
    uniform_trajectory_policy,
    worst_case_regret,
)
from umrl.theory.evaluation import GOAL_DISTRIBUTIONS
from umrl.theory.figures import plot_grid_marginals, plot_regret_against_latents

WALLS = ((1, 1), (1, 2), (1, 3), (3, 2))


def cmps():
    return [chain(9, 4, start=4), grid(5, 5, 6, walls=WALLS), tree(3), random_cmp(12, 3, 3, seed=0)]


def proposal_table(seed: int) -> dict:
    print(f"{'CMP':14s} {'|S_T|':>5s} {'proposal':26s} {'worst-case':>10s} "
          + " ".join(f"{name:>11s}" for name in GOAL_DISTRIBUTIONS))
    grids = {}
    for cmp in cmps():
        rows = compare_proposals(cmp, temperatures=(0.0, 1.0), seed=seed)
        for row in rows:
            print(f"{cmp.name:14s} {int(reachable_at(cmp).sum()):5d} {row.proposal:26s} {row.worst_case:10.4g} "
                  + " ".join(f"{row.regrets[name]:11.4g}" for name in GOAL_DISTRIBUTIONS))
        optimum = {name: float(regret(optimal_marginal(p), p)) for name, p in goal_distributions(cmp).items()}
        print(f"{cmp.name:14s} {'':5s} {'Eq. 4 optimum (knows p)':26s} {'-':>10s} "
              + " ".join(f"{optimum[name]:11.4g}" for name in GOAL_DISTRIBUTIONS))
        if cmp.shape is not None:
            grids[cmp] = rows
    return grids


def trajectory_table(seed: int) -> None:
    print(f"\n{'CMP':14s} {'|S_T|':>5s} {'K':>4s} {'traj. worst-case: uniform-traj':>31s} {'random':>9s} "
          f"{'goal worst-case of uniform-traj':>32s} {'I(tau;z) / log K (|Z|=K)':>25s}")
    for cmp in [chain(5, 3), grid(3, 3, 3, walls=((1, 1),)), tree(3), random_cmp(6, 3, 3, seed=0)]:
        paths = enumerate_trajectories(cmp)
        k = paths.shape[0]
        uniform_traj = uniform_trajectory_policy(cmp)
        mi = maximise_trajectory_information(cmp, k, seed=seed)
        print(f"{cmp.name:14s} {int(reachable_at(cmp).sum()):5d} {k:4d} {float(worst_case_regret(trajectory_probabilities(cmp, uniform_traj, paths))):31.4g} "
              f"{float(worst_case_regret(trajectory_probabilities(cmp, uniform_policy(cmp), paths))):9.4g} "
              f"{float(worst_case_regret(terminal_marginal(cmp, uniform_traj), reachable_at(cmp))):32.4g} "
              f"{mi.mutual_information:11.4f} / {math.log(k):.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/theory"), help="folder for the figures")
    parser.add_argument("--seed", type=int, default=0, help="MI ascent's initial logits, random discriminator")
    args = parser.parse_args()
    torch.set_num_threads(1)  # tiny tensors: threads only add contention
    grids = proposal_table(args.seed)
    trajectory_table(args.seed)
    for cmp, rows in grids.items():
        print(f"\n{plot_grid_marginals(cmp, rows, args.out / f'marginals_{cmp.name}.png')}")
        reachable = int(reachable_at(cmp).sum())
        latents = sorted({2, 4, reachable // 2, reachable - 1, reachable, reachable + 1, 3 * reachable // 2,
                          2 * reachable})
        curves = regret_against_latents(cmp, latents, seed=args.seed)
        print(plot_regret_against_latents(cmp, latents, curves, args.out / f"regret_vs_latents_{cmp.name}.png"))
        shown = ["MI reached", "MI maximum"] + [key for key in curves if key.endswith("worst-case")]
        print(f"{'|Z|':>4s} " + " ".join(f"{key.removesuffix(' worst-case'):>24s}" for key in shown))
        for i, z in enumerate(latents):
            print(f"{z:4d} " + " ".join(f"{curves[key][i]:24.4g}" for key in shown))


if __name__ == "__main__":
    main()
