"""The policy-gradient losses' value estimator: rllab's linear feature baseline with GAE, a TorchRL value estimator.

:meth:`umrl.objectives.maml.MAMLLoss.make_value_estimator` and
:meth:`umrl.objectives.trpo_surrogate.ImportanceSamplingLoss.make_value_estimator` build one, so a loss carries its
discount like TorchRL's losses do (``loss.make_value_estimator(gamma=0.99)``; ``loss.value_estimator(batch)``), and
``loss.set_keys(...)`` renames the keys the estimator shares with the loss.
"""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.utils import ValueEstimators
from torchrl.objectives.value import ValueEstimatorBase

from umrl.objectives.policy_gradient import compute_advantages
from umrl.validation import check_float

__all__ = ["LinearBaselineGAE", "check_value_type"]


def check_value_type(value_type) -> None:
    """Refuse any value type but GAE (the only one a fitted linear baseline supports), in the house format."""
    if value_type not in (None, ValueEstimators.GAE):
        raise ValueError(f"value_type: got {value_type!r}; expected None or ValueEstimators.GAE (the linear feature "
                         "baseline with GAE, umrl.objectives.advantage.LinearBaselineGAE).")


class LinearBaselineGAE(ValueEstimatorBase):
    """``td -> td`` with advantages written in place by :func:`~umrl.objectives.policy_gradient.compute_advantages`.

    A :class:`~torchrl.objectives.value.ValueEstimatorBase` without a value network: the baseline is a ridge fit on
    the batch itself, so ``forward`` takes no parameters and :meth:`value_estimate` is not offered.

    Keyword Args:
        gamma: discount (default 0.99, MAML-RL's). lmbda: GAE's λ (default 1.0: Monte-Carlo returns minus the
            baseline, MAML-RL's). normalize: standardise each task's advantages (rllab's ``center_adv``, default on).

    Reads ``"observation"``, ``"step_count"``, ``("next", "reward")``, ``("next", "done")`` (and ``"mask"`` if
    present) of a ``[..., N, H]`` batch; writes ``"value_target"``, ``"state_value"``, ``"mask"`` (if absent) and
    ``"advantage"``, ``[..., N, H, 1]``. Every key can be renamed with :meth:`set_keys`.

    Example:
        >>> estimator = LinearBaselineGAE(gamma=0.9)
        >>> estimator.set_keys(advantage="adv", mask="valid")
        >>> estimator.out_keys
        ['adv', 'value_target', 'state_value', 'valid']
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read and written (change them with :meth:`set_keys`).

        Attributes:
            advantage, value_target, value: written, ``[..., N, H, 1]``. Defaults ``"advantage"``,
                ``"value_target"``, ``"state_value"``.
            reward, done: under ``"next"``. Defaults ``"reward"``, ``"done"`` (a time-limit ``done`` is a true end:
                the baseline's features include time, so nothing is bootstrapped past the horizon).
            mask: valid steps ``[..., N, H]``, computed from ``done`` and written if absent. Default ``"mask"``.
            observation, step_count: the baseline's features. Defaults ``"observation"``, ``"step_count"``.
        """

        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"
        value: NestedKey = "state_value"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        mask: NestedKey = "mask"
        observation: NestedKey = "observation"
        step_count: NestedKey = "step_count"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, *, gamma: float = 0.99, lmbda: float = 1.0, normalize: bool = True):
        super().__init__(value_network=None)
        self.gamma = check_float("gamma", gamma, ge=0, le=1)
        self.lmbda = check_float("lmbda", lmbda, ge=0, le=1)
        self.normalize = bool(normalize)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [keys.observation, keys.step_count, ("next", keys.reward), ("next", keys.done)]

    @property
    def out_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [keys.advantage, keys.value_target, keys.value, keys.mask]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        return compute_advantages(
            tensordict, gamma=self.gamma, lmbda=self.lmbda, normalize=self.normalize,
            observation_key=keys.observation, step_count_key=keys.step_count, reward_key=keys.reward,
            done_key=keys.done, mask_key=keys.mask, advantage_key=keys.advantage, value_target_key=keys.value_target,
            value_key=keys.value,
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}(gamma={self.gamma}, lmbda={self.lmbda}, normalize={self.normalize})"
