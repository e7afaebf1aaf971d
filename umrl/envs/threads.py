"""Torch's intra-op threads while MuJoCo physics runs on CPU threads of the same process.

After every parallel region, torch's OpenMP workers spin-wait for the next one on the cores that MuJoCo's own
threads step the copies on. With the 2x300 policy in the loop (half_cheetah, ``B = 800``, 2 cores, 2 torch threads)
``mujoco.batch``'s step took 16.7 ms instead of 10.4 ms with free actions. On one torch thread no parallel region
starts, so nothing spins: ``benchmarks/throughput.py --scaling`` measures both settings side by side (README).

``OMP_WAIT_POLICY=PASSIVE`` would stop the spinning too, but only for a whole process and from its start, and it
slowed the MAML learning step on point_nav (0.85-1.00 s -> 1.14-1.16 s, ``meta_iteration.py --preset reference
--hvp-fraction 0.1``): threads are lowered only around collection instead.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import AbstractContextManager

from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

from umrl.process import torch_threads

__all__ = ["batches_beside_physics", "physics_threads", "torch_threads_beside_physics"]


def physics_threads(env: EnvBase) -> int:
    """CPU threads ``env`` steps its physics on: the batched MuJoCo env's ``physics_threads``, else 1."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return getattr(env, "physics_threads", 1)


def torch_threads_beside_physics(env: EnvBase) -> AbstractContextManager[None]:
    """Run the block (a rollout of ``env``) on one torch thread if ``env`` steps physics on several CPU threads.

    No-op otherwise (point_nav, the gym backend, a batched MuJoCo env on one thread); the thread count is restored
    on exit, also after an error (:func:`umrl.process.torch_threads`).
    """
    return torch_threads(1 if physics_threads(env) > 1 else None)


def batches_beside_physics(collector: Iterable[TensorDictBase], env: EnvBase) -> Iterator[TensorDictBase]:
    """Iterate a TorchRL collector of ``env``, each batch collected under :func:`torch_threads_beside_physics`
    (the work between batches, e.g. the updates, runs on the caller's threads)."""
    batches = iter(collector)
    while True:
        with torch_threads_beside_physics(env):
            data = next(batches, None)
        if data is None:
            return
        yield data
