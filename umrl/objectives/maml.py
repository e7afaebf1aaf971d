"""Functional MAML for policy gradients (Finn et al., 2017, https://arxiv.org/abs/1703.03400).

The policy's parameters live in a TensorDict (``TensorDict.from_module(policy)``). :meth:`MAMLLoss.adapt` takes
policy-gradient steps on each task's *support* batch and returns adapted parameters with a leading task
dimension; :meth:`MAMLLoss.forward` scores them on the *query* batch (collected with those same adapted parameters)
with TRPO's importance-weighted surrogate. The inner loss is an argument (vanilla PG by default). The outer optimiser
(``umrl.optim.trpo.TRPOStep``), its KL Hessian-vector products through the inner step (``umrl.optim.meta_hvp``) and
the advantage computation (``umrl.objectives.advantage.LinearBaselineGAE``) live outside the loss.

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

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torch.distributions import Normal, kl_divergence
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators

from umrl.objectives.advantage import LinearBaselineGAE, check_value_type
from umrl.objectives.policy_gradient import vpg_loss
from umrl.rollout import FunctionalPolicy
from umrl.validation import check_int, check_positive

__all__ = ["InnerLoss", "MAMLLoss", "gaussian_kl", "masked_mean"]

InnerLoss = Callable[..., torch.Tensor]
"""The inner step's loss: ``(log_prob, support, *, advantage_key, mask_key) -> [T]``. ``log_prob`` ``[T, N, H]`` is
the log-probability of the support's actions under the parameters being adapted, ``support`` the ``[T, N, H]`` batch,
the keys where it holds the advantage ``[T, N, H, 1]`` and the valid-step mask ``[T, N, H]``; the result, one loss
per task, is differentiated w.r.t. the parameters (:func:`~umrl.objectives.policy_gradient.vpg_loss` is the
default)."""


def gaussian_kl(loc0: torch.Tensor, scale0: torch.Tensor, loc1: torch.Tensor, scale1: torch.Tensor) -> torch.Tensor:
    """``KL(N(loc0, scale0²) ‖ N(loc1, scale1²))`` for diagonal Gaussians, summed over the last dim."""
    p, q = Normal(loc0, scale0, validate_args=False), Normal(loc1, scale1, validate_args=False)
    return kl_divergence(p, q).sum(-1)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` ``[T, N, H]`` over the valid steps of each task, then over tasks."""
    w = mask.to(x.dtype)
    return ((x * w).sum((-2, -1)) / w.sum((-2, -1)).clamp_min(1)).mean()


