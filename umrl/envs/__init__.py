"""Environments: reward-free CMPs, batched, as TorchRL envs, each described by one record in the registry.

``make_env(name, num_envs, seed=...)`` returns a ``TransformedEnv`` with batch size ``[num_envs]`` whose last
transform is a ``StepCounter`` enforcing the horizon (``"step_count"`` ``[B, 1]``). ``make_task_env`` adds a
:class:`~umrl.envs.task_reward.TaskReward` with one hand-designed task per env copy. The envs are those of
:data:`ENV_NAMES`: the built-in ones (:mod:`umrl.envs.builtin`) and any added with :func:`register_env`, e.g. a
gymnasium env with a task family of its user's (:func:`umrl.envs.gym_cmp.gym_env_spec`, docs/own_env.md).
"""
from __future__ import annotations

import inspect

import torch
from torchrl.envs import StepCounter, TransformedEnv

from umrl.envs import builtin  # noqa: F401  (registers point_nav, half_cheetah, ant)
from umrl.envs.registry import ENV_NAMES, EnvSpec, get_env_spec, register_env, unregister_env
from umrl.envs.task_reward import TaskReward
from umrl.envs.tasks import TaskFamily, get_task_family
from umrl.validation import check_choice, check_device, check_int

BACKENDS = ("default", "batched", "gym")


def make_env(
    name: str,
    num_envs: int = 1,
    *,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    horizon: int = 100,
    backend: str = "default",
    **options,
) -> TransformedEnv:
    """Build the reward-free CMP ``name`` with ``num_envs`` copies stepped as one batch.

    Args:
        name: one of :data:`ENV_NAMES`.
        num_envs: batch size ``B`` (> 0).

    Keyword Args:
        seed: seeds the env's reset noise (MuJoCo envs); ``None`` leaves it unseeded.
        device: device of the returned tensors (a ``torch.device``, its name, or ``"auto"``: CUDA when available);
            a CUDA device is refused on a machine without one.
        horizon: episode length enforced by ``StepCounter`` (> 0).
        backend: MuJoCo simulation path, ``"batched"`` (default: our batched MjData env) or ``"gym"`` (TorchRL's
            wrapper over a gymnasium sync vector env, the reference). Ignored for point_nav.
        **options: options only some envs take, passed to ``EnvSpec.make`` (point_nav: ``arena``, see
            :class:`~umrl.envs.point_nav.PointNavEnv`); one the env does not take is refused.
    """
    spec = get_env_spec(name)
    num_envs = check_int("num_envs", num_envs, min=1)
    horizon = check_int("horizon", horizon, min=1)
    backend = check_choice("backend", backend, BACKENDS)
    device = check_device("device", device)
    accepted = [p for p in inspect.signature(spec.make).parameters if p not in ("num_envs", "seed", "device", "backend")]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ValueError(f"make_env({name!r}): got env options {unknown}; {name} accepts {accepted or 'none'}.")
    base = spec.make(num_envs, seed=seed, device=device, backend=backend, **options)
    if isinstance(base, TransformedEnv):  # the gym backend already carries transforms: extend them, don't nest
        base.append_transform(StepCounter(max_steps=horizon))
        env = base
    else:
        env = TransformedEnv(base, StepCounter(max_steps=horizon))
    if seed is not None:
        env.set_seed(seed)
    return env


def make_task_env(name: str, tasks: torch.Tensor, **kwargs) -> TransformedEnv:
    """``make_env(name, len(tasks), **kwargs)`` with env copy ``i`` rewarded by task ``tasks[i]``.

    ``tasks`` has shape ``[B, task_dim]`` (a tensor or nested lists; one task is a batch of one, ``[[x, y]]``; see
    :mod:`umrl.envs.tasks`); change them later with
    ``env.transform[-1].set_tasks(new_tasks)``.
    """
    family = get_task_family(name)
    tasks = family.check_tasks(tasks)
    env = make_env(name, tasks.shape[0], **kwargs)
    env.append_transform(TaskReward(family, tasks))
    return env


__all__ = [
    "BACKENDS",
    "ENV_NAMES",
    "EnvSpec",
    "TaskFamily",
    "TaskReward",
    "get_env_spec",
    "get_task_family",
    "make_env",
    "make_task_env",
    "register_env",
    "unregister_env",
]
