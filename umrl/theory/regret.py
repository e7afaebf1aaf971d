"""Regret of the learning procedure f_pi on goal-reaching tasks, and the exploration marginals that minimise it.

f_pi explores with pi until an episode ends on the goal g, then repeats that episode: it loses one unit per episode
before the first success, so its regret on goal g is the hitting time, geometric with mean ``1 / rho(g)`` for the
terminal marginal ``rho = rho_pi^T``. On a goal distribution ``p`` (vectors ``[..., S]`` over states):

* :func:`regret` -- ``sum_g p(g) / rho(g)`` (the paper's Eq. 3), infinite when ``p`` puts mass where ``rho`` has none;
* :func:`worst_case_regret` -- its maximum over goal distributions on a support (the reachable set S_T): the
  objective is linear in ``p``, so the maximum is at a vertex, the Dirac on the least-visited goal: ``1 / min rho``;
* :func:`optimal_marginal` -- the closed form ``sqrt(p) / sum sqrt(p)`` (Eq. 4), and :func:`minimise_regret`, a
  generic solver of the same convex problem (mirror descent on the simplex over S_T) to check it against.

>>> rho = torch.tensor([0.5, 0.25, 0.25], dtype=torch.float64)
>>> regret(rho, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)).item()
4.0
>>> worst_case_regret(rho).item(), worst_case_regret(torch.full((3,), 1 / 3, dtype=torch.float64)).item()
(4.0, 3.0)
"""
from __future__ import annotations

import torch

from umrl.validation import InvalidValue, check_int, check_positive


def check_distribution(name: str, value: torch.Tensor, size: int | None = None) -> torch.Tensor:
    """``value`` if it is a float64 tensor ``[..., size]`` of non-negative entries summing to 1 over the last axis."""
    expected = f"a float64 probability vector [..., {size or 'S'}] (non-negative, summing to 1)"
    if (not isinstance(value, torch.Tensor) or value.dtype != torch.float64 or value.dim() == 0
            or (size is not None and value.shape[-1] != size)):
        raise InvalidValue(name, value, expected)
    if (value < 0).any() or not torch.allclose(value.sum(-1), torch.ones((), dtype=torch.float64), atol=1e-9):
        raise InvalidValue(name, value, expected)
    return value


def _support(rho: torch.Tensor, support: torch.Tensor | None) -> torch.Tensor:
    if support is None:
        return torch.ones(rho.shape[-1], dtype=torch.bool)
    if support.dtype != torch.bool or tuple(support.shape) != (rho.shape[-1],) or not support.any():
        raise InvalidValue("support", support, f"a non-empty bool mask [{rho.shape[-1]}] over states")
    return support


