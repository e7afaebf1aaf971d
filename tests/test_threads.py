"""Torch threads during collection beside multi-threaded MuJoCo physics (umrl.envs.threads)."""
import os

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import StepCounter, TransformedEnv

from umrl.envs import make_env
from umrl.envs.threads import batches_beside_physics, physics_threads, torch_threads_beside_physics
from umrl.modules.policy import make_gaussian_policy
from umrl.rollout import collect


@pytest.fixture
def two_torch_threads():
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(previous)


def test_physics_threads_of_each_env():
    cpus = len(os.sched_getaffinity(0))
    assert physics_threads(make_env("half_cheetah", 32, seed=0)) == min(cpus, 2)  # >= 16 copies per thread
    assert physics_threads(make_env("half_cheetah", 8, seed=0)) == 1  # fewer than 16 copies per thread
    assert physics_threads(make_env("half_cheetah", 32, seed=0, backend="gym")) == 1
    assert physics_threads(make_env("point_nav", 32)) == 1


def _threaded_cheetah():
    from umrl.envs.mujoco_batched import BATCHED_ENVS

    env = BATCHED_ENVS["half_cheetah"](32, seed=0, num_threads=2)
    assert env.physics_threads == 2
    return env


def test_one_torch_thread_inside_restored_after_even_on_error(two_torch_threads):
    env = _threaded_cheetah()
    with torch_threads_beside_physics(env):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError, match="boom"), torch_threads_beside_physics(env):
        raise RuntimeError("boom")
    assert torch.get_num_threads() == 2
    with torch_threads_beside_physics(make_env("point_nav", 32)):  # torch physics: keeps its threads
        assert torch.get_num_threads() == 2


def test_collect_runs_the_policy_on_one_thread_beside_threaded_physics(two_torch_threads):
    env = _threaded_cheetah()
    policy = make_gaussian_policy(env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1])
    seen = []
    policy.register_forward_pre_hook(lambda *_: seen.append(torch.get_num_threads()))
    batch = collect(TransformedEnv(env, StepCounter(5)), policy, num_tasks=2, horizon=5)
    assert batch.shape == (2, 16, 5) and seen == [1] * 5
    assert torch.get_num_threads() == 2


def test_batches_beside_physics_yields_every_batch_and_frees_threads_between(two_torch_threads):
    env = _threaded_cheetah()
    inside = []

    def fake_collector():
        for i in range(3):
            inside.append(torch.get_num_threads())
            yield TensorDict(i=torch.tensor(i))

    got = []
    for data in batches_beside_physics(fake_collector(), env):
        got.append(int(data["i"]))
        assert torch.get_num_threads() == 2  # the updates between batches keep their threads
    assert got == [0, 1, 2] and inside == [1, 1, 1]
