"""Batched 2-D point navigation CMP, in pure torch.

All ``B`` copies step in one tensor operation; there is no Python loop over copies.

Semantics (docs/protocol.md): the point starts at (0, 0); the action is clipped to [-1, 1]² and scaled by 0.1, so a step
moves at most 0.1 per axis; the position is unbounded unless ``arena=a`` clips it to [-a, a]² after every step (an
ablation used only in meta-training, see :mod:`umrl.proposals`: ``random_arena``). The CMP has no reward: ``("next", "reward")`` is zero and
task rewards are written by :class:`~umrl.transforms.task_reward.TaskReward`. The horizon (100) is a
``StepCounter`` added by :func:`umrl.envs.make_env`.

Keys (batch size ``[B]``): ``"observation"`` and ``"position"`` ``[B, 2]`` (the same values), ``"action"``
``[B, 2]``, ``("next", "reward")`` ``[B, 1]`` and the usual ``"done"``/``"terminated"``/``"truncated"``.

The episodes in progress are the positions: :meth:`PointNavEnv.episode_state` / :meth:`PointNavEnv.load_episode_state`.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from umrl.validation import check_float

ACTION_SCALE = 0.1


class PointNavEnv(EnvBase):
    """A batch of independent 2-D points, reset to the origin.

    Args:
        num_envs: number of copies ``B`` (> 0).

    Keyword Args:
        device: torch device of every tensor.
        arena: half-width ``a`` > 0 of the square [-a, a]² the position is clipped to after each step; ``None``
            (default): unbounded.
    """

    batch_locked = True
    graph_capturable = True  # the step is pure device work on in-place state (see umrl.rollout.collect)

    def __init__(self, num_envs: int, *, device: torch.device | str = "cpu", arena: float | None = None):
        if num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs}.")
        self.arena = None if arena is None else check_float("arena", arena, gt=0)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        shape = (num_envs,)
        self.observation_spec = Composite(
            observation=Unbounded(shape + (2,), device=device),
            position=Unbounded(shape + (2,), device=device),
            shape=shape,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape + (2,), device=device)
        self.reward_spec = Unbounded(shape + (1,), device=device)
        self.done_spec = Composite(
            {key: Categorical(2, shape + (1,), dtype=torch.bool, device=device)
             for key in ("done", "terminated", "truncated")},
            shape=shape,
        )
        # Buffers updated in place, so a CUDA graph of the step (``collect(..., cudagraphs=True)``) reads the live state.
        self.register_buffer("_position", torch.zeros(shape + (2,), device=device), persistent=False)
        self._not_done = torch.zeros(shape + (1,), dtype=torch.bool, device=device)

    def _state(self, **extra) -> TensorDict:
        position = self._position.clone()
        return TensorDict(
            {"observation": position, "position": position, "done": self._not_done.clone(),
             "terminated": self._not_done.clone(), "truncated": self._not_done.clone(), **extra},
            batch_size=self.batch_size, device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        reset_mask = None if tensordict is None else tensordict.get("_reset", None)
        if reset_mask is None:
            self._position.zero_()
        else:
            self._position.masked_fill_(reset_mask.reshape(self.batch_size + (1,)), 0.0)
        return self._state()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        self._position.add_(ACTION_SCALE * action.clamp(-1.0, 1.0))
        if self.arena is not None:
            self._position.clamp_(-self.arena, self.arena)
        return self._state(reward=torch.zeros(self.batch_size + (1,), device=self.device))

    def episode_state(self) -> dict[str, torch.Tensor]:
        """Every copy where it stands: ``"position"`` ``[B, 2]`` (a copy)."""
        return {"position": self._position.clone()}

    def load_episode_state(self, state: dict[str, torch.Tensor]) -> None:
        """Put every copy where :meth:`episode_state` took it (from an env of the same batch size), in place;
        ``ValueError`` if the shape differs."""
        found = list(state["position"].shape) if "position" in state else "none"
        if found != list(self._position.shape):
            raise ValueError(f"episode state 'position' of a point_nav env of {self.batch_size[0]} copies must have "
                             f"shape {list(self._position.shape)}, got {found}.")
        self._position.copy_(state["position"])

    def _set_seed(self, seed: int | None) -> None:
        # The dynamics and the start state are deterministic: a seed changes nothing here.
        return None