class MAMLLoss(LossModule):
    """MAML with a policy-gradient inner loop (vanilla PG by default) and a TRPO-style outer surrogate.

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
        inner_loss_fn: the inner step's per-task loss (:data:`InnerLoss`): ``(log_prob, support, *, advantage_key,
            mask_key) -> [T]``; default :func:`~umrl.objectives.policy_gradient.vpg_loss`. The loss's
            ``advantage`` and ``mask`` keys are passed on.

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
            reward, done: under ``"next"`` in each batch (the diagnostics' returns: a ``done`` ends each
                episode, as the env's own end or the horizon's ``StepCounter`` marks it; optional, without it each
                row holding a valid step is one episode). Defaults ``"reward"``, ``"done"``.
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
        done: NestedKey = "done"

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
        inner_loss_fn: InnerLoss = vpg_loss,
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
        if not callable(inner_loss_fn):
            raise TypeError(f"inner_loss_fn: got {inner_loss_fn!r}; expected a callable (log_prob, support, *, "
                            "advantage_key, mask_key) -> per-task losses [T], e.g. "
                            "umrl.objectives.policy_gradient.vpg_loss.")
        self.inner_loss_fn = inner_loss_fn

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            keys = self.tensor_keys
            self._value_estimator.set_keys(advantage=keys.advantage, mask=keys.mask, reward=keys.reward,
                                           done=keys.done)

    def make_value_estimator(self, value_type=None, **hyperparams) -> MAMLLoss:
        """Set :attr:`value_estimator`: rllab's linear feature baseline with GAE (``value_type`` None or
        ``ValueEstimators.GAE``); ``hyperparams``: ``gamma``, ``lmbda``, ``normalize`` of
        :class:`~umrl.objectives.advantage.LinearBaselineGAE` (MAML-RL's 0.99, 1.0, true by default). The loss's
        ``advantage``, ``mask``, ``reward`` and ``done`` keys are the estimator's (:meth:`set_keys` renames them in
        both); its own keys (``observation``, ``step_count``, ...) are renamed with ``value_estimator.set_keys``."""
        check_value_type(value_type)
        hyperparams.pop("device", None)  # TorchRL's default construction passes it; the baseline fits on the data's
        self._value_estimator = LinearBaselineGAE(**hyperparams)
        self._forward_value_estimator_keys()
        return self

    @property
    def in_keys(self) -> list[NestedKey]:
        """Every key :meth:`forward` reads (besides the optional ``adapted``), nested under support / query."""
        keys = self.tensor_keys
        shared = [keys.action, keys.advantage, keys.mask, ("next", keys.reward), ("next", keys.done),
                  *self.functional_policy.net.in_keys]
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

    def unpack(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        """``(support, query)`` of :meth:`pack`'s TensorDict."""
        return tensordict.get(self.tensor_keys.support), tensordict.get(self.tensor_keys.query)

    @property
    def params(self) -> TensorDictBase:
        """θ: a TensorDict sharing storage with the policy's parameters (what the outer optimiser updates)."""
        return TensorDict.from_module(self.policy)

    def _check(self, td: TensorDictBase, name: str, keys) -> None:
        if td.batch_dims != 3:
            raise ValueError(f"{name} must be a [T, N, H] batch of trajectories, got batch size {tuple(td.batch_size)}.")
        missing = [k for k in keys if k not in td.keys(True)]
        if missing:
            raise ValueError(f"{name} lacks keys {missing}: run the loss's value_estimator on rollouts from "
                             "umrl.rollout.collect (rename their entries to the keys set with set_keys).")

    def inner_loss(self, params: TensorDictBase, support: TensorDictBase) -> torch.Tensor:
        """Per-task inner loss ``[T]`` (:attr:`inner_loss_fn`) of ``params`` (shared or ``[T]``) on ``support``."""
        keys = self.tensor_keys
        log_prob = self.functional_policy.dist(params, support).log_prob(support[keys.action])
        return self.inner_loss_fn(log_prob, support, advantage_key=keys.advantage, mask_key=keys.mask)

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

    def dist_params(self, params: TensorDictBase, batch: TensorDictBase) -> TensorDictBase:
        """The Gaussian's ``"loc"`` and ``"scale"`` ``[T, N, H, act]`` of ``params`` (shared or ``[T]``) on
        ``batch`` ``[T, N, H]``."""
        return self.functional_policy.dist_params(params, batch)

    def mean_kl(self, loc0: torch.Tensor, scale0: torch.Tensor, loc1: torch.Tensor, scale1: torch.Tensor,
                batch: TensorDictBase) -> torch.Tensor:
        """``KL(N(loc0, scale0²) ‖ N(loc1, scale1²))`` (each ``[T, N, H, act]``) averaged over the valid steps of
        each task of ``batch``, then over tasks: a scalar."""
        return masked_mean(gaussian_kl(loc0, scale0, loc1, scale1), batch.get(self.tensor_keys.mask))

    def _surrogate_and_kl(
        self, phi: TensorDictBase, query: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        keys = self.tensor_keys
        dist_params = self.dist_params(phi, query)
        dist = self.policy.build_dist_from_params(dist_params)
        ratio = (dist.log_prob(query[keys.action]) - query[keys.action_log_prob]).exp()
        surrogate = -masked_mean(ratio * query[keys.advantage].squeeze(-1), query[keys.mask])
        kl = self.mean_kl(query[keys.loc], query[keys.scale], dist_params["loc"], dist_params["scale"], query)
        return surrogate, kl, ratio

    def _episode_return(self, td: TensorDictBase) -> torch.Tensor:
        """Mean undiscounted return of the batch's episodes, over each task's episodes (its valid steps' reward over
        its valid ``done`` flags: rows padded empty count for none, and a packed batch's rows, which are not
        episodes, give the same), then over tasks. A batch without ``done`` counts its rows that hold a valid step."""
        keys = self.tensor_keys
        mask = td.get(keys.mask)
        reward = (td.get(("next", keys.reward)).squeeze(-1) * mask).sum((-2, -1))
        done = td.get(("next", keys.done), None)
        episodes = mask.any(-1).sum(-1) if done is None else (done.squeeze(-1) & mask).sum((-2, -1))
        return (reward / episodes.clamp_min(1)).mean()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        support, query = self.unpack(tensordict)
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
