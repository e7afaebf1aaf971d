"""Hand-designed task families: the oracle's meta-training tasks and every method's meta-test tasks.

A task is a row vector of parameters (``task_dim`` floats); each env copy carries its own. Rewards follow
PROTOCOL.md and are computed from the physics keys that every env writes into ``"next"``:

==============  ==========  ============================  ==========================================================
env             task_dim    family                        reward
==============  ==========  ============================  ==========================================================
point_nav       2 (goal)    U[-0.5, 0.5]²                 −‖s − g‖₂ (ends early when |dx| < 0.01 and |dy| < 0.01)
half_cheetah    1 (speed)   U[0, 2]                       −|v_x − v| − 0.05‖a‖²
ant             2 (goal)    U[-3, 3]²                     −‖xy − g‖₁ + healthy reward + contact reward − 0.5‖a‖²
==============  ==========  ============================  ==========================================================

Actions enter the control costs clipped to the action bounds [-1, 1], i.e. as the simulator applied them.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

#: Seed of the held-out evaluation tasks; never used to draw meta-training tasks.
EVAL_TASK_SEED = 20190531


@dataclass(frozen=True)
class TaskFamily:
    """A distribution of tasks ``U[low, high]^task_dim`` over one environment, with its reward.

    Attributes:
        env_name: the environment the family belongs to.
        task_dim: number of parameters per task.
        low, high: bounds of the uniform task distribution.
    """

    env_name: str
    task_dim: int
    low: float
    high: float

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` tasks, shape ``[n, task_dim]``."""
        if n < 1:
            raise ValueError(f"the number of tasks must be positive, got {n}.")
        return self.low + (self.high - self.low) * torch.rand(n, self.task_dim, generator=generator)

    def eval_tasks(self, n: int = 20) -> torch.Tensor:
        """The fixed held-out evaluation tasks, shape ``[n, task_dim]`` (the same on every call and machine)."""
        return self.sample(n, torch.Generator().manual_seed(EVAL_TASK_SEED))

    def check_tasks(self, tasks: torch.Tensor, batch_size: int | None = None) -> torch.Tensor:
        """Validate a task batch ``[B, task_dim]`` and return it as float32."""
        if tasks.ndim != 2 or tasks.shape[-1] != self.task_dim:
            raise ValueError(
                f"{self.env_name} tasks must have shape [num_envs, {self.task_dim}], got {tuple(tasks.shape)}."
            )
        if batch_size is not None and tasks.shape[0] != batch_size:
            raise ValueError(f"got {tasks.shape[0]} tasks for an env batch of {batch_size}: give one task per env copy.")
        return tasks.to(torch.float32)

    def reward(self, next_td: TensorDictBase, action: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
        """Task reward ``[B, 1]`` from the ``"next"`` physics keys, the action ``[B, act_dim]`` and tasks ``[B, task_dim]``."""
        ctrl = action.clamp(-1.0, 1.0).pow(2).sum(-1, keepdim=True)
        if self.env_name == "point_nav":
            return -(next_td["position"] - task).norm(dim=-1, keepdim=True)
        if self.env_name == "half_cheetah":
            return -(next_td["x_velocity"] - task).abs() - 0.05 * ctrl
        # ant
        distance = (next_td["xy_position"] - task).abs().sum(-1, keepdim=True)
        return -distance + next_td["reward_survive"] + next_td["reward_contact"] - 0.5 * ctrl

    def goal_reached(self, next_td: TensorDictBase, task: torch.Tensor) -> torch.Tensor | None:
        """``[B, 1]`` bool where an episode ends early on success (point_nav only), else ``None``."""
        if self.env_name != "point_nav":
            return None
        return ((next_td["position"] - task).abs() < 0.01).all(-1, keepdim=True)


TASK_FAMILIES = {
    "point_nav": TaskFamily("point_nav", task_dim=2, low=-0.5, high=0.5),
    "half_cheetah": TaskFamily("half_cheetah", task_dim=1, low=0.0, high=2.0),
    "ant": TaskFamily("ant", task_dim=2, low=-3.0, high=3.0),
}


def get_task_family(env_name: str) -> TaskFamily:
    """The hand-designed task family of ``env_name``."""
    try:
        return TASK_FAMILIES[env_name]
    except KeyError:
        raise ValueError(f"no task family for env {env_name!r}; valid choices: {sorted(TASK_FAMILIES)}.") from None
