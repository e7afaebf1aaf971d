"""DIAYN for S independent seeds in one update: stacked networks, one batched matmul per layer for all seeds.

:class:`StackedDIAYNLoss` is :class:`~umrl.objectives.diayn.DIAYNLoss` (TorchRL's ``SACLoss`` v2 with a TD(0) target,
plus the discriminator's cross-entropy) written for ``S`` seeds at once: every network is a
:class:`~umrl.modules.stacked_mlp.StackedMLP` and a batch has shape ``[S, B]`` (row ``s``: seed ``s``'s replay sample).
TorchRL's ``SACLoss`` evaluates one parameter set per call, so a per-seed loop would pay its Python and TensorDict
work S times per update; here it is paid once. The arithmetic is ``SACLoss``'s, term by term (tested equal on the same
batch and noise): the target ``r + gamma (1 - terminated) (min_i Q'_i(s', a') - alpha log pi(a'|s'))`` with target
Q-networks and ``a' ~ pi(.|s')`` under no gradient; the Q loss ``sum_i (Q_i(s, a) - target)^2`` averaged over the
batch; the actor loss ``alpha log pi(a~|s) - min_i Q_i(s, a~)`` with the Q-networks' parameters detached; the
tanh-Gaussian of TorchRL's ``TanhNormal`` (``NormalParamExtractor``'s biased softplus scale).

The action noise is an input (``"action_noise"`` and ``("next", "action_noise")``, standard normal ``[S, B, act]``)
so that each seed's noise comes from that seed's own generator (:class:`umrl.seed_replay.SeedReplay` draws it with
the sample): seed ``s``'s draws never depend on which other seeds share the program.

:meth:`StackedDIAYNLoss.gradients` computes the same outputs and every gradient by a hand-derived backward pass (no
autograd graph: the networks' activations kept, two matmuls and a ReLU mask per layer), equal to autograd's to float
rounding (measured: 2.2e-7 of a gradient's largest element in float32, 6e-16 in float64; ``tests/test_diayn_seeds.py``).
Its tensor work is one side-effect-free function (:meth:`StackedDIAYNLoss.hand_derived_gradients`), which
``StackedDIAYNUpdate(compile=True)`` compiles on a CPU.

:class:`StackedDIAYNUpdate` takes one Adam step on every seed's networks and Polyak-averages the targets, with the
hand-derived gradients by default (``gradients="autograd"``: the loss's forward and autograd). Adam and
Polyak averaging are element-wise, so one optimiser over stacked parameters is S independent optimisers (to float
rounding: a fused kernel's vectorised loop and its tail may round an element differently).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import NormalParamExtractor
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from umrl.modules.discriminator import ObservationDims
from umrl.modules.stacked_mlp import StackedMLP, linear_layers
from umrl.objectives.diayn import DIAYNLoss, UpdateRunner, check_capturable
from umrl.transforms.discriminator_reward import skill_reward
from umrl.validation import check_keys, check_probability

__all__ = ["GRADIENTS", "StackedDIAYNLoss", "StackedDIAYNUpdate", "tanh_normal_action", "tanh_normal_sample"]

GRADIENTS = ("analytic", "autograd")
"""How :class:`StackedDIAYNUpdate` computes gradients: derived by hand (the default) or by autograd."""

_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def _weight_bias_pairs(params: TensorDictBase) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The (weight, bias) leaves of a TorchRL MLP's parameter TensorDict, in layer order."""
    leaves = list(params.flatten_keys().values())
    return list(zip(leaves[0::2], leaves[1::2]))


