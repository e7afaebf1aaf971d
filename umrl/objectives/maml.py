"""Functional MAML for policy gradients (Finn et al., 2017, https://arxiv.org/abs/1703.03400).

The policy's parameters live in a TensorDict (``TensorDict.from_module(policy)``). :meth:`MAMLLoss.adapt` takes
vanilla policy-gradient steps on each task's *support* batch and returns adapted parameters with a leading task
dimension; :meth:`MAMLLoss.forward` scores them on the *query* batch (collected with those same adapted parameters)
with TRPO's importance-weighted surrogate. The outer optimiser (``umrl.optim.trpo.TRPOStep``) and the advantage
computation (``umrl.objectives.policy_gradient.compute_advantages``) live outside the loss.

Batches are ``[T, N, H]`` TensorDicts from :func:`umrl.rollout.collect`; the loss's value estimator
(:meth:`MAMLLoss.make_value_estimator`, a :class:`~umrl.objectives.advantage.LinearBaselineGAE`) writes their
``"advantage"``. :meth:`MAMLLoss.forward` reads one TensorDict of batch ``[T]`` holding both (:meth:`MAMLLoss.pack`).

Example (point_nav's oracle goals as tasks):
    >>> import torch
    >>> from umrl.modules.policy import make_gaussian_policy
    >>> from umrl.proposals import make_proposal
    >>> from umrl.rollout import collect
    >>> T, N, H = 2, 3, 5                                             # tasks, trajectories per task, horizon
    >>> proposal = make_proposal("oracle", "point_nav", num_tasks=T, trajectories_per_task=N, horizon=H)
    >>> goals = proposal.resample(torch.Generator().manual_seed(0))   # [T, 2]
    >>> policy = make_gaussian_policy(2, 2, hidden=[16])
    >>> loss = MAMLLoss(policy, inner_lr=0.1)
    >>> support = loss.value_estimator(collect(proposal.env, policy, num_tasks=T, horizon=H))
    >>> adapted = loss.adapt(support)                                  # batch [T]
    >>> adapted.batch_size
    torch.Size([2])
    >>> query = loss.value_estimator(collect(proposal.env, policy, num_tasks=T, horizon=H, params=adapted.detach()))
    >>> out = loss(loss.pack(support, query, adapted))                 # reuses adapted's graph
    >>> out["loss_objective"].backward()                               # meta-gradient, through the inner step
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torch.distributions import Normal, kl_divergence
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators

from umrl.modules.batched_mlp import ReLUMLPLinearization
from umrl.objectives.advantage import LinearBaselineGAE, check_value_type
from umrl.objectives.policy_gradient import vpg_loss
from umrl.rollout import FunctionalPolicy
from umrl.validation import check_int, check_positive

__all__ = ["MAMLLoss", "gaussian_kl", "masked_mean"]


def gaussian_kl(loc0: torch.Tensor, scale0: torch.Tensor, loc1: torch.Tensor, scale1: torch.Tensor) -> torch.Tensor:
    """``KL(N(loc0, scale0²) ‖ N(loc1, scale1²))`` for diagonal Gaussians, summed over the last dim."""
    p, q = Normal(loc0, scale0, validate_args=False), Normal(loc1, scale1, validate_args=False)
    return kl_divergence(p, q).sum(-1)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` ``[T, N, H]`` over the valid steps of each task, then over tasks."""
    w = mask.to(x.dtype)
    return ((x * w).sum((-2, -1)) / w.sum((-2, -1)).clamp_min(1)).mean()


