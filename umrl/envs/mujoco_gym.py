"""Reference MuJoCo path: TorchRL's ``GymWrapper`` over a gymnasium *sync* vector env, with our keys.

Same keys and specs as :mod:`umrl.envs.mujoco_batched` (float32 ``"observation"``, zero ``("next", "reward")``,
``"env_reward"``, physics keys read from gymnasium's ``info``; Ant's centre of mass, which gymnasium does not report,
is added to ``info`` by :class:`CentreOfMassInfo`). Gymnasium's autoreset is disabled: TorchRL resets done copies
itself through the ``"_reset"`` mask.
"""

from __future__ import annotations

from collections.abc import Mapping

import gymnasium
import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Compose, DoubleToFloat, GymWrapper, Transform, TransformedEnv
from torchrl.envs.gym_like import BaseInfoDictReader

from umrl.envs.mujoco_batched import MODEL_SPECS, physics_keys, torso_com_xy

# Physics key -> the gymnasium info keys stacked into it (missing keys, e.g. velocities at reset, read as 0).
_INFO_SOURCES = {
    "x_position": ("x_position",),
    "xy_position": ("x_position", "y_position"),
    "xy_com": ("com_x", "com_y"),
    "x_velocity": ("x_velocity",),
    "reward_survive": ("reward_survive",),
    "reward_contact": ("reward_contact",),
}


class CentreOfMassInfo(gymnasium.Wrapper):
    """Adds ``"com_x"``, ``"com_y"`` to a MuJoCo env's reset and step ``info``: :func:`torso_com_xy` at its current
    positions, computed on a scratch ``MjData`` so that the env's own data (and its next step) stay untouched."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        self._scratch = mujoco.MjData(env.unwrapped.model)

    def _with_com(self, info: dict) -> dict:
        self._scratch.qpos[:] = self.unwrapped.data.qpos
        com_x, com_y = torso_com_xy(self.unwrapped.model, self._scratch)
        return {**info, "com_x": float(com_x), "com_y": float(com_y)}

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, self._with_com(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._with_com(info)


class InfoPhysicsReader(BaseInfoDictReader):
    """Writes each physics key, float32 ``[B, width]``, by stacking its gymnasium ``info`` names (a name missing from
    an ``info``, e.g. a velocity at reset, reads as 0): ``sources`` is ``{physics key: (info name, ...)}``."""

    def __init__(self, sources: Mapping[str, tuple[str, ...]], num_envs: int, device: torch.device | str = "cpu"):
        self.sources, self.num_envs = dict(sources), num_envs
        self._info_spec = Composite({key: Unbounded((num_envs, len(names)), dtype=torch.float32, device=device)
                                     for key, names in self.sources.items()}, shape=(num_envs,), device=device)

    def __call__(self, info_dict: dict, tensordict: TensorDictBase) -> TensorDictBase:
        zeros = np.zeros(self.num_envs)
        for key, names in self.sources.items():
            cols = [np.asarray(info_dict.get(name, zeros), dtype=np.float32) for name in names]
            tensordict.set(key, torch.as_tensor(np.stack(cols, -1), device=tensordict.device))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._info_spec


class EnvRewardToKey(Transform):
    """Moves the env's own reward to ``"env_reward"`` (float32 ``[B, 1]``, 0 at reset); ``"reward"`` becomes 0."""

    def __init__(self):
        super().__init__(in_keys=["reward"], out_keys=["env_reward"])

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        reward = next_tensordict.get("reward").to(torch.float32)
        next_tensordict.set("env_reward", reward)
        next_tensordict.set("reward", torch.zeros_like(reward))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        shape = (*tensordict_reset.batch_size, 1)
        tensordict_reset.set("env_reward", torch.zeros(shape, device=tensordict_reset.device))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = (*observation_spec.shape, 1)
        observation_spec["env_reward"] = Unbounded(shape, dtype=torch.float32, device=observation_spec.device)
        return observation_spec

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        reward_spec["reward"] = Unbounded(
            reward_spec["reward"].shape, dtype=torch.float32, device=reward_spec.device
        )
        return reward_spec


class GymnasiumVectorEnv(GymWrapper):
    """TorchRL's ``GymWrapper`` over a gymnasium vector env whose ``state_dict()`` carries the sub-envs' reset-noise
    generators (``np_random``), so a resumed run resets exactly as an uninterrupted one."""

    def get_extra_state(self) -> dict:
        return {"reset_rngs": [e.unwrapped.np_random.bit_generator.state for e in self._env.envs]}

    def set_extra_state(self, state: dict) -> None:
        rngs = state.get("reset_rngs") if isinstance(state, dict) else None
        if rngs is None or len(rngs) != len(self._env.envs):
            raise ValueError(f"expected extra state {{'reset_rngs': [{len(self._env.envs)} numpy generator states]}}, "
                             f"got {state!r:.200}.")
        for e, rng in zip(self._env.envs, rngs):
            e.unwrapped.np_random.bit_generator.state = rng


def make_gym_mujoco_env(name: str, num_envs: int, *, device: torch.device | str = "cpu") -> TransformedEnv:
    """``GymWrapper(gymnasium.make_vec(<v5 id>, num_envs, "sync"))`` with our keys; batch size ``[num_envs]``."""
    spec = MODEL_SPECS[name]
    vec_env = gymnasium.make_vec(
        spec.gym_id,
        num_envs=num_envs,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": gymnasium.vector.AutoresetMode.DISABLED},
        wrappers=[CentreOfMassInfo] if "xy_com" in physics_keys(name) else None,
        **spec.gym_kwargs,
    )
    env = GymnasiumVectorEnv(vec_env, device=device)
    env.set_info_dict_reader(InfoPhysicsReader({key: _INFO_SOURCES[key] for key in physics_keys(name)}, num_envs,
                                               device))
    return TransformedEnv(env, Compose(DoubleToFloat(in_keys=["observation"]), EnvRewardToKey()))