def regret(rho: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Expected hitting time ``sum_g p(g) / rho(g)`` of f_pi with terminal marginal ``rho`` on goals ``p``; ``[...]``.

    Goals with ``p(g) = 0`` contribute nothing (also where ``rho(g) = 0``); ``p(g) > 0 = rho(g)`` gives ``inf``.
    """
    check_distribution("rho", rho)
    check_distribution("p", p, rho.shape[-1])
    ratio = torch.where(p > 0, p / rho, torch.zeros((), dtype=torch.float64))
    return ratio.sum(-1)


def regret_within(rho: torch.Tensor, p: torch.Tensor, episodes: int) -> torch.Tensor:
    """Expected hitting time capped at K = ``episodes``: ``sum_g p(g) (1 - (1 - rho(g))^K) / rho(g)``, ``[...]``.

    The hitting time H (episodes up to and including the first one ending on g) is geometric with success
    probability ``rho(g)``, and ``E[min(H, K)] = sum_{k<K} P(H > k)``; as K grows this tends to :func:`regret`.
    """
    check_distribution("rho", rho)
    check_distribution("p", p, rho.shape[-1])
    episodes = check_int("episodes", episodes, min=1)
    miss = 1 - rho
    per_goal = torch.where(rho > 0, (1 - miss ** episodes) / rho.clamp(min=1e-300),
                           torch.full_like(rho, float(episodes)))
    return (p * per_goal).sum(-1)


def worst_case_regret(rho: torch.Tensor, support: torch.Tensor | None = None) -> torch.Tensor:
    """``max_p regret(rho, p)`` over goal distributions on ``support`` ``[S]`` (default all states): ``1 / min rho``."""
    check_distribution("rho", rho)
    return 1.0 / rho[..., _support(rho, support)].min(-1).values


def worst_case_goal(rho: torch.Tensor, support: torch.Tensor | None = None) -> torch.Tensor:
    """The maximiser of :func:`worst_case_regret`: a Dirac ``[S]`` on the least-visited state of ``support``."""
    check_distribution("rho", rho)
    if rho.dim() != 1:
        raise InvalidValue("rho", rho, "one marginal [S]")
    masked = torch.where(_support(rho, support), rho, torch.full_like(rho, float("inf")))
    return torch.nn.functional.one_hot(masked.argmin(), rho.shape[-1]).double()


def optimal_marginal(p: torch.Tensor) -> torch.Tensor:
    """Eq. 4: the terminal marginal minimising :func:`regret` for known goals ``p``, ``sqrt(p) / sum sqrt(p)``."""
    root = check_distribution("p", p).sqrt()
    return root / root.sum(-1, keepdim=True)


def minimise_regret(p: torch.Tensor, support: torch.Tensor, *, tol: float = 1e-14, max_steps: int = 100_000
                    ) -> torch.Tensor:
    """``argmin_rho regret(rho, p)`` over distributions ``rho`` on ``support`` ``[S]``, by mirror descent; ``[S]``.

    Why this set: on a deterministic CMP every distribution on the states reachable at T (``support`` =
    :func:`~umrl.theory.cmp.reachable_at`) is the terminal marginal of some time-dependent Markov policy (mix one
    open-loop plan per goal, :func:`~umrl.theory.marginals.policy_for_marginal`), and no policy puts mass elsewhere.
    Minimising over policies is therefore the convex problem ``min sum p / rho`` on that simplex, whatever the
    (non-convex) policy parametrisation. ``p`` must be on ``support``.

    The solver knows nothing of the closed form: exponentiated-gradient steps ``rho <- rho exp(-eta grad)`` with a
    backtracking step size (the step is accepted when the objective is below its linearisation plus
    ``KL(rho' || rho) / eta``), stopped when the Frank-Wolfe gap ``max_g p/rho^2 - regret``, an upper bound on the
    suboptimality, is below ``tol`` times the regret, or when no step decreases the regret any more (rounding).
    """
    check_distribution("p", p, support.shape[-1])
    if p.dim() != 1 or (p[~_support(p, support)] > 0).any():
        raise InvalidValue("p", p, "one goal distribution [S] supported on the reachable states")
    check_positive("tol", tol)
    check_int("max_steps", max_steps, min=1)
    log_rho = torch.where(support, 0.0, -torch.inf).double()
    log_rho = log_rho - log_rho.logsumexp(0)
    eta = 1.0

    def objective(log_r: torch.Tensor) -> torch.Tensor:
        return (p * (-log_r).exp()).where(p > 0, torch.zeros((), dtype=torch.float64)).sum()

    value = objective(log_rho)
    for _ in range(max_steps):
        rho = log_rho.exp()
        descent = torch.where(support, p / rho.clamp(min=1e-300) ** 2, torch.zeros((), dtype=torch.float64))
        if descent.max() - value <= tol * value:
            break
        for _ in range(200):  # halvings of eta; a step that rounding keeps from passing the test ends the descent
            candidate = log_rho + eta * descent
            candidate = candidate - candidate.logsumexp(0)
            new_rho = candidate.exp()
            kl = (new_rho * (candidate - log_rho)).where(support, torch.zeros((), dtype=torch.float64)).sum()
            new_value = objective(candidate)
            if new_value <= value - (descent * (new_rho - rho)).sum() + kl / eta:
                break
            eta /= 2
        if not new_value < value:
            break
        log_rho, value, eta = candidate, new_value, eta * 1.5
    return log_rho.exp()
