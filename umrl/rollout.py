"""Batched per-task collection, with one shared parameter set or one adapted parameter set per task.

The env batch is ``B = T × N``: env copy ``b`` belongs to task ``b // N`` (tasks are contiguous blocks of ``N``
copies, e.g. ``make_task_env(name, tasks.repeat_interleave(N, 0))``). :func:`collect` drives TorchRL's own
``env.rollout`` (auto-reset, ``StepCounter`` truncation, transforms) with a policy callable that does **one batched
network call per env step**:

* shared parameters (pre-update): the policy is called on the whole ``[B]`` batch;
* per-task parameters ``[T, ...]`` (post-update): the observation batch is viewed as ``[T, N]`` and every task's
  adapted weights run in one batched matmul per layer (:class:`FunctionalPolicy`).

``env.rollout`` is the simplest correct driver here: every copy runs exactly ``horizon`` steps in lockstep, which is
what a ``[T, N, H]`` batch needs, and it adds no process or buffer machinery a ``Collector`` would bring (measured:
the env step and the policy MLP dominate, see ``benchmarks/meta_iteration.py``).

:class:`FunctionalPolicy` is the one place that evaluates the policy with explicit parameters; ``MAMLLoss`` uses it
too, so collection and the loss cannot disagree about what "adapted parameters" mean.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torch.func import functional_call
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from umrl.envs.threads import torch_threads_beside_physics
from umrl.modules.batched_mlp import BatchedGaussianMLP
from umrl.trajectories import trajectory_mask

__all__ = ["FunctionalPolicy", "collect"]


class FunctionalPolicy:
    """Evaluate a :class:`~torchrl.modules.ProbabilisticActor` with parameters held in a TensorDict.

    ``params`` is either shared (batch size ``[]``, e.g. ``TensorDict.from_module(policy)``) or per task (batch size
    ``[T]``, e.g. from :meth:`umrl.objectives.maml.MAMLLoss.adapt`). With per-task params the data's leading dim
    must be ``T``. The module's own parameters are never touched.

    Args:
        policy: the actor; its last module must be the probabilistic head (``loc``/``scale`` -> distribution).

    Keyword Args:
        task_loop: how per-task params are evaluated: ``None`` (default) all tasks at once with one batched matmul
            per layer (:class:`umrl.modules.batched_mlp.BatchedGaussianMLP`; networks it does not recognise use
            ``vmap``), ``False`` one ``torch.func.vmap(functional_call)``, ``True`` a Python loop of
            ``functional_call`` over tasks (the per-task reference). Results agree to float rounding (tested).
            Measured on 2 CPU cores (``benchmarks/meta_iteration.py --preset reference --task-loop batched loop``,
            40 tasks, 2×100 MLP, 2000 samples per task): with the full-batch KL Hessian the batched learning step
            was no faster than the loop (the loop took 0.89-0.92× its time in two runs, 0.86× on one thread); with
            ``--hvp-fraction 0.1`` it was 1.75-2.2× faster.
    """

    def __init__(self, policy: ProbabilisticActor, *, task_loop: bool | None = None):
        if task_loop not in (None, True, False):
            raise ValueError(f"task_loop must be None (batched), True (loop) or False (vmap), got {task_loop!r}.")
        self.policy = policy
        self.net = TensorDictSequential(*policy.module[:-1])  # shares the modules: same parameter names
        self.head = policy.module[-1]
        self.task_loop = task_loop
        self.batched = BatchedGaussianMLP.from_net(self.net) if task_loop is None else None

    @staticmethod
    def _flat(params: TensorDictBase) -> dict[str, torch.Tensor]:
        return dict(params.flatten_keys(".").items())

    def _call(self, flat: dict[str, torch.Tensor], td: TensorDictBase) -> TensorDictBase:
        return functional_call(self.net, flat, (td,))

    def dist_params(self, params: TensorDictBase, td: TensorDictBase) -> TensorDictBase:
        """``td`` restricted to the net's in_keys, plus ``"loc"``/``"scale"`` computed with ``params``."""
        inputs = td.select(*self.net.in_keys)
        if params.batch_dims == 0:
            return self._call(self._flat(params), inputs)
        if params.batch_dims != 1 or td.batch_size[:1] != params.batch_size:
            raise ValueError(
                f"per-task params have batch size {tuple(params.batch_size)} but the data's leading dims are "
                f"{tuple(td.batch_size)}: the data must be shaped [T, ...] with T = number of tasks."
            )
        if self.batched is not None:
            loc, scale = self.batched(params, [inputs.get(k) for k in self.net.in_keys])
            return inputs.set("loc", loc).set("scale", scale)
        if self.task_loop:
            return torch.stack([self._call(self._flat(params[i]), inputs[i]) for i in range(params.shape[0])])
        return torch.func.vmap(self._call, (0, 0), randomness="error")(self._flat(params), inputs)

    def dist(self, params: TensorDictBase, td: TensorDictBase) -> torch.distributions.Distribution:
        """The action distribution at ``td`` (batch shape ``td.batch_size``)."""
        return self.policy.build_dist_from_params(self.dist_params(params, td))

    def log_prob(self, params: TensorDictBase, td: TensorDictBase) -> torch.Tensor:
        """``log π_params(td["action"] | td)`` with shape ``td.batch_size``."""
        return self.dist(params, td).log_prob(td["action"])

    def act(self, params: TensorDictBase, td: TensorDictBase) -> TensorDictBase:
        """Sample actions: a TensorDict shaped like ``td`` with ``"loc"``, ``"scale"``, ``"action"``,
        ``"action_log_prob"``."""
        return self.head(self.dist_params(params, td)).select("loc", "scale", "action", "action_log_prob")


