"""Reward-free CMPs from gymnasium envs: ``env.name=gym:<EnvId>`` once :func:`gym_env_spec` has registered it.

:func:`gym_env_spec` turns a gymnasium id, a task family and the physics its reward reads into an
:class:`~umrl.envs.registry.EnvSpec` named ``gym:<EnvId>``; ``register_env`` makes it a valid ``env.name``::

    register_env(gym_env_spec("Hopper-v5", TaskFamily("hopper", 1, 0.0, 2.0, reward_fn=speed_reward),
                              physics={"x_velocity": "x_velocity"}, coverage_reduction="mean"))

The CMP (:func:`make_gym_cmp`) is TorchRL's ``GymWrapper`` over a gymnasium sync vector env (autoreset off: TorchRL
resets done copies through ``"_reset"``) with actions clipped to ``[-1, 1]`` and rescaled to the env's bounds,
float32 ``"observation"``, the env's own reward moved to ``"env_reward"`` and a zero ``("next", "reward")``, and
the physics keys, float32 ``[B, width]``, read from gymnasium's ``info`` (an info name, a list of them, or a function
of the unwrapped env). Every check runs when the spec is built, before any work: an unknown id, a discrete action
space, a physics source the env does not report, a reward of the wrong shape.
"""
from __future__ import annotations

import difflib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, DoubleToFloat, TransformedEnv

from umrl.envs.mujoco_gym import EnvRewardToKey, GymnasiumVectorEnv, InfoPhysicsReader
from umrl.envs.registry import EnvSpec
from umrl.envs.tasks import TaskFamily
from umrl.validation import InvalidType, InvalidValue, describe

GYM_PREFIX = "gym:"
"""Prefix of the env names of gymnasium CMPs: ``gym:Hopper-v5``."""

#: Where one physics key comes from: a gymnasium ``info`` name (width 1), a list of them (stacked), or a function of
#: the unwrapped gymnasium env returning a 1-D array (its width is read once, when the spec is built).
PhysicsSource = str | Sequence[str] | Callable[[gymnasium.Env], Any]

__all__ = ["GYM_PREFIX", "PhysicsSource", "check_gym_id", "gym_env_spec", "make_gym_cmp"]


def check_gym_id(name: str, gym_id: Any) -> str:
    """``gym_id`` if gymnasium's registry has it, else an error naming ``name`` with gymnasium's closest ids."""
    if not isinstance(gym_id, str) or not gym_id:
        raise InvalidType(name, gym_id, "a gymnasium env id such as 'Hopper-v5'")
    if gym_id not in gymnasium.registry:
        close = difflib.get_close_matches(gym_id, list(gymnasium.registry), n=3)
        raise InvalidValue(name, gym_id, f"an id of gymnasium's registry ({len(gymnasium.registry)} envs, "
                           f"e.g. 'Hopper-v5', 'InvertedPendulum-v5'; a package's envs after importing it)",
                           note=f"did you mean {', '.join(map(repr, close))}?" if close else None)
    return gym_id


