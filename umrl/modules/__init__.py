"""Networks: the Gaussian policy MAML meta-trains, DIAYN's skill actor/critic and discriminator, VIME's Bayesian
dynamics model."""
from umrl.modules.batched_mlp import BatchedGaussianMLP
from umrl.modules.bnn import BayesianDynamics, BayesianLinear
from umrl.modules.discriminator import make_discriminator
from umrl.modules.policy import make_gaussian_policy, policy_log_std
from umrl.modules.sac import make_skill_actor, make_skill_qvalue

__all__ = [
    "BatchedGaussianMLP",
    "BayesianDynamics",
    "BayesianLinear",
    "make_discriminator",
    "make_gaussian_policy",
    "make_skill_actor",
    "make_skill_qvalue",
    "policy_log_std",
]
