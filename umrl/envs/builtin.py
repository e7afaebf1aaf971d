"""The built-in environments, one :class:`~umrl.envs.registry.EnvSpec` record each (docs/protocol.md settings).

==============  =======  =======  ====================  ===========================================
env             obs_dim  act_dim  tasks                 coverage
==============  =======  =======  ====================  ===========================================
point_nav       2        2        goals U[-0.5, 0.5]²   final ``"position"``, 0.1 cells
half_cheetah    17       6        speeds U[0, 2]        mean ``"x_velocity"``
ant             105      8        goals U[-3, 3]²       final ``"xy_position"``, 0.25 cells
==============  =======  =======  ====================  ===========================================

The recipes' hyperparameters on each env (skill counts, DIAYN's episode length, budget and widths, MAML's
iterations) are in ``umrl/configs/diayn_env/<env>.yaml`` and ``umrl/configs/maml_env/<env>.yaml``.

ant is gymnasium's ``Ant-v5`` (its model, dynamics and termination) with the MAML reference code's goal reward
(:func:`umrl.envs.tasks.ant_goal_reward`) and gymnasium's default observation, x-y excluded as the paper states
(105-D; the paper's 111 is ``Ant-v1``'s, see :class:`umrl.envs.mujoco_batched.AntBatchedEnv`).
"""
from __future__ import annotations

import torch
from torchrl.envs import EnvBase

from umrl.envs.point_nav import PointNavEnv
from umrl.envs.registry import EnvSpec, register_env
from umrl.envs.tasks import (
    TaskFamily,
    ant_goal_reward,
    goal_distance_reward,
    goal_within,
    target_velocity_reward,
)


def make_point_nav(num_envs: int, *, seed: int | None = None, device: torch.device | str = "cpu",
                   backend: str = "default", arena: float | None = None) -> EnvBase:
    """:class:`~umrl.envs.point_nav.PointNavEnv` (deterministic: ``seed`` and the MuJoCo ``backend`` are unused;
    ``arena``: the optional position bound)."""
    return PointNavEnv(num_envs, device=device, arena=arena)


def mujoco_maker(name: str):
    """``make`` of the MuJoCo CMP ``name`` (:func:`umrl.envs.mujoco.make_mujoco_env`, imported on first use);
    ``backend="default"`` is the batched simulator."""

    def make(num_envs: int, *, seed: int | None = None, device: torch.device | str = "cpu",
             backend: str = "default") -> EnvBase:
        from umrl.envs.mujoco import make_mujoco_env

        return make_mujoco_env(name, num_envs, seed=seed, device=device,
                               backend="batched" if backend == "default" else backend)

    return make


POINT_NAV = register_env(EnvSpec(
    name="point_nav", make=make_point_nav, obs_dim=2, act_dim=2,
    task_family=TaskFamily("point_nav", task_dim=2, low=-0.5, high=0.5, reward_fn=goal_distance_reward,
                           success_fn=goal_within(0.01)),
    physics_keys={"position": 2}, coverage_key="position", coverage_cell=0.1,
))
HALF_CHEETAH = register_env(EnvSpec(
    name="half_cheetah", make=mujoco_maker("half_cheetah"), obs_dim=17, act_dim=6,
    task_family=TaskFamily("half_cheetah", task_dim=1, low=0.0, high=2.0, reward_fn=target_velocity_reward),
    physics_keys={"x_position": 1, "x_velocity": 1}, coverage_key="x_velocity", coverage_reduction="mean",
))
ANT = register_env(EnvSpec(
    name="ant", make=mujoco_maker("ant"), obs_dim=105, act_dim=8,
    task_family=TaskFamily("ant", task_dim=2, low=-3.0, high=3.0, reward_fn=ant_goal_reward),
    physics_keys={"xy_position": 2, "xy_com": 2, "x_velocity": 1, "reward_survive": 1, "reward_contact": 1},
    coverage_key="xy_position", coverage_cell=0.25,
))

__all__ = ["ANT", "HALF_CHEETAH", "POINT_NAV", "make_point_nav", "mujoco_maker"]
