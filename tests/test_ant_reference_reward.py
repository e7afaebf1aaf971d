"""ant's task reward and termination against the MAML reference code, transcribed line by line into numpy.

The reference is cbfinn/maml_rl's ``rllab/envs/mujoco/ant_env_rand_goal.py`` (``AntEnvRandGoal.step``), run by its
``maml_examples/*_ant.py`` as ``normalize(AntEnvRandGoal())``. Its inputs are recorded from gymnasium's ``Ant-v5``
(the physics umrl keeps) stepped with the same actions: the centre of mass after ``model.forward()``, the contact
forces, the state. Both umrl backends must give the same rewards and ``terminated`` flags, the terminating step
included.
"""
import copy

import gymnasium
import mujoco
import numpy as np
import pytest
import torch

from umrl.envs import make_task_env
from umrl.envs.mujoco import MUJOCO_BACKENDS

#: maml_rl ``vendor/mujoco_models/ant.xml``: every motor has ``ctrlrange="-150.0 150.0"`` (gear 1)
REFERENCE_ACTION_BOUNDS = (np.full(8, -150.0), np.full(8, 150.0))
GOALS = np.array([[2.0, -1.0], [-3.0, 3.0]])
STEPS = 25


def normalized_action(action, lb, ub):
    """rllab ``NormalizedEnv.step``: the policy's action mapped from [-1, 1] onto the env's bounds."""
    scaled_action = lb + (action + 1.) * 0.5 * (ub - lb)
    scaled_action = np.clip(scaled_action, lb, ub)
    return scaled_action


def reference_step(com, cfrc_ext, state, action, goal_pos, action_bounds):
    """``AntEnvRandGoal.step`` after ``forward_dynamics(action)``: ``(reward, done)``.

    ``com`` is its ``get_body_com("torso")`` (``com_subtree`` of the torso), ``cfrc_ext`` its
    ``model.data.cfrc_ext``, ``state`` its ``_state`` (qpos, qvel), ``action_bounds`` its ``self.action_bounds``.
    """
    goal_reward = -np.sum(np.abs(com[:2] - goal_pos)) + 4.0  # make it happy, not suicidal
    lb, ub = action_bounds
    scaling = (ub - lb) * 0.5
    ctrl_cost = 0.5 * 1e-2 * np.sum(np.square(action / scaling))
    contact_cost = 0.5 * 1e-3 * np.sum(
        np.square(np.clip(cfrc_ext, -1, 1))),  # (sic: the reference's trailing comma makes a 1-tuple)
    survive_reward = 0.05
    reward = goal_reward - ctrl_cost - contact_cost + survive_reward
    notdone = np.isfinite(state).all() \
        and state[2] >= 0.2 and state[2] <= 1.0
    done = not notdone
    return float(np.squeeze(reward)), done  # its Step(ob, float(reward), done) of the 1-element array


def _initial_states(init_qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Copy 0 starts near rest; copy 1 is thrown upwards and leaves the healthy range within a few steps."""
    rng = np.random.default_rng(0)
    qpos = init_qpos + rng.uniform(-0.1, 0.1, (2, 15))
    qvel = 0.1 * rng.standard_normal((2, 14))
    qvel[1, 2] = 2.0
    return qpos, qvel


def _reference_episode(actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step gymnasium's Ant-v5 per copy with ``actions`` ``[T, 2, 8]``; the reference's rewards and dones ``[T, 2]``."""
    rewards, dones = np.zeros(actions.shape[:2]), np.zeros(actions.shape[:2], dtype=bool)
    for i in range(2):
        env = gymnasium.make("Ant-v5").unwrapped
        env.reset(seed=0)
        qpos, qvel = _initial_states(env.init_qpos)
        env.set_state(qpos[i], qvel[i])
        for t, u in enumerate(actions[:, i]):
            env.step(u)
            forwarded = copy.copy(env.data)  # the reference's model.forward() after model.step()
            mujoco.mj_forward(env.model, forwarded)
            a = normalized_action(u.astype(np.float64), *REFERENCE_ACTION_BOUNDS)
            rewards[t, i], dones[t, i] = reference_step(forwarded.subtree_com[1], env.data.cfrc_ext,
                                                        env.state_vector(), a, GOALS[i], REFERENCE_ACTION_BOUNDS)
    return rewards, dones


@pytest.mark.parametrize("backend", MUJOCO_BACKENDS)
def test_ant_reward_and_termination_match_the_reference(backend):
    rng = np.random.default_rng(1)
    actions = rng.normal(0.0, 0.8, (STEPS, 2, 8)).astype(np.float32)  # partly outside [-1, 1]: clipped
    ref_rewards, ref_dones = _reference_episode(actions)
    assert not ref_dones[:, 0].any() and ref_dones[:, 1].any(), "copy 1 must terminate, copy 0 not"
    end = int(np.argmax(ref_dones[:, 1]))  # copy 1's terminating step: compared, later ones are not
    assert end >= 2

    env = make_task_env("ant", torch.as_tensor(GOALS, dtype=torch.float32), seed=0, horizon=STEPS, backend=backend)
    td = env.reset()
    base = env.base_env
    qpos, qvel = _initial_states(base._init_qpos if backend == "batched" else base._env.envs[0].unwrapped.init_qpos)
    for i in range(2):
        if backend == "batched":
            base.set_mj_state(qpos[i : i + 1], qvel[i : i + 1], env_ids=[i])
        else:
            base._env.envs[i].unwrapped.set_state(qpos[i], qvel[i])
    rewards, terminated = [], []
    for u in actions:
        td["action"] = torch.from_numpy(u)
        td, next_td = env.step_and_maybe_reset(td)  # copy 1 restarts after terminating (not compared then)
        rewards.append(td["next", "reward"].squeeze(-1).double())
        terminated.append(td["next", "terminated"].squeeze(-1))
        td = next_td
    rewards, terminated = torch.stack(rewards).numpy(), torch.stack(terminated).numpy()
    np.testing.assert_allclose(rewards[:, 0], ref_rewards[:, 0], atol=1e-4, rtol=0)
    np.testing.assert_allclose(rewards[: end + 1, 1], ref_rewards[: end + 1, 1], atol=1e-4, rtol=0)
    np.testing.assert_array_equal(terminated[:, 0], ref_dones[:, 0])
    np.testing.assert_array_equal(terminated[: end + 1, 1], ref_dones[: end + 1, 1])
    # the terminating step is paid like any other (+4.05 and the goal distance): no penalty, no forfeit
    assert ref_rewards[end, 1] == pytest.approx(rewards[end, 1], abs=1e-4)
    assert abs(ref_rewards[end, 1] - ref_rewards[end - 1, 1]) < 1.0
