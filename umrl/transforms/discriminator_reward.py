"""DIAYN pseudo-reward r_z(s) = log D(z|s) - log p(z) with a uniform prior p(z) = 1/K.

Which state: by default the reward of transition (s_t, a_t, s_{t+1}) scores the state the action was taken in,
s_t = ``"observation"``, as DIAYN's reference code does (``sac/algos/diayn.py`` feeds the discriminator the batch's
``observations``, for the pseudo-reward and for its cross-entropy alike). The discriminator loss in
:class:`umrl.objectives.diayn.DIAYNLoss` uses the same key, so training and reward agree. The MAML task proposals
(:mod:`umrl.proposals`) pass ``observation_key=("next", "observation")``: a task rewards the state its action led
to, as the hand-designed task rewards do. The skill is read from the root ``"skill"`` (the skill that produced a_t;
identical to ``("next", "skill")`` within an episode).

The skill reward is written to ``("next", "reward")``, the key the losses read. The env's own reward is kept under
``("next", "env_reward")``: an env that already writes that key (umrl's MuJoCo envs put gymnasium's reward there and
leave ``"reward"`` at zero) keeps it as it is; otherwise the reward the env wrote to ``"reward"`` moves there first
(zero in point_nav's reward-free CMP).
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from umrl.modules.discriminator import discriminator_logits
from umrl.validation import InvalidValue, check_keys

__all__ = ["DiscriminatorReward", "check_skills", "skill_reward", "skill_rewards"]


def check_skills(name: str, skill: torch.Tensor, num_skills: int) -> torch.Tensor:
    """``skill`` if its last dim holds ``num_skills`` entries (one-hot skills ``[*B, K]``), else an error naming
    ``name``."""
    if skill.shape[-1:] != (num_skills,):
        raise InvalidValue(name, skill, f"one-hot skills [*B, {num_skills}] (num_skills)", note=f"shape {list(skill.shape)}")
    return skill


def skill_rewards(logits: torch.Tensor) -> torch.Tensor:
    """r_z = log D(z|s) - log p(z) = log_softmax(logits)[z] + log K for every skill: logits ``[*B, K]`` -> ``[*B, K]``.

    Differentiable; callers that only score states pass detached logits or run it under ``torch.no_grad``.
    """
    return torch.log_softmax(logits, dim=-1) + math.log(logits.shape[-1])


def skill_reward(logits: torch.Tensor, skill: torch.Tensor) -> torch.Tensor:
    """r_z for the given one-hot skills: logits ``[*B, K]``, skill ``[*B, K]`` -> ``[*B, 1]``."""
    return (skill_rewards(logits) * skill).sum(-1, keepdim=True)


class DiscriminatorReward(Transform):
    """Writes r = log_softmax(D(s))[z] + log K into ``("next", reward_key)``, computed under ``torch.no_grad``, and
    keeps the env's own reward under ``("next", env_reward_key)``.

    In an env (``_step``) it scores each new transition; called on a replay sample (``forward``) it *relabels* the
    batch with the discriminator's current weights (stale pseudo-rewards in a buffer are a bug). The module is held
    by reference: training it elsewhere changes the rewards this transform writes. A frozen random discriminator
    (``make_discriminator(..., seed=s).requires_grad_(False)``) gives UML-random's rewards.

    The env's reward: if ``("next", env_reward_key)`` is already there (written by the env, or by an earlier pass of
    this transform), it is left as it is; otherwise the incoming ``("next", reward_key)`` (zeros if the env writes
    no such key) is moved there before being replaced. At reset the key holds zeros; it is declared in the
    observation spec as float32 ``[*B, 1]``.

    Keys, TorchRL-style: ``in_keys = [observation_key, skill_key, reward_key]`` (the observation and skill of the
    step's input tensordict, or of ``"next"`` for a key starting with ``"next"``; the reward of ``"next"``),
    ``out_keys = [reward_key, env_reward_key]`` (under ``"next"``).

    Args:
        discriminator (TensorDictModuleBase): one in_key (observation, [*B, obs_dim]), one out_key (logits [*B, K]).
        num_skills (int): K; the prior is uniform, log p(z) = -log K.

    Keyword Args:
        observation_key (NestedKey): the state fed to D. Defaults to ``"observation"`` (s_t, DIAYN's reference).
        skill_key (NestedKey): one-hot skill [*B, K]. Defaults to ``"skill"``.
        reward_key (NestedKey): the skill reward, written under ``"next"``. Defaults to ``"reward"``.
        env_reward_key (NestedKey): where the env's own reward is kept, under ``"next"``. Defaults to
            ``"env_reward"``.

    Examples:
        >>> from umrl.envs import make_env
        >>> from umrl.modules.discriminator import make_discriminator
        >>> from umrl.transforms.skill import SkillTransform
        >>> disc = make_discriminator(2, 10)
        >>> env = make_env("point_nav", num_envs=4, seed=0)
        >>> env = env.append_transform(SkillTransform(10)).append_transform(DiscriminatorReward(disc, 10))
        >>> rollout = env.rollout(3)
        >>> rollout["next", "reward"].shape, rollout["next", "env_reward"].abs().max().item()  # point_nav: no reward
        (torch.Size([4, 3, 1]), 0.0)
    """

    def __init__(
        self,
        discriminator: TensorDictModuleBase,
        num_skills: int,
        *,
        observation_key: NestedKey = "observation",
        skill_key: NestedKey = "skill",
        reward_key: NestedKey = "reward",
        env_reward_key: NestedKey = "env_reward",
    ):
        if num_skills < 2:
            raise ValueError(f"num_skills must be >= 2, got {num_skills}.")
        if len(discriminator.in_keys) != 1 or len(discriminator.out_keys) != 1:
            raise ValueError(
                "the discriminator must read one key (the observation) and write one key (the logits); got "
                f"in_keys={discriminator.in_keys}, out_keys={discriminator.out_keys}."
            )
        observation_key, skill_key, reward_key, env_reward_key = map(
            unravel_key, (observation_key, skill_key, reward_key, env_reward_key))
        super().__init__(in_keys=[observation_key, skill_key, reward_key], out_keys=[reward_key, env_reward_key])
        self.discriminator = discriminator
        self.num_skills = num_skills
        self.observation_key, self.skill_key = observation_key, skill_key
        self.reward_key, self.env_reward_key = reward_key, env_reward_key

    def pseudo_reward(self, observation: torch.Tensor, skill: torch.Tensor) -> torch.Tensor:
        """log D(z|s) + log K for observations [*B, obs_dim] and one-hot skills [*B, K] -> [*B, 1], no grad."""
        check_skills("skill", skill, self.num_skills)
        with torch.no_grad():
            return skill_reward(discriminator_logits(self.discriminator, observation), skill)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        key = self.observation_key
        if isinstance(key, tuple) and key[0] == "next":
            observation = next_tensordict.get(key[1:], None)
        else:
            observation = tensordict.get(key, None)
        skill = tensordict.get(self.skill_key, None)
        if observation is None or skill is None:  # an env without the keys (no SkillTransform before this one)
            missing = [k for k, v in ((key, observation), (self.skill_key, skill)) if v is None]
            raise InvalidValue("env", self.parent, f"an env writing {[key, self.skill_key]} before this "
                               "DiscriminatorReward (append a SkillTransform first)",
                               note=f"no {', '.join(map(repr, missing))}")
        reward = self.pseudo_reward(observation, skill)
        self._keep_env_reward(next_tensordict)
        next_tensordict.set(self.reward_key, reward)
        return next_tensordict

    def _keep_env_reward(self, next_tensordict: TensorDictBase) -> None:
        """Move the env's reward from ``reward_key`` to ``env_reward_key`` (zeros if it wrote none there) unless the
        env already keeps it there."""
        if next_tensordict.get(self.env_reward_key, None) is None:
            env_reward = next_tensordict.get(self.reward_key, None)
            if env_reward is None:
                env_reward = torch.zeros((*next_tensordict.batch_size, 1), device=next_tensordict.device)
            next_tensordict.set(self.env_reward_key, env_reward)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if tensordict_reset.get(self.env_reward_key, None) is None:
            shape = (*tensordict_reset.batch_size, 1)
            tensordict_reset.set(self.env_reward_key, torch.zeros(shape, device=tensordict_reset.device))
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Relabels a batch of transitions (e.g. a replay sample) in place with the current discriminator; the
        batch's ``("next", reward_key)`` moves to ``("next", env_reward_key)`` first if that key is absent."""
        keys = [self.observation_key, self.skill_key]
        check_keys("tensordict", tensordict, keys, f"a batch of transitions with {keys}")
        reward = self.pseudo_reward(tensordict.get(self.observation_key), tensordict.get(self.skill_key))
        next_tensordict = tensordict.get("next", None)
        if next_tensordict is not None:
            self._keep_env_reward(next_tensordict)
        tensordict.set(unravel_key(("next", self.reward_key)), reward)
        return tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        if self.env_reward_key not in observation_spec.keys(True):
            observation_spec[self.env_reward_key] = Unbounded(
                shape=(*observation_spec.shape, 1), dtype=torch.float32, device=observation_spec.device
            )
        return observation_spec

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        reward_spec[self.reward_key] = Unbounded(
            shape=(*reward_spec.shape, 1), dtype=torch.float32, device=reward_spec.device
        )
        return reward_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_skills={self.num_skills}, in_keys={self.in_keys}, out_keys={self.out_keys})"
