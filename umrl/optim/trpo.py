"""Trust-region policy optimisation step on TensorDict parameters (Schulman et al., 2015).

TorchRL has no TRPO; this module is the one used by MAML's meta-update (``umrl.objectives.maml``) and by VIME's
policy updates. It is agnostic to what the surrogate is: it only needs

* ``closure() -> (surrogate_loss, kl)``: two differentiable scalars evaluated at the *current* values of the
  parameters (the loss to minimise, and the mean KL divergence between the policy that collected the data and the
  current one). It is called once with gradients enabled to build the step and once per line-search trial under
  ``torch.no_grad`` (a closure that differentiates internally, like MAML's inner step, re-enables grad itself).
  The first call can be replaced by its ready value (``initial=``) when the caller already has it.
* a Hessian-vector product strategy, given once at construction (``hvp=``, :mod:`umrl.optim.hvp`): by default the
  double backward of the closure's ``kl`` (:class:`~umrl.optim.hvp.KLHessian`); MAML's products through the inner
  step are in :mod:`umrl.optim.meta_hvp`. The step's ``batch=`` argument is handed to the strategy.

Example (a linear Gaussian policy's mean pulled towards targets, unit variance):
    >>> from tensordict import TensorDict
    >>> _ = torch.manual_seed(0)
    >>> policy = torch.nn.Linear(3, 2)
    >>> x, target = torch.randn(64, 3), torch.randn(64, 2)
    >>> old_mean = policy(x).detach()
    >>> def closure():  # (loss to minimise, mean KL(N(old_mean, I) || N(mean, I)))
    ...     mean = policy(x)
    ...     return ((mean - target) ** 2).mean(), 0.5 * ((mean - old_mean) ** 2).sum(-1).mean()
    >>> trpo = TRPOStep(TensorDict.from_module(policy), max_kl=0.01)
    >>> info = trpo(closure)
    >>> info["accepted"] == 1.0, info["kl"] <= 0.01, info["improvement"] > 0
    (True, True, True)

The conjugate-gradient system is ``(H + damping * I) x = g`` with ``H`` the KL Hessian at the current parameters
(exact when ``kl`` is taken through MAML's inner update, since the KL's gradient vanishes there). The full step is
scaled so that the quadratic KL model equals ``max_kl``; the backtracking line search then shrinks it by
``backtrack_ratio`` until the surrogate improves *and* the measured KL is within ``max_kl``. If no trial is accepted the
parameters are restored bit-exactly from a saved copy.
"""
from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase

from umrl.optim.hvp import HessianVectorProduct, KLHessian, flat_grad
from umrl.profiling import device_clock
from umrl.validation import check_float, check_int, check_positive

__all__ = ["TRPOStep", "conjugate_gradient"]


