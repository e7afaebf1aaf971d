"""Skill (latent) sampling for latent-conditioned rollouts.

:class:`SkillTransform` is a :class:`~torchrl.envs.transforms.TensorDictPrimer` that writes a one-hot ``"skill"``
[*B, K] (float32) at every (partial) reset, drawn uniformly from the K skills, and carries it unchanged through the
episode (into ``("next", "skill")`` at every step). The skill lives in the env's state spec, so
``env.full_state_spec["skill"]`` is a ``OneHot(K)`` and policies read it as a separate key (e.g. an ``MLP`` over
``["observation", "skill"]``), never by slicing it out of the observation.

Evaluation pins a skill per env copy with :meth:`SkillTransform.pin`; the pinned index is used from the next reset of
each copy on, ``pin(None)`` restores uniform sampling.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torchrl.data import OneHot
from torchrl.envs.transforms import TensorDictPrimer

__all__ = ["SkillTransform"]


class SkillTransform(TensorDictPrimer):
    """Samples z ~ Uniform{0..K-1} at each (partial) reset and writes it one-hot under ``skill_key``.

    Args:
        num_skills (int): K >= 2.

    Keyword Args:
        skill_key (NestedKey): where the one-hot skill [*B, K] float32 is written. Defaults to ``"skill"``.
        generators (sequence of torch.Generator, optional): one per equal group of consecutive env copies (a
            multi-seed run: one per seed), on any device; a reset copy draws its skill from its group's generator,
            and only reset copies draw, so a group's skills never depend on the other groups. Defaults to ``None``:
            torch's global generator, for every copy at each reset (TorchRL's ``TensorDictPrimer``).

    Examples:
        >>> from umrl.envs import make_env
        >>> env = make_env("point_nav", num_envs=4, seed=0).append_transform(SkillTransform(8))
        >>> td = env.reset()
        >>> td["skill"].shape
        torch.Size([4, 8])
        >>> env.transform[-1].pin(torch.tensor([0, 1, 2, 3]))
        >>> env.reset()["skill"].argmax(-1)
        tensor([0, 1, 2, 3])
    """

    def __init__(self, num_skills: int, *, skill_key="skill", generators: Sequence[torch.Generator] | None = None):
        if not isinstance(num_skills, int) or num_skills < 2:
            raise ValueError(f"num_skills must be an int >= 2, got {num_skills!r}.")
        super().__init__(
            primers={skill_key: OneHot(num_skills, dtype=torch.float32)}, random=True, expand_specs=True
        )
        self.num_skills = num_skills
        self.skill_key = skill_key
        self._pinned: torch.Tensor | None = None
        self._generators = None if generators is None else list(generators)

    def pin(self, skills: torch.Tensor | None) -> None:
        """Fixes the skill index of each env copy (LongTensor [*B], values in [0, K)); ``None`` samples again.

        Takes effect at the next reset of each copy (a full ``env.reset()`` applies it everywhere).
        """
        if skills is None:
            self._pinned = None
            return
        skills = torch.as_tensor(skills)
        if skills.dtype.is_floating_point or skills.dtype == torch.bool:
            raise ValueError(f"pin expects integer skill indices, got dtype {skills.dtype}.")
        if skills.numel() and (skills.min() < 0 or skills.max() >= self.num_skills):
            raise ValueError(f"pinned skills must lie in [0, {self.num_skills}), got {skills.tolist()}.")
        self._pinned = skills.long()

    @property
    def pinned(self) -> torch.Tensor | None:
        """The pinned skill indices, or ``None`` when skills are sampled."""
        return self._pinned

    def _apply_pin(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._pinned is None:
            return tensordict
        current = tensordict.get(self.skill_key)
        batch_shape = current.shape[:-1]
        try:
            pinned = self._pinned.to(current.device).expand(batch_shape)
        except RuntimeError as err:
            raise ValueError(
                f"pinned skills of shape {tuple(self._pinned.shape)} do not fit the env batch {tuple(batch_shape)}."
            ) from err
        one_hot = torch.nn.functional.one_hot(pinned, self.num_skills).to(current.dtype)
        tensordict.set(self.skill_key, one_hot)
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if self._generators is not None:
            return self._apply_pin(self._draw_per_group(tensordict, tensordict_reset))
        # The parent samples a skill for every copy; env.reset keeps the new value only where "_reset" is set.
        tensordict_reset = super()._reset(tensordict, tensordict_reset)
        if self.skill_key in tensordict_reset.keys(True):
            tensordict_reset = self._apply_pin(tensordict_reset)
        return tensordict_reset

    def _draw_per_group(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        """A skill for every copy, drawn from its group's generator where the copy resets (env.reset keeps only
        those)."""
        batch = tensordict_reset.batch_size
        mask = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones(batch.numel(), dtype=torch.bool) if mask is None else mask.reshape(-1).cpu()
        groups = len(self._generators)
        if mask.numel() % groups:
            raise ValueError(f"{groups} skill generators cannot split {mask.numel()} env copies into equal groups.")
        index = torch.zeros(mask.numel(), dtype=torch.long)
        for group, (rows, generator) in enumerate(zip(mask.view(groups, -1), self._generators)):
            reset = rows.nonzero().squeeze(-1)
            if reset.numel():
                # a generator draws on its own device (a CUDA run's are on the GPU, shared with the replay)
                draw = torch.randint(self.num_skills, (reset.numel(),), generator=generator, device=generator.device)
                index[reset + group * rows.numel()] = draw.cpu()
        skill = torch.nn.functional.one_hot(index.view(batch), self.num_skills).float()
        tensordict_reset.set(self.skill_key, skill.to(tensordict_reset.device))
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Out-of-env use: writes a fresh (or pinned) skill for every element of ``tensordict``."""
        index = torch.randint(self.num_skills, tensordict.shape, device=tensordict.device)
        tensordict.set(self.skill_key, torch.nn.functional.one_hot(index, self.num_skills).float())
        return self._apply_pin(tensordict)
