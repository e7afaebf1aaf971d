"""The state of an env and of a replay buffer, as a checkpoint stores it for a faithful ``resume=true``.

Beside the networks, optimisers and :func:`umrl.rng.rng_state`, a resume restores the env's random state (MuJoCo
reset noise, :func:`env_state`) and the replay buffers' content (:func:`replay_buffer_state`)."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase, TransformedEnv


def env_state(env: EnvBase) -> dict:
    """The random state of ``env`` (e.g. MuJoCo reset noise) and of its transforms, for :func:`load_env_state`.

    TorchRL's ``TransformedEnv.state_dict()`` leaves the base env out, so both are taken here."""
    if isinstance(env, TransformedEnv):
        return {"base_env": env_state(env.base_env), "transform": env.transform.state_dict()}
    return {"env": env.state_dict()}


def load_env_state(env: EnvBase, state: Mapping[str, Any]) -> None:
    """Restore what :func:`env_state` took from an env built the same way."""
    if isinstance(env, TransformedEnv):
        load_env_state(env.base_env, state["base_env"])
        env.transform.load_state_dict(state["transform"])
    else:
        env.load_state_dict(state["env"])


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
