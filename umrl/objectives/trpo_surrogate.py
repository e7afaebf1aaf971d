"""TRPO's surrogate for a single policy: :class:`ImportanceSamplingLoss` (VIME's policy update).

``loss_objective = −mean_valid(π(a|s) / π_old(a|s) · A)`` and ``kl = mean_valid KL(π_old ‖ π)`` over the valid steps
of a batch of trajectories collected by ``π_old`` (Schulman et al., 2015, https://arxiv.org/abs/1502.05477), the two
scalars :class:`umrl.optim.trpo.TRPOStep`'s closure returns.
"""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators

from umrl.objectives.advantage import LinearBaselineGAE, check_value_type
from umrl.objectives.maml import gaussian_kl, masked_mean
from umrl.rollout import FunctionalPolicy

__all__ = ["ImportanceSamplingLoss"]


class ImportanceSamplingLoss(LossModule):
    """Importance-weighted policy-gradient surrogate and the KL to the collecting policy, for a Gaussian actor.

    Args:
        actor_network: the Gaussian actor being optimised (:func:`umrl.modules.policy.make_gaussian_policy`).

    Input of :meth:`forward`: a batch ``[N, H]`` of trajectories (:func:`umrl.rollout.collect` for one task) with
    the actor's in_keys, ``"action"``, ``"action_log_prob"``, ``"loc"``, ``"scale"`` (of the collecting policy),
    ``"advantage"`` (:attr:`value_estimator`) and ``"mask"``. Outputs (:attr:`out_keys`): ``loss_objective``,
    ``trust_region_kl`` (differentiable: TRPO's constraint, not a loss term) and the detached ``kl`` (its value) and
    ``ratio_max``.

    The actor is evaluated as one task of :class:`~umrl.rollout.FunctionalPolicy`'s task-batched path, the path
    MAML's outer surrogate takes, so a TRPO step gives the same numbers (bit for bit) as MAML's outer step without an
    inner step would.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from umrl.modules.policy import make_gaussian_policy
        >>> policy = make_gaussian_policy(2, 1, hidden=(8,))
        >>> batch = policy(TensorDict({"observation": torch.randn(3, 5, 2)}, [3, 5]))
        >>> batch.update({"advantage": torch.randn(3, 5, 1), "mask": torch.ones(3, 5, dtype=torch.bool)})
        ...  # doctest: +ELLIPSIS
        TensorDict(...)
        >>> out = ImportanceSamplingLoss(policy)(batch)
        >>> round(out["kl"].item(), 6), round(out["ratio_max"].item(), 4)   # at the collecting policy
        (0.0, 1.0)
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read by the loss (change them with ``set_keys``).

        Attributes:
            action, action_log_prob, loc, scale: the collecting policy's action, its log-probability and
                distribution parameters. advantage: the advantage ``[N, H, 1]``. mask: valid steps ``[N, H]``.
        """

        action: NestedKey = "action"
        action_log_prob: NestedKey = "action_log_prob"
        loc: NestedKey = "loc"
        scale: NestedKey = "scale"
        advantage: NestedKey = "advantage"
        mask: NestedKey = "mask"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE

    def __init__(self, actor_network: ProbabilisticActor):
        super().__init__()
        self.out_keys = [  # an instance list: select_out_keys on one loss leaves the others alone
            "loss_objective", "trust_region_kl", "kl", "ratio_max"]
        self.actor_network = actor_network
        self.functional_policy = FunctionalPolicy(actor_network)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [*self.functional_policy.net.in_keys, keys.action, keys.action_log_prob, keys.loc, keys.scale,
                keys.advantage, keys.mask]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            self._value_estimator.set_keys(advantage=self.tensor_keys.advantage, mask=self.tensor_keys.mask)

    def make_value_estimator(self, value_type=None, **hyperparams) -> ImportanceSamplingLoss:
        """Set :attr:`value_estimator` (:class:`~umrl.objectives.advantage.LinearBaselineGAE`, ``gamma``,
        ``lmbda``, ``normalize``); ``value_type`` None or ``ValueEstimators.GAE``."""
        check_value_type(value_type)
        hyperparams.pop("device", None)
        self._value_estimator = LinearBaselineGAE(**hyperparams)
        self._forward_value_estimator_keys()
        return self

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        task = tensordict.unsqueeze(0)  # [1, N, H]: one task of the task-batched evaluation
        dist_params = self.functional_policy.dist_params(TensorDict.from_module(self.actor_network).expand(1), task)
        dist = self.actor_network.build_dist_from_params(dist_params)
        ratio = (dist.log_prob(task.get(keys.action)) - task.get(keys.action_log_prob)).exp()
        mask = task.get(keys.mask)
        surrogate = -masked_mean(ratio * task.get(keys.advantage).squeeze(-1), mask)
        kl = masked_mean(gaussian_kl(task.get(keys.loc), task.get(keys.scale), dist_params["loc"], dist_params["scale"]), mask)
        return TensorDict({"loss_objective": surrogate, "trust_region_kl": kl, "kl": kl.detach(),
                           "ratio_max": ratio.detach().max()}, batch_size=[])
