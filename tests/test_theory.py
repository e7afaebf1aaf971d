"""Exact checks of the goal-reaching and trajectory-matching analysis on small deterministic CMPs."""
import itertools
import math

import pytest
import torch

from umrl.theory import (
    chain,
    compare_proposals,
    enumerate_trajectories,
    goal_rewards,
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
    simulate_learning,
    simulate_regret,
    slip_policy,
    state_marginals,
    terminal_marginal,
    terminal_marginal_by_enumeration,
    trajectory_probabilities,
    tree,
    uniform_policy,
    uniform_trajectory_policy,
    worst_case_goal,
    worst_case_regret,
    worst_case_under_slips,
)
from umrl.validation import InvalidValue

WALLED = grid(3, 3, 3, walls=((1, 1),))


def random_policy(cmp, *batch, seed=0):
    generator = torch.Generator().manual_seed(seed)
    logits = 2 * torch.randn(*batch, cmp.horizon, cmp.num_states, cmp.num_actions, generator=generator,
                             dtype=torch.float64)
    return logits.softmax(-1)


def dirichlet(n, seed, concentration=1.0):
    torch.manual_seed(seed)
    return torch.distributions.Dirichlet(torch.full((n,), concentration, dtype=torch.float64)).sample()


def on_reachable(cmp, values):
    out = torch.zeros(cmp.num_states, dtype=torch.float64)
    out[reachable_at(cmp)] = values
    return out


@pytest.mark.parametrize("cmp", [WALLED, chain(4, 3), tree(2, 3), random_cmp(6, 3, 3, seed=1)], ids=lambda c: c.name)
def test_dynamic_programme_matches_enumeration_of_action_sequences(cmp):
    policy = random_policy(cmp)
    rho = terminal_marginal(cmp, policy)
    assert torch.allclose(rho, terminal_marginal_by_enumeration(cmp, policy), atol=1e-14)
    assert set(rho.nonzero().flatten().tolist()) <= set(reachable_at(cmp).nonzero().flatten().tolist())
    # a batch of latent-conditioned policies gives each policy's own marginals
    batch = random_policy(cmp, 3, seed=1)
    assert torch.allclose(state_marginals(cmp, batch)[1], state_marginals(cmp, batch[1]))


def test_reachable_sets_of_the_families():
    assert reachable_at(chain(9, 4, start=4)).sum() == 9
    assert reachable_at(tree(3)).nonzero().flatten().tolist() == list(range(7, 15))
    assert not reachable_at(WALLED)[4]  # the wall cell
    assert reachable_at(WALLED).sum() == 7  # odd-parity cells need an odd number of moves, "stay" fixes parity


