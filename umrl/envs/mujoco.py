"""MuJoCo CMPs ``half_cheetah`` (``HalfCheetah-v5``) and ``ant`` (``Ant-v5``), gymnasium's default observations.

Two backends with identical keys, specs and (bit-for-bit) dynamics:

- ``"batched"`` (default): :class:`~umrl.envs.mujoco_batched.BatchedMujocoEnv`, ``B`` state rows stepped by
  ``mujoco.batch`` (HalfCheetah: one native multi-threaded call per step) or per copy on a thread pool (Ant, whose
  contact forces need ``mj_rnePostConstraint``), no gymnasium in the loop.
- ``"gym"``: the reference, TorchRL's ``GymWrapper`` over gymnasium's sync vector env
  (:func:`~umrl.envs.mujoco_gym.make_gym_mujoco_env`).
"""

from __future__ import annotations

import torch
from torchrl.envs import EnvBase

from umrl.envs.mujoco_batched import BATCHED_ENVS, MODEL_SPECS
from umrl.envs.mujoco_gym import make_gym_mujoco_env

MUJOCO_ENV_NAMES = tuple(MODEL_SPECS)
MUJOCO_BACKENDS = ("batched", "gym")


def make_mujoco_env(
    name: str,
    num_envs: int,
    *,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    backend: str = "batched",
) -> EnvBase:
    """The reward-free MuJoCo CMP ``name`` with batch size ``[num_envs]`` and no time limit.

    Args:
        name: ``"half_cheetah"`` or ``"ant"``.
        num_envs: batch size ``B`` (> 0).

    Keyword Args:
        seed: seeds the reset noise; ``None`` leaves it unseeded.
        device: device of the returned tensors (physics runs on CPU).
        backend: ``"batched"`` or ``"gym"`` (see the module docstring).

    Returns:
        An ``EnvBase`` writing float32 ``"observation"``, zero ``("next", "reward")``, ``"env_reward"`` (gymnasium's
        reward), the physics keys (half_cheetah: ``"x_position"``, ``"x_velocity"``; ant: ``"xy_position"``,
        ``"xy_com"``, ``"x_velocity"``, ``"reward_survive"``, ``"reward_contact"``) and
        ``"done"``/``"terminated"``/``"truncated"``.
    """
    if name not in MODEL_SPECS:
        raise ValueError(f"unknown MuJoCo env {name!r}; valid choices: {list(MUJOCO_ENV_NAMES)}.")
    if backend not in MUJOCO_BACKENDS:
        raise ValueError(f"unknown MuJoCo backend {backend!r}; valid choices: {list(MUJOCO_BACKENDS)}.")
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}.")
    if backend == "batched":
        env = BATCHED_ENVS[name](num_envs, device=device)
    else:
        env = make_gym_mujoco_env(name, num_envs, device=device)
    if seed is not None:
        env.set_seed(seed)
    return env


__all__ = ["MUJOCO_BACKENDS", "MUJOCO_ENV_NAMES", "make_mujoco_env"]
