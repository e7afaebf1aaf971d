"""Exact state marginals of tabular, time-dependent policies on a :class:`~umrl.theory.cmp.DeterministicCMP`.

A policy is a tensor of action probabilities ``[T, S, A]`` (``policy[t, s, a] = pi(a | s, t)``); a latent-conditioned
policy has a leading latent dimension, ``[Z, T, S, A]``. Marginals come from a forward dynamic programme (exact, float64,
differentiable), and :func:`terminal_marginal_by_enumeration` recomputes them from all ``A**T`` action sequences.

>>> from umrl.theory.cmp import chain
>>> cmp = chain(4, horizon=2)
>>> (9 * terminal_marginal(cmp, uniform_policy(cmp))).round().tolist()  # of 9 action pairs from the left end
[5.0, 3.0, 1.0, 0.0]
"""
from __future__ import annotations

import itertools

import torch

from umrl.theory.cmp import DeterministicCMP, reachable_at
from umrl.validation import InvalidValue


def check_policy(cmp: DeterministicCMP, policy: torch.Tensor, name: str = "policy") -> torch.Tensor:
    """``policy`` if it is ``[..., T, S, A]`` float64 with rows on the simplex, else an error naming ``name``."""
    shape = (cmp.horizon, cmp.num_states, cmp.num_actions)
    if not isinstance(policy, torch.Tensor) or policy.dtype != torch.float64 or tuple(policy.shape[-3:]) != shape:
        raise InvalidValue(name, policy, f"a float64 tensor [..., {shape[0]}, {shape[1]}, {shape[2]}] ([..., T, S, A])")
    if (policy < 0).any() or not torch.allclose(policy.sum(-1), torch.ones((), dtype=torch.float64), atol=1e-9):
        raise InvalidValue(name, policy, "non-negative action probabilities summing to 1 over the last dimension")
    return policy


def uniform_policy(cmp: DeterministicCMP) -> torch.Tensor:
    """Uniformly random actions at every state and step, ``[T, S, A]``."""
    return torch.full((cmp.horizon, cmp.num_states, cmp.num_actions), 1.0 / cmp.num_actions, dtype=torch.float64)


def state_marginals(cmp: DeterministicCMP, policy: torch.Tensor) -> torch.Tensor:
    """``rho[..., t, s] = P(s_t = s)`` for ``t = 0 .. T``, ``[..., T+1, S]``, for a policy ``[..., T, S, A]``."""
    return propagate(cmp, check_policy(cmp, policy))


def propagate(cmp: DeterministicCMP, policy: torch.Tensor) -> torch.Tensor:
    """:func:`state_marginals` without the input check (for inner loops over policies already known valid)."""
    successors = cmp.next_state.flatten()
    rho = torch.zeros(*policy.shape[:-3], cmp.num_states, dtype=torch.float64)
    rho[..., cmp.start] = 1.0
    marginals = [rho]
    for t in range(cmp.horizon):
        # P(s_{t+1} = s') = sum_{s, a: next(s, a) = s'} P(s_t = s) pi(a | s, t)
        flow = (rho.unsqueeze(-1) * policy[..., t, :, :]).flatten(-2)
        rho = torch.zeros_like(rho).index_add(-1, successors, flow)
        marginals.append(rho)
    return torch.stack(marginals, dim=-2)


def terminal_marginal(cmp: DeterministicCMP, policy: torch.Tensor) -> torch.Tensor:
    """``rho_pi^T``: the distribution of the last state ``s_T``, ``[..., S]``, for a policy ``[..., T, S, A]``."""
    return state_marginals(cmp, policy)[..., -1, :]



def terminal_marginal_by_enumeration(cmp: DeterministicCMP, policy: torch.Tensor) -> torch.Tensor:
    """``rho_pi^T`` ``[S]`` summed over every action sequence (``A**T`` of them; for checks on tiny CMPs)."""
    policy = check_policy(cmp, policy)
    if policy.dim() != 3:
        raise InvalidValue("policy", policy, "one policy [T, S, A] (no latent dimension)")
    rho = torch.zeros(cmp.num_states, dtype=torch.float64)
    for actions in itertools.product(range(cmp.num_actions), repeat=cmp.horizon):
        state, probability = cmp.start, 1.0
        for t, action in enumerate(actions):
            probability *= float(policy[t, state, action])
            state = int(cmp.next_state[state, action])
        rho[state] += probability
    return rho


def policy_for_marginal(cmp: DeterministicCMP, rho: torch.Tensor) -> torch.Tensor:
    """A time-dependent Markov policy ``[T, S, A]`` whose terminal marginal is ``rho`` ``[S]``.

    ``rho`` must be a distribution supported on the states reachable at T. Construction: for every goal ``g`` take one
    shortest-to-compute action sequence reaching it at T (breadth-first, deterministic dynamics) and mix these open-loop
    plans with weights ``rho[g]``; the mixture's state-action occupancies ``occ[t, s, a]`` define
    ``pi(a | s, t) = occ[t, s, a] / sum_a occ[t, s, a]``, which has the same per-step state marginals as the mixture
    (the Markov policy built from a history-dependent one's occupancies; Puterman, Thm 5.5.1). Hence the set of
    achievable terminal marginals is the whole simplex over the reachable set. Unvisited states get uniform actions.
    """
    reachable = reachable_at(cmp)
    if (rho.dtype != torch.float64 or tuple(rho.shape) != (cmp.num_states,) or (rho < 0).any()
            or abs(float(rho.sum()) - 1) > 1e-9 or (rho[~reachable] > 0).any()):
        raise InvalidValue("rho", rho, f"a float64 distribution [{cmp.num_states}] on the states reachable at T")
    occupancy = torch.zeros(cmp.horizon, cmp.num_states, cmp.num_actions, dtype=torch.float64)
    for goal, plan in _plans(cmp).items():
        state = cmp.start
        for t, action in enumerate(plan):
            occupancy[t, state, action] += rho[goal]
            state = int(cmp.next_state[state, action])
    visits = occupancy.sum(-1, keepdim=True)
    uniform = torch.full_like(occupancy, 1.0 / cmp.num_actions)
    return torch.where(visits > 0, occupancy / visits.clamp(min=1e-300), uniform)


def _plans(cmp: DeterministicCMP) -> dict[int, tuple[int, ...]]:
    """One action sequence of length T reaching each state reachable at T (first found by breadth over steps)."""
    plans: dict[int, tuple[int, ...]] = {cmp.start: ()}
    for _ in range(cmp.horizon):
        following: dict[int, tuple[int, ...]] = {}
        for state, plan in plans.items():
            for action in range(cmp.num_actions):
                following.setdefault(int(cmp.next_state[state, action]), plan + (action,))
        plans = following
    return plans
