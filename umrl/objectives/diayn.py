"""DIAYN: "Diversity is All You Need" (Eysenbach et al., 2018, https://arxiv.org/abs/1802.06070).

A skill-conditioned policy pi(a|s,z) is trained by SAC on the pseudo-reward r = log D(z|s') - log p(z) while a
discriminator D(z|s') learns to tell the skills apart from the states they visit. UMRL (Gupta et al., 2018,
https://arxiv.org/abs/1806.04640) keeps D as a task proposal: r_z(s) = log D(z|s) defines one task per skill.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule, SACLoss
from torchrl.objectives.utils import ValueEstimators

from umrl.transforms.discriminator_reward import DiscriminatorReward

__all__ = ["DIAYNLoss"]


class DIAYNLoss(LossModule):
    """SAC on discriminator pseudo-rewards (TorchRL's :class:`~torchrl.objectives.SACLoss`) + D's cross-entropy.

    At every call the batch's ``("next", "reward")`` is recomputed with the *current* discriminator (on a shallow
    copy: the input tensordict is not modified), as DIAYN's reference code does, so replay samples never carry stale
    rewards. The discriminator is trained on the same state its reward scores (``discriminator_observation``, s_{t+1}
    by default) with the skill index as label.

    Args:
        actor_network (ProbabilisticActor): pi(a|s,z), e.g. :func:`umrl.modules.sac.make_skill_actor`.
        qvalue_network (TensorDictModule): Q(s,z,a), e.g. :func:`umrl.modules.sac.make_skill_qvalue`; SACLoss
            makes ``num_qvalue_nets`` independently initialised copies (and their target copies).
        discriminator (TensorDictModuleBase): D, one in_key (observation) and one out_key (logits [*B, K]), e.g.
            :func:`umrl.modules.discriminator.make_discriminator`.

    Keyword Args:
        num_skills (int): K >= 2 (uniform prior p(z) = 1/K).
        alpha_init (float): entropy coefficient. Defaults to 0.1 (DIAYN's entropy scale).
        fixed_alpha (bool): keep alpha at ``alpha_init`` (paper). Defaults to ``True``; then ``loss_alpha`` is 0.
        target_entropy (float or "auto"): for a learned alpha; ``"auto"`` needs ``action_spec``.
        action_spec (TensorSpec, optional): unbatched action spec, used by ``target_entropy="auto"``.
        num_qvalue_nets (int): twin Q by default (2).
        loss_function (str): Q regression loss. Defaults to ``"l2"`` (the reference SAC's MSE).

    Returns (``forward``): a TensorDict with ``loss_actor``, ``loss_qvalue``, ``loss_alpha``,
    ``loss_discriminator`` (each reaches only its own parameters) and detached diagnostics ``alpha``,
    ``entropy``, ``discriminator_accuracy`` (fraction of the batch whose argmax D(s') is the true skill) and
    ``pseudo_reward`` (mean relabelled reward).

    The discount is set as in TorchRL: ``loss.make_value_estimator(gamma=0.99)`` (TD(0), gamma 0.99 by default).
    Target Q-networks are updated with ``SoftUpdate(loss.sac_loss, tau=0.01)``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from umrl.modules.discriminator import make_discriminator
        >>> from umrl.modules.sac import make_skill_actor, make_skill_qvalue
        >>> obs_dim, act_dim, K, B = 2, 2, 4, 8
        >>> loss = DIAYNLoss(make_skill_actor(obs_dim, K, act_dim, hidden=(16,)),
        ...                  make_skill_qvalue(obs_dim, K, act_dim, hidden=(16,)),
        ...                  make_discriminator(obs_dim, K, hidden=(16,)), num_skills=K)
        >>> skill = torch.eye(K)[torch.randint(K, (B,))]
        >>> data = TensorDict({
        ...     "observation": torch.randn(B, obs_dim), "skill": skill, "action": torch.rand(B, act_dim) * 2 - 1,
        ...     "next": {"observation": torch.randn(B, obs_dim), "skill": skill, "reward": torch.zeros(B, 1),
        ...              "done": torch.zeros(B, 1, dtype=torch.bool),
        ...              "terminated": torch.zeros(B, 1, dtype=torch.bool)},
        ... }, [B])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_alpha', 'loss_discriminator', 'loss_qvalue']
        >>> sum(out[k] for k in out.keys() if k.startswith("loss_")).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss (change them with ``set_keys``).

        Attributes:
            skill (NestedKey): one-hot skill [*B, K]. Defaults to ``"skill"``.
            discriminator_observation (NestedKey): the state D scores and is trained on. Defaults to
                ``("next", "observation")`` (s_{t+1}).
            action (NestedKey): Defaults to ``"action"``.
            log_prob (NestedKey): Defaults to ``"action_log_prob"``.
            reward (NestedKey): pseudo-reward, written under ``"next"`` on the copy. Defaults to ``"reward"``.
            done (NestedKey): Defaults to ``"done"``.
            terminated (NestedKey): Defaults to ``"terminated"``; bootstrapping stops only at termination, so
                time-limit truncation keeps its bootstrap.
            state_action_value (NestedKey): Q output. Defaults to ``"state_action_value"``.
            priority (NestedKey): SAC's TD error key (written on the copy only). Defaults to ``"td_error"``.
        """

        skill: NestedKey = "skill"
        discriminator_observation: NestedKey = ("next", "observation")
        action: NestedKey = "action"
        log_prob: NestedKey = "action_log_prob"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"
        priority: NestedKey = "td_error"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    _SAC_KEYS = ("action", "log_prob", "reward", "done", "terminated", "state_action_value", "priority")

    def __init__(
        self,
        actor_network: ProbabilisticActor,
        qvalue_network: TensorDictModule,
        discriminator: TensorDictModuleBase,
        *,
        num_skills: int,
        alpha_init: float = 0.1,
        fixed_alpha: bool = True,
        target_entropy: float | str = "auto",
        action_spec: TensorSpec | None = None,
        num_qvalue_nets: int = 2,
        loss_function: str = "l2",
    ):
        if num_skills < 2:
            raise ValueError(f"num_skills must be >= 2, got {num_skills}.")
        if alpha_init <= 0:
            raise ValueError(f"alpha_init must be positive, got {alpha_init}.")
        super().__init__()
        self.num_skills = num_skills
        self.fixed_alpha = fixed_alpha
        self.sac_loss = SACLoss(
            actor_network,
            qvalue_network,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            alpha_init=alpha_init,
            fixed_alpha=fixed_alpha,
            target_entropy=0.0 if fixed_alpha else target_entropy,
            action_spec=action_spec,
        )
        # SACLoss registers its target-entropy buffer lazily; materialise it so state dicts round-trip.
        _ = self.sac_loss.target_entropy
        self.discriminator = discriminator
        self._forward_value_estimator_keys()

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self.sac_loss.set_keys(**{name: getattr(self.tensor_keys, name) for name in self._SAC_KEYS})
        # Held outside the module registry: the discriminator's weights are saved once, under "discriminator".
        self.__dict__["_relabel"] = DiscriminatorReward(
            self.discriminator,
            self.num_skills,
            observation_key=self.tensor_keys.discriminator_observation,
            skill_key=self.tensor_keys.skill,
            reward_key=self.tensor_keys.reward,
        )

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        """Sets SAC's value estimator (e.g. ``make_value_estimator(gamma=0.99)``)."""
        self.sac_loss.make_value_estimator(value_type, **hyperparams)
        return self

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = set(self.sac_loss.in_keys) | {
            unravel_key(self.tensor_keys.skill), unravel_key(self.tensor_keys.discriminator_observation)
        }
        return sorted(keys, key=str)

    def discriminator_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Cross-entropy of D(z|s') against the true skill, and the (detached) accuracy of its argmax."""
        observation = tensordict.get(self.tensor_keys.discriminator_observation)
        label = tensordict.get(self.tensor_keys.skill).argmax(-1)
        td = TensorDict({self.discriminator.in_keys[0]: observation}, batch_size=observation.shape[:-1])
        logits = self.discriminator(td).get(self.discriminator.out_keys[0])
        loss = torch.nn.functional.cross_entropy(logits.flatten(0, -2), label.flatten())
        accuracy = (logits.argmax(-1) == label).float().mean().detach()
        return loss, accuracy

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        data = tensordict.copy()  # shallow: the relabelled reward and SAC's td_error land on the copy only
        self._relabel(data)
        out = self.sac_loss(data)
        if self.fixed_alpha:
            out.set("loss_alpha", torch.zeros((), device=out["loss_actor"].device))
        loss_discriminator, accuracy = self.discriminator_loss(data)
        out.set("loss_discriminator", loss_discriminator)
        out.set("discriminator_accuracy", accuracy)
        out.set("pseudo_reward", data.get(("next", self.tensor_keys.reward)).mean().detach())
        return out