def collect(
    env: EnvBase,
    policy: ProbabilisticActor,
    *,
    num_tasks: int,
    horizon: int,
    params: TensorDictBase | None = None,
) -> TensorDictBase:
    """Roll out ``horizon`` steps from a fresh reset in every env copy and return a ``[T, N, horizon]`` batch.

    Args:
        env: batched env with ``batch_size == [T * N]``; copy ``b`` belongs to task ``b // N``.
        policy: the Gaussian actor (see :func:`umrl.modules.policy.make_gaussian_policy`).

    Keyword Args:
        num_tasks: ``T``.
        horizon: steps per copy ``H`` (the env's ``StepCounter`` should end episodes at the same horizon).
        params: ``None`` for the module's own parameters, a shared TensorDict (batch ``[]``) or per-task
            parameters with batch ``[T]`` (e.g. ``MAMLLoss.adapt(support)``); evaluated without gradients.

    Returns:
        TensorDict ``[T, N, H]`` with the env's keys (``"observation"``, ``"step_count"``, ``"task"``/``"skill"``
        if the env writes them, ``("next", "reward")``, ``("next", "done")``, ...), the policy's ``"loc"``,
        ``"scale"``, ``"action"``, ``"action_log_prob"``, and ``"mask"`` ``[T, N, H]`` (True up to and including
        each copy's first ``done``; later steps come from auto-resets and must be ignored).
    """
    batch = env.batch_size.numel()
    if len(env.batch_size) != 1 or num_tasks < 1 or batch % num_tasks:
        raise ValueError(
            f"env batch {tuple(env.batch_size)} is not a flat batch of num_tasks={num_tasks} × N copies."
        )
    per_task = batch // num_tasks
    functional = FunctionalPolicy(policy)
    if params is not None and params.batch_dims == 1 and params.shape[0] != num_tasks:
        raise ValueError(f"got per-task params for {params.shape[0]} tasks but num_tasks={num_tasks}.")

    def act(td: TensorDictBase) -> TensorDictBase:
        if params is None:
            return policy(td)
        if params.batch_dims == 0:
            return td.update(functional.act(params, td))
        return td.update(functional.act(params, td.view(num_tasks, per_task)).view(batch))

    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM), torch_threads_beside_physics(env):
        rollout = env.rollout(horizon, policy=act, auto_reset=True, break_when_any_done=False)
    rollout = rollout.view(num_tasks, per_task, horizon)
    rollout.set("mask", trajectory_mask(rollout["next", "done"]))
    return rollout

