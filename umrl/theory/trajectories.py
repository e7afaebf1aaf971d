"""Trajectory matching on a deterministic CMP: distributions over the length-T state sequences from the start.

A trajectory is a state sequence ``(s_0, ..., s_T)``; several action sequences may produce the same one (a move into
a wall and "stay"), and a task ``r(tau) = 1(tau = tau*)`` cannot tell them apart. :func:`enumerate_trajectories` lists
the distinct ones ``[K, T+1]``; :func:`trajectory_probabilities` gives a policy's exact distribution over them ``[K]``,
to which :mod:`umrl.theory.regret` applies unchanged (goals = trajectories, hitting time ``1 / pi(tau)``).

Any distribution over trajectories is the law of some history-dependent policy (trajectories form a tree: choose each
branch with its conditional probability). A Markov time-dependent policy has fewer: its law factorises through
``(t, s_t)``. The uniform law is Markov nonetheless, since the number of continuations of a prefix depends only on
``(t, s_t)`` (:func:`uniform_trajectory_policy`).

>>> from umrl.theory.cmp import chain
>>> cmp = chain(3, horizon=2)
>>> enumerate_trajectories(cmp).tolist()
[[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [0, 1, 2]]
>>> law = trajectory_probabilities(cmp, uniform_trajectory_policy(cmp), enumerate_trajectories(cmp))
>>> (5 * law).round(decimals=12).tolist()
[1.0, 1.0, 1.0, 1.0, 1.0]
"""
from __future__ import annotations

import torch

from umrl.theory.cmp import DeterministicCMP
from umrl.theory.marginals import check_policy
from umrl.theory.mutual_information import MIProposal, maximise_mutual_information
from umrl.validation import InvalidValue


def enumerate_trajectories(cmp: DeterministicCMP) -> torch.Tensor:
    """The distinct state sequences of length T+1 from the start, ``[K, T+1]`` long, in lexicographic order."""
    paths = [(cmp.start,)]
    for _ in range(cmp.horizon):
        paths = [path + (nxt,) for path in paths for nxt in sorted(set(cmp.next_state[path[-1]].tolist()))]
    return torch.tensor(paths, dtype=torch.long)


def trajectory_probabilities(cmp: DeterministicCMP, policy: torch.Tensor, trajectories: torch.Tensor) -> torch.Tensor:
    """``pi(tau)`` for each of ``trajectories`` ``[K, T+1]`` under ``policy`` ``[..., T, S, A]``, ``[..., K]``.

    ``pi(tau) = prod_t sum_{a: next(s_t, a) = s_{t+1}} pi(a | s_t, t)``; differentiable in ``policy``.
    """
    policy = check_policy(cmp, policy)
    if trajectories.dim() != 2 or trajectories.shape[1] != cmp.horizon + 1:
        raise InvalidValue("trajectories", trajectories, f"a long tensor [K, {cmp.horizon + 1}] of state sequences")
    probability = torch.ones(*policy.shape[:-3], trajectories.shape[0], dtype=torch.float64)
    for t in range(cmp.horizon):
        here, there = trajectories[:, t], trajectories[:, t + 1]
        moves = (cmp.next_state[here] == there.unsqueeze(1)).double()  # [K, A]: actions taking s_t to s_{t+1}
        probability = probability * (policy[..., t, here, :] * moves).sum(-1)
    return probability


def uniform_trajectory_policy(cmp: DeterministicCMP) -> torch.Tensor:
    """A Markov time-dependent policy ``[T, S, A]`` whose law is uniform over the distinct trajectories.

    With ``N(t, s)`` the number of distinct continuations from state ``s`` at step ``t`` (``N(T, s) = 1``), it moves
    to each distinct successor ``s'`` with probability ``N(t+1, s') / N(t, s)``, split evenly between the actions
    leading there; every trajectory then has probability ``1 / N(0, start)``.
    """
    counts = torch.ones(cmp.horizon + 1, cmp.num_states, dtype=torch.float64)
    distinct = torch.nn.functional.one_hot(cmp.next_state, cmp.num_states).amax(1).double()  # [S, S]: s -> s'
    for t in reversed(range(cmp.horizon)):
        counts[t] = distinct @ counts[t + 1]
    duplicates = (cmp.next_state.unsqueeze(2) == cmp.next_state.unsqueeze(1)).sum(2)  # [S, A]: actions to same s'
    return counts[1:, cmp.next_state] / counts[:-1].unsqueeze(2) / duplicates


def maximise_trajectory_information(cmp: DeterministicCMP, num_latents: int, **ascent) -> MIProposal:
    """Ascend ``I(tau; z)`` over latent-conditioned policies ``[Z, T, S, A]``; the proposal's ``conditionals`` are
    ``mu(tau | z)`` ``[Z, K]`` over :func:`enumerate_trajectories`. Keyword arguments go to
    :func:`~umrl.theory.mutual_information.maximise_mutual_information`.
    """
    trajectories = enumerate_trajectories(cmp)
    return maximise_mutual_information(
        cmp, num_latents, outcome=lambda policy: trajectory_probabilities(cmp, policy, trajectories), **ascent)
