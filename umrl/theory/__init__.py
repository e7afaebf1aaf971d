"""The paper's regret analysis, computed exactly on small deterministic CMPs (tabular, CPU, float64).

:mod:`~umrl.theory.cmp` (CMPs and reachable sets), :mod:`~umrl.theory.marginals` (terminal marginals by dynamic
programming), :mod:`~umrl.theory.regret` (regret of f_pi, its worst case, Eq. 4 and a convex solver),
:mod:`~umrl.theory.learning` (f_pi simulated, to check the hitting time), :mod:`~umrl.theory.mutual_information`
(the MI proposal), :mod:`~umrl.theory.proposals` (other proposals, their task marginals and the Eq. 4 learner
meta-trained on them), :mod:`~umrl.theory.trajectories` (trajectory matching), :mod:`~umrl.theory.noise` (slip
noise: the same CMPs with stochastic dynamics) and :mod:`~umrl.theory.evaluation` (the comparison table).
"""
from umrl.theory.cmp import DeterministicCMP, chain, grid, random_cmp, reachable_at, tree
from umrl.theory.evaluation import (
    Evaluation,
    compare_proposals,
    evaluate_marginal,
    evaluate_proposal,
    goal_distributions,
    proposal_tasks,
    regret_against_latents,
)
from umrl.theory.learning import simulate_learning, simulate_regret
from umrl.theory.marginals import (
    policy_for_marginal,
    state_marginals,
    terminal_marginal,
    terminal_marginal_by_enumeration,
    uniform_policy,
)
from umrl.theory.mutual_information import (
    MIProposal,
    max_mutual_information,
    maximise_mutual_information,
    mutual_information,
)
from umrl.theory.noise import slip_policy, worst_case_under_slips
from umrl.theory.proposals import (
    far_goals,
    goal_rewards,
    meta_learned_marginal,
    optimal_policy_marginal,
    random_discriminator_rewards,
)
from umrl.theory.regret import (
    minimise_regret,
    optimal_marginal,
    regret,
    regret_within,
    worst_case_goal,
    worst_case_regret,
)
from umrl.theory.trajectories import (
    enumerate_trajectories,
    maximise_trajectory_information,
    trajectory_probabilities,
    uniform_trajectory_policy,
)

__all__ = [
    "DeterministicCMP",
    "Evaluation",
    "MIProposal",
    "chain",
    "compare_proposals",
    "enumerate_trajectories",
    "evaluate_marginal",
    "evaluate_proposal",
    "far_goals",
    "goal_distributions",
    "goal_rewards",
    "grid",
    "max_mutual_information",
    "maximise_mutual_information",
    "maximise_trajectory_information",
    "meta_learned_marginal",
    "minimise_regret",
    "mutual_information",
    "optimal_marginal",
    "optimal_policy_marginal",
    "policy_for_marginal",
    "proposal_tasks",
    "random_cmp",
    "random_discriminator_rewards",
    "reachable_at",
    "regret",
    "regret_against_latents",
    "regret_within",
    "simulate_learning",
    "simulate_regret",
    "slip_policy",
    "state_marginals",
    "terminal_marginal",
    "terminal_marginal_by_enumeration",
    "trajectory_probabilities",
    "tree",
    "uniform_policy",
    "uniform_trajectory_policy",
    "worst_case_goal",
    "worst_case_regret",
    "worst_case_under_slips",
]
