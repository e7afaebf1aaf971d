"""Slip noise: the same CMPs with stochastic dynamics, where each action slips with probability ``eps``.

With probability ``eps`` the action taken is replaced by one drawn uniformly from all ``A`` actions (possibly the same
one), independently at every step; the successor is then the table's. A policy ``pi`` under slips has exactly the
state marginals of the policy ``(1 - eps) pi + eps / A`` on the deterministic CMP (:func:`slip_policy`), so the
dynamic programme stays exact. Every state reachable at T then has positive probability under every policy.

f_pi keeps its meaning: it explores with ``pi`` (slips included) until an episode ends on the goal; from then on it
knows the goal and acts as well as a learner told the goal would. What separates learners is the hitting time, still
geometric: each exploring episode ends on ``g`` with probability ``rho_eps(g)``, the slipped terminal marginal, so
:func:`~umrl.theory.regret.regret` and :func:`~umrl.theory.regret.worst_case_regret` apply to ``rho_eps`` unchanged.
Under slips the learner is a policy, not a marginal: policies with one noiseless marginal differ once actions slip.

>>> from umrl.theory.cmp import chain
>>> from umrl.theory.marginals import policy_for_marginal, terminal_marginal
>>> cmp = chain(3, horizon=1)  # actions left, stay, right from state 0: S_T = {0, 1}
>>> to_one = policy_for_marginal(cmp, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
>>> terminal_marginal(cmp, slip_policy(cmp, to_one, 0.3)).round(decimals=12).tolist()  # 2 of 3 slips stay at 0
[0.2, 0.8, 0.0]
"""
from __future__ import annotations

import torch

from umrl.theory.cmp import DeterministicCMP, reachable_at
from umrl.theory.marginals import check_policy, terminal_marginal
from umrl.theory.regret import worst_case_regret
from umrl.validation import check_float


def slip_policy(cmp: DeterministicCMP, policy: torch.Tensor, slip: float) -> torch.Tensor:
    """``(1 - slip) policy + slip / A``, ``[..., T, S, A]``: the action actually taken by ``policy`` under slips."""
    policy = check_policy(cmp, policy)
    slip = check_float("slip", slip, ge=0, le=1)
    return (1 - slip) * policy + slip / cmp.num_actions


def worst_case_under_slips(cmp: DeterministicCMP, policies: dict[str, torch.Tensor], slips: tuple[float, ...]
                           ) -> dict[str, list[float]]:
    """Worst-case regret over goals on S_T of each of ``policies`` (``[T, S, A]`` each) at each slip probability.

    Returns, per name, a list aligned with ``slips``: ``1 / min_g rho_eps(g)`` over the states reachable at T,
    ``rho_eps`` the terminal marginal of :func:`slip_policy`. No policy does better than ``|S_T|``.
    """
    reachable = reachable_at(cmp)
    return {name: [float(worst_case_regret(terminal_marginal(cmp, slip_policy(cmp, policy, eps)), reachable))
                   for eps in slips] for name, policy in policies.items()}
