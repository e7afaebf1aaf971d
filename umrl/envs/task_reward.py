"""``TaskReward``: the hand-designed reward of a task family, one task per env copy (what ``make_task_env`` adds).

It lives with the envs (as TorchRL's transforms live in ``torchrl.envs``) because the task families it computes are
part of each env's record; ``umrl.transforms`` re-exports it.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from umrl.envs.tasks import TaskFamily


class TaskReward(Transform):
    """Writes each env copy's task and task reward into the rollout.

    The tasks ``[B, task_dim]`` are held by the transform (``set_tasks``) so that they survive the partial resets
    a collector performs; they are written as ``"task"`` into every reset and step output. At every step the reward
    of :meth:`TaskFamily.reward` replaces ``("next", "reward")`` (the CMP's own reward keys are untouched), and tasks
    with a success condition (point_nav goals) end the episode: ``terminated`` and ``done`` are set.

    ``forward`` recomputes ``("next", "reward")`` of a stored batch from its ``"task"``, ``"action"`` and next
    physics keys (the replay-buffer path).

    Args:
        family: the task family (see :func:`umrl.envs.get_task_family`).
        tasks: optional initial tasks ``[B, task_dim]``.
    """

    def __init__(self, family: TaskFamily, tasks: torch.Tensor | None = None):
        super().__init__(in_keys=[], out_keys=[])
        self.family = family
        self.register_buffer("tasks", torch.zeros(0, family.task_dim))
        if tasks is not None:
            self.set_tasks(tasks)

    def set_tasks(self, tasks: torch.Tensor) -> None:
        """Give env copy ``i`` the task ``tasks[i]``; ``tasks`` has shape ``[B, task_dim]``."""
        batch = self.parent.batch_size.numel() if self.parent is not None else None
        tasks = self.family.check_tasks(tasks, batch).to(self.tasks.device)
        if tasks.shape == self.tasks.shape:
            self.tasks.copy_(tasks)  # in place: a CUDA graph of the step keeps reading the live tasks
        else:
            self.tasks = tasks.clone()  # never the caller's tensor: later calls write into this one

    def _tasks_for(self, tensordict: TensorDictBase) -> torch.Tensor:
        if self.tasks.shape[0] == 0:
            raise RuntimeError("TaskReward has no tasks: call set_tasks(tasks) with one task per env copy first.")
        if self.tasks.shape[0] != tensordict.batch_size.numel():
            raise ValueError(
                f"TaskReward holds {self.tasks.shape[0]} tasks but the env batch is {tuple(tensordict.batch_size)}."
            )
        return self.tasks.reshape(*tensordict.batch_size, self.family.task_dim)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set("task", self._tasks_for(tensordict_reset).clone())
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        task = self._tasks_for(next_tensordict)
        next_tensordict.set("task", task.clone())
        next_tensordict.set("reward", self.family.reward(next_tensordict, tensordict["action"], task))
        reached = self.family.goal_reached(next_tensordict, task)
        if reached is not None:
            next_tensordict.set("terminated", next_tensordict["terminated"] | reached)
            next_tensordict.set("done", next_tensordict["done"] | reached)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        next_td = tensordict.get("next")
        next_td.set("reward", self.family.reward(next_td, tensordict["action"], tensordict["task"]))
        return tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec["task"] = Unbounded(
            (*observation_spec.shape, self.family.task_dim), device=observation_spec.device
        )
        return observation_spec