class UnitBoxAction(gymnasium.ActionWrapper):
    """Actions in ``[-1, 1]^act_dim`` (the declared space), clipped to it and mapped linearly onto the env's Box
    bounds: a Gaussian policy's samples outside the box act as its edge, as in the built-in MuJoCo envs."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        space = env.action_space
        self._low, self._half_range = space.low, (space.high - space.low) / 2
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, space.shape, dtype=space.dtype)

    def action(self, action):
        return (self._low + (np.clip(action, -1.0, 1.0) + 1.0) * self._half_range).astype(self.env.action_space.dtype)


class ComputedPhysicsInfo(gymnasium.Wrapper):
    """Adds the physics keys computed from the unwrapped env to every reset and step ``info``: column ``j`` of key
    ``k`` as the scalar ``info["k[j]"]`` (what a vector env stacks into ``[num_envs]`` arrays)."""

    def __init__(self, env: gymnasium.Env, functions: Mapping[str, Callable[[gymnasium.Env], Any]]):
        super().__init__(env)
        self.functions = dict(functions)

    def _with_physics(self, info: dict) -> dict:
        extra = {}
        for key, function in self.functions.items():
            for j, value in enumerate(np.asarray(function(self.unwrapped), dtype=np.float64).reshape(-1)):
                extra[f"{key}[{j}]"] = float(value)
        return {**info, **extra}

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, self._with_physics(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._with_physics(info)


def _split_physics(physics: Mapping[str, PhysicsSource]) -> tuple[dict[str, tuple[str, ...]], dict[str, Callable]]:
    """``(info names per key, functions of the env per key)``, or an error naming the bad ``physics`` entry."""
    if not isinstance(physics, Mapping) or not physics:
        raise InvalidType("physics", physics, "a non-empty mapping {physics key: info name | [info names] | "
                          "function of the unwrapped env}")
    names, functions = {}, {}
    for key, source in physics.items():
        if not isinstance(key, str) or not key or key in ("observation", "action", "reward", "task"):
            raise InvalidValue("physics", key, "physics keys that are non-empty strings other than observation, "
                               "action, reward and task")
        if callable(source):
            functions[key] = source
        elif isinstance(source, str):
            names[key] = (source,)
        elif isinstance(source, Sequence) and source and all(isinstance(s, str) for s in source):
            names[key] = tuple(source)
        else:
            raise InvalidType(f"physics[{key!r}]", source, "an info name, a non-empty list of info names, or a "
                              "function of the unwrapped gymnasium env returning a 1-D array")
    return names, functions


def make_gym_cmp(gym_id: str, num_envs: int, *, sources: Mapping[str, tuple[str, ...]],
                 functions: Mapping[str, Callable] | None = None, gym_kwargs: Mapping | None = None,
                 seed: int | None = None, device: torch.device | str = "cpu") -> TransformedEnv:
    """The reward-free CMP over gymnasium's ``gym_id``, batch size ``[num_envs]``, no time limit (see the module
    docstring); ``sources`` maps each physics key to the ``info`` names stacked into it (the ``"k[j]"`` names of
    the keys computed by ``functions``). ``seed`` seeds the reset noise."""
    wrappers = [UnitBoxAction]
    if functions:
        wrappers.append(lambda e: ComputedPhysicsInfo(e, functions))
    vec_env = gymnasium.make_vec(gym_id, num_envs=num_envs, vectorization_mode="sync",
                                 vector_kwargs={"autoreset_mode": gymnasium.vector.AutoresetMode.DISABLED},
                                 wrappers=wrappers, **dict(gym_kwargs or {}))
    env = GymnasiumVectorEnv(vec_env, device=device)
    env.set_info_dict_reader(InfoPhysicsReader(sources, num_envs, device))
    observation_dtype = env.observation_spec["observation"].dtype
    to_float = [DoubleToFloat(in_keys=["observation"])] if observation_dtype == torch.float64 else []
    env = TransformedEnv(env, Compose(*to_float, EnvRewardToKey()))  # MuJoCo observes float64, classic control float32
    if seed is not None:
        env.set_seed(seed)
    return env


def _probe(gym_id: str, gym_kwargs: Mapping, names: Mapping[str, tuple[str, ...]],
           functions: Mapping[str, Callable]) -> tuple[int, int, dict[str, np.ndarray]]:
    """``(obs_dim, act_dim, {physics key: its value after one step})`` of one copy of the env, stepped once with the
    middle of its action range; a non-Box space or a physics source the env does not report is an error."""
    try:
        env = gymnasium.make(gym_id, **gym_kwargs)
    except Exception as e:
        raise InvalidValue("gym_kwargs", dict(gym_kwargs), f"keyword arguments gymnasium.make({gym_id!r}) accepts",
                           note=f"{type(e).__name__}: {e}") from e
    try:
        act, obs = env.action_space, env.observation_space
        if not (isinstance(act, gymnasium.spaces.Box) and len(act.shape) == 1 and np.isfinite(act.low).all()
                and np.isfinite(act.high).all()):
            raise InvalidValue(f"action space of {gym_id}", act, "a continuous gymnasium Box of one dimension with "
                               "finite bounds (umrl's policies are Gaussian; discrete actions are not supported)")
        if not (isinstance(obs, gymnasium.spaces.Box) and len(obs.shape) == 1):
            raise InvalidValue(f"observation space of {gym_id}", obs, "a gymnasium Box of one dimension (wrap the "
                               "env with gymnasium.wrappers.FlattenObservation for others)")
        _, reset_info = env.reset(seed=0)
        *_, info = env.step(((act.low + act.high) / 2).astype(act.dtype))
        seen = {**reset_info, **info}
        values = {}
        for key, sources in names.items():
            missing = [s for s in sources if s not in seen]
            if missing:
                raise InvalidValue(f"physics[{key!r}]", list(sources), f"info names {gym_id} reports: "
                                   f"{sorted(seen) or 'none'} (or a function of the unwrapped env)",
                                   note=f"{missing} not in its reset or step info")
            values[key] = np.asarray([seen[s] for s in sources], dtype=np.float32)
        for key, function in functions.items():
            try:
                value = np.asarray(function(env.unwrapped), dtype=np.float32)
            except Exception as e:
                raise InvalidValue(f"physics[{key!r}]", function, "a function of the unwrapped env returning a "
                                   "1-D array of numbers", note=f"it raised {type(e).__name__}: {e}") from e
            if value.ndim > 1 or value.size == 0 or not np.isfinite(value).all():
                raise InvalidValue(f"physics[{key!r}]", function, "a function of the unwrapped env returning a "
                                   "non-empty 1-D array of finite numbers", note=f"it returned {describe(value)}")
            values[key] = value.reshape(-1)
        return obs.shape[0], act.shape[0], values
    finally:
        env.close()


def _check_reward(family: TaskFamily, obs_dim: int, act_dim: int, physics: Mapping[str, np.ndarray]) -> None:
    """Call the family's reward (and success) on a probe batch of two steps; a wrong shape is an error."""
    batch = 2
    next_td = TensorDict({"observation": torch.zeros(batch, obs_dim),
                          **{k: torch.as_tensor(v).expand(batch, -1).clone() for k, v in physics.items()}},
                         batch_size=[batch])
    tasks = family.sample(batch, torch.Generator().manual_seed(0))
    expected = f"a function reward(next_td, action, task) -> a float tensor [B, 1] (here [{batch}, 1])"
    try:
        reward = family.reward(next_td, torch.zeros(batch, act_dim), tasks)
    except Exception as e:
        raise InvalidValue("task_family.reward_fn", family.reward_fn, expected,
                           note=f"on a probe batch of keys {sorted(next_td.keys())} it raised {type(e).__name__}: "
                                f"{e}") from e
    if not (isinstance(reward, torch.Tensor) and reward.is_floating_point() and reward.shape == (batch, 1)):
        raise InvalidValue("task_family.reward_fn", family.reward_fn, expected,
                           note=f"it returned {describe(reward)} for tasks of shape {list(tasks.shape)}")
    if family.success_fn is not None:
        done = family.goal_reached(next_td, tasks)
        if not (isinstance(done, torch.Tensor) and done.dtype == torch.bool and done.shape == (batch, 1)):
            raise InvalidValue("task_family.success_fn", family.success_fn,
                               f"a function success(next_td, task) -> a bool tensor [B, 1] (here [{batch}, 1])",
                               note=f"it returned {describe(done)}")