def conjugate_gradient(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    *,
    iters: int = 10,
    residual_tol: float = 1e-10,
    with_product: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Approximately solve ``A x = b`` for symmetric positive-definite ``A`` given only ``matvec(v) = A v``.

    Args:
        matvec: function mapping a vector of shape ``b.shape`` to ``A @ v``.
        b: right-hand side, a 1-D tensor.

    Keyword Args:
        iters: maximum number of iterations (matvec calls).
        residual_tol: stop early once the squared residual norm falls below it.
        with_product: also return ``A x``, accumulated as ``Σ αᵢ A pᵢ`` from the products CG already took (equal to
            ``matvec(x)`` up to float rounding, without the extra call).

    Returns:
        ``x`` with the shape of ``b``, or ``(x, A x)`` with ``with_product``.
    """
    if b.dim() != 1:
        raise ValueError(f"conjugate_gradient expects a 1-D right-hand side, got shape {tuple(b.shape)}.")
    x = torch.zeros_like(b)
    ax = torch.zeros_like(b)
    r = b.clone()
    p = b.clone()
    rr = r.dot(r)
    for _ in range(iters):
        if rr <= residual_tol:
            break
        ap = matvec(p)
        alpha = rr / p.dot(ap)
        x = x + alpha * p
        ax = ax + alpha * ap
        r = r - alpha * ap
        rr_new = r.dot(r)
        p = r + (rr_new / rr) * p
        rr = rr_new
    return (x, ax) if with_product else x


class TRPOStep:
    """One natural-gradient step with a KL trust region, applied in place to a TensorDict of parameters.

    Args:
        params: TensorDict whose leaves are the tensors to optimise (``TensorDict.from_module(policy)`` shares
            storage with the module, so updating ``params`` updates the module). Leaves must require grad.

    Keyword Args:
        hvp: how to multiply by the KL Hessian (:class:`~umrl.optim.hvp.HessianVectorProduct`); default
            :class:`~umrl.optim.hvp.KLHessian` of the closure's KL.
        max_kl: trust-region radius on the mean KL (default 0.01).
        damping: Tikhonov damping added to the Hessian-vector product (default 1e-5).
        cg_iters: conjugate-gradient iterations (default 10).
        backtrack_ratio: step shrink factor per line-search trial (default 0.8).
        max_backtracks: number of line-search trials (default 15).

    Calling the step returns a dict of floats: ``surrogate_before``, ``surrogate_after``, ``improvement``
    (before − after, positive is better), ``kl`` (measured at the accepted point, 0 if rejected), ``accepted``
    (1.0/0.0), ``backtracks`` (trials evaluated), of them ``rejected_surrogate`` (no improvement) and ``rejected_kl``
    (KL over ``max_kl`` or not finite; a trial can fail both), of those ``nonfinite_kl`` (a NaN/inf KL: a step
    rejected for it also warns, ``RuntimeWarning``), ``step_norm``, ``grad_norm``, and wall-clock seconds
    ``direction_s`` (gradient, Hessian-vector product set-up and ``cg_iters`` conjugate-gradient products), of it
    ``cg_s`` (the conjugate-gradient products alone), and ``line_search_s`` (the trials). They end at a ``.item()``
    the step makes anyway, so on CUDA they include the queued work; ``cg_s`` starts after one synchronisation (a
    dozen host reads happen in the step already).
    """

    def __init__(
        self,
        params: TensorDictBase,
        *,
        hvp: HessianVectorProduct | None = None,
        max_kl: float = 0.01,
        damping: float = 1e-5,
        cg_iters: int = 10,
        backtrack_ratio: float = 0.8,
        max_backtracks: int = 15,
    ) -> None:
        max_kl = check_positive("max_kl", max_kl)
        damping = check_float("damping", damping, ge=0)
        cg_iters = check_int("cg_iters", cg_iters, min=1)
        backtrack_ratio = check_float("backtrack_ratio", backtrack_ratio, gt=0, lt=1)
        max_backtracks = check_int("max_backtracks", max_backtracks, min=1)
        if hvp is not None and not isinstance(hvp, HessianVectorProduct):
            raise TypeError(f"hvp: got {hvp!r}; expected a umrl.optim.hvp.HessianVectorProduct (e.g. KLHessian()).")
        self.hvp = KLHessian() if hvp is None else hvp
        self.params = params
        self.leaves = list(params.values(include_nested=True, leaves_only=True))
        if not self.leaves or not all(p.requires_grad for p in self.leaves):
            raise ValueError("TRPOStep needs a non-empty TensorDict of parameters that all require grad.")
        self.max_kl = max_kl
        self.damping = damping
        self.cg_iters = cg_iters
        self.backtrack_ratio = backtrack_ratio
        self.max_backtracks = max_backtracks

    def _grad(self, scalar: torch.Tensor, **kwargs) -> torch.Tensor:
        return flat_grad(scalar, self.leaves, **kwargs)

    @torch.no_grad()
    def _set(self, saved: list[torch.Tensor], step: torch.Tensor | None) -> None:
        """Write ``saved - step`` into the parameters (``step=None`` restores ``saved`` exactly)."""
        offset = 0
        for p, p0 in zip(self.leaves, saved):
            if step is None:
                p.copy_(p0)
            else:
                n = p.numel()
                p.copy_(p0 - step[offset : offset + n].view_as(p))
                offset += n

    def __call__(
        self,
        closure: Callable[[], tuple[torch.Tensor, torch.Tensor]],
        *,
        batch: Any = None,
        initial: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> dict[str, float]:
        """One step. ``batch``: the data the Hessian-vector product strategy needs (e.g. a MAML meta-batch), passed
        to its ``build``. ``initial``: ``closure()``'s value at the current parameters, already computed with its
        graph (e.g. reusing MAML's inner-step graph); the closure is then only called for line-search trials."""
        with torch.enable_grad():
            loss, kl = closure() if initial is None else initial
            if loss.dim() != 0 or kl.dim() != 0:
                raise ValueError(f"closure must return two scalars, got shapes {loss.shape} and {kl.shape}.")
            loss_before = loss.item()
            direction_start = time.perf_counter()
            if not math.isfinite(loss_before):
                raise ValueError(f"TRPO surrogate is not finite ({loss_before}); check rewards and log-probs.")
            grad = self._grad(loss, retain_graph=self.hvp.uses_closure_kl)
            undamped = self.hvp.build(kl, self.leaves, batch)

            def damped(v: torch.Tensor) -> torch.Tensor:
                return undamped(v) + self.damping * v
            cg_start = device_clock(grad.device)
            direction, h_direction = conjugate_gradient(damped, grad, iters=self.cg_iters, with_product=True)
            shs = direction.dot(h_direction).item()
        del damped, kl, loss
        line_search_start = time.perf_counter()
        info = {
            "surrogate_before": loss_before,
            "grad_norm": grad.norm().item(),
            "surrogate_after": loss_before,
            "improvement": 0.0,
            "kl": 0.0,
            "accepted": 0.0,
            "backtracks": 0.0,
            "rejected_surrogate": 0.0,
            "rejected_kl": 0.0,
            "nonfinite_kl": 0.0,
            "step_norm": 0.0,
            "direction_s": line_search_start - direction_start,
            "cg_s": line_search_start - cg_start,
            "line_search_s": 0.0,
        }
        if not math.isfinite(shs) or shs <= 0:
            return info
        full_step = math.sqrt(2.0 * self.max_kl / (shs + 1e-8)) * direction
        saved = [p.detach().clone() for p in self.leaves]
        for i in range(self.max_backtracks):
            step = self.backtrack_ratio**i * full_step
            self._set(saved, step)
            with torch.no_grad():
                new_loss, new_kl = (t.detach().item() for t in closure())
            info["backtracks"] = float(i + 1)
            worse = not (math.isfinite(new_loss) and new_loss < loss_before)
            too_far = not new_kl <= self.max_kl  # a NaN KL too
            info["rejected_surrogate"] += worse
            info["rejected_kl"] += too_far
            info["nonfinite_kl"] += not math.isfinite(new_kl)
            if not (worse or too_far):
                info.update(
                    surrogate_after=new_loss,
                    improvement=loss_before - new_loss,
                    kl=new_kl,
                    accepted=1.0,
                    step_norm=step.norm().item(),
                    line_search_s=time.perf_counter() - line_search_start,
                )
                return info
        self._set(saved, None)
        info["line_search_s"] = time.perf_counter() - line_search_start
        if info["nonfinite_kl"]:
            warnings.warn(f"TRPO step rejected: the KL was not finite at {info['nonfinite_kl']:.0f} of "
                          f"{info['backtracks']:.0f} line-search trials (NaN/inf policy outputs?); the parameters are "
                          "unchanged.", RuntimeWarning, stacklevel=2)
        return info
