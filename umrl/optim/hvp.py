"""How :class:`umrl.optim.trpo.TRPOStep` multiplies by the KL Hessian: one object per strategy, passed as ``hvp=``.

A strategy's :meth:`HessianVectorProduct.build` returns the *undamped* product ``v -> H v`` on flat vectors ordered
like the parameters' leaves; TRPO adds its damping. It is called once per step, after the surrogate's gradient, with
the closure's KL (a differentiable scalar), the parameter leaves and the step's ``batch`` (whatever the caller passed
to the step, e.g. a MAML meta-batch). :class:`KLHessian` is the general one (double backward of a KL); MAML's
products through the inner step are in :mod:`umrl.optim.meta_hvp`.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> params = TensorDict.from_module(torch.nn.Linear(2, 1))
    >>> leaves = list(params.values(True, True))
    >>> kl = sum((p ** 2).sum() for p in leaves) / 2             # Hessian: the identity
    >>> product = KLHessian().build(kl, leaves, batch=None)
    >>> product(torch.ones(3)).tolist()
    [1.0, 1.0, 1.0]
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

__all__ = ["HessianVectorProduct", "KLHessian", "flat_grad"]


def flat_grad(scalar: torch.Tensor, leaves: list[torch.Tensor], **kwargs) -> torch.Tensor:
    """``∂ scalar / ∂ leaves`` as one flat vector (zeros for leaves the scalar does not reach)."""
    grads = torch.autograd.grad(scalar, leaves, allow_unused=True, **kwargs)
    return torch.cat([(torch.zeros_like(p) if g is None else g).reshape(-1) for p, g in zip(leaves, grads)])


class HessianVectorProduct:
    """A way to multiply by the KL Hessian at the current parameters (subclass and implement :meth:`build`).

    ``uses_closure_kl``: whether :meth:`build` differentiates the closure's KL, whose graph TRPO must then keep after
    taking the surrogate's gradient (they share the forward pass).
    """

    uses_closure_kl: bool = False

    def build(self, kl: torch.Tensor, leaves: list[torch.Tensor], batch: Any) -> Callable[[torch.Tensor], torch.Tensor]:
        """The undamped product ``v -> H v`` for this step."""
        raise NotImplementedError


class KLHessian(HessianVectorProduct):
    """Double backward of a KL: the closure's own (default) or ``kl_fn(batch)``, e.g. the KL on a subsample.

    The KL's gradient graph is built once (``create_graph=True``) and reused by every product, which saves a
    forward/backward through the KL per conjugate-gradient iteration.
    """

    def __init__(self, kl_fn: Callable[[Any], torch.Tensor] | None = None):
        self.kl_fn = kl_fn
        self.uses_closure_kl = kl_fn is None

    def build(self, kl: torch.Tensor, leaves: list[torch.Tensor], batch: Any) -> Callable[[torch.Tensor], torch.Tensor]:
        target = kl if self.kl_fn is None else self.kl_fn(batch)
        flat_grad_kl = flat_grad(target, leaves, create_graph=True)
        if not flat_grad_kl.requires_grad:
            raise ValueError("The KL's gradient does not depend on the parameters: is it computed from them?")

        def product(v: torch.Tensor) -> torch.Tensor:
            return flat_grad(flat_grad_kl.dot(v), leaves, retain_graph=True)

        return product

    def __repr__(self) -> str:
        return f"{type(self).__name__}({'closure KL' if self.kl_fn is None else repr(self.kl_fn)})"