@pytest.mark.parametrize("seed", range(3))
def test_every_distribution_on_the_reachable_set_is_achievable(seed):
    cmp = random_cmp(8, 3, 3, seed=seed)
    target = on_reachable(cmp, dirichlet(int(reachable_at(cmp).sum()), seed))
    assert torch.allclose(terminal_marginal(cmp, policy_for_marginal(cmp, target)), target, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_eq4_closed_form_matches_the_mirror_descent_solver(seed):
    cmp = random_cmp(12, 3, 3, seed=seed)
    support = reachable_at(cmp)
    p = on_reachable(cmp, dirichlet(int(support.sum()), seed, concentration=0.5))
    solved = minimise_regret(p, support)
    closed = optimal_marginal(p)
    assert (solved - closed).abs().max() < 1e-9  # the bound docs/theory.md and the README quote
    assert regret(closed, p) <= regret(on_reachable(cmp, dirichlet(int(support.sum()), seed + 10)), p)
    # the optimum is achievable and the policy achieving it has the predicted regret
    achieved = terminal_marginal(cmp, policy_for_marginal(cmp, closed))
    assert torch.isclose(regret(achieved, p), p.sqrt().sum() ** 2)


def test_lemma1_uniform_marginal_is_minimax():
    cmp = WALLED
    support = reachable_at(cmp)
    n = int(support.sum())
    uniform = support.double() / n
    assert worst_case_regret(uniform, support) == pytest.approx(n)
    for seed in range(5):  # every goal distribution has the same regret under the uniform marginal
        assert regret(uniform, on_reachable(cmp, dirichlet(n, seed))) == pytest.approx(n)
    for seed in range(5):
        rho = terminal_marginal(cmp, policy_for_marginal(cmp, on_reachable(cmp, dirichlet(n, 100 + seed))))
        worst = worst_case_regret(rho, support)
        assert worst > n
        # the worst case is attained by a Dirac and no sampled goal distribution exceeds it
        diracs = [regret(rho, torch.eye(cmp.num_states, dtype=torch.float64)[g]) for g in support.nonzero().flatten()]
        assert max(diracs) == pytest.approx(float(worst))
        assert regret(rho, worst_case_goal(rho, support)) == pytest.approx(float(worst))
        assert all(regret(rho, on_reachable(cmp, dirichlet(n, s, 0.2))) <= worst for s in range(20))


def test_lemma2_mutual_information_with_as_many_latents_as_reachable_states():
    cmp = chain(4, 2)  # S_T = {0, 1, 2}
    support = reachable_at(cmp)
    for num_latents in (3, 6):
        mi = maximise_mutual_information(cmp, num_latents, steps=150)
        assert mi.mutual_information == pytest.approx(math.log(3), abs=1e-3)
        assert (mi.marginal[support] - 1 / 3).abs().max() < 1e-3
        assert mi.conditionals.max(1).values.min() > 0.99  # Dirac conditionals
        assert worst_case_regret(meta_learned_marginal(cmp, mi.rewards()), support) == pytest.approx(3)


def test_lemma2_fails_with_fewer_latents_or_a_number_not_divisible_by_the_reachable_states():
    cmp = chain(4, 2)
    support = reachable_at(cmp)
    few = maximise_mutual_information(cmp, 2, steps=150)
    assert few.mutual_information == pytest.approx(math.log(2), abs=1e-3)  # log |Z|, not log |S_T|
    assert torch.isinf(worst_case_regret(meta_learned_marginal(cmp, few.rewards()), support))
    odd = maximise_mutual_information(cmp, 4, steps=150)
    best = max_mutual_information(4, 3)  # split 2 + 1 + 1
    assert best < math.log(3) - 0.01
    assert odd.mutual_information == pytest.approx(best, abs=1e-3)
    # tasks on states split 2 + 1 + 1: q = (1/2, 1/4, 1/4); the Eq. 4 learner explores (sqrt 2, 1, 1) / (2 + sqrt 2)
    assert worst_case_regret(meta_learned_marginal(cmp, odd.rewards()), support) == pytest.approx(2 + math.sqrt(2))
    assert worst_case_regret(optimal_policy_marginal(cmp, odd.rewards()), support) == pytest.approx(4)  # posterior


def test_hitting_time_of_f_pi_matches_monte_carlo():
    cmp = WALLED
    policy = random_policy(cmp, seed=3)
    rho = terminal_marginal(cmp, policy)
    p = reachable_at(cmp).double() / reachable_at(cmp).sum()
    episodes, runs = 40, 4000
    hitting = simulate_regret(cmp, policy, p, episodes=episodes, runs=runs, seed=0)
    exact = float(regret_within(rho, p, episodes))
    assert abs(hitting.mean().item() - exact) < 4 * hitting.std().item() / math.sqrt(runs)
    assert regret_within(rho, p, 10**6) == pytest.approx(float(regret(rho, p)))
    # a run that found its goal reaches it in every later episode (the replay)
    rewards = simulate_learning(cmp, policy, torch.tensor([0, 2, 8] * 20), episodes=episodes, seed=1)
    first = rewards.argmax(1)
    assert all(bool(rewards[i, first[i]:].all()) for i in range(60) if rewards[i].any())


def test_random_discriminator_tasks_go_to_their_most_likely_states():
    cmp = WALLED
    support = reachable_at(cmp)
    rewards = random_discriminator_rewards(cmp.num_states, 7, seed=0)
    expected = torch.zeros(cmp.num_states, dtype=torch.float64)
    for z in range(7):
        expected[torch.where(support, rewards[z], -torch.inf).argmax()] += 1 / 7
    q = optimal_policy_marginal(cmp, rewards)
    assert torch.allclose(q, expected)
    # two tasks share a state, so another goal is never tried, whether the learner explores with q or sqrt(q)
    assert torch.isinf(worst_case_regret(q, support))
    assert torch.isinf(worst_case_regret(meta_learned_marginal(cmp, rewards), support))


def test_trajectory_law_and_lemma3():
    cmp = WALLED
    paths = enumerate_trajectories(cmp)
    policy = random_policy(cmp, seed=4)
    law = trajectory_probabilities(cmp, policy, paths)
    assert law.sum().item() == pytest.approx(1.0)
    # the trajectory law pushes forward to the terminal marginal
    pushed = torch.zeros(cmp.num_states, dtype=torch.float64).index_add(0, paths[:, -1], law)
    assert torch.allclose(pushed, terminal_marginal(cmp, policy))
    k = paths.shape[0]
    uniform = trajectory_probabilities(cmp, uniform_trajectory_policy(cmp), paths)
    assert torch.allclose(uniform, torch.full((k,), 1 / k, dtype=torch.float64))
    assert worst_case_regret(uniform) == pytest.approx(k)
    assert worst_case_regret(trajectory_probabilities(cmp, uniform_policy(cmp), paths)) > k
    p = dirichlet(k, 0)
    assert (minimise_regret(p, torch.ones(k, dtype=torch.bool)) - optimal_marginal(p)).abs().max() < 1e-9


def test_trajectory_mutual_information_reaches_log_of_the_number_of_trajectories():
    cmp = chain(3, 2)  # 5 trajectories
    mi = maximise_trajectory_information(cmp, 5, steps=150)
    assert mi.mutual_information == pytest.approx(math.log(5), abs=1e-3)
    assert (mi.marginal - 0.2).abs().max() < 1e-3


def test_bad_input_is_refused_before_work():
    with pytest.raises(InvalidValue, match=r"^policy: got .*; expected a float64 tensor"):
        terminal_marginal(WALLED, uniform_policy(chain(3, 3)))
    with pytest.raises(InvalidValue, match=r"^rho: got .*; expected .*states reachable at T"):
        policy_for_marginal(WALLED, torch.eye(9, dtype=torch.float64)[4])
    with pytest.raises(InvalidValue, match=r"^horizon: got 0; expected an integer >= 1"):
        chain(3, 0)


def test_meta_learned_learner_explores_with_the_square_root_of_the_task_marginal():
    cmp = WALLED
    support = reachable_at(cmp)
    rewards = random_discriminator_rewards(cmp.num_states, 7, seed=0)
    q = optimal_policy_marginal(cmp, rewards, temperature=1.0)  # soft task policies: q > 0 on all of S_T
    rho = meta_learned_marginal(cmp, rewards, temperature=1.0)
    assert torch.allclose(rho, q.sqrt() / q.sqrt().sum(), rtol=0, atol=1e-15)
    assert rho.sum().item() == pytest.approx(1.0, abs=1e-15)
    assert (rho - q).abs().max() > 0.05  # q is not uniform: the learner is not posterior sampling
    # it is the f_pi with least regret on q: the solver's optimum, (sum sqrt q)^2, below posterior sampling's |S_T|
    assert regret(rho, q) == pytest.approx(float(regret(minimise_regret(q, support), q)), rel=1e-12)
    assert regret(rho, q) == pytest.approx(float(q.sqrt().sum() ** 2))
    assert regret(q, q) == pytest.approx(int(support.sum()))
    assert regret(rho, q) < int(support.sum()) - 1
    # and its worst case is never above posterior sampling's (min sqrt q / sum sqrt q >= min q)
    assert worst_case_regret(rho, support) < worst_case_regret(q, support)
    # uniform task marginals: one goal per reachable state, or twice each; the learner is posterior sampling
    goals = support.nonzero().flatten().tolist()
    for tasks in (goals, goals * 2):
        q = optimal_policy_marginal(cmp, goal_rewards(tasks, cmp.num_states))
        assert torch.allclose(meta_learned_marginal(cmp, goal_rewards(tasks, cmp.num_states)), q, rtol=0, atol=1e-15)


def test_comparison_rows_and_regret_against_latents():
    cmp = grid(3, 3, 2)  # S_T: the 6 cells within 2 moves of the corner
    rows = {row.proposal: row for row in compare_proposals(cmp, temperatures=(0.0, 1.0), mi_steps=150)}
    assert rows["uniform-over-reachable"].worst_case == pytest.approx(6)
    assert rows["MI-optimal"].worst_case == pytest.approx(6)
    assert rows["random actions"].worst_case == pytest.approx(25)  # the far corners: 1 of 25 action pairs each
    assert rows["random actions"].tasks is None and math.isnan(rows["random actions"].posterior_worst_case)
    assert all(row.worst_case >= 6 - 1e-9 for row in rows.values())
    for name, row in rows.items():
        if row.tasks is None:
            continue
        assert torch.allclose(row.marginal, row.tasks.sqrt() / row.tasks.sqrt().sum()), name
        assert row.on_tasks == pytest.approx(float(row.tasks.sqrt().sum() ** 2)), name
        assert row.on_tasks <= row.posterior_on_tasks + 1e-9 and row.worst_case <= row.posterior_worst_case, name
        assert row.posterior_on_tasks == pytest.approx(int((row.tasks > 0).sum())), name
    soft = rows["random discriminator a=1"]
    assert soft.worst_case < soft.posterior_worst_case and soft.on_tasks < soft.posterior_on_tasks
    curves = regret_against_latents(cmp, [3, 6], mi_steps=150)
    assert curves["MI-optimal worst-case"][0] == float("inf") and curves["MI-optimal worst-case"][1] == pytest.approx(6)


def test_slipped_marginal_matches_enumeration_of_intended_and_taken_actions():
    cmp, eps = chain(3, 2), 0.3
    policy = random_policy(cmp, seed=5)
    expected = torch.zeros(cmp.num_states, dtype=torch.float64)
    choices = range(cmp.num_actions)
    for intended in itertools.product(choices, repeat=cmp.horizon):
        for taken in itertools.product(choices, repeat=cmp.horizon):
            state, probability = cmp.start, 1.0
            for t in range(cmp.horizon):
                slip = eps / cmp.num_actions + (1 - eps) * (taken[t] == intended[t])
                probability *= float(policy[t, state, intended[t]]) * slip
                state = int(cmp.next_state[state, taken[t]])
            expected[state] += probability
    assert torch.allclose(terminal_marginal(cmp, slip_policy(cmp, policy, eps)), expected, rtol=0, atol=1e-15)
    assert torch.equal(slip_policy(cmp, policy, 0.0), policy)


def test_slips_make_every_reachable_goal_findable_and_cost_the_minimax_learner():
    cmp = WALLED
    support = reachable_at(cmp)
    n = int(support.sum())
    to_corner = torch.zeros(cmp.num_states, dtype=torch.float64)
    to_corner[2] = 1.0  # the corner two moves right of the start
    policies = {"minimax": policy_for_marginal(cmp, support.double() / n),
                "one goal": policy_for_marginal(cmp, to_corner), "random": uniform_policy(cmp)}
    slips = (0.0, 0.05, 0.2)
    worst = worst_case_under_slips(cmp, policies, slips)
    assert worst["minimax"][0] == pytest.approx(n)
    assert n < worst["minimax"][1] < worst["minimax"][2]  # the plan mixture loses its uniform marginal
    assert math.isinf(worst["one goal"][0]) and all(math.isfinite(v) for v in worst["one goal"][1:])
    assert worst["random"] == pytest.approx([worst["random"][0]] * 3)  # a slipped uniform action is uniform
    # on the tree every action sequence ends on its own leaf, so the minimax policy is uniform and slips change nothing
    leaves = tree(3)
    uniform_leaves = reachable_at(leaves).double() / 8
    slipped = worst_case_under_slips(leaves, {"minimax": policy_for_marginal(leaves, uniform_leaves)}, slips)
    assert slipped["minimax"] == pytest.approx([8.0] * 3)
