"""Regret of the learners that task proposals induce, on fixed test-goal distributions: the comparison table.

The learner meta-trained on a proposal explores with the Eq. 4 marginal of the proposal's task marginal ``q``
(:func:`~umrl.theory.proposals.meta_learned_marginal`); :func:`evaluate_marginal` reports an exploration marginal's
worst-case regret and its regret (expected hitting time) on the test-goal distributions of
:func:`goal_distributions`, and :func:`evaluate_proposal` adds the regret on ``q`` itself and, as the alternative,
the posterior-sampling learner's (exploring with ``q``).

>>> from umrl.theory.cmp import chain
>>> rows = compare_proposals(chain(5, horizon=2), mi_steps=200)
>>> [row.proposal for row in rows]
['uniform-over-reachable', 'MI-optimal', 'random discriminator', 'hand-designed', 'random actions']
>>> rows[0].worst_case  # |S_T| = 3 states reachable at T
3.0
>>> rows[3].on_tasks, rows[3].posterior_on_tasks  # one far goal: Eq. 4 and posterior sampling agree
(1.0, 1.0)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from umrl.theory.cmp import DeterministicCMP, reachable_at
from umrl.theory.marginals import terminal_marginal, uniform_policy
from umrl.theory.mutual_information import max_mutual_information, maximise_mutual_information
from umrl.theory.proposals import (
    far_goals,
    goal_rewards,
    meta_learned_marginal,
    optimal_policy_marginal,
    random_discriminator_rewards,
)
from umrl.theory.regret import optimal_marginal, regret, worst_case_regret

#: test-goal distributions, in table order
GOAL_DISTRIBUTIONS = ("uniform", "skewed", "adversarial")


def goal_distributions(cmp: DeterministicCMP) -> dict[str, torch.Tensor]:
    """Goal distributions ``[S]`` on the states reachable at T, fixed before any proposal is seen.

    ``uniform``; ``skewed``: proportional to the square of the random-action marginal (goals a random walk finds
    easily, near the start; the square because ``p = rho`` itself has regret exactly |S_T| under ``rho``);
    ``adversarial``: proportional to its inverse (goals a random walk rarely reaches).
    """
    reachable = reachable_at(cmp)
    walk = terminal_marginal(cmp, uniform_policy(cmp))
    weights = {"uniform": reachable.double(), "skewed": walk ** 2,
               "adversarial": torch.where(reachable, 1 / walk.clamp(min=1e-300), 0.0)}
    return {name: w / w.sum() for name, w in weights.items()}


@dataclass
class Evaluation:
    """One row: ``proposal`` name, exploration ``marginal`` ``[S]``, ``worst_case`` regret and ``regrets`` per
    test-goal distribution (``inf`` where the marginal misses a goal the distribution can draw).

    Rows of a proposal (:func:`evaluate_proposal`) also carry its task marginal ``tasks`` ``[S]`` (``q``), the
    learner's regret ``on_tasks`` on ``q``, and the posterior-sampling learner's (exploring with ``q``)
    ``posterior_worst_case`` and ``posterior_on_tasks``; these are ``None``/``nan`` for a bare marginal.
    """

    proposal: str
    marginal: torch.Tensor
    worst_case: float
    regrets: dict[str, float] = field(default_factory=dict)
    tasks: torch.Tensor | None = None
    on_tasks: float = math.nan
    posterior_worst_case: float = math.nan
    posterior_on_tasks: float = math.nan


def evaluate_marginal(cmp: DeterministicCMP, proposal: str, rho: torch.Tensor) -> Evaluation:
    """Worst-case regret over goals on S_T and regret on each of :func:`goal_distributions` for ``rho`` ``[S]``."""
    goals = goal_distributions(cmp)
    return Evaluation(proposal, rho, float(worst_case_regret(rho, reachable_at(cmp))),
                      {name: float(regret(rho, p)) for name, p in goals.items()})


def evaluate_proposal(cmp: DeterministicCMP, proposal: str, q: torch.Tensor) -> Evaluation:
    """:func:`evaluate_marginal` of the learner meta-trained on task marginal ``q`` ``[S]`` (its Eq. 4 marginal
    ``sqrt(q) / sum sqrt(q)``), with the regret on ``q`` itself and the posterior-sampling learner's columns."""
    row = evaluate_marginal(cmp, proposal, optimal_marginal(q))
    row.tasks, row.on_tasks = q, float(regret(row.marginal, q))
    row.posterior_worst_case = float(worst_case_regret(q, reachable_at(cmp)))
    row.posterior_on_tasks = float(regret(q, q))
    return row


