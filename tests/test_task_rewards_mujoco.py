"""TaskReward on the MuJoCo CMPs, recomputed by hand from the physics state of a rollout."""
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from umrl.envs import make_env, make_task_env

DT = 0.05  # both v5 models: timestep 0.01 × frame_skip 5


@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
@pytest.mark.parametrize("num_envs", [1, 3])
def test_make_env_specs(name, num_envs):
    env = make_env(name, num_envs, seed=0)
    check_env_specs(env)
    assert env.batch_size == (num_envs,)


def _rollout(name, tasks, steps=12):
    env = make_task_env(name, tasks, seed=1)
    actions = torch.rand(steps, len(tasks), env.action_spec.shape[-1], generator=torch.Generator().manual_seed(0))
    actions = 3 * actions - 1.5  # partly outside [-1, 1]: costs must use the clipped action
    it = iter(actions)
    return env.rollout(steps, lambda td: td.set("action", next(it)), break_when_any_done=False)


def test_half_cheetah_goal_velocity_reward_by_hand():
    tasks = torch.tensor([[0.0], [1.0], [2.0]])
    rollout = _rollout("half_cheetah", tasks)
    x = torch.cat([rollout["x_position"][:, :1], rollout["next", "x_position"]], dim=1)
    velocity = (x[:, 1:] - x[:, :-1]) / DT
    torch.testing.assert_close(rollout["next", "x_velocity"], velocity, atol=1e-4, rtol=1e-4)
    ctrl = rollout["action"].clamp(-1, 1).pow(2).sum(-1, keepdim=True)
    expected = -(velocity - tasks[:, None]).abs() - 0.05 * ctrl
    torch.testing.assert_close(rollout["next", "reward"], expected, atol=1e-4, rtol=1e-4)
    assert not torch.allclose(rollout["next", "reward"], rollout["next", "env_reward"])


def test_ant_goal_position_reward_by_hand():
    tasks = torch.tensor([[2.0, -1.0], [-3.0, 3.0]])
    rollout = _rollout("ant", tasks)
    com = rollout["next", "xy_com"]  # the centre of mass, beside (not equal to) the torso's position
    assert torch.all((com - rollout["next", "xy_position"]).abs() < 0.2)
    ctrl = rollout["action"].clamp(-1, 1).pow(2).sum(-1, keepdim=True)
    distance = (com - tasks[:, None]).abs().sum(-1, keepdim=True)
    expected = -distance + 4.0 + 0.05 - 0.005 * ctrl + rollout["next", "reward_contact"]
    torch.testing.assert_close(rollout["next", "reward"], expected)


def test_wrong_task_dim_for_half_cheetah_is_rejected():
    with pytest.raises(ValueError, match=r"\[num_envs, 1\]"):
        make_task_env("half_cheetah", torch.zeros(2, 2))
