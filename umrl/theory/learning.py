"""The learning procedure f_pi, run episode by episode on a deterministic CMP, to check its closed-form regret.

f_pi explores with the (time-dependent) policy pi until an episode ends on the goal, then replays that episode's
action sequence in every later episode; the dynamics being deterministic, every replay ends on the goal. It keeps no
other memory (the paper's memoryless learners: a policy-gradient step on zero rewards changes nothing). Its regret on
a goal is the hitting time, the number of episodes up to and including the first rewarded one.
:func:`simulate_regret` samples it: a Monte-Carlo check of :func:`umrl.theory.regret.regret_within`, never a
substitute for it.

>>> from umrl.theory.cmp import chain
>>> from umrl.theory.marginals import uniform_policy
>>> cmp = chain(3, horizon=1)
>>> rewards = simulate_learning(cmp, uniform_policy(cmp), torch.tensor([1, 0]), episodes=30, seed=0)
>>> rewards.shape
torch.Size([2, 30])
>>> first = rewards.argmax(1)  # once the goal is found it is reached in every later episode
>>> all(bool(rewards[run, first[run]:].all()) for run in range(2))
True
"""
from __future__ import annotations

import torch

from umrl.theory.cmp import DeterministicCMP
from umrl.theory.marginals import check_policy
from umrl.validation import InvalidValue, check_int


def simulate_learning(cmp: DeterministicCMP, policy: torch.Tensor, goals: torch.Tensor, *, episodes: int,
                      seed: int) -> torch.Tensor:
    """Rewards ``1(s_T = goal)`` of f_pi, ``[runs, episodes]`` float64, one independent run per entry of ``goals``.

    ``policy`` ``[T, S, A]`` picks the actions (sampled with a ``torch.Generator`` seeded with ``seed``) until a run's
    first rewarded episode; from then on that run replays the rewarded action sequence.
    """
    policy = check_policy(cmp, policy)
    if policy.dim() != 3:
        raise InvalidValue("policy", policy, "one policy [T, S, A]")
    if goals.dtype != torch.long or goals.dim() != 1 or goals.min() < 0 or goals.max() >= cmp.num_states:
        raise InvalidValue("goals", goals, f"a long tensor [runs] of states in [0, {cmp.num_states - 1}]")
    check_int("episodes", episodes, min=1)
    generator = torch.Generator().manual_seed(check_int("seed", seed, min=0))
    runs = goals.shape[0]
    plans = torch.zeros(runs, cmp.horizon, dtype=torch.long)
    found = torch.zeros(runs, dtype=torch.bool)
    rewards = torch.zeros(runs, episodes, dtype=torch.float64)
    for k in range(episodes):
        states = torch.full((runs,), cmp.start, dtype=torch.long)
        actions = torch.empty(runs, cmp.horizon, dtype=torch.long)
        for t in range(cmp.horizon):
            # inverse-CDF sampling of a_t ~ policy[t, s_t] for all runs at once
            uniform = torch.rand(runs, 1, generator=generator, dtype=torch.float64)
            explored = (policy[t, states].cumsum(1) <= uniform).sum(1).clamp(max=cmp.num_actions - 1)
            actions[:, t] = torch.where(found, plans[:, t], explored)
            states = cmp.next_state[states, actions[:, t]]
        hit = states == goals
        plans[hit & ~found] = actions[hit & ~found]
        found |= hit
        rewards[:, k] = hit.double()
    return rewards


def simulate_regret(cmp: DeterministicCMP, policy: torch.Tensor, p: torch.Tensor, *, episodes: int, runs: int,
                    seed: int) -> torch.Tensor:
    """Hitting times of f_pi capped at ``episodes``, ``[runs]`` float64; each run's goal is drawn from ``p`` ``[S]``.

    A run counts the episodes up to and including the first rewarded one (``episodes`` if none is); the mean
    estimates ``regret_within(terminal_marginal(cmp, policy), p, episodes)``.
    """
    check_int("runs", runs, min=1)
    generator = torch.Generator().manual_seed(check_int("seed", seed, min=0))
    goals = torch.multinomial(p, runs, replacement=True, generator=generator)
    rewards = simulate_learning(cmp, policy, goals, episodes=episodes, seed=seed + 1)
    rewarded = rewards.any(1)
    return torch.where(rewarded, rewards.argmax(1) + 1.0, float(episodes)).double()