def proposal_tasks(cmp: DeterministicCMP, *, num_latents: int | None = None, seed: int = 0, mi_steps: int = 600
                   ) -> dict[str, torch.Tensor]:
    """The task tables ``[Z, S]`` of the proposals compared (``num_latents`` defaults to |S_T|).

    ``MI-optimal``: ``log mu(s_T | z)`` of an MI-ascended policy
    (:func:`~umrl.theory.mutual_information.maximise_mutual_information`, ``mi_steps``); ``random discriminator``:
    frozen random logits (``seed``); ``hand-designed``: one task per far goal (:func:`~umrl.theory.proposals.far_goals`).
    """
    num_latents = num_latents or int(reachable_at(cmp).sum())
    mi = maximise_mutual_information(cmp, num_latents, steps=mi_steps, seed=seed)
    return {
        "MI-optimal": mi.rewards(),
        "random discriminator": random_discriminator_rewards(cmp.num_states, num_latents, seed=seed),
        "hand-designed": goal_rewards(far_goals(cmp), cmp.num_states),
    }


def compare_proposals(cmp: DeterministicCMP, *, temperatures: tuple[float, ...] = (0.0,), **options
                      ) -> list[Evaluation]:
    """:func:`evaluate_proposal` rows for uniform goals on S_T (``uniform-over-reachable``, whose learner is the
    minimax one) and each of :func:`proposal_tasks` (``options`` go there) at each of ``temperatures``
    (``optimal_policy_marginal``'s; rows named ``"<proposal> a=<t>"`` when ``t > 0``), then the
    :func:`evaluate_marginal` row ``random actions`` (no proposal: the uniformly random policy's marginal).
    """
    reachable = reachable_at(cmp)
    rows = [evaluate_proposal(cmp, "uniform-over-reachable", reachable.double() / reachable.sum())]
    tasks = proposal_tasks(cmp, **options)
    for temperature in temperatures:
        for name, rewards in tasks.items():
            label = f"{name} a={temperature:g}" if temperature > 0 else name
            q = optimal_policy_marginal(cmp, rewards, temperature=temperature)
            rows.append(evaluate_proposal(cmp, label, q))
    rows.append(evaluate_marginal(cmp, "random actions", terminal_marginal(cmp, uniform_policy(cmp))))
    return rows


def regret_against_latents(cmp: DeterministicCMP, latents: list[int], *, seed: int = 0, mi_steps: int = 600,
                           temperatures: tuple[float, ...] = (0.0, 1.0)) -> dict[str, list[float]]:
    """Worst-case and uniform-goal regret of the learners meta-trained on the MI-optimal and random-discriminator
    proposals (:func:`~umrl.theory.proposals.meta_learned_marginal`) for each ``|Z|``.

    Returns lists aligned with ``latents`` under keys ``"<proposal>[ a=<t>] worst-case"`` and ``"... uniform"`` for
    each of ``temperatures`` (as in :func:`compare_proposals`), and ``"MI reached"``/``"MI maximum"`` (nats: the
    ascent's value and :func:`~umrl.theory.mutual_information.max_mutual_information`'s).
    """
    reachable = reachable_at(cmp)
    uniform = reachable.double() / reachable.sum()
    curves: dict[str, list[float]] = {}
    for z in latents:
        mi = maximise_mutual_information(cmp, z, steps=mi_steps, seed=seed)
        tasks = {"MI-optimal": mi.rewards(),
                 "random discriminator": random_discriminator_rewards(cmp.num_states, z, seed=seed)}
        for temperature in temperatures:
            for name, rewards in tasks.items():
                rho = meta_learned_marginal(cmp, rewards, temperature=temperature)
                label = f"{name} a={temperature:g}" if temperature > 0 else name
                curves.setdefault(f"{label} worst-case", []).append(float(worst_case_regret(rho, reachable)))
                curves.setdefault(f"{label} uniform", []).append(float(regret(rho, uniform)))
        curves.setdefault("MI reached", []).append(mi.mutual_information)
        curves.setdefault("MI maximum", []).append(max_mutual_information(z, int(reachable.sum())))
    return curves
