"""The batched MuJoCo backend reproduces gymnasium's v5 envs: trajectories, rewards, termination, reset noise."""

import copy

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from torchrl.envs.utils import step_mdp

from umrl.envs.mujoco import make_mujoco_env
from umrl.envs.mujoco_batched import BATCHED_ENVS, MODEL_SPECS

STEPS = 100
BATCH, COPY = 34, 33  # the copy that mirrors gymnasium is stepped by the second of 2 worker threads
TOL = {"atol": 1e-6, "rtol": 1e-6}


def _gym_env(name: str):
    spec = MODEL_SPECS[name]
    return gymnasium.make(spec.gym_id, **spec.gym_kwargs).unwrapped


def _gym_physics(name: str, gym_env, info: dict) -> dict[str, float | list[float]]:
    if name == "half_cheetah":
        return {"x_position": [info["x_position"]], "x_velocity": [info["x_velocity"]]}
    forwarded = copy.copy(gym_env.data)  # the MAML reference code's model.forward() after the step
    mujoco.mj_forward(gym_env.model, forwarded)
    return {
        "xy_position": [info["x_position"], info["y_position"]],
        "xy_com": forwarded.subtree_com[1, :2],
        "x_velocity": [info["x_velocity"]],
        "reward_survive": [info["reward_survive"]],
        "reward_contact": [info["reward_contact"]],
    }


def _f32(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float32))


def _initial_state(gym_env, rng: np.random.Generator, z: float | None):
    qpos = gym_env.init_qpos + rng.uniform(-0.1, 0.1, gym_env.model.nq)
    qvel = 0.1 * rng.standard_normal(gym_env.model.nv)
    if z is not None:
        qpos[2] = z
    return qpos, qvel


@pytest.mark.parametrize(
    ("name", "z"),
    [
        ("half_cheetah", None),
        ("ant", None),
        ("ant", 1.3),
    ],  # ant at z=1.3 starts unhealthy, then falls into range
)
def test_trajectory_matches_gymnasium(name, z):
    rng = np.random.default_rng(0)
    gym_env = _gym_env(name)
    gym_env.reset(seed=0)
    env = BATCHED_ENVS[name](BATCH, seed=0, num_threads=2)
    td = env.reset()
    qpos, qvel = _initial_state(gym_env, rng, z)
    gym_env.set_state(qpos, qvel)
    env.set_mj_state(qpos[None], qvel[None], env_ids=[COPY])
    torch.testing.assert_close(env._observe()[COPY], gym_env._get_obs(), atol=0, rtol=0)
    terminated = []
    for t in range(STEPS):
        if t == STEPS // 2:  # set_state mid-episode keeps warm start, controls and last contact forces
            qpos, qvel = _initial_state(gym_env, rng, z)
            gym_env.set_state(qpos, qvel)
            env.set_mj_state(qpos[None], qvel[None], env_ids=[COPY])
            np.testing.assert_array_equal(env._observe()[COPY], gym_env._get_obs())
        # actions up to 1.2: the simulator clips them, the control cost does not
        action = rng.uniform(-1.2, 1.2, (BATCH, gym_env.action_space.shape[0])).astype(np.float32)
        obs, reward, term, _, info = gym_env.step(action[COPY])
        td["action"] = torch.from_numpy(action)
        nxt = env.step(td)["next"][COPY]
        np.testing.assert_array_equal(env._qstate[COPY], gym_env.state_vector())  # bit-exact float64 physics
        torch.testing.assert_close(nxt["observation"], _f32(obs), **TOL)
        torch.testing.assert_close(nxt["env_reward"], _f32([reward]), **TOL)
        for key, value in _gym_physics(name, gym_env, info).items():
            torch.testing.assert_close(nxt[key], _f32(value), **TOL, msg=key)
        assert nxt["terminated"].item() == term == nxt["done"].item()
        terminated.append(term)
        td = step_mdp(td)
    if z is not None:
        assert terminated[0] and not all(terminated), "the unhealthy start must exercise both flag values"


@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
def test_gym_and_batched_backends_agree(name):
    """Same state, same actions through both TorchRL backends: identical keys and values."""
    envs = {b: make_mujoco_env(name, 2, seed=0, backend=b) for b in ("gym", "batched")}
    tds = {b: env.reset() for b, env in envs.items()}
    rng = np.random.default_rng(1)
    gym_copies = envs["gym"].base_env._env.envs
    for i in range(2):
        qpos, qvel = _initial_state(gym_copies[i].unwrapped, rng, None)
        gym_copies[i].unwrapped.set_state(qpos, qvel)
        envs["batched"].set_mj_state(qpos[None], qvel[None], env_ids=[i])
    for _ in range(20):
        action = (
            torch.rand(2, envs["gym"].action_spec.shape[-1], generator=torch.Generator().manual_seed(3)) * 2
            - 1
        )
        nxt = {}
        for b, env in envs.items():
            tds[b]["action"] = action
            tds[b] = env.step(tds[b])
            nxt[b] = tds[b]["next"]
            tds[b] = step_mdp(tds[b])
        keys = set(nxt["gym"].keys())
        assert keys == set(nxt["batched"].keys())
        for key in keys:
            torch.testing.assert_close(nxt["batched"][key], nxt["gym"][key], **TOL, msg=key)


@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
def test_reset_noise_matches_gymnasium_in_distribution(name):
    """Means and stds of the reset observation's qpos/qvel part over many resets, ours vs gymnasium's."""
    n = 2000
    gym_env = _gym_env(name)
    gym_env.reset(seed=0)
    nqv = gym_env.model.nq + gym_env.model.nv - (1 if name == "half_cheetah" else 2)  # the x (x-y) excluded
    ref = np.stack([gym_env.reset()[0][:nqv] for _ in range(n)])
    env = make_mujoco_env(name, n // 8, seed=0, backend="batched")
    ours = torch.cat([env.reset()["observation"][:, :nqv] for _ in range(8)]).double().numpy()
    np.testing.assert_allclose(ours.mean(0), ref.mean(0), atol=0.012)
    np.testing.assert_allclose(ours.std(0), ref.std(0), rtol=0.1)
    nq_obs = nqv - gym_env.model.nv
    # uniform(+-0.1) qpos noise (std 0.0577) and N(0, 0.1^2) qvel noise
    np.testing.assert_allclose(ours[:, :nq_obs].std(0), 0.2 / np.sqrt(12), rtol=0.1)
    np.testing.assert_allclose(ours[:, nq_obs:].std(0), 0.1, rtol=0.1)
    assert np.abs(ours[:, :nq_obs] - gym_env.init_qpos[-nq_obs:]).max() <= 0.1 + 1e-6
