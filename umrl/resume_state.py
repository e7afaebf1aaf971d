"""The state of an env and of a replay buffer, as a checkpoint stores it for a faithful ``resume=true``.

Beside the networks, optimisers and :func:`umrl.rng.rng_state`, a resume restores the env's random state (MuJoCo
reset noise, :func:`env_state`), where asked the episodes in progress in its copies, and the replay buffers' content
(:func:`replay_buffer_state`)."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase, TransformedEnv


def env_state(env: EnvBase, *, episodes: bool = False) -> dict:
    """The random state of ``env`` (e.g. MuJoCo reset noise) and of its transforms, for :func:`load_env_state`;
    with ``episodes``, also the episodes in progress (``"episodes"``: the innermost env's ``episode_state()``, its
    copies' physics) where that env has one (the batched MuJoCo envs and point_nav do; gymnasium's do not).

    TorchRL's ``TransformedEnv.state_dict()`` leaves the base env out, so both are taken here. What the transforms
    add to the episodes (the step count, a skill) lives in the env's last output TensorDict, which the caller keeps."""
    if isinstance(env, TransformedEnv):
        return {"base_env": env_state(env.base_env, episodes=episodes), "transform": env.transform.state_dict()}
    state = {"env": env.state_dict()}
    if episodes and hasattr(env, "episode_state"):
        state["episodes"] = env.episode_state()
    return state


def keeps_episodes(env: EnvBase) -> bool:
    """Whether :func:`env_state` with ``episodes=True`` holds the episodes in progress of ``env`` (its innermost env
    has ``episode_state``)."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return hasattr(env, "episode_state")


def load_env_state(env: EnvBase, state: Mapping[str, Any]) -> bool:
    """Restore what :func:`env_state` took from an env built the same way; whether it held the episodes in progress
    (then restored: the env steps on as the saved one would; else the caller restarts them)."""
    if isinstance(env, TransformedEnv):
        restored = load_env_state(env.base_env, state["base_env"])
        env.transform.load_state_dict(state["transform"])
        return restored
    env.load_state_dict(state["env"])
    if "episodes" not in state:
        return False
    if not hasattr(env, "load_episode_state"):
        raise ValueError(f"the env state holds episodes in progress, which a {type(env).__name__} cannot restore.")
    env.load_episode_state(state["episodes"])
    return True


def replay_buffer_state(buffer: ReplayBuffer) -> dict:
    """TorchRL's ``buffer.state_dict()`` with the storage cut to its filled rows.

    A ``LazyTensorStorage`` allocates all ``max_size`` rows on its first write and its ``state_dict`` holds them all
    (a 10⁶-row DIAYN buffer was ~250 MB per checkpoint after 1,000 transitions); rows are written from 0 up until
    the buffer wraps, so the first ``len(buffer)`` rows are the whole content."""
    state = buffer.state_dict()
    filled = len(buffer.storage)  # a clone: a slice view would pickle the whole allocation
    state["_storage"] = {"rows": buffer.storage[:filled].clone() if filled else None}
    return state


def load_replay_buffer_state(buffer: ReplayBuffer, state: Mapping[str, Any]) -> None:
    """Restore what :func:`replay_buffer_state` took into a buffer built the same way (same storage size)."""
    rows = state["_storage"]["rows"]
    if rows is not None:
        buffer.storage.set(torch.arange(len(rows), device=rows.device), rows)
    buffer.load_state_dict({**state, "_storage": buffer.storage.state_dict()})