MOVED_TO_CONFIG = {
    "num_skills": "num_skills=10 for DIAYN, default_num_skills=10 for MAML",
    "diayn_horizon": "env.horizon=... for DIAYN",
    "diayn_frames": "collector.total_frames=... for DIAYN",
    "diayn_hidden": "network.hidden=[...] network.discriminator_hidden=[...] for DIAYN, discriminator_hidden=[...] "
                    "for MAML",
    "maml_iterations": "iterations=... for MAML",
}
"""The former :class:`EnvSpec` fields that are recipe settings now, with the keys that set them."""


def gym_env_spec(gym_id: str, task_family: TaskFamily, physics: Mapping[str, PhysicsSource], *,
                 coverage_key: str | None = None, gym_kwargs: Mapping | None = None, **fields) -> EnvSpec:
    """The :class:`EnvSpec` ``gym:<gym_id>`` of gymnasium's ``gym_id`` with the hand-designed ``task_family``.

    Args:
        gym_id: a gymnasium env id (``"Hopper-v5"``), continuous (Box) actions, a 1-D Box observation.
        task_family: the tasks and their reward (:class:`~umrl.envs.tasks.TaskFamily`; its ``env_name`` becomes the
            spec's name). Its reward reads ``next_td["observation"]`` and the physics keys, ``action`` ``[B,
            act_dim]`` in ``[-1, 1]`` and ``task`` ``[B, task_dim]``, and returns ``[B, 1]``.
        physics: ``{key: source}`` (:data:`PhysicsSource`): the keys written into every step's ``"next"``.

    Keyword Args:
        coverage_key: the physics key DIAYN's and VIME's coverage metrics read; default: the first of ``physics``.
        gym_kwargs: keyword arguments of ``gymnasium.make`` (e.g. ``{"exclude_current_positions_from_observation":
            False}``).
        **fields: further :class:`EnvSpec` fields (``coverage_reduction``, ``coverage_cell``, ``horizon``,
            ``num_eval_tasks``). The recipes' hyperparameters (skill count, DIAYN's episode length and budget,
            MAML's iterations) are config: ``umrl/configs/<recipe>_env/default.yaml``, or the command line.

    Raises:
        InvalidValue / InvalidType: naming the bad argument, its value and what is accepted; one copy of the env is
        built and stepped once to check the spaces, the physics sources and the reward's shape.
    """
    check_gym_id("gym_id", gym_id)
    moved = sorted(set(fields) & set(MOVED_TO_CONFIG))
    if moved:
        raise InvalidValue(moved[0], fields[moved[0]], "no such argument: a recipe setting, given on the command line "
                           f"or in the overrides of umrl.trainers.train ({MOVED_TO_CONFIG[moved[0]]})")
    if not isinstance(task_family, TaskFamily):
        raise InvalidType("task_family", task_family, "a umrl.envs.TaskFamily (task_dim, low, high, reward_fn)")
    names, functions = _split_physics(physics)
    gym_kwargs = dict(gym_kwargs or {})
    obs_dim, act_dim, values = _probe(gym_id, gym_kwargs, names, functions)
    sources = {key: names.get(key) or tuple(f"{key}[{j}]" for j in range(len(values[key]))) for key in physics}
    name = f"{GYM_PREFIX}{gym_id}"
    family = replace(task_family, env_name=name)
    _check_reward(family, obs_dim, act_dim, values)

    def make(num_envs: int, *, seed: int | None = None, device: torch.device | str = "cpu",
             backend: str = "default") -> TransformedEnv:
        return make_gym_cmp(gym_id, num_envs, sources=sources, functions=functions, gym_kwargs=gym_kwargs,
                            seed=seed, device=device)

    return EnvSpec(name=name, make=make, obs_dim=obs_dim, act_dim=act_dim, task_family=family, physics_keys={key: len(s) for key, s in sources.items()},
                   coverage_key=coverage_key if coverage_key is not None else next(iter(physics)), **fields)
