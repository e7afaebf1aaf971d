"""The MI task proposal: latent-conditioned tabular policies maximising I(s_T; z), by exact gradient ascent.

With a uniform prior over ``Z`` latents and a policy ``[Z, T, S, A]``, the conditionals ``mu(s_T | z)`` ``[Z, S]`` come
from the exact dynamic programme (:func:`~umrl.theory.marginals.terminal_marginal`), so ``I(s_T; z)`` and its gradient
with respect to the policy logits are exact; :func:`maximise_mutual_information` ascends it with Adam steps.

For a fixed prior, I is convex in the conditionals, so its maximum over the achievable conditionals (any distribution
on the reachable set S_T, for each z) is at a deterministic assignment z -> s_z, where I = H(s_T); the best
assignment spreads the latents as evenly as possible over min(Z, |S_T|) states: :func:`max_mutual_information`.

>>> round(max_mutual_information(4, 4), 6) == round(math.log(4), 6)
True
>>> max_mutual_information(5, 4) < math.log(4)  # 5 latents cannot cover 4 states evenly
True
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from umrl.theory.cmp import DeterministicCMP
from umrl.theory.marginals import propagate
from umrl.validation import InvalidValue, check_float, check_int, check_positive


def mutual_information(conditionals: torch.Tensor, prior: torch.Tensor | None = None) -> torch.Tensor:
    """``I(s; z) = sum_z p(z) sum_s mu(s|z) log(mu(s|z) / mu(s))`` in nats for ``conditionals`` ``[Z, S]``.

    ``prior`` ``[Z]`` defaults to uniform. Differentiable; ``0 log 0 = 0``.
    """
    if conditionals.dim() != 2:
        raise InvalidValue("conditionals", conditionals, "a tensor [Z, S] of distributions over states")
    if prior is None:
        prior = torch.full(conditionals.shape[:1], 1.0 / conditionals.shape[0], dtype=conditionals.dtype)
    marginal = prior @ conditionals
    log_ratio = conditionals.clamp(min=1e-300).log() - marginal.clamp(min=1e-300).log()
    return (prior.unsqueeze(1) * torch.where(conditionals > 0, conditionals * log_ratio, 0.0)).sum()


def max_mutual_information(num_latents: int, num_goals: int) -> float:
    """``max I(s_T; z)`` over conditionals on ``num_goals`` states with a uniform prior on ``num_latents`` latents.

    The entropy of the most even split of the latents over ``min(num_latents, num_goals)`` states: ``log Z`` when
    Z <= |S_T|, ``log |S_T|`` when |S_T| divides Z, and strictly less otherwise.
    """
    z, n = check_int("num_latents", num_latents, min=1), check_int("num_goals", num_goals, min=1)
    counts = [z // n + (i < z % n) for i in range(n)]
    return -sum(c / z * math.log(c / z) for c in counts if c)


@dataclass
class MIProposal:
    """A trained MI proposal: ``policy`` ``[Z, T, S, A]``, ``conditionals`` ``mu(s_T | z)`` ``[Z, S]`` (or over
    trajectories, ``[Z, K]``), their ``marginal`` ``[S]`` (or ``[K]``) and ``mutual_information`` (nats) at the end of the ascent."""

    policy: torch.Tensor
    conditionals: torch.Tensor
    marginal: torch.Tensor
    mutual_information: float

    def rewards(self) -> torch.Tensor:
        """The proposal's tasks ``r_z(s_T) = log mu(s_T | z)``, ``[Z, S]`` (``-inf`` where ``mu(s_T | z) = 0``)."""
        return self.conditionals.log()


def conditional_entropy(conditionals: torch.Tensor) -> torch.Tensor:
    """``H(s | z)`` in nats for ``conditionals`` ``[Z, S]`` under a uniform prior; differentiable."""
    plogp = torch.where(conditionals > 0, conditionals * conditionals.clamp(min=1e-300).log(), 0.0)
    return -plogp.sum(1).mean()


def maximise_mutual_information(cmp: DeterministicCMP, num_latents: int, *, steps: int = 600, lr: float = 0.3,
                                anneal_fraction: float = 0.5, seed: int = 0,
                                outcome: Callable[[torch.Tensor], torch.Tensor] | None = None) -> MIProposal:
    """Ascend ``I(s_T; z)`` over the logits ``[Z, T, S, A]`` of a latent-conditioned softmax policy (uniform prior).

    ``outcome`` maps a policy ``[Z, T, S, A]`` to the conditionals ``[Z, K]`` whose MI is maximised; the default is
    the terminal marginal (K = S). :func:`umrl.theory.trajectories.maximise_trajectory_information` passes the
    distribution over length-T trajectories instead.

    I is convex in the conditionals, and softmax logits turn its escape directions from a collision (two latents on
    one state while another state is free) into vanishing gradients, so plain ascent stops at such local maxima.
    The ascent therefore starts on ``H(s_T) = I + H(s_T | z)`` (concave in the conditionals: its maximum is a uniform
    marginal) and anneals the weight of ``H(s_T | z)`` linearly from 1 to 0 over the first ``anneal_fraction`` of
    the ``steps``; the rest is plain ascent on I. Logits start as standard normal draws (``seed``) to break the
    symmetry between latents. Softmax policies are never exactly deterministic, so I approaches its maximum from below.
    """
    check_int("num_latents", num_latents, min=1)
    check_int("steps", steps, min=1)
    check_positive("lr", lr)
    check_float("anneal_fraction", anneal_fraction, ge=0, le=1)
    generator = torch.Generator().manual_seed(check_int("seed", seed, min=0))
    outcome = outcome or (lambda policy: propagate(cmp, policy)[..., -1, :])
    logits = torch.randn(num_latents, cmp.horizon, cmp.num_states, cmp.num_actions, generator=generator,
                         dtype=torch.float64).requires_grad_()
    anneal = int(anneal_fraction * steps)
    first, second = torch.zeros_like(logits), torch.zeros_like(logits)
    for step in range(steps):
        conditionals = outcome(logits.softmax(-1))
        beta = max(0.0, 1.0 - step / anneal) if anneal else 0.0
        objective = mutual_information(conditionals) + beta * conditional_entropy(conditionals)
        (gradient,) = torch.autograd.grad(objective, logits)
        with torch.no_grad():  # Adam's ascent step (betas 0.9, 0.999), written out: the first
            # step of torch.optim.Adam costs seconds of one-time setup, longer than a whole ascent here
            first.mul_(0.9).add_(gradient, alpha=0.1)
            second.mul_(0.999).addcmul_(gradient, gradient, value=0.001)
            unbiased = first / (1 - 0.9 ** (step + 1))
            logits += lr * unbiased / ((second / (1 - 0.999 ** (step + 1))).sqrt() + 1e-8)
    with torch.no_grad():
        policy = logits.softmax(-1)
        conditionals = outcome(policy)
        value = float(mutual_information(conditionals))
    return MIProposal(policy, conditionals, conditionals.mean(0), value)

