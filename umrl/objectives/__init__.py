"""Losses, one algorithm per module, as in ``torchrl.objectives``: ``from umrl.objectives import MAMLLoss``.

- :class:`DIAYNLoss` (:mod:`umrl.objectives.diayn`): SAC on the skill pseudo-reward + the discriminator;
  :class:`DIAYNUpdate` performs one update with it (eager, compiled or in a CUDA graph).
- :class:`MAMLLoss` (:mod:`umrl.objectives.maml`): MAML with a policy-gradient inner step and TRPO's surrogate.
- :class:`VIMELoss` (:mod:`umrl.objectives.vime`): the Bayesian dynamics model's negative ELBO.
- :class:`ImportanceSamplingLoss` (:mod:`umrl.objectives.trpo_surrogate`): TRPO's surrogate for one policy (VIME).
- the policy-gradient losses' value estimator :class:`LinearBaselineGAE` (:mod:`umrl.objectives.advantage`).
- policy-gradient helpers (:mod:`umrl.objectives.policy_gradient`): advantages, baseline, surrogate, returns.
"""
from umrl.objectives.advantage import LinearBaselineGAE
from umrl.objectives.diayn import DIAYNLoss, DIAYNUpdate, make_diayn_optimizers
from umrl.objectives.maml import MAMLLoss
from umrl.objectives.policy_gradient import (
    baseline_features,
    compute_advantages,
    episode_lengths,
    episode_returns,
    fit_linear_baseline,
    trajectory_mask,
    vpg_loss,
)
from umrl.objectives.trpo_surrogate import ImportanceSamplingLoss
from umrl.objectives.vime import VIMELoss

__all__ = [
    "DIAYNLoss",
    "DIAYNUpdate",
    "ImportanceSamplingLoss",
    "LinearBaselineGAE",
    "MAMLLoss",
    "VIMELoss",
    "baseline_features",
    "compute_advantages",
    "episode_lengths",
    "episode_returns",
    "fit_linear_baseline",
    "make_diayn_optimizers",
    "trajectory_mask",
    "vpg_loss",
]
