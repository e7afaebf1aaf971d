"""The policy-gradient losses' value estimator: rllab's linear feature baseline with GAE, as a callable object.

:meth:`umrl.objectives.maml.MAMLLoss.make_value_estimator` and
:meth:`umrl.objectives.trpo_surrogate.ImportanceSamplingLoss.make_value_estimator` build one, so a loss carries its
discount like TorchRL's losses do (``loss.make_value_estimator(gamma=0.99)``; ``loss.value_estimator(batch)``).
"""
from __future__ import annotations

from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.utils import ValueEstimators

from umrl.objectives.policy_gradient import compute_advantages
from umrl.validation import check_float

__all__ = ["LinearBaselineGAE", "check_value_type"]


def check_value_type(value_type) -> None:
    """Refuse any value type but GAE (the only one a fitted linear baseline supports), in the house format."""
    if value_type not in (None, ValueEstimators.GAE):
        raise ValueError(f"value_type: got {value_type!r}; expected None or ValueEstimators.GAE (the linear feature "
                         "baseline with GAE, umrl.objectives.advantage.LinearBaselineGAE).")


class LinearBaselineGAE:
    """``td -> td`` with advantages written in place by :func:`~umrl.objectives.policy_gradient.compute_advantages`.

    Keyword Args:
        gamma: discount (default 0.99, MAML-RL's). lmbda: GAE's λ (default 1.0: Monte-Carlo returns minus the
            baseline, MAML-RL's). normalize: standardise each task's advantages (rllab's ``center_adv``, default on).
        advantage_key: where the advantage is written (``"advantage"``).

    Reads ``"observation"``, ``"step_count"``, ``("next", "reward")``, ``("next", "done")`` of a ``[..., N, H]``
    batch; writes ``"value_target"``, ``"state_value"``, ``"mask"`` (if absent) and the advantage, ``[..., N, H, 1]``.
    """

    def __init__(self, *, gamma: float = 0.99, lmbda: float = 1.0, normalize: bool = True,
                 advantage_key: NestedKey = "advantage"):
        self.gamma = check_float("gamma", gamma, ge=0, le=1)
        self.lmbda = check_float("lmbda", lmbda, ge=0, le=1)
        self.normalize = bool(normalize)
        self.advantage_key = advantage_key

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        compute_advantages(td, gamma=self.gamma, lmbda=self.lmbda, normalize=self.normalize)
        if self.advantage_key != "advantage":
            td.rename_key_("advantage", self.advantage_key)
        return td

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(gamma={self.gamma}, lmbda={self.lmbda}, normalize={self.normalize}, "
                f"advantage_key={self.advantage_key!r})")
