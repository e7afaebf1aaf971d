"""MAML's KL Hessian-vector products through the inner step, as strategies for :class:`umrl.optim.trpo.TRPOStep`.

The meta-objective's KL is ``mean_t KL(π_φ_t(θ̄) ‖ π_φ_t(θ))`` with ``φ_t(θ) = θ − α ∇L_t(θ)`` the adapted
parameters of task ``t`` and θ̄ = stop-gradient(θ); its Hessian at θ drives TRPO's conjugate gradient. Each strategy
takes the meta-loss (:class:`~umrl.objectives.maml.MAMLLoss`), the share of each task's trajectories the products use
(``fraction``, in (0, 1]) and the generator that draws that share; the TRPO step's ``batch`` is the loss's packed
meta-batch (``loss.pack(support, query)``). ``trpo.hvp`` in the MAML config names one (:data:`META_HVPS`):

- ``gauss_newton`` (:class:`GaussNewtonHVP`): ``Σ_t J_tᵀ F_t J_t v`` by autograd, no third-order derivatives.
- ``analytic`` (:class:`AnalyticHVP`): the same product derived by hand for a ReLU MLP policy and the VPG inner loss
  (float rounding).
- ``exact`` (:class:`ExactHVP`): the double backward of the KL through the inner step (the closure's own KL graph
  with ``fraction=1``, else :meth:`ExactHVP.kl` on the subsample).

What the strategies take from the loss (``MAMLLoss`` provides each): ``params`` (θ, a TensorDict), ``inner_lr``,
``num_inner_steps``, ``first_order``, ``unpack(batch) -> (support, query)`` (``[T, N, H]`` each),
``inner_loss(params, support) -> [T]``, ``adapt(support) -> φ`` (batch ``[T]``),
``dist_params(params, batch) -> TensorDict`` with the Gaussian's ``"loc"`` and ``"scale"`` ``[T, N, H, act]``, and
``mean_kl(loc0, scale0, loc1, scale1, batch)`` (the KL's mean over the batch's valid steps, then tasks). The
hand-derived product also reads the task-batched MLP (``functional_policy.batched``), the inner loss callable
(``inner_loss_fn``) and the batch keys (``tensor_keys.action``, ``.advantage``, ``.mask``).

Example:
    >>> trpo = TRPOStep(loss.params, hvp=GaussNewtonHVP(loss, fraction=0.1, generator=generator))  # doctest: +SKIP
    >>> trpo(closure, batch=loss.pack(support, query, adapted), initial=initial)  # doctest: +SKIP
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase

from umrl.modules.batched_mlp import ReLUMLPLinearization
from umrl.objectives.policy_gradient import vpg_loss
from umrl.optim.hvp import HessianVectorProduct, KLHessian
from umrl.validation import check_float

__all__ = ["META_HVPS", "AnalyticHVP", "ExactHVP", "GaussNewtonHVP", "MetaHVP", "make_meta_hvp"]

Product = Callable[[torch.Tensor], torch.Tensor]


class MetaHVP(HessianVectorProduct):
    """Base of MAML's products: the meta-loss, the trajectory share and its generator (``None``: torch's global one).

    Subclasses implement :meth:`product`; :meth:`build` applies it to the TRPO step's packed batch.
    """

    def __init__(self, loss: Any, *, fraction: float = 1.0, generator: torch.Generator | None = None):
        self.loss = loss
        self.fraction = check_float("fraction", fraction, gt=0, le=1)
        self.generator = generator

    def subsample(self, support: TensorDictBase, query: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        """The same random ``fraction`` of each task's trajectories (dim 1) of ``support`` and ``query``; when they
        hold different numbers of trajectories (``sample_by=env_steps`` on an env whose episodes end early), the
        query's share is drawn separately."""
        if self.fraction == 1:
            return support, query
        generator = self.generator
        device = generator.device if generator is not None else support.device  # randperm runs where the generator is

        def share(n: int) -> torch.Tensor:
            return torch.randperm(n, generator=generator, device=device)[: max(1, math.ceil(self.fraction * n))]

        idx = share(support.shape[1])
        query_idx = idx if query.shape[1] == support.shape[1] else share(query.shape[1])
        return support[:, idx.to(support.device)], query[:, query_idx.to(query.device)]

    def _batches(self, batch: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        if not isinstance(batch, TensorDictBase):
            raise TypeError(f"batch: got {type(batch).__name__}; expected the MAMLLoss.pack(support, query) "
                            "TensorDict passed as TRPOStep(...)(closure, batch=...).")
        return self.loss.unpack(batch)

    def _check_one_inner_step(self) -> None:
        if self.loss.num_inner_steps != 1:
            raise ValueError(f"{type(self).__name__} supports num_inner_steps=1, got "
                             f"{self.loss.num_inner_steps}; use ExactHVP (trpo.hvp=exact) for other values.")

    def product(self, support: TensorDictBase, query: TensorDictBase) -> Product:
        """``v -> H v`` on this strategy's share of ``support`` and ``query``, on flat vectors ordered like
        ``loss.params.values(True, True)``."""
        raise NotImplementedError

    def build(self, kl, leaves, batch) -> Product:
        return self.product(*self._batches(batch))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(fraction={self.fraction})"


class ExactHVP(MetaHVP):
    """The KL's own Hessian through the inner step (double backward): the closure's KL with ``fraction=1``, else
    :meth:`kl` on the subsample. Any number of inner steps, any inner loss."""

    def __init__(self, loss: Any, *, fraction: float = 1.0, generator: torch.Generator | None = None):
        super().__init__(loss, fraction=fraction, generator=generator)
        self.uses_closure_kl = self.fraction == 1

    def kl(self, support: TensorDictBase, query: TensorDictBase) -> torch.Tensor:
        """KL whose Hessian drives TRPO's conjugate gradient, on this strategy's share of the trajectories.

        KL(π_φ(θ̄) ‖ π_φ(θ)) with φ the adapted parameters computed from the *subsampled* support: zero with zero
        gradient at θ, so its Hessian there is the (Gauss–Newton) Fisher of the adapted policy through the inner
        step. With ``fraction=1`` it has the Hessian of the loss's ``trust_region_kl``.
        """
        support, query = self.subsample(support, query)
        new = self.loss.dist_params(self.loss.adapt(support), query)  # its detached value is the stop-gradient side
        return self.loss.mean_kl(new["loc"].detach(), new["scale"].detach(), new["loc"], new["scale"], query)

    def product(self, support: TensorDictBase, query: TensorDictBase) -> Product:
        leaves = list(self.loss.params.values(True, True))
        return KLHessian(lambda batch: self.kl(*batch)).build(None, leaves, (support, query))

    def build(self, kl, leaves, batch) -> Product:
        if self.uses_closure_kl:
            return KLHessian().build(kl, leaves, batch)
        return KLHessian(lambda packed: self.kl(*self._batches(packed))).build(kl, leaves, batch)


class GaussNewtonHVP(MetaHVP):
    """``v -> Σ_t J_tᵀ F_t J_t v`` by autograd, without third-order derivatives (``num_inner_steps=1``).

    With φ_t(θ) = θ − α ∇L_t(θ) and the KL's gradient w.r.t. φ vanishing at θ = θ̄, the KL Hessian is exactly
    ``Σ_t J_tᵀ F_t J_t`` with ``J_t = I − α ∇²L_t`` and ``F_t`` the KL's Hessian in φ_t. Each product costs two
    double-backward passes through the inner gradient (support data) and one through the KL's gradient (query data);
    both graphs are built once per step and reused by every product. Equals :class:`ExactHVP`'s product (tested),
    typically ~2× cheaper.
    """

    def product(self, support: TensorDictBase, query: TensorDictBase) -> Product:
        self._check_one_inner_step()
        loss = self.loss
        support, query = self.subsample(support, query)
        theta = loss.params
        keys = list(theta.keys(True, True))
        num_tasks = support.shape[0]
        with torch.enable_grad():
            theta_t = theta.expand(num_tasks)
            theta_leaves = [theta_t.get(k) for k in keys]
            inner = loss.inner_loss(theta_t, support).sum()
            grads = torch.autograd.grad(inner, theta_leaves, create_graph=not loss.first_order)
            phi = theta_t.empty()
            for key, p, g in zip(keys, theta_leaves, grads):
                phi.set(key, (p - loss.inner_lr * g).detach().requires_grad_(True))
            phi_leaves = [phi.get(k) for k in keys]
            new = loss.dist_params(phi, query)  # phi is a leaf: the stop-gradient copy is new's value
            kl = loss.mean_kl(new["loc"].detach(), new["scale"].detach(), new["loc"], new["scale"], query)
            kl_grads = torch.autograd.grad(kl, phi_leaves, create_graph=True)
        shapes = [p.shape[1:] for p in phi_leaves]
        sizes = [s.numel() for s in shapes]

        def jacobian_t(vectors):  # per-task (I - α ∇²L_t) v_t
            if loss.first_order:
                return vectors
            hv = torch.autograd.grad(grads, theta_leaves, grad_outputs=vectors, retain_graph=True)
            return [v - loss.inner_lr * h for v, h in zip(vectors, hv)]

        def hvp(v: torch.Tensor) -> torch.Tensor:
            parts = [c.view(s).expand(num_tasks, *s) for c, s in zip(v.split(sizes), shapes)]
            jv = jacobian_t(parts)
            fjv = torch.autograd.grad(kl_grads, phi_leaves, grad_outputs=jv, retain_graph=True)
            return torch.cat([x.sum(0).reshape(-1) for x in jacobian_t(list(fjv))])

        return hvp


class AnalyticHVP(MetaHVP):
    """:class:`GaussNewtonHVP`'s product ``Σ_t J_tᵀ F_t J_t v``, derived by hand for a ReLU MLP policy.

    Same mathematics, no autograd graph: every Hessian-vector product of the inner loss and every Fisher product is a
    forward tangent and a backward pass of the MLP in batched matmuls
    (:class:`umrl.modules.batched_mlp.ReLUMLPLinearization`), with the Gaussian log-likelihood's and the KL's
    curvature in the action mean and log-std written out. Equal to :class:`GaussNewtonHVP` to float rounding
    (tested), with fewer element-wise passes over the activations. Needs ``num_inner_steps=1``, the VPG inner loss
    (:func:`~umrl.objectives.policy_gradient.vpg_loss`) and a policy that :meth:`supports` accepts.
    """

    @staticmethod
    def supports(loss: Any) -> bool:
        """Whether the hand-derived product applies: a ReLU MLP Gaussian policy with an exp scale, VPG inner loss."""
        net = loss.functional_policy.batched
        return net is not None and net.is_relu_mlp and loss.inner_loss_fn is vpg_loss

    def product(self, support: TensorDictBase, query: TensorDictBase) -> Product:
        self._check_one_inner_step()
        loss = self.loss
        if not self.supports(loss):
            raise ValueError("AnalyticHVP needs a ReLU MLP Gaussian policy with an exp scale "
                             "(umrl.modules.policy.make_gaussian_policy) and the VPG inner loss "
                             "(umrl.objectives.policy_gradient.vpg_loss); use GaussNewtonHVP (trpo.hvp=gauss_newton).")
        support, query = self.subsample(support, query)
        net, keys = loss.functional_policy.batched, loss.tensor_keys
        inner_lr, first_order = loss.inner_lr, loss.first_order
        theta = loss.params.detach()
        num_tasks = support.shape[0]
        layer_keys = [key for pair in net.linear_keys() for key in pair if key is not None]
        order = [*layer_keys, net.scale_key]  # how the product's parts are laid out in hvp()'s vectors
        flat_keys = list(theta.keys(True, True))
        if sorted(flat_keys) != sorted(order):
            raise ValueError(f"the policy's parameters {flat_keys} are not those of its MLP and scale {order}.")
        shapes = [theta.get(k).shape for k in flat_keys]

        def samples(td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:  # inputs [T, M, in], weights [T, M]
            x = net.flat_input([td.get(k) for k in net.in_keys])[0]
            return x, td.get(keys.mask).reshape(num_tasks, -1).to(x.dtype)

        def scale_terms(log_std: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # 1/σ², dσ-clamp [T, 1, act]
            unclamped = log_std.exp()
            scale = unclamped.clamp_min(net.scale_lb)
            return scale.pow(-2).unsqueeze(-2), (unclamped >= net.scale_lb).to(scale.dtype).unsqueeze(-2)

        with torch.no_grad():
            # Inner loss at θ on the support: L_t = Σ_i c_i Σ_d [(a - μ)² / 2σ² + log σ], c_i = w_i A_i / W_t.
            x, w = samples(support)
            c = (w * support.get(keys.advantage).reshape(num_tasks, -1) / w.sum(-1, keepdim=True).clamp_min(1))
            c = c.unsqueeze(-1)
            theta_t = theta.expand(num_tasks)
            inner = ReLUMLPLinearization(net.linear_params(theta_t), x)
            log_std = theta_t.get(net.scale_key)
            inv_var, clamp = scale_terms(log_std)
            residual = support.get(keys.action).reshape(num_tasks, -1, inner.loc.shape[-1]) - inner.loc
            grad_loc = -c * residual * inv_var  # ∂L/∂μ [T, M, act]
            grads, deltas = inner.vjp(grad_loc)
            grad_log_std = (clamp * c * (1 - residual.pow(2) * inv_var)).sum(-2)
            curv_log_std = 2 * (clamp * c * residual.pow(2) * inv_var).sum(-2)  # ∂²L/∂(log σ)² [T, act]
            # φ = θ - α ∇L; the query's KL Hessian at φ is q_i / σ² in each step's mean and 2 Σ_i q_i in the
            # log-std, with q_i = w_i / (W_t T) (mean over a task's valid steps, then over tasks).
            phi = [(wt - inner_lr * gw, None if b is None else b - inner_lr * gb)
                   for (wt, b), (gw, gb) in zip(net.linear_params(theta_t), grads)]
            x_q, w_q = samples(query)
            outer = ReLUMLPLinearization(phi, x_q)
            q = (w_q / (w_q.sum(-1, keepdim=True).clamp_min(1) * num_tasks)).unsqueeze(-1)
            inv_var_q, clamp_q = scale_terms(log_std - inner_lr * grad_log_std)
            fisher_log_std = 2 * clamp_q.squeeze(-2) * q.sum(-2)  # [T, act] (clamp² = clamp)

        def split(vectors: list[torch.Tensor]) -> tuple[list, torch.Tensor]:  # [T, ...] parts -> layers, log-std
            by_key = dict(zip(flat_keys, vectors))
            layers = [(by_key[wk], None if bk is None else by_key[bk]) for wk, bk in net.linear_keys()]
            return layers, by_key[net.scale_key]

        def join(layers: list, log_std_part: torch.Tensor) -> list[torch.Tensor]:
            by_key = {net.scale_key: log_std_part}
            for (wk, bk), (gw, gb) in zip(net.linear_keys(), layers):
                by_key[wk] = gw
                if bk is not None:
                    by_key[bk] = gb
            return [by_key[k] for k in flat_keys]

        def jacobian_t(vectors: list[torch.Tensor]) -> list[torch.Tensor]:  # per-task (I - α ∇²L_t) v_t
            if first_order:
                return vectors
            direction, u = split(vectors)
            r_loc, r_inputs = inner.jvp(direction)
            u = clamp.squeeze(-2) * u
            r_grad_loc = c * inv_var * r_loc - 2 * grad_loc * u.unsqueeze(-2)
            hv_layers = inner.rvjp(direction, r_inputs, deltas, r_grad_loc)
            hv_log_std = clamp.squeeze(-2) * (-2 * (grad_loc * r_loc).sum(-2)) + curv_log_std * u
            return [v - inner_lr * h for v, h in zip(vectors, join(hv_layers, hv_log_std))]

        def fisher(vectors: list[torch.Tensor]) -> list[torch.Tensor]:  # per-task F_t v_t
            direction, u = split(vectors)
            r_loc, _ = outer.jvp(direction)
            layers, _ = outer.vjp(q * inv_var_q * r_loc)
            return join(layers, fisher_log_std * u)

        sizes = [math.prod(s) for s in shapes]

        def hvp(v: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                parts = [part.view(s).expand(num_tasks, *s).contiguous() for part, s in zip(v.split(sizes), shapes)]
                return torch.cat([x.sum(0).reshape(-1) for x in jacobian_t(fisher(jacobian_t(parts)))])

        return hvp


META_HVPS: dict[str, type[MetaHVP]] = {"gauss_newton": GaussNewtonHVP, "analytic": AnalyticHVP, "exact": ExactHVP}
"""The MAML config's ``trpo.hvp`` names and their strategies."""


def make_meta_hvp(name: str, loss: Any, *, fraction: float = 1.0,
                  generator: torch.Generator | None = None) -> MetaHVP:
    """The strategy ``trpo.hvp=name`` selects (one of :data:`META_HVPS`) for the meta-loss ``loss``."""
    if name not in META_HVPS:
        raise ValueError(f"trpo.hvp: got {name!r}; expected one of {', '.join(map(repr, META_HVPS))}.")
    return META_HVPS[name](loss, fraction=fraction, generator=generator)
