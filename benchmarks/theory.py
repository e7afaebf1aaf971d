"""The paper's regret analysis on small deterministic CMPs, computed exactly (CPU, seconds).

    python benchmarks/theory.py                       # tables on stdout, figures under outputs/theory
    python benchmarks/theory.py --out docs/theory     # the figures docs/theory.md shows

For each CMP (a chain, a 5x5 grid with walls, a binary tree, a random CMP) and each task proposal (uniform goals on
the reachable set, MI-optimal, a frozen random discriminator, hand-designed far goals, each with hard-optimal and
maximum-entropy (a=1) task policies), the first table gives the learner meta-trained on the proposal: it explores
with the Eq. 4 marginal sqrt(q) / sum sqrt(q) of the proposal's task marginal q
(:func:`umrl.theory.meta_learned_marginal`). Columns: its worst-case regret, its regret (expected hitting time,
episodes) on uniform, skewed and adversarial goal distributions (:func:`umrl.theory.goal_distributions`) and on q
itself, then the posterior-sampling alternative (exploring with q): worst case and regret on q. "random actions" has
no proposal. Further tables: trajectory matching; worst-case regret when each action slips to a uniformly random one
with probability eps (:mod:`umrl.theory.noise`); the checks docs/theory.md quotes; worst-case regret against the
number of latents |Z| on the grid (MI in nats). Figures: the grid marginals per proposal, and the |Z| curves.
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
    max_mutual_information,
    maximise_mutual_information,
    maximise_trajectory_information,
    meta_learned_marginal,
    minimise_regret,
    optimal_marginal,
    optimal_policy_marginal,
    policy_for_marginal,
    random_cmp,
    random_discriminator_rewards,
    reachable_at,
    regret,
    regret_against_latents,
    regret_within,
    simulate_regret,
    terminal_marginal,
    trajectory_probabilities,
    tree,
    uniform_policy,
    uniform_trajectory_policy,
    worst_case_regret,
    worst_case_under_slips,
)
from umrl.theory.evaluation import GOAL_DISTRIBUTIONS
from umrl.theory.figures import plot_grid_marginals, plot_regret_against_latents

WALLS = ((1, 1), (1, 2), (1, 3), (3, 2))
SLIPS = (0.0, 0.01, 0.05, 0.1, 0.2)


def cmps():
    return [chain(9, 4, start=4), grid(5, 5, 6, walls=WALLS), tree(3), random_cmp(12, 3, 3, seed=0)]


def proposal_table(seed: int) -> dict:
    print(f"{'CMP':14s} {'|S_T|':>5s} {'proposal':26s} {'worst-case':>10s} "
          + " ".join(f"{name:>11s}" for name in GOAL_DISTRIBUTIONS)
          + f" {'on q':>8s} | {'PS worst':>10s} {'PS on q':>8s}")
    grids = {}
    for cmp in cmps():
        rows = compare_proposals(cmp, temperatures=(0.0, 1.0), seed=seed)
        for row in rows:
            print(f"{cmp.name:14s} {int(reachable_at(cmp).sum()):5d} {row.proposal:26s} {row.worst_case:10.4g} "
                  + " ".join(f"{row.regrets[name]:11.4g}" for name in GOAL_DISTRIBUTIONS)
                  + (f" {row.on_tasks:8.4g} | {row.posterior_worst_case:10.4g} {row.posterior_on_tasks:8.4g}"
                     if row.tasks is not None else f" {'-':>8s} | {'-':>10s} {'-':>8s}"))
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
        print(f"{cmp.name:14s} {int(reachable_at(cmp).sum()):5d} {k:4d} "
              f"{float(worst_case_regret(trajectory_probabilities(cmp, uniform_traj, paths))):31.4g} "
              f"{float(worst_case_regret(trajectory_probabilities(cmp, uniform_policy(cmp), paths))):9.4g} "
              f"{float(worst_case_regret(terminal_marginal(cmp, uniform_traj), reachable_at(cmp))):32.4g} "
              f"{mi.mutual_information:11.4f} / {math.log(k):.4f}")


def slip_table(seed: int) -> None:
    """Worst-case regret under slips of the minimax learner, the random discriminator's learner (each as the Markov
    policy of :func:`umrl.theory.policy_for_marginal`) and random actions."""
    print(f"\n{'CMP':14s} {'|S_T|':>5s} {'learner (worst-case regret)':28s} "
          + " ".join(f"{f'eps={eps:g}':>10s}" for eps in SLIPS))
    for cmp in cmps():
        reachable = reachable_at(cmp)
        discriminator = random_discriminator_rewards(cmp.num_states, int(reachable.sum()), seed=seed)
        policies = {"minimax (uniform on S_T)": policy_for_marginal(cmp, reachable.double() / reachable.sum()),
                    "random discriminator": policy_for_marginal(cmp, meta_learned_marginal(cmp, discriminator)),
                    "random actions": uniform_policy(cmp)}
        for name, values in worst_case_under_slips(cmp, policies, SLIPS).items():
            print(f"{cmp.name:14s} {int(reachable.sum()):5d} {name:28s} " + " ".join(f"{v:10.4g}" for v in values))


def dirichlet(n: int, seed: int, concentration: float = 1.0) -> torch.Tensor:
    """A Dirichlet draw ``[n]`` after ``torch.manual_seed(seed)`` (as tests/test_theory.py draws them)."""
    torch.manual_seed(seed)
    return torch.distributions.Dirichlet(torch.full((n,), concentration, dtype=torch.float64)).sample()


def on_reachable(cmp, values: torch.Tensor) -> torch.Tensor:
    """``values`` ``[|S_T|]`` placed on the states reachable at T, zero elsewhere; ``[S]``."""
    out = torch.zeros(cmp.num_states, dtype=torch.float64)
    out[reachable_at(cmp)] = values
    return out


def checks(seed: int) -> None:
    """The figures docs/theory.md quotes beside the tables, on the CMPs and draws of tests/test_theory.py."""
    gaps = []
    for s in range(5):
        cmp = random_cmp(12, 3, 3, seed=s)
        p = on_reachable(cmp, dirichlet(int(reachable_at(cmp).sum()), s, concentration=0.5))
        gaps.append(float((minimise_regret(p, reachable_at(cmp)) - optimal_marginal(p)).abs().max()))
    walled = grid(3, 3, 3, walls=((1, 1),))
    k = enumerate_trajectories(walled).shape[0]
    p = dirichlet(k, 0)
    trajectory_gap = float((minimise_regret(p, torch.ones(k, dtype=torch.bool)) - optimal_marginal(p)).abs().max())
    print(f"\nEq. 4: solver against closed form, max |difference|: goals {max(gaps):.2g} (5 random CMPs), "
          f"trajectories {trajectory_gap:.2g} ({walled.name})")
    support = reachable_at(walled)
    n = int(support.sum())
    uniform = support.double() / n
    under_uniform = [float(regret(uniform, on_reachable(walled, dirichlet(n, s)))) for s in range(5)]
    worst, sampled = [], []
    for s in range(5):
        rho = terminal_marginal(walled, policy_for_marginal(walled, on_reachable(walled, dirichlet(n, 100 + s))))
        worst.append(float(worst_case_regret(rho, support)))
        sampled.append(max(float(regret(rho, on_reachable(walled, dirichlet(n, t, 0.2)))) for t in range(20)))
    print(f"Lemma 1 ({walled.name}, |S_T| = {n}): uniform marginal's regret on 5 goal distributions "
          + ", ".join(f"{v:.6g}" for v in under_uniform) + "; worst cases of 5 random marginals "
          + ", ".join(f"{v:.4g}" for v in worst) + "; largest of 20 sampled goal distributions each "
          + ", ".join(f"{v:.4g}" for v in sampled))
    small = chain(4, 2)
    reachable = reachable_at(small)
    n_small = int(reachable.sum())
    for z in (2, 3, 4, 6):
        mi = maximise_mutual_information(small, z, seed=seed)
        learner = worst_case_regret(meta_learned_marginal(small, mi.rewards()), reachable)
        posterior = worst_case_regret(optimal_policy_marginal(small, mi.rewards()), reachable)
        print(f"Lemma 2 ({small.name}, T=2, |S_T| = {n_small}, |Z| = {z}): I {mi.mutual_information:.4f} of max "
              f"{max_mutual_information(z, n_small):.4f} (log |S_T| = {math.log(n_small):.4f}); marginal "
              f"{[round(v, 3) for v in mi.marginal[reachable].tolist()]}; conditionals' largest entries "
              f"{[round(v, 4) for v in mi.conditionals.max(1).values.tolist()]}; worst case: Eq. 4 learner "
              f"{float(learner):.4g}, posterior sampling {float(posterior):.4g}")
    stall = grid(4, 4, 3, walls=((1, 1), (1, 2)))
    z = int(reachable_at(stall).sum())
    plain = maximise_mutual_information(stall, z, steps=800, anneal_fraction=0, seed=seed)
    annealed = maximise_mutual_information(stall, z, seed=seed)
    print(f"Lemma 2 ascent ({stall.name} with 2 walls, T=3, |Z| = |S_T| = {z}): plain {plain.mutual_information:.4f}, "
          f"annealed {annealed.mutual_information:.4f}, log |S_T| = {math.log(z):.4f}")
    generator = torch.Generator().manual_seed(3)
    policy = (2 * torch.randn(walled.horizon, walled.num_states, walled.num_actions, generator=generator,
                              dtype=torch.float64)).softmax(-1)
    rho = terminal_marginal(walled, policy)
    episodes, runs = 40, 4000
    hitting = simulate_regret(walled, policy, uniform, episodes=episodes, runs=runs, seed=0)
    print(f"f_pi ({walled.name}, uniform goals, random softmax policy): {runs} runs of {episodes} episodes "
          f"{hitting.mean().item():.2f} +- {hitting.std().item() / math.sqrt(runs):.2f}, exact capped "
          f"{float(regret_within(rho, uniform, episodes)):.2f}, uncapped {float(regret(rho, uniform)):.4g}")
    for cmp in (chain(5, 3), walled):
        rho = terminal_marginal(cmp, uniform_trajectory_policy(cmp))
        print(f"Lemma 3 ({cmp.name}, T=3): trajectory-minimax learner's terminal marginal on S_T "
              f"{[round(v, 3) for v in rho[reachable_at(cmp)].tolist()]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/theory"), help="folder for the figures")
    parser.add_argument("--seed", type=int, default=0, help="MI ascent's initial logits, random discriminator")
    args = parser.parse_args()
    torch.set_num_threads(1)  # tiny tensors: threads only add contention
    grids = proposal_table(args.seed)
    trajectory_table(args.seed)
    slip_table(args.seed)
    checks(args.seed)
    for cmp, rows in grids.items():
        print(f"\n{plot_grid_marginals(cmp, rows, args.out / f'marginals_{cmp.name}.png')}")
        reachable = int(reachable_at(cmp).sum())
        latents = sorted({2, 4, reachable // 2, reachable - 1, reachable, reachable + 1, 3 * reachable // 2,
                          2 * reachable})
        curves = regret_against_latents(cmp, latents, seed=args.seed)
        print(plot_regret_against_latents(cmp, latents, curves, args.out / f"regret_vs_latents_{cmp.name}.png"))
        gap = max(m - r for m, r in zip(curves["MI maximum"], curves["MI reached"]))
        print(f"{cmp.name}: learners meta-trained on each |Z|; MI maximum - MI reached at most {gap:.2g} nats")
        shown = ["MI reached", "MI maximum"] + [key for key in curves if key.endswith("worst-case")]
        print(f"{'|Z|':>4s} " + " ".join(f"{key.removesuffix(' worst-case'):>24s}" for key in shown))
        for i, z in enumerate(latents):
            print(f"{z:4d} " + " ".join(f"{curves[key][i]:24.4g}" for key in shown))


if __name__ == "__main__":
    main()
