"""Task proposals on a deterministic CMP as reward tables over terminal states, and the exploration they induce.

A proposal is a set of tasks ``r_z(s_T)`` (a table ``[Z, S]``) with a prior over ``z``. Its task marginal ``q``
(:func:`optimal_policy_marginal`) is where its tasks' optimal policies end: the goal distribution a learner
meta-trained on the proposal is trained for. Meta-learning over the learners f_pi minimises the regret
``sum_g q(g) / rho(g)`` on those goals, so in the analysis' limit the learner explores with the Eq. 4 marginal
``sqrt(q) / sum sqrt(q)`` (:func:`meta_learned_marginal`). Exploring with ``q`` itself (posterior sampling: draw a
task, act as its optimal policy) is the same learner only when ``q`` is uniform on its support, and otherwise has
more regret on the proposal's own goals (``|supp q|`` against ``(sum sqrt q)^2``). Proposals compared:

* the MI-optimal one, ``r_z = log mu(s_T | z)`` (:class:`~umrl.theory.mutual_information.MIProposal`);
* a frozen random discriminator, ``r_z(s) = log softmax(W[s])_z`` for random logits ``W`` ``[S, Z]``
  (:func:`random_discriminator_rewards`, the UML-random proposal);
* hand-designed goals, ``r_z(s) = 1(s = g_z)`` (:func:`goal_rewards`), e.g. the far goals of :func:`far_goals`.

>>> from umrl.theory.cmp import chain
>>> cmp = chain(5, horizon=2)
>>> rewards = goal_rewards([2, 2, 1], cmp.num_states)
>>> optimal_policy_marginal(cmp, rewards).tolist()
[0.0, 0.3333333333333333, 0.6666666666666666, 0.0, 0.0]
>>> [round(x, 4) for x in meta_learned_marginal(cmp, rewards).tolist()]  # sqrt(1/3) : sqrt(2/3)
[0.0, 0.4142, 0.5858, 0.0, 0.0]
"""
from __future__ import annotations

import torch

from umrl.theory.cmp import DeterministicCMP, reachable_at
from umrl.theory.marginals import terminal_marginal, uniform_policy
from umrl.theory.regret import optimal_marginal
from umrl.validation import InvalidValue, check_float, check_int


def optimal_policy_marginal(cmp: DeterministicCMP, rewards: torch.Tensor, prior: torch.Tensor | None = None, *,
                            temperature: float = 0.0) -> torch.Tensor:
    """The task marginal ``q`` ``[S]``: the tasks' optimal policies' terminal marginals, mixed over ``prior`` ``[Z]``
    (default uniform). It is the posterior-sampling learner's exploration marginal, not the meta-learned one's
    (:func:`meta_learned_marginal`).

    ``rewards`` ``[Z, S]`` are terminal rewards (``-inf`` allowed). With ``temperature`` 0 each task's optimal
    policies go to a best reachable state (ties split evenly). With ``temperature`` alpha > 0 they are the
    maximum-entropy optimal policies (SAC's objective, entropy of each action weighted by alpha): on deterministic
    dynamics these make every action sequence ending in ``s`` as likely as ``exp(r_z(s) / alpha)``, so
    ``mu(s | z)`` is proportional to ``n(s) exp(r_z(s) / alpha)``, ``n(s)`` the number of action sequences reaching ``s``.
    """
    if rewards.dim() != 2 or rewards.shape[1] != cmp.num_states or rewards.dtype != torch.float64:
        raise InvalidValue("rewards", rewards, f"a float64 tensor [Z, {cmp.num_states}] of terminal rewards")
    temperature = check_float("temperature", temperature, ge=0)
    if prior is None:
        prior = torch.full(rewards.shape[:1], 1.0 / rewards.shape[0], dtype=torch.float64)
    reachable = reachable_at(cmp)
    masked = torch.where(reachable, rewards, -torch.inf)
    if temperature == 0:
        best = masked.max(1, keepdim=True).values
        ties = (masked >= best - 1e-12) & reachable
        conditionals = ties.double() / ties.sum(1, keepdim=True)
    else:
        log_paths = terminal_marginal(cmp, uniform_policy(cmp)).log()  # log n(s) up to a constant
        conditionals = (masked / temperature + log_paths).softmax(1)
    return prior @ conditionals


def meta_learned_marginal(cmp: DeterministicCMP, rewards: torch.Tensor, prior: torch.Tensor | None = None, *,
                          temperature: float = 0.0) -> torch.Tensor:
    """Exploration marginal ``[S]`` of the learner meta-trained on the proposal: Eq. 4 for its task marginal ``q``.

    ``sqrt(q) / sum sqrt(q)`` with ``q = optimal_policy_marginal(cmp, rewards, prior, temperature=temperature)``
    (arguments as there): the f_pi with least regret on goals drawn from ``q``. It is achievable, ``q`` being
    supported on the states reachable at T (:func:`~umrl.theory.marginals.policy_for_marginal`).
    """
    return optimal_marginal(optimal_policy_marginal(cmp, rewards, prior, temperature=temperature))


def random_discriminator_rewards(num_states: int, num_latents: int, *, seed: int, scale: float = 1.0) -> torch.Tensor:
    """``r_z(s) = log softmax_z(W[s])`` for a frozen ``W`` ``[S, Z]`` of normal draws times ``scale``; ``[Z, S]``."""
    check_int("num_states", num_states, min=1)
    check_int("num_latents", num_latents, min=1)
    generator = torch.Generator().manual_seed(check_int("seed", seed, min=0))
    logits = check_float("scale", scale, gt=0) * torch.randn(num_states, num_latents, generator=generator,
                                                             dtype=torch.float64)
    return logits.log_softmax(1).T.contiguous()


def goal_rewards(goals: list[int], num_states: int) -> torch.Tensor:
    """One goal-reaching task per entry of ``goals``: ``r_z(s) = 1(s = goals[z])``, ``[Z, S]``."""
    if not goals or any(not 0 <= g < num_states for g in goals):
        raise InvalidValue("goals", goals, f"a non-empty list of states in [0, {num_states - 1}]")
    return torch.nn.functional.one_hot(torch.tensor(goals), num_states).double()


def far_goals(cmp: DeterministicCMP) -> list[int]:
    """The states reachable at T that are farthest (in steps) from the start: a designer's "far away" goals."""
    distance = torch.full((cmp.num_states,), cmp.num_states, dtype=torch.long)
    for step in range(cmp.horizon + 1):
        distance[reachable_at(cmp, step) & (distance > step)] = step
    reachable = reachable_at(cmp)
    farthest = distance[reachable].max()
    return (reachable & (distance == farthest)).nonzero().flatten().tolist()
