"""MAML's KL Hessian-vector products through the inner step, as strategies for :class:`umrl.optim.trpo.TRPOStep`.

Each takes the :class:`~umrl.objectives.maml.MAMLLoss`, the share of each task's trajectories the products use
(``fraction``, in (0, 1]) and the generator that draws that share; the TRPO step's ``batch`` is the loss's packed
meta-batch (:meth:`MAMLLoss.pack <umrl.objectives.maml.MAMLLoss.pack>`). ``trpo.hvp`` in the MAML config names one
(:data:`META_HVPS`):

- ``gauss_newton`` (:class:`GaussNewtonHVP`): ``Σ_t J_tᵀ F_t J_t v`` by autograd, no third-order derivatives.
- ``analytic`` (:class:`AnalyticHVP`): the same product derived by hand for the ReLU MLP policy (float rounding).
- ``exact`` (:class:`ExactHVP`): the double backward of the KL through the inner step (the closure's own KL graph
  with ``fraction=1``, else :meth:`MAMLLoss.hvp_kl <umrl.objectives.maml.MAMLLoss.hvp_kl>` on the subsample).

Example:
    >>> trpo = TRPOStep(loss.params, hvp=GaussNewtonHVP(loss, fraction=0.1, generator=generator))  # doctest: +SKIP
    >>> trpo(closure, batch=loss.pack(support, query, adapted), initial=initial)  # doctest: +SKIP
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from umrl.objectives.maml import MAMLLoss
from umrl.optim.hvp import HessianVectorProduct, KLHessian
from umrl.validation import check_float

__all__ = ["META_HVPS", "AnalyticHVP", "ExactHVP", "GaussNewtonHVP", "MetaHVP", "make_meta_hvp"]


class MetaHVP(HessianVectorProduct):
    """Base of MAML's products: the loss, the trajectory share and its generator (``None``: torch's global one)."""

    def __init__(self, loss: MAMLLoss, *, fraction: float = 1.0, generator: torch.Generator | None = None):
        self.loss = loss
        self.fraction = check_float("fraction", fraction, gt=0, le=1)
        self.generator = generator

    def _batches(self, batch: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        if not isinstance(batch, TensorDictBase):
            raise TypeError(f"batch: got {type(batch).__name__}; expected the MAMLLoss.pack(support, query) "
                            "TensorDict passed as TRPOStep(...)(closure, batch=...).")
        keys = self.loss.tensor_keys
        return batch.get(keys.support), batch.get(keys.query)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(fraction={self.fraction})"


class GaussNewtonHVP(MetaHVP):
    """:meth:`MAMLLoss.gauss_newton_hvp <umrl.objectives.maml.MAMLLoss.gauss_newton_hvp>` on the step's batch."""

    def build(self, kl, leaves, batch) -> Callable[[torch.Tensor], torch.Tensor]:
        support, query = self._batches(batch)
        return self.loss.gauss_newton_hvp(support, query, fraction=self.fraction, generator=self.generator)


class AnalyticHVP(MetaHVP):
    """:meth:`MAMLLoss.analytic_gauss_newton_hvp <umrl.objectives.maml.MAMLLoss.analytic_gauss_newton_hvp>` on the
    step's batch."""

    def build(self, kl, leaves, batch) -> Callable[[torch.Tensor], torch.Tensor]:
        support, query = self._batches(batch)
        return self.loss.analytic_gauss_newton_hvp(support, query, fraction=self.fraction, generator=self.generator)


class ExactHVP(MetaHVP):
    """The KL's own Hessian through the inner step: the closure's KL with ``fraction=1``, else
    :meth:`MAMLLoss.hvp_kl <umrl.objectives.maml.MAMLLoss.hvp_kl>` on the subsample."""

    def __init__(self, loss: MAMLLoss, *, fraction: float = 1.0, generator: torch.Generator | None = None):
        super().__init__(loss, fraction=fraction, generator=generator)
        self.uses_closure_kl = self.fraction == 1

    def build(self, kl, leaves, batch) -> Callable[[torch.Tensor], torch.Tensor]:
        if self.uses_closure_kl:
            return KLHessian().build(kl, leaves, batch)

        def subsampled_kl(batch: TensorDictBase) -> torch.Tensor:
            support, query = self._batches(batch)
            return self.loss.hvp_kl(support, query, fraction=self.fraction, generator=self.generator)

        return KLHessian(subsampled_kl).build(kl, leaves, batch)


META_HVPS: dict[str, type[MetaHVP]] = {"gauss_newton": GaussNewtonHVP, "analytic": AnalyticHVP, "exact": ExactHVP}
"""The MAML config's ``trpo.hvp`` names and their strategies."""


def make_meta_hvp(name: str, loss: MAMLLoss, *, fraction: float = 1.0,
                  generator: torch.Generator | None = None) -> MetaHVP:
    """The strategy ``trpo.hvp=name`` selects (one of :data:`META_HVPS`)."""
    if name not in META_HVPS:
        raise ValueError(f"trpo.hvp: got {name!r}; expected one of {', '.join(map(repr, META_HVPS))}.")
    return META_HVPS[name](loss, fraction=fraction, generator=generator)