class MAMLLoss(LossModule):
    """MAML with a vanilla policy-gradient inner loop and a TRPO-style outer surrogate.

    Args:
        policy: Gaussian actor (:func:`umrl.modules.policy.make_gaussian_policy`); its parameters are θ.

    Keyword Args:
        inner_lr: inner SGD step size α (default 0.1).
        num_inner_steps: inner steps (default 1). Every step uses the same support batch. ``0`` makes ``adapt`` the
            identity, so the loss is plain policy gradient on the query batch.
        first_order: drop the second-order terms (FOMAML): inner gradients are treated as constants.
        task_loop: evaluate per-task parameters all at once with one batched matmul per layer (``None``, default),
            with ``vmap`` (``False``) or with a Python loop over tasks (``True``, the per-task reference); see
            :class:`umrl.rollout.FunctionalPolicy`. The inner step, surrogate, KL and Hessian-vector products all go
            through it, so with the default no Python loop over tasks runs on the learning step's hot path.

    Input of :meth:`forward`: a TensorDict of batch ``[T]`` (:meth:`pack`) with ``"support"`` and ``"query"``, each
    ``[T, N, H]`` (see :func:`umrl.rollout.collect`): ``support`` with ``"observation"``, ``"action"``,
    ``"advantage"``, ``"mask"``, ``("next", "reward")``; ``query`` with the same plus ``"action_log_prob"``,
    ``"loc"``, ``"scale"`` from the adapted policy that collected it. Optionally ``"adapted"``: :meth:`adapt`'s
    result at the current θ (with its graph), which the forward then reuses instead of redoing the inner step.
    Every key can be renamed with :meth:`set_keys`; :attr:`in_keys` lists them.

    Outputs of :meth:`forward` (:attr:`out_keys`): ``loss_objective`` (−importance-weighted advantage on the query,
    differentiable through the inner step), ``trust_region_kl`` (mean KL(collecting policy ‖ current adapted
    policy), also differentiable: TRPO's constraint, not a term to add to the loss) and detached diagnostics ``kl``
    (its value), ``inner_loss`` (the inner loss at θ), ``return_pre`` / ``return_post`` (mean undiscounted episode
    return of support / query), ``ratio_max``.

    The advantages are the caller's: :meth:`make_value_estimator` (``gamma``, ``lmbda``, ``normalize``) configures
    :attr:`value_estimator`, a :class:`~umrl.objectives.advantage.LinearBaselineGAE` writing ``"advantage"``.
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read by the loss (change with ``set_keys``).

        Attributes:
            support, query: the two ``[T, N, H]`` batches inside the forward's input. Default ``"support"``,
                ``"query"``.
            adapted: optional adapted parameters ``[T]`` inside the input. Default ``"adapted"``.
            action, action_log_prob, advantage, loc, scale, mask: inside each batch (the log-prob, loc and scale of
                the collecting policy: query only). Defaults are their names.
            reward: under ``"next"`` in each batch (the diagnostics' returns). Default ``"reward"``.
        """

        support: NestedKey = "support"
        query: NestedKey = "query"
        adapted: NestedKey = "adapted"
        action: NestedKey = "action"
        action_log_prob: NestedKey = "action_log_prob"
        advantage: NestedKey = "advantage"
        loc: NestedKey = "loc"
        scale: NestedKey = "scale"
        mask: NestedKey = "mask"
        reward: NestedKey = "reward"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE

    def __init__(
        self,
        policy: ProbabilisticActor,
        *,
        inner_lr: float = 0.1,
        num_inner_steps: int = 1,
        first_order: bool = False,
        task_loop: bool | None = None,
    ) -> None:
        super().__init__()
        self.out_keys = [  # an instance list: select_out_keys on one loss leaves the others alone
            "loss_objective", "trust_region_kl", "kl", "inner_loss", "return_pre", "return_post", "ratio_max"]
        inner_lr = check_positive("inner_lr", inner_lr)
        num_inner_steps = check_int("num_inner_steps", num_inner_steps, min=0)
        self.policy = policy
        self.functional_policy = FunctionalPolicy(policy, task_loop=task_loop)
        self.inner_lr = inner_lr
        self.num_inner_steps = num_inner_steps
        self.first_order = first_order

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            self._value_estimator.advantage_key = self.tensor_keys.advantage

    def make_value_estimator(self, value_type=None, **hyperparams) -> MAMLLoss:
        """Set :attr:`value_estimator`: rllab's linear feature baseline with GAE (``value_type`` None or
        ``ValueEstimators.GAE``); ``hyperparams``: ``gamma``, ``lmbda``, ``normalize`` of
        :class:`~umrl.objectives.advantage.LinearBaselineGAE` (MAML-RL's 0.99, 1.0, true by default)."""
        check_value_type(value_type)
        hyperparams.pop("device", None)  # TorchRL's default construction passes it; the baseline fits on the data's
        self._value_estimator = LinearBaselineGAE(**hyperparams, advantage_key=self.tensor_keys.advantage)
        return self

    @property
    def in_keys(self) -> list[NestedKey]:
        """Every key :meth:`forward` reads (besides the optional ``adapted``), nested under support / query."""
        keys = self.tensor_keys
        shared = [keys.action, keys.advantage, keys.mask, ("next", keys.reward), *self.functional_policy.net.in_keys]
        query_only = [keys.action_log_prob, keys.loc, keys.scale]
        return ([unravel_key((keys.support, k)) for k in shared]
                + [unravel_key((keys.query, k)) for k in [*shared, *query_only]])

    def pack(self, support: TensorDictBase, query: TensorDictBase,
             adapted: TensorDictBase | None = None) -> TensorDictBase:
        """The forward's input: ``support`` and ``query`` (``[T, N, H]``) and optionally ``adapted`` (``[T]``, with
        its graph) in one TensorDict of batch ``[T]``, under this loss's keys."""
        keys = self.tensor_keys
        td = TensorDict({keys.support: support, keys.query: query}, batch_size=support.shape[:1])
        if adapted is not None:
            td.set(keys.adapted, adapted)
        return td

    @property
    def params(self) -> TensorDictBase:
        """θ: a TensorDict sharing storage with the policy's parameters (what the outer optimiser updates)."""
        return TensorDict.from_module(self.policy)

    def _check(self, td: TensorDictBase, name: str, keys) -> None:
        if td.batch_dims != 3:
            raise ValueError(f"{name} must be a [T, N, H] batch of trajectories, got batch size {tuple(td.batch_size)}.")
        missing = [k for k in keys if k not in td.keys(True)]
        if missing:
            raise ValueError(f"{name} lacks keys {missing}: run compute_advantages on rollouts from umrl.rollout.collect.")

    def inner_loss(self, params: TensorDictBase, support: TensorDictBase) -> torch.Tensor:
        """Per-task vanilla PG loss ``[T]`` of ``params`` (shared or ``[T]``) on ``support``."""
        keys = self.tensor_keys
        log_prob = self.functional_policy.dist(params, support).log_prob(support[keys.action])
        return vpg_loss(log_prob, support, advantage_key=keys.advantage, mask_key=keys.mask)

    def adapt(self, support: TensorDictBase, params: TensorDictBase | None = None) -> TensorDictBase:
        """Adapted parameters φ_t, one set per task, with batch size ``[T]``.

        ``φ ← φ − α ∇_φ L_inner(φ; support_t)``, ``num_inner_steps`` times from φ = θ (``params`` or the policy's).
        With gradients enabled and ``first_order=False`` the result is differentiable (second order) w.r.t. θ;
        under ``torch.no_grad`` (e.g. for collection) the inner gradients are still taken and the result is
        detached.
        """
        return self._adapt(support, params)[0]

    def _adapt(self, support: TensorDictBase, params: TensorDictBase | None) -> tuple[TensorDictBase, torch.Tensor | None]:
        """:meth:`adapt`'s parameters and the first inner step's mean inner loss at θ (detached; ``None`` without
        inner steps)."""
        self._check(support, "support", [self.tensor_keys.action, self.tensor_keys.advantage, self.tensor_keys.mask])
        theta = self.params if params is None else params
        num_tasks = support.shape[0]
        track = torch.is_grad_enabled()
        create_graph = track and not self.first_order
        phi = theta.expand(num_tasks) if track else theta.detach().expand(num_tasks)
        keys = list(phi.keys(True, True))
        first_loss = None
        for _ in range(self.num_inner_steps):
            with torch.enable_grad():
                if not track:
                    phi = phi.detach().requires_grad_(True)
                loss = self.inner_loss(phi, support).sum()  # tasks are independent: grad of the sum is per task
                grads = torch.autograd.grad(loss, [phi.get(k) for k in keys], create_graph=create_graph)
            if first_loss is None:
                first_loss = loss.detach() / num_tasks
            new_phi = phi.empty()
            for key, grad in zip(keys, grads):
                new_phi.set(key, phi.get(key) - self.inner_lr * grad)
            phi = new_phi if track else new_phi.detach()
        return phi, first_loss

    def _surrogate_and_kl(
        self, phi: TensorDictBase, query: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        keys = self.tensor_keys
        dist_params = self.functional_policy.dist_params(phi, query)
        dist = self.policy.build_dist_from_params(dist_params)
        ratio = (dist.log_prob(query[keys.action]) - query[keys.action_log_prob]).exp()
        surrogate = -masked_mean(ratio * query[keys.advantage].squeeze(-1), query[keys.mask])
        kl = gaussian_kl(query[keys.loc], query[keys.scale], dist_params["loc"], dist_params["scale"])
        return surrogate, masked_mean(kl, query[keys.mask]), ratio

    def objective_and_kl(
        self, support: TensorDictBase, query: TensorDictBase, phi: TensorDictBase | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(loss_objective, kl)`` as differentiable scalars: the closure for :class:`umrl.optim.trpo.TRPOStep`.

        ``phi``: ``self.adapt(support)`` at the current θ if already computed (with its graph, to differentiate
        through it), e.g. the adaptation that gave the query's collecting parameters; saves redoing the inner step.
        """
        surrogate, kl, _ = self._surrogate_and_kl(self.adapt(support) if phi is None else phi, query)
        return surrogate, kl

    def hvp_kl(
        self,
        support: TensorDictBase,
        query: TensorDictBase,
        *,
        fraction: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """KL whose Hessian drives TRPO's conjugate gradient, on a random ``fraction`` of each task's trajectories.

        KL(π_φ(θ̄) ‖ π_φ(θ)) with θ̄ = stop-gradient(θ) and φ the adapted parameters computed from the *subsampled*
        support: zero with zero gradient at θ, so its Hessian there is the (Gauss–Newton) Fisher of the adapted
        policy through the inner step. With ``fraction=1`` it equals the Hessian of the ``kl`` of
        :meth:`objective_and_kl`.
        """
        support, query = self._subsample(support, query, fraction, generator)
        phi = self.adapt(support)
        new = self.functional_policy.dist_params(phi, query)  # its detached value is the stop-gradient side
        kl = gaussian_kl(new["loc"].detach(), new["scale"].detach(), new["loc"], new["scale"])
        return masked_mean(kl, query[self.tensor_keys.mask])

    def _subsample(self, support, query, fraction, generator):
        if not 0 < fraction <= 1:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}.")
        if fraction == 1:
            return support, query
        n = support.shape[1]
        device = generator.device if generator is not None else support.device  # randperm runs where the generator is
        idx = torch.randperm(n, generator=generator, device=device)[: max(1, math.ceil(fraction * n))]
        return support[:, idx.to(support.device)], query[:, idx.to(query.device)]

    def gauss_newton_hvp(
        self,
        support: TensorDictBase,
        query: TensorDictBase,
        *,
        fraction: float = 1.0,
        generator: torch.Generator | None = None,
    ):
        """``v -> H v`` for the KL Hessian through the inner step, without third-order derivatives.

        With φ_t(θ) = θ − α ∇L_t(θ) and KL = mean_t KL(π_φ_t(θ̄) ‖ π_φ_t(θ)), whose gradient w.r.t. φ vanishes at
        θ = θ̄, the Hessian is exactly ``Σ_t J_tᵀ F_t J_t`` with ``J_t = I − α ∇²L_t`` and ``F_t`` the KL's Hessian
        in φ_t. Each product costs two double-backward passes through the inner gradient (support data) and one
        through the KL's gradient (query data); both graphs are built once here and reused by every call. Equals
        the Hessian-vector product of :meth:`hvp_kl` (tested), typically ~2× cheaper. Needs ``num_inner_steps=1``.

        Returns a function of a flat vector ordered like ``self.params.values(True, True)``.
        """
        if self.num_inner_steps != 1:
            raise ValueError("gauss_newton_hvp supports num_inner_steps=1; use hvp_kl for other values.")
        support, query = self._subsample(support, query, fraction, generator)
        theta = self.params
        keys = list(theta.keys(True, True))
        num_tasks = support.shape[0]
        with torch.enable_grad():
            theta_t = theta.expand(num_tasks)
            theta_leaves = [theta_t.get(k) for k in keys]
            inner = self.inner_loss(theta_t, support).sum()
            grads = torch.autograd.grad(inner, theta_leaves, create_graph=not self.first_order)
            phi = theta_t.empty()
            for key, p, g in zip(keys, theta_leaves, grads):
                phi.set(key, (p - self.inner_lr * g).detach().requires_grad_(True))
            phi_leaves = [phi.get(k) for k in keys]
            new = self.functional_policy.dist_params(phi, query)  # phi is a leaf: the stop-gradient copy is new's value
            kl = gaussian_kl(new["loc"].detach(), new["scale"].detach(), new["loc"], new["scale"])
            kl = masked_mean(kl, query[self.tensor_keys.mask])
            kl_grads = torch.autograd.grad(kl, phi_leaves, create_graph=True)
        shapes = [p.shape[1:] for p in phi_leaves]
        sizes = [s.numel() for s in shapes]

        def jacobian_t(vectors):  # per-task (I - α ∇²L_t) v_t
            if self.first_order:
                return vectors
            hv = torch.autograd.grad(grads, theta_leaves, grad_outputs=vectors, retain_graph=True)
            return [v - self.inner_lr * h for v, h in zip(vectors, hv)]

        def hvp(v: torch.Tensor) -> torch.Tensor:
            parts = [c.view(s).expand(num_tasks, *s) for c, s in zip(v.split(sizes), shapes)]
            jv = jacobian_t(parts)
            fjv = torch.autograd.grad(kl_grads, phi_leaves, grad_outputs=jv, retain_graph=True)
            return torch.cat([x.sum(0).reshape(-1) for x in jacobian_t(list(fjv))])

        return hvp

    def analytic_gauss_newton_hvp(
        self,
        support: TensorDictBase,
        query: TensorDictBase,
        *,
        fraction: float = 1.0,
        generator: torch.Generator | None = None,
    ):
        """:meth:`gauss_newton_hvp`'s product ``Σ_t J_tᵀ F_t J_t v``, derived by hand for a ReLU MLP policy.

        Same mathematics, no autograd graph: every Hessian-vector product of the inner loss and every Fisher product
        is a forward tangent and a backward pass of the MLP in batched matmuls
        (:class:`umrl.modules.batched_mlp.ReLUMLPLinearization`), with the Gaussian log-likelihood's and the KL's
        curvature in the action mean and log-std written out. Equal to :meth:`gauss_newton_hvp` to float rounding
        (tested), with fewer element-wise passes over the activations. Needs ``num_inner_steps=1`` and a policy
        that :meth:`supports_analytic_hvp`.
        """
        if self.num_inner_steps != 1:
            raise ValueError("analytic_gauss_newton_hvp supports num_inner_steps=1; use hvp_kl for other values.")
        if not self.supports_analytic_hvp:
            raise ValueError("analytic_gauss_newton_hvp needs a ReLU MLP Gaussian policy with an exp scale "
                             "(umrl.modules.policy.make_gaussian_policy); use gauss_newton_hvp.")
        support, query = self._subsample(support, query, fraction, generator)
        net, keys = self.functional_policy.batched, self.tensor_keys
        theta = self.params.detach()
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
            phi = [(wt - self.inner_lr * gw, None if b is None else b - self.inner_lr * gb)
                   for (wt, b), (gw, gb) in zip(net.linear_params(theta_t), grads)]
            x_q, w_q = samples(query)
            outer = ReLUMLPLinearization(phi, x_q)
            q = (w_q / (w_q.sum(-1, keepdim=True).clamp_min(1) * num_tasks)).unsqueeze(-1)
            inv_var_q, clamp_q = scale_terms(log_std - self.inner_lr * grad_log_std)
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
            if self.first_order:
                return vectors
            direction, u = split(vectors)
            r_loc, r_inputs = inner.jvp(direction)
            u = clamp.squeeze(-2) * u
            r_grad_loc = c * inv_var * r_loc - 2 * grad_loc * u.unsqueeze(-2)
            hv_layers = inner.rvjp(direction, r_inputs, deltas, r_grad_loc)
            hv_log_std = clamp.squeeze(-2) * (-2 * (grad_loc * r_loc).sum(-2)) + curv_log_std * u
            return [v - self.inner_lr * h for v, h in zip(vectors, join(hv_layers, hv_log_std))]

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

    @property
    def supports_analytic_hvp(self) -> bool:
        """Whether :meth:`analytic_gauss_newton_hvp` can differentiate this policy (a ReLU MLP with an exp scale)."""
        net = self.functional_policy.batched
        return net is not None and net.is_relu_mlp

    def _episode_return(self, td: TensorDictBase) -> torch.Tensor:
        """Mean undiscounted return of the batch's first episodes (the mask's valid steps)."""
        keys = self.tensor_keys
        return (td.get(("next", keys.reward)).squeeze(-1) * td.get(keys.mask)).sum(-1).mean()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        support, query = tensordict.get(keys.support), tensordict.get(keys.query)
        self._check(query, "query", [keys.action, keys.action_log_prob, keys.advantage, keys.loc, keys.scale, keys.mask])
        if query.shape[0] != support.shape[0]:
            raise ValueError(f"support has {support.shape[0]} tasks but query has {query.shape[0]}.")
        phi, inner = tensordict.get(keys.adapted, None), None
        if phi is None:
            phi, inner = self._adapt(support, None)
        surrogate, kl, ratio = self._surrogate_and_kl(phi, query)
        with torch.no_grad():
            if inner is None:  # adapted given, or no inner step
                inner = self.inner_loss(self.params, support).mean()
            return_pre, return_post = self._episode_return(support), self._episode_return(query)
        return TensorDict(
            {
                "loss_objective": surrogate,
                "kl": kl.detach(),
                "trust_region_kl": kl,
                "inner_loss": inner,
                "return_pre": return_pre,
                "return_post": return_post,
                "ratio_max": ratio.detach().max(),
            },
            batch_size=[],
        )
