"""Hand-designed task families: the oracle's meta-training tasks and every method's meta-test tasks.

A task is a row vector of parameters (``task_dim`` floats); each env copy carries its own. A family is part of its
env's record (:class:`umrl.envs.registry.EnvSpec`); :func:`get_task_family` reads it from there. Rewards follow
docs/protocol.md and are computed from the physics keys that every env writes into ``"next"``:

============  ==========  ==============  ============================================================================
env           task_dim    family          reward
============  ==========  ==============  ============================================================================
point_nav     2 (goal)    U[-0.5, 0.5]²   −‖s − g‖₂ (ends early when |dx| < 0.01 and |dy| < 0.01)
half_cheetah  1 (speed)   U[0, 2]         −|v_x − v| − 0.05‖a‖²
ant           2 (goal)    U[-3, 3]²       −‖com_xy − g‖₁ + 4 + 0.05 − 0.005‖a‖² − 5e-4‖clip(cfrc_ext, −1, 1)‖²
============  ==========  ==============  ============================================================================

ant's reward is the MAML reference code's (:func:`ant_goal_reward`); its episodes end when the torso height leaves
[0.2, 1.0] (the CMP's termination, Ant-v5's and the reference's).

Actions enter the control costs clipped to the action bounds [-1, 1], i.e. as the simulator applied them.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from umrl.envs.registry import get_env_spec
from umrl.validation import InvalidType, InvalidValue, check_finite, check_float, describe

#: Seed of the held-out evaluation tasks; never used to draw meta-training tasks.
EVAL_TASK_SEED = 20190531


#: ``reward(next_td, action, task) -> [B, 1]``: the task reward from the ``"next"`` physics keys, the action
#: ``[B, act_dim]`` and the tasks ``[B, task_dim]``.
RewardFn = Callable[[TensorDictBase, torch.Tensor, torch.Tensor], torch.Tensor]
#: ``success(next_td, task) -> [B, 1]`` bool: where an episode ends early because the task is solved.
SuccessFn = Callable[[TensorDictBase, torch.Tensor], torch.Tensor]
#: ``sampler(n, generator) -> [n, task_dim]``: ``n`` tasks drawn with ``generator`` (a ``torch.Generator`` or None).
SamplerFn = Callable[[int, "torch.Generator | None"], torch.Tensor]

FUNCTION_SIGNATURES = {
    "reward_fn": "a function reward(next_td, action, task) -> [B, 1] (the task reward of a batch of steps)",
    "success_fn": "None or a function success(next_td, task) -> bool [B, 1]",
    "sampler": "None or a function sampler(n, generator) -> [n, task_dim] drawing only from generator",
}
"""What each function of a :class:`TaskFamily` must be (for error messages)."""


@dataclass(frozen=True)
class TaskFamily:
    """A distribution of tasks ``U[low, high]^task_dim`` over one environment, with its reward.

    Attributes:
        env_name: the environment the family belongs to (for messages).
        task_dim: number of parameters per task.
        low, high: bounds of the uniform task distribution.
        reward_fn: the task reward (:data:`RewardFn`).
        success_fn: optional early-termination condition (:data:`SuccessFn`); ``None``: episodes run to the horizon.
        sampler: optional task distribution (:data:`SamplerFn`) replacing ``U[low, high]^task_dim`` (``low`` and
            ``high`` then only describe the range, e.g. for plots); it must draw all its randomness from the
            generator it is given, so that the held-out tasks (:meth:`eval_tasks`) are the same on every call.

    A family without a callable ``reward_fn``, with a ``task_dim`` that is not a positive integer, ``low >= high``,
    or a ``sampler`` whose tasks have another shape or change for one seed is refused when it is built.
    """

    env_name: str
    task_dim: int
    low: float
    high: float
    reward_fn: RewardFn
    success_fn: SuccessFn | None = None
    sampler: SamplerFn | None = None

    def __post_init__(self) -> None:
        if isinstance(self.task_dim, bool) or not isinstance(self.task_dim, int) or self.task_dim < 1:
            raise InvalidValue("task_family.task_dim", self.task_dim, "a positive integer (numbers per task)")
        if not self.low < self.high:
            raise InvalidValue("task_family.low", self.low, f"a number below high ({self.high})")
        for key in ("reward_fn", "success_fn", "sampler"):
            function = getattr(self, key)
            if not callable(function) and (key == "reward_fn" or function is not None):
                raise InvalidType(f"task_family.{key}", function, FUNCTION_SIGNATURES[key])
        if self.sampler is not None:
            first, again = (self.sample(2, torch.Generator().manual_seed(0)) for _ in range(2))
            if not torch.equal(first, again):
                raise InvalidValue("task_family.sampler", self.sampler, FUNCTION_SIGNATURES["sampler"],
                                   note="two draws with one seed differ")

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` tasks, shape ``[n, task_dim]``."""
        if n < 1:
            raise ValueError(f"the number of tasks must be positive, got {n}.")
        if self.sampler is None:
            return self.low + (self.high - self.low) * torch.rand(n, self.task_dim, generator=generator)
        tasks = self.sampler(n, generator)
        if not (isinstance(tasks, torch.Tensor) and tasks.shape == (n, self.task_dim)):
            raise InvalidValue("task_family.sampler", self.sampler, FUNCTION_SIGNATURES["sampler"],
                               note=f"asked for {n} tasks of task_dim={self.task_dim}, it returned {describe(tasks)}")
        return check_finite("task_family.sampler", tasks.to(torch.float32))

    def eval_tasks(self, n: int = 20) -> torch.Tensor:
        """The fixed held-out evaluation tasks, shape ``[n, task_dim]`` (the same on every call and machine)."""
        return self.sample(n, torch.Generator().manual_seed(EVAL_TASK_SEED))

    def check_tasks(self, tasks: Any, batch_size: int | None = None) -> torch.Tensor:
        """``tasks`` ``[B, task_dim]`` (a tensor or nested sequences of numbers; ``B == batch_size`` when given) as
        float32, or an error naming the argument ``tasks``: a single task must be given as a batch of one."""
        rows = "num_envs" if batch_size is None else batch_size
        expected = f"a [{rows}, {self.task_dim}] tensor (one {self.env_name} task of {self.task_dim} numbers per env copy)"
        try:
            checked = torch.as_tensor(tasks, dtype=torch.float32)
        except (TypeError, ValueError, RuntimeError):
            raise InvalidType("tasks", tasks, expected) from None
        if not (checked.ndim == 2 and checked.shape[1] == self.task_dim and batch_size in (None, checked.shape[0])):
            note = None if isinstance(tasks, torch.Tensor) else f"shape {list(checked.shape)}"
            raise InvalidValue("tasks", tasks, expected, note=note)
        return check_finite("tasks", checked)

    def reward(self, next_td: TensorDictBase, action: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
        """Task reward ``[B, 1]`` from the ``"next"`` physics keys, the action ``[B, act_dim]`` and tasks ``[B, task_dim]``."""
        return self.reward_fn(next_td, action, task)

    def goal_reached(self, next_td: TensorDictBase, task: torch.Tensor) -> torch.Tensor | None:
        """``[B, 1]`` bool where an episode ends early on success, or ``None`` if the family has no such condition."""
        return None if self.success_fn is None else self.success_fn(next_td, task)


def control_cost(action: torch.Tensor) -> torch.Tensor:
    """``||clip(a, -1, 1)||^2`` ``[B, 1]``: the action as the simulator applied it."""
    return action.clamp(-1.0, 1.0).pow(2).sum(-1, keepdim=True)


def goal_distance_reward(next_td: TensorDictBase, action: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
    """point_nav: ``-||position - goal||_2``."""
    return -(next_td["position"] - task).norm(dim=-1, keepdim=True)


def goal_within(tolerance: float) -> SuccessFn:
    """point_nav's success: every coordinate of ``"position"`` within ``tolerance`` (> 0) of the goal."""
    check_float("tolerance", tolerance, gt=0)

    def success(next_td: TensorDictBase, task: torch.Tensor) -> torch.Tensor:
        return ((next_td["position"] - task).abs() < tolerance).all(-1, keepdim=True)

    return success


def target_velocity_reward(next_td: TensorDictBase, action: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
    """half_cheetah: ``-|v_x - v| - 0.05 ||a||^2``."""
    return -(next_td["x_velocity"] - task).abs() - 0.05 * control_cost(action)


#: ant's per-step constants, from the MAML reference code (``rllab/envs/mujoco/ant_env_rand_goal.py``): the offset
#: that keeps every step's reward positive near the goal ("make it happy, not suicidal"), the survive reward (paid on
#: every step, the terminating one included) and the control-cost weight ``0.5 * 1e-2``.
ANT_GOAL_OFFSET = 4.0
ANT_SURVIVE_REWARD = 0.05
ANT_CTRL_WEIGHT = 0.5 * 1e-2


def ant_goal_reward(next_td: TensorDictBase, action: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
    """ant: ``-||com_xy - goal||_1 + 4.0 + 0.05 - 0.005 ||a / scaling||^2 - 5e-4 ||clip(cfrc_ext, -1, 1)||^2``.

    The MAML reference code's goal reward, term by term (docs/protocol.md). ``com_xy`` is ``"xy_com"``, the ant's centre
    of mass (its ``get_body_com("torso")``); the contact term is ``"reward_contact"`` (Ant-v5's contact cost: the
    same weight ``0.5 * 1e-3`` on the same clipped forces).

    ``a / scaling``: the reference's policy output ``u`` passes through rllab's ``normalize`` wrapper, which maps
    ``[-1, 1]`` onto its ant.xml's ctrlrange ``[-150, 150]`` and clips, so the env receives ``a = clip(150 u, -150,
    150)`` and ``scaling = (ub - lb) / 2 = 150``: ``a / scaling = clip(u, -1, 1)``. umrl's action is that ``u``
    (the simulator clips it to Ant-v5's ctrlrange ``[-1, 1]``; with gear 150 the torque range is the reference's
    ±150), so ``a / scaling`` is the clipped action (:func:`control_cost`).
    """
    distance = (next_td["xy_com"] - task).abs().sum(-1, keepdim=True)
    return (-distance + ANT_GOAL_OFFSET + ANT_SURVIVE_REWARD + next_td["reward_contact"]
            - ANT_CTRL_WEIGHT * control_cost(action))


def get_task_family(env_name: str) -> TaskFamily:
    """The hand-designed task family of the registered env ``env_name`` (its :class:`~umrl.envs.registry.EnvSpec`)."""
    return get_env_spec(env_name).task_family
