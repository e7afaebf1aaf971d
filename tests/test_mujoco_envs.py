"""MuJoCo CMPs (both backends): specs, keys, seeding, partial resets, Ant termination, bad input."""

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

from umrl.envs import make_task_env
from umrl.envs.mujoco import MUJOCO_BACKENDS, make_mujoco_env
from umrl.envs.mujoco_batched import BATCHED_ENVS
from umrl.envs.tasks import get_task_family
from umrl.resume_state import env_state, load_env_state

DIMS = {"half_cheetah": (17, 6), "ant": (105, 8)}
PHYSICS = {
    "half_cheetah": {"x_position": 1, "x_velocity": 1},
    "ant": {"xy_position": 2, "xy_com": 2, "x_velocity": 1, "reward_survive": 1, "reward_contact": 1},
}


def _actions(n: int, act_dim: int, steps: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(steps, n, act_dim, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def _run(env, actions: torch.Tensor) -> list:
    """Reset, then step with ``actions`` [T, B, act_dim]; returns the T "next" tensordicts."""
    td, out = env.reset(), []
    for a in actions:
        td["action"] = a
        td = env.step(td)
        out.append(td["next"].clone())
        td = step_mdp(td)
    return out


@pytest.mark.parametrize("backend", MUJOCO_BACKENDS)
@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
@pytest.mark.parametrize("num_envs", [1, 3])
def test_specs_and_keys(name, backend, num_envs):
    env = make_mujoco_env(name, num_envs, seed=0, backend=backend)
    check_env_specs(env)
    obs_dim, act_dim = DIMS[name]
    assert env.batch_size == (num_envs,)
    assert env.action_spec.shape == (num_envs, act_dim)
    assert torch.all(env.action_spec.space.low == -1) and torch.all(env.action_spec.space.high == 1)
    nxt = _run(env, _actions(num_envs, act_dim, 3))[-1]
    assert nxt["observation"].shape == (num_envs, obs_dim) and nxt["observation"].dtype == torch.float32
    assert torch.all(nxt["reward"] == 0), "the CMP is reward-free"
    assert nxt["env_reward"].shape == (num_envs, 1) and torch.all(nxt["env_reward"] != 0)
    for key, width in PHYSICS[name].items():
        assert nxt[key].shape == (num_envs, width) and nxt[key].dtype == torch.float32
    for key in ("done", "terminated", "truncated"):
        assert nxt[key].shape == (num_envs, 1) and nxt[key].dtype == torch.bool
    position = nxt["xy_position"] if name == "ant" else nxt["x_position"]
    assert torch.all(position[:, 0] != 0)
    if name == "ant":  # contact term is a cost, survive term 1 while healthy; the centre of mass is near the torso
        assert torch.all(nxt["reward_contact"] <= 0) and torch.all(nxt["reward_survive"] == 1)
        assert torch.all((nxt["xy_com"] - nxt["xy_position"]).abs() < 0.2)
        assert not torch.equal(nxt["xy_com"], nxt["xy_position"])


@pytest.mark.parametrize("backend", MUJOCO_BACKENDS)
def test_ant_observation_excludes_the_xy_position(backend):
    """Two copies in the same pose, one moved by (3, -2) on the floor: the same observation, positions 3, -2 apart."""
    env = make_mujoco_env("ant", 2, seed=0, backend=backend)
    td = env.reset()
    rng = np.random.default_rng(0)
    qpos = np.tile(BATCHED_ENVS["ant"](1)._init_qpos + rng.uniform(-0.1, 0.1, 15), (2, 1))
    qvel = np.tile(0.1 * rng.standard_normal(14), (2, 1))
    qpos[1, :2] += (3.0, -2.0)
    for i in range(2):
        if backend == "batched":
            env.set_mj_state(qpos[i : i + 1], qvel[i : i + 1], env_ids=[i])
        else:
            env.base_env._env.envs[i].unwrapped.set_state(qpos[i], qvel[i])
    for a in _actions(1, 8, 3):
        td["action"] = a.expand(2, 8)
        td = step_mdp(env.step(td))
    assert td["observation"].shape == (2, 105)
    torch.testing.assert_close(td["observation"][0], td["observation"][1], atol=1e-4, rtol=0)
    shift = torch.tensor([3.0, -2.0])
    for key in ("xy_position", "xy_com"):
        torch.testing.assert_close(td[key][1] - td[key][0], shift, atol=1e-4, rtol=0)


@pytest.mark.parametrize("backend", MUJOCO_BACKENDS)
def test_seeding_reproducible(backend):
    actions = _actions(2, 8, 10)
    runs = [_run(make_mujoco_env("ant", 2, seed=s, backend=backend), actions) for s in (7, 7, 8)]
    for a, b in zip(runs[0], runs[1]):
        assert torch.equal(a["observation"], b["observation"]) and torch.equal(
            a["env_reward"], b["env_reward"]
        )
    assert not torch.allclose(runs[0][0]["observation"], runs[2][0]["observation"])
    # copies of one env get different reset noise
    assert not torch.allclose(runs[0][0]["observation"][0], runs[0][0]["observation"][1])


@pytest.mark.parametrize("backend", MUJOCO_BACKENDS)
def test_partial_reset_leaves_other_copies_alone(backend):
    """Resetting copy 0 gives it a fresh start; copies 1 and 2 continue exactly as in a twin env without reset."""
    env, twin = (make_mujoco_env("half_cheetah", 3, seed=3, backend=backend) for _ in range(2))
    actions = _actions(3, 6, 12)
    td, td_twin = env.reset(), twin.reset()
    for t, a in enumerate(actions):
        if t == 6:
            td["_reset"] = torch.tensor([[True], [False], [False]])
            before = td["observation"].clone()
            td = env.reset(td)
            assert torch.equal(td["observation"][1:], before[1:])
            assert td["x_position"][0].abs() <= 0.1 and before[0].ne(td["observation"][0]).all()
        td["action"], td_twin["action"] = a, a
        td, td_twin = env.step(td), twin.step(td_twin)
        torch.testing.assert_close(
            td["next", "observation"][1:], td_twin["next", "observation"][1:], atol=0, rtol=0
        )
        td, td_twin = step_mdp(td), step_mdp(td_twin)
    assert not torch.allclose(td["observation"][0], td_twin["observation"][0])


def test_ant_unhealthy_copy_terminates_and_is_reset():
    env = make_mujoco_env("ant", 2, seed=0)
    td = env.reset()
    qpos = env._init_qpos.copy()
    qpos[2] = 1.5  # torso above healthy_z_range[1] = 1.0
    env.set_mj_state(qpos[None], np.zeros((1, env.model.nv)), env_ids=[1])
    td["action"] = torch.zeros(2, 8)
    td, td_next = env.step_and_maybe_reset(td)
    assert td["next", "terminated"].squeeze(-1).tolist() == [False, True]
    assert td["next", "reward_survive"].squeeze(-1).tolist() == [1.0, 0.0]
    assert 0.2 <= td_next["observation"][1, 0] <= 1.0, "the terminated copy was reset (dim 0: torso height)"
    torch.testing.assert_close(td_next["observation"][0], td["next", "observation"][0])


@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
def test_task_reward_on_batched_backend(name):
    family = get_task_family(name)
    tasks = family.sample(3, torch.Generator().manual_seed(0))
    env = make_task_env(name, tasks, seed=0, horizon=5, backend="batched")
    ro = env.rollout(5, break_when_any_done=False)
    expected = family.reward(ro["next"], ro["action"], ro["task"])
    torch.testing.assert_close(ro["next", "reward"], expected)
    assert ro["next", "truncated"][:, -1].all() and ro["next", "env_reward"].abs().sum() > 0


def test_bad_input():
    with pytest.raises(ValueError, match="half_cheetah"):
        make_mujoco_env("hopper", 2)
    with pytest.raises(ValueError, match="batched"):
        make_mujoco_env("ant", 2, backend="async")
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="positive integer"):
            make_mujoco_env("ant", bad)
    env = make_mujoco_env("half_cheetah", 2)
    with pytest.raises(ValueError, match=r"qpos \[1, 9\]"):
        env.set_mj_state(np.zeros((1, 8)), np.zeros((1, 9)), env_ids=[0])


@pytest.mark.parametrize(("name", "act_dim"), [("half_cheetah", 6), ("ant", 8)])
def test_thread_count_does_not_change_trajectories(name, act_dim):
    """Stepping the copies on 2 threads gives the same trajectories as on one (mujoco.batch or Ant's pool)."""
    envs = [BATCHED_ENVS[name](32, seed=4, num_threads=n) for n in (1, 2)]
    assert [env._sim.nthread for env in envs] == [1, 2]
    runs = [_run(env, _actions(32, act_dim, 5)) for env in envs]
    for a, b in zip(*runs):
        assert torch.equal(a["observation"], b["observation"]) and torch.equal(
            a["env_reward"], b["env_reward"]
        )


def _resets_and_steps(env, n: int, act_dim: int) -> list[torch.Tensor]:
    """Observations of ``n`` rounds of (full reset, partial reset of copy 0, 3 steps) with fixed actions."""
    out, actions = [], _actions(env.batch_size[0], act_dim, 3 * n, seed=5)
    for k in range(n):
        td = env.reset()
        td["_reset"] = torch.zeros(env.batch_size[0], 1, dtype=torch.bool)
        td["_reset"][0] = True
        td = env.reset(td)
        out.append(td["observation"].clone())
        for a in actions[3 * k : 3 * k + 3]:
            td["action"] = a
            td = step_mdp(env.step(td))
            out.append(td["observation"].clone())
    return out


@pytest.mark.parametrize(("name", "act_dim"), [("half_cheetah", 6), ("ant", 8)])
def test_reset_rng_state_round_trips_through_state_dict(name, act_dim):
    """The reset-noise generator saved mid-run and loaded into a fresh env gives bit-identical resets and steps."""
    env = make_mujoco_env(name, 4, seed=11)
    _resets_and_steps(env, 2, act_dim)  # mid-run: the generator has advanced
    saved, saved_rng = env.state_dict(), env.rng_state
    expected = _resets_and_steps(env, 3, act_dim)
    fresh = make_mujoco_env(name, 4, seed=0)
    assert not torch.equal(_resets_and_steps(fresh, 1, act_dim)[0], expected[0])
    fresh.load_state_dict(saved)
    for a, b in zip(_resets_and_steps(fresh, 3, act_dim), expected, strict=True):
        assert torch.equal(a, b)
    other = make_mujoco_env(name, 4)
    other.rng_state = saved_rng  # the getter/setter pair gives the same
    assert all(torch.equal(a, b) for a, b in zip(_resets_and_steps(other, 3, act_dim), expected, strict=True))
    with pytest.raises(ValueError, match="PCG64"):
        other.rng_state = {"bit_generator": "MT19937"}


def test_gym_backend_reset_noise_round_trips_through_env_state():
    """The reference backend's resume state: the gymnasium sub-envs' generators (``umrl.resume_state.env_state``)."""
    env = make_mujoco_env("half_cheetah", 3, seed=11, backend="gym")
    _resets_and_steps(env, 1, 6)
    saved = env_state(env)
    expected = _resets_and_steps(env, 2, 6)
    fresh = make_mujoco_env("half_cheetah", 3, seed=0, backend="gym")
    load_env_state(fresh, saved)
    assert all(torch.equal(a, b) for a, b in zip(_resets_and_steps(fresh, 2, 6), expected, strict=True))


def test_no_mujoco_log_file_in_working_directory(tmp_path, monkeypatch):
    """Model compiler warnings and unstable-simulation warnings reach no ./MUJOCO_LOG.TXT (both backends)."""
    monkeypatch.chdir(tmp_path)
    for backend in MUJOCO_BACKENDS:
        make_mujoco_env("half_cheetah", 2, backend=backend)  # loading the v5 XML warns (settotalmass)
    env = BATCHED_ENVS["ant"](2, seed=0)
    env.reset()
    env.set_mj_state(np.full((1, env.model.nq), np.nan), np.zeros((1, env.model.nv)), env_ids=[1])
    env.step(env.reset().set("action", torch.zeros(2, 8)))  # MuJoCo warns "Nan, Inf or huge value in QPOS"
    assert env.model.nq and not (tmp_path / "MUJOCO_LOG.TXT").exists()