def _twin_input(observation: torch.Tensor, skill: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The input ``[2S, M, in]`` of the twin Q-networks (rows ``2s``, ``2s + 1``: seed ``s``'s pair), each ``[S, M, ·]``."""
    x = torch.cat([observation, skill, action], -1)
    S, M = x.shape[:2]
    return x.unsqueeze(1).expand(S, 2, M, x.shape[-1]).reshape(2 * S, M, x.shape[-1])


def tanh_normal_action(loc: torch.Tensor, scale: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """The action of :func:`tanh_normal_sample` alone (acting needs no log-probability): ``tanh(loc + scale *
    noise)``."""
    return torch.tanh(loc + scale * noise)


def tanh_normal_sample(loc: torch.Tensor, scale: torch.Tensor, noise: torch.Tensor):
    """``(action, log_prob)`` of TorchRL's ``TanhNormal(loc, scale, low=-1, high=1)`` reparametrised by standard
    normal ``noise``: ``a = tanh(loc + scale * noise)``, ``log_prob`` summed over the last dim ``[*B]``."""
    pre_tanh = loc + scale * noise
    normal = -0.5 * noise.pow(2) - scale.log() - _LOG_SQRT_2PI
    # log |d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), torch's TanhTransform.log_abs_det_jacobian
    log_det = 2.0 * (math.log(2.0) - pre_tanh - torch.nn.functional.softplus(-2.0 * pre_tanh))
    return torch.tanh(pre_tanh), (normal - log_det).sum(-1)


class StackedDIAYNLoss(LossModule):
    """DIAYN's loss for ``S`` seeds with stacked networks (see the module docstring).

    Build it with :meth:`from_losses` from one :class:`~umrl.objectives.diayn.DIAYNLoss` per seed (each seed's
    networks initialised as a single-seed run initialises them); :meth:`copy_to` writes seed ``s`` back into such a
    loss (checkpoints, evaluation).

    Input (batch ``[S, B]``): ``observation`` [S, B, obs], ``skill`` [S, B, K] one-hot, ``action`` [S, B, act],
    ``action_noise`` [S, B, act]; under ``"next"``: ``observation``, ``skill``, ``terminated`` [S, B, 1],
    ``action_noise``. Output (batch ``[S]``, one value per seed): ``loss_actor``, ``loss_qvalue``, ``loss_alpha`` (0
    for a fixed alpha), ``loss_discriminator``, and detached ``alpha``, ``entropy``, ``discriminator_accuracy``,
    ``pseudo_reward``. Summing every ``loss_*`` over seeds and backpropagating gives each seed its own gradients.

    Examples:
        >>> from umrl.modules.discriminator import make_discriminator
        >>> from umrl.modules.sac import make_skill_actor, make_skill_qvalue
        >>> K = 4
        >>> def one_seed(seed):
        ...     torch.manual_seed(seed)
        ...     return DIAYNLoss(make_skill_actor(2, K, 2, hidden=(16,)), make_skill_qvalue(2, K, 2, hidden=(16,)),
        ...                      make_discriminator(2, K, hidden=(16,)), num_skills=K)
        >>> loss = StackedDIAYNLoss.from_losses([one_seed(0), one_seed(1)], gamma=0.99)
        >>> S, B = 2, 8
        >>> skill = torch.eye(K)[torch.randint(K, (S, B))]
        >>> batch = TensorDict({
        ...     "observation": torch.randn(S, B, 2), "skill": skill, "action": torch.rand(S, B, 2) * 2 - 1,
        ...     "action_noise": torch.randn(S, B, 2),
        ...     "next": {"observation": torch.randn(S, B, 2), "skill": skill, "action_noise": torch.randn(S, B, 2),
        ...              "terminated": torch.zeros(S, B, 1, dtype=torch.bool)}}, [S, B])
        >>> out = loss(batch)
        >>> out["loss_qvalue"].shape
        torch.Size([2])
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss (change them with ``set_keys``).

        Attributes:
            observation (NestedKey): the actor's and Q-networks' state input. Defaults to ``"observation"``.
            skill (NestedKey): one-hot skill. Defaults to ``"skill"``.
            discriminator_observation (NestedKey): the state D scores. Defaults to ``"observation"`` (s_t).
            action (NestedKey): Defaults to ``"action"``.
            noise (NestedKey): standard normal action noise, at the root (s_t) and under ``"next"`` (s'). Defaults
                to ``"action_noise"``.
            terminated (NestedKey): read under ``"next"``; bootstrapping stops only at termination. Defaults to
                ``"terminated"``.
        """

        observation: NestedKey = "observation"
        skill: NestedKey = "skill"
        discriminator_observation: NestedKey = "observation"
        action: NestedKey = "action"
        noise: NestedKey = "action_noise"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy", "loss_discriminator",
                "discriminator_accuracy", "pseudo_reward")

    def __init__(
        self,
        actor: StackedMLP,
        qvalue: StackedMLP,
        target_qvalue: StackedMLP,
        discriminator: StackedMLP,
        log_alpha: torch.Tensor,
        *,
        num_skills: int,
        gamma: float,
        fixed_alpha: bool = True,
        target_entropy: float = 0.0,
        discriminator_input_dims: Sequence[int] | None = None,
    ):
        super().__init__()
        self.num_seeds = actor.num_networks
        if qvalue.num_networks != 2 * self.num_seeds or target_qvalue.num_networks != 2 * self.num_seeds:
            raise ValueError(f"expected twin Q-networks for {self.num_seeds} seeds ({2 * self.num_seeds} stacked), "
                             f"got {qvalue.num_networks} and {target_qvalue.num_networks}.")
        self.actor, self.qvalue, self.discriminator = actor, qvalue, discriminator
        self.target_qvalue = target_qvalue.requires_grad_(False)
        self.num_skills, self.gamma, self.fixed_alpha = num_skills, check_probability("gamma", gamma), fixed_alpha
        self.target_entropy = target_entropy
        if fixed_alpha:
            self.register_buffer("log_alpha", log_alpha.detach().clone())
        else:
            self.log_alpha = torch.nn.Parameter(log_alpha.detach().clone())
        self.input_dims = None if discriminator_input_dims is None else ObservationDims(discriminator_input_dims)
        self.scale_map = NormalParamExtractor()  # TorchRL's biased softplus, as make_skill_actor's head
        self._required = None

    @classmethod
    def from_losses(cls, losses: Sequence[DIAYNLoss], *, gamma: float) -> StackedDIAYNLoss:
        """Stack one :class:`DIAYNLoss` per seed (same sizes and settings), copying their current parameters."""
        first = losses[0]
        dims = [module.dims.tolist() for module in first.discriminator.modules() if isinstance(module, ObservationDims)]

        def stacked_pairs(pairs_per_seed):  # [(w, b) per layer] per seed, each w [*lead, out, in]
            depth = len(pairs_per_seed[0])
            weights = [torch.stack([p[i][0].detach() for p in pairs_per_seed]) for i in range(depth)]
            biases = [torch.stack([p[i][1].detach() for p in pairs_per_seed]) for i in range(depth)]
            return StackedMLP([w.flatten(0, -3) for w in weights], [b.flatten(0, -2) for b in biases])

        sac = [loss.sac_loss for loss in losses]
        targets = [_weight_bias_pairs(s.target_qvalue_network_params) for s in sac]
        return cls(
            stacked_pairs([_weight_bias_pairs(s.actor_network_params) for s in sac]),
            stacked_pairs([_weight_bias_pairs(s.qvalue_network_params) for s in sac]),
            stacked_pairs(targets),
            StackedMLP.from_linears([linear_layers(loss.discriminator) for loss in losses]),
            torch.stack([s.log_alpha.detach() for s in sac]).reshape(len(losses)),
            num_skills=first.num_skills, gamma=gamma, fixed_alpha=first.fixed_alpha,
            target_entropy=float(sac[0].target_entropy), discriminator_input_dims=dims[0] if dims else None,
        )

    @torch.no_grad()
    def copy_to(self, seed_index: int, loss: DIAYNLoss) -> None:
        """Write seed ``seed_index``'s networks (actor, twin Q, targets, discriminator, alpha) into ``loss``."""
        sac = loss.sac_loss
        for stacked, params, twins in ((self.actor, sac.actor_network_params, 1),
                                       (self.qvalue, sac.qvalue_network_params, 2),
                                       (self.target_qvalue, sac.target_qvalue_network_params, 2)):
            rows = slice(seed_index * twins, (seed_index + 1) * twins)
            for (weight, bias), w, b in zip(_weight_bias_pairs(params), stacked.weights, stacked.biases, strict=True):
                weight.data.copy_(w[rows].reshape(weight.shape))
                bias.data.copy_(b[rows].reshape(bias.shape))
        self.discriminator.copy_to(seed_index, linear_layers(loss.discriminator))
        sac.log_alpha.data.copy_(self.log_alpha[seed_index].reshape(sac.log_alpha.shape))

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._required = None

    def make_value_estimator(self, value_type=None, **hyperparams):
        """The target is TD(0) with ``gamma`` (set at construction); ``gamma=`` here changes it."""
        if value_type is not None:
            raise NotImplementedError(f"{type(self).__name__} computes a TD(0) target only, got {value_type}.")
        self.gamma = hyperparams.get("gamma", self.gamma)
        return self

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        keys = {k.observation, k.skill, k.discriminator_observation, k.action, k.noise,
                ("next", k.observation), ("next", k.skill), ("next", k.noise), ("next", k.terminated)}
        return sorted(keys, key=str)

    def policy_params(self, observation: torch.Tensor, skill: torch.Tensor, *, detach: bool = False):
        """``(loc, scale)`` ``[S, M, act]`` of every seed's policy at ``observation`` [S, M, obs], ``skill`` [S, M, K]."""
        params = self.actor(torch.cat([observation, skill], -1), detach=detach)
        return self.scale_map(params)

    def twin_q(self, observation, skill, action, network: StackedMLP, *, detach: bool = False) -> torch.Tensor:
        """``[S, 2, M]``: both Q-networks of every seed at (observation, skill, action), each ``[S, M, ·]``."""
        return network(_twin_input(observation, skill, action), detach=detach).view(observation.shape[0], 2, -1)

    def discriminator_logits(self, observation: torch.Tensor) -> torch.Tensor:
        """D's logits ``[S, M, K]`` for every seed."""
        return self.discriminator(self.discriminator_input(observation))

    def discriminator_input(self, observation: torch.Tensor) -> torch.Tensor:
        """The observation dims D sees (all of them unless ``discriminator_input_dims``)."""
        return observation if self.input_dims is None else self.input_dims(observation)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self.tensor_keys
        if self._required is None:
            self._required = self.in_keys
        check_keys("tensordict", tensordict, self._required, f"a batch [S, B] of transitions with {self._required}")
        obs, skill, action = tensordict.get(k.observation), tensordict.get(k.skill), tensordict.get(k.action)
        next_obs, next_skill = tensordict.get(("next", k.observation)), tensordict.get(("next", k.skill))
        not_terminated = (~tensordict.get(("next", k.terminated))).squeeze(-1).to(obs.dtype)
        alpha = self.log_alpha.detach().exp().unsqueeze(-1)  # [S, 1]

        logits = self.discriminator_logits(tensordict.get(k.discriminator_observation))
        reward = skill_reward(logits.detach(), skill).squeeze(-1)  # [S, B]
        with torch.no_grad():
            loc, scale = self.policy_params(next_obs, next_skill)
            next_action, next_log_prob = tanh_normal_sample(loc, scale, tensordict.get(("next", k.noise)))
            next_q = self.twin_q(next_obs, next_skill, next_action, self.target_qvalue)
            next_value = (next_q - alpha.unsqueeze(1) * next_log_prob.unsqueeze(1)).min(1).values
            target = reward + self.gamma * not_terminated * next_value
        predicted = self.twin_q(obs, skill, action, self.qvalue)
        loss_qvalue = (predicted - target.unsqueeze(1)).pow(2).sum(1).mean(-1)

        loc, scale = self.policy_params(obs, skill)
        new_action, log_prob = tanh_normal_sample(loc, scale, tensordict.get(k.noise))
        min_q = self.twin_q(obs, skill, new_action, self.qvalue, detach=True).min(1).values
        loss_actor = (alpha * log_prob - min_q).mean(-1)
        if self.fixed_alpha:
            loss_alpha = torch.zeros_like(loss_actor)
        else:
            loss_alpha = -(self.log_alpha.unsqueeze(-1) * (log_prob.detach() + self.target_entropy)).mean(-1)

        label = skill.argmax(-1)
        loss_discriminator = torch.nn.functional.cross_entropy(
            logits.flatten(0, 1), label.flatten(), reduction="none").view(label.shape).mean(-1)
        return TensorDict({
            "loss_actor": loss_actor, "loss_qvalue": loss_qvalue, "loss_alpha": loss_alpha,
            "loss_discriminator": loss_discriminator, "alpha": alpha.squeeze(-1),
            "entropy": -log_prob.detach().mean(-1),
            "discriminator_accuracy": (logits.detach().argmax(-1) == label).float().mean(-1),
            "pseudo_reward": reward.mean(-1),
        }, batch_size=[self.num_seeds])

    def gradient_inputs(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """The batch tensors :meth:`hand_derived_gradients` reads, in its argument order (observation, skill,
        action, noise, the discriminator's observation; under ``"next"``: observation, skill, noise,
        terminated)."""
        k = self.tensor_keys
        return tuple(tensordict.get(key) for key in (
            k.observation, k.skill, k.action, k.noise, k.discriminator_observation,
            ("next", k.observation), ("next", k.skill), ("next", k.noise), ("next", k.terminated)))

    def matmul_plan(self, batch: torch.Tensor) -> tuple[bool, bool, bool, bool]:
        """Whether the actor, the Q-networks, the target Q-networks and the discriminator run network by network
        (:meth:`StackedMLP.per_network_matmuls`) on ``batch``'s device: decided outside
        :meth:`hand_derived_gradients`, which a compiler may trace."""
        return tuple(network.per_network_matmuls(batch)
                     for network in (self.actor, self.qvalue, self.target_qvalue, self.discriminator))

    @torch.no_grad()
    def gradients(self, tensordict: TensorDictBase, function=None) -> TensorDictBase:
        """:meth:`forward`'s outputs (detached) on ``tensordict``, with every trained parameter's ``.grad`` (actor,
        Q-networks, discriminator, a learned ``log_alpha``) set to the gradient of their sum over seeds: autograd's
        result, derived by hand and without an autograd graph (equal to float rounding, ``tests/test_diayn_seeds.py``).

        ``function``: :meth:`hand_derived_gradients` (None) or a compiled version of it
        (:class:`StackedDIAYNUpdate` with ``compile``)."""
        inputs = self.gradient_inputs(tensordict)
        outputs, grads = (function or self.hand_derived_gradients)(*inputs, self.matmul_plan(inputs[0]))
        for network, (weight_grads, bias_grads) in zip((self.discriminator, self.actor, self.qvalue), grads):
            network.set_grads(weight_grads, bias_grads)
        if not self.fixed_alpha:
            self.log_alpha.grad = grads[-1]
        return TensorDict(dict(zip(self._GRADIENT_OUTPUTS, outputs)), batch_size=[self.num_seeds])

    _GRADIENT_OUTPUTS = ("loss_actor", "loss_qvalue", "loss_alpha", "loss_discriminator", "alpha", "entropy",
                         "discriminator_accuracy", "pseudo_reward")

    @torch.no_grad()
    def hand_derived_gradients(self, obs, skill, action, noise, discriminator_obs, next_obs, next_skill, next_noise,
                               terminated, plan: tuple[bool, bool, bool, bool]):
        """The tensor work of :meth:`gradients` (arguments: :meth:`gradient_inputs` and :meth:`matmul_plan`):
        ``(outputs, grads)``, ``outputs`` the values of ``_GRADIENT_OUTPUTS`` ``[S]`` each, ``grads`` the
        discriminator's, the actor's and the Q-networks' ``(weight_grads, bias_grads)`` and the learned
        ``log_alpha``'s gradient (None for a fixed alpha). Tensors in, tensors out, no side effect: a compiler can
        trace it whole.

        Each network keeps its activations in the forward (:meth:`StackedMLP.forward_saving`) and backpropagates
        with two matmuls and a ReLU mask per layer (:meth:`StackedMLP.backward`). The actor runs once on ``[s; s']``
        (the actor loss at s, the target's a' at s'), the Q-networks once on ``[(s, a); (s, a~)]``: the actor loss's
        rows reach only the action input, as through ``SACLoss``'s detached Q parameters. With ``u = loc + scale
        noise``, ``a~ = tanh(u)``, ``log pi = sum_j (log N(noise_j) - log scale_j - log(1 - tanh(u_j)^2))``, the
        actor loss ``mean_b (alpha log pi - min_i Q_i(s, a~))`` has ``d/du = (2 alpha tanh u - dQ_min/da (1 -
        tanh(u)^2)) / B``, ``d/dloc = d/du`` and ``d/dscale = d/du noise - alpha / (B scale)``; the biased softplus
        ``scale = softplus(raw + c) + 0.01`` gives ``d/draw = d/dscale sigmoid(raw + c)`` (its ``clamp_min(1e-4)``
        never binds). The Q loss gives ``2 (Q_i(s, a) - y) / B`` at each Q output, the cross-entropy ``(softmax -
        onehot(z)) / B`` at D's logits, a learned alpha's loss ``-mean_b (log pi + H)`` at ``log_alpha``.
        """
        actor_per_network, q_per_network, target_per_network, d_per_network = plan
        not_terminated = (~terminated).squeeze(-1).to(obs.dtype)
        S, B, act_dim = *obs.shape[:2], action.shape[-1]
        alpha = self.log_alpha.exp().unsqueeze(-1)  # [S, 1]
        alpha_by_batch = (alpha / B).unsqueeze(-1)  # [S, 1, 1]

        # discriminator: the pseudo-reward and the cross-entropy from one log-softmax
        d_activations = self.discriminator.forward_saving(self.discriminator_input(discriminator_obs),
                                                          per_network=d_per_network)
        log_p = torch.log_softmax(d_activations[-1], -1)  # [S, B, K]
        log_p_skill = (log_p * skill).sum(-1)  # [S, B]: only skill z's term is nonzero
        reward = log_p_skill + math.log(log_p.shape[-1])  # skill_reward's arithmetic, bit for bit
        loss_discriminator = -log_p_skill.mean(-1)
        d_weights, d_biases, _ = self.discriminator.backward(d_activations, (log_p.exp() - skill).div_(B),
                                                             per_network=d_per_network)

        # the actor at s (rows :B) and at s' (rows B:, the target's next action)
        actor_activations = self.actor.forward_saving(
            torch.cat([torch.cat([obs, skill], -1), torch.cat([next_obs, next_skill], -1)], 1),
            per_network=actor_per_network)
        loc, scale = self.scale_map(actor_activations[-1])
        next_action, next_log_prob = tanh_normal_sample(loc[:, B:], scale[:, B:], next_noise)
        next_q = self.target_qvalue.forward_saving(_twin_input(next_obs, next_skill, next_action),
                                                   per_network=target_per_network)[-1].view(S, 2, B)
        next_value = (next_q - alpha.unsqueeze(1) * next_log_prob.unsqueeze(1)).min(1).values
        target = reward + self.gamma * not_terminated * next_value

        new_action, log_prob = tanh_normal_sample(loc[:, :B], scale[:, :B], noise)
        q_activations = self.qvalue.forward_saving(_twin_input(
            torch.cat([obs, obs], 1), torch.cat([skill, skill], 1), torch.cat([action, new_action], 1)),
            per_network=q_per_network)
        q = q_activations[-1].view(S, 2, 2 * B)
        error, min_q = q[..., :B] - target.unsqueeze(1), q[..., B:].min(1)
        loss_qvalue = error.pow(2).sum(1).mean(-1)
        loss_actor = (alpha * log_prob - min_q.values).mean(-1)

        # Q: the Q loss's rows train the networks; the actor loss's reach the action through the lower twin only
        grad_q = torch.cat([error.mul_(2.0 / B),
                            torch.zeros_like(error).scatter_(1, min_q.indices.unsqueeze(1), -1.0 / B)], -1)
        q_weights, q_biases, grad_action = self.qvalue.backward(
            q_activations, grad_q.view(2 * S, 2 * B, 1), weight_rows=slice(0, B), input_rows=slice(B, 2 * B),
            input_columns=slice(-act_dim, None), per_network=q_per_network)
        grad_action = grad_action.view(S, 2, B, act_dim).sum(1)  # both twins read the same action

        # the actor: through tanh, the reparametrised sample and the biased softplus of the scale
        grad_u = alpha_by_batch * 2.0 * new_action + grad_action * (1.0 - new_action * new_action)
        grad_scale = grad_u * noise - alpha_by_batch / scale[:, :B]
        raw_scale = actor_activations[-1][:, :B, act_dim:]
        grad_raw = grad_scale.mul_(torch.sigmoid(raw_scale + self.scale_map.scale_mapping.bias))
        actor_weights, actor_biases, _ = self.actor.backward(
            [activation[:, :B] for activation in actor_activations], torch.cat([grad_u, grad_raw], -1),
            per_network=actor_per_network)

        if self.fixed_alpha:
            loss_alpha, alpha_grad = torch.zeros_like(loss_actor), None
        else:
            loss_alpha = -(self.log_alpha.unsqueeze(-1) * (log_prob + self.target_entropy)).mean(-1)
            alpha_grad = -(log_prob + self.target_entropy).mean(-1)
        outputs = (loss_actor, loss_qvalue, loss_alpha, loss_discriminator, alpha.squeeze(-1), -log_prob.mean(-1),
                   (d_activations[-1].argmax(-1) == skill.argmax(-1)).float().mean(-1), reward.mean(-1))
        return outputs, ((d_weights, d_biases), (actor_weights, actor_biases), (q_weights, q_biases), alpha_grad)


class StackedDIAYNUpdate:
    """One update of every seed: :class:`StackedDIAYNLoss` -> backward -> Adam steps -> Polyak-averaged targets.

    Args:
        loss (StackedDIAYNLoss): the loss (its parameters and the batches on one device).

    Keyword Args:
        lr (float): Adam's rate for the actor and the Q-networks (and a learned alpha).
        discriminator_lr (float): Adam's rate for the discriminator.
        tau (float): Polyak rate of the target Q-networks (TorchRL's ``SoftUpdate``: ``target.lerp_(online, tau)``).
        compile (bool or str), cudagraphs (bool): as :class:`~umrl.objectives.diayn.DIAYNUpdate` (CUDA only for
            graphs, whose batches must keep one shape; the optimisers are then built ``capturable``). On a CPU with
            the hand-derived gradients, ``compile`` compiles :meth:`StackedDIAYNLoss.hand_derived_gradients` alone
            (inductor: its element-wise work fused into a few C++ loops, the matmuls left to the BLAS; ``True``:
            mode ``"default"``) and Adam stays the fused eager kernel; the first update then compiles, ≈ 20 s at 2
            × 300 networks and S = 1, ≈ 1 min at S = 3 on a 2-core CPU (measured; seconds when inductor's on-disk
            cache holds it), and the compiled gradients equal the eager ones to float rounding
            (``tests/test_diayn_seeds.py``): a run resumed with another ``compile`` continues to rounding, not bit
            for bit.
        gradients (str): ``"analytic"`` (default): :meth:`StackedDIAYNLoss.gradients`, the hand-derived backward;
            ``"autograd"``: the loss's forward and autograd (the reference it is tested against).

    ``update(batch)`` returns the loss's output, detached (batch ``[S]``). :attr:`optimizers` holds the one Adam
    optimiser (``{"adam": ...}``, for checkpoints), whose parameter groups are the actor, the Q-networks, the
    discriminator (at ``discriminator_lr``) and a learned alpha: one ``step`` call a update, each group the Adam of
    TorchRL's recipe for it.
    """

    def __init__(self, loss: StackedDIAYNLoss, *, lr: float, discriminator_lr: float, tau: float,
                 compile: bool | str = False, cudagraphs: bool = False, gradients: str = "analytic"):
        if gradients not in GRADIENTS:
            raise ValueError(f"gradients={gradients!r} is not one of {GRADIENTS}.")
        self.loss, self.tau, self.gradients = loss, tau, gradients
        adam = {"capturable": cudagraphs, "fused": True}
        groups = [{"params": list(loss.actor.parameters())}, {"params": list(loss.qvalue.parameters())},
                  {"params": list(loss.discriminator.parameters()), "lr": discriminator_lr}]
        if not loss.fixed_alpha:
            groups.append({"params": [loss.log_alpha]})
        self.optimizers = {"adam": torch.optim.Adam(groups, lr=lr, **adam)}
        self._targets = list(loss.target_qvalue.parameters())
        self._online = list(loss.qvalue.parameters())
        device = loss.log_alpha.device
        check_capturable(self.optimizers, cudagraphs, device)
        # on a CPU the hand-derived gradients alone are compiled: Adam is already fused
        target = loss.hand_derived_gradients if device.type == "cpu" and gradients == "analytic" else None
        self.runner = UpdateRunner(self._step, compile=compile, cudagraphs=cudagraphs, device=device,
                                   compile_target=target)

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        return self.runner(batch)

    def _step(self, batch: TensorDictBase) -> TensorDictBase:
        if self.gradients == "analytic":
            out = self.loss.gradients(batch, self.runner.compiled_target)
        else:
            out = self.loss(batch)
            sum(out[key].sum() for key in ("loss_actor", "loss_qvalue", "loss_alpha", "loss_discriminator")).backward()
        for optimizer in self.optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            torch._foreach_lerp_(self._targets, self._online, self.tau)
        return out.detach()
