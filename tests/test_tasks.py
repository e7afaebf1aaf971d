"""Task families and the TaskReward transform."""
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from umrl.envs import ENV_NAMES, make_task_env
from umrl.envs.tasks import get_task_family


@pytest.mark.parametrize("name, low, high, dim", [("point_nav", -0.5, 0.5, 2), ("half_cheetah", 0, 2, 1), ("ant", -3, 3, 2)])
def test_families_sample_in_their_bounds(name, low, high, dim):
    family = get_task_family(name)
    tasks = family.sample(2000, torch.Generator().manual_seed(0))
    assert tasks.shape == (2000, dim)
    assert tasks.min() >= low and tasks.max() <= high
    # uniform: the mean sits at the centre and both halves of the range are used
    assert abs(tasks.mean().item() - (low + high) / 2) < 0.05 * (high - low)
    assert tasks.min() < low + 0.05 * (high - low) and tasks.max() > high - 0.05 * (high - low)


def test_eval_tasks_are_fixed_and_differ_from_training_draws():
    family = get_task_family("point_nav")
    assert torch.equal(family.eval_tasks(20), family.eval_tasks(20))
    assert torch.equal(family.eval_tasks(40)[:20], family.eval_tasks(20))
    assert not torch.equal(family.eval_tasks(20), family.sample(20, torch.Generator().manual_seed(0)))


def test_point_nav_task_reward_matches_hand_computation_per_copy():
    tasks = torch.tensor([[0.3, -0.2], [-0.5, 0.5], [0.0, 0.0]])
    env = make_task_env("point_nav", tasks)
    check_env_specs(env)
    actions = torch.tensor([[1.0, -1.0], [-0.5, 2.0], [0.2, 0.1]])
    rollout = env.rollout(3, lambda td: td.set("action", actions.clone()), break_when_any_done=False)
    position = rollout["next", "position"]
    expected = -(position - tasks[:, None]).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(rollout["next", "reward"], expected)
    torch.testing.assert_close(position[:, 0], 0.1 * actions.clamp(-1, 1))
    assert torch.equal(rollout["task"][:, 0], tasks)


def test_point_nav_episode_ends_early_at_the_goal():
    tasks = torch.tensor([[0.2, 0.0], [0.5, 0.5]])
    env = make_task_env("point_nav", tasks)
    rollout = env.rollout(5, lambda td: td.set("action", torch.tensor([[1.0, 0.0], [0.0, 0.0]])),
                          break_when_any_done=False)
    terminated = rollout["next", "terminated"].squeeze(-1)
    assert terminated[0].tolist() == [False, True, False, True, False]  # reaches (0.2, 0) after 2 steps, resets
    assert not terminated[1].any()
    assert torch.equal(rollout["next", "done"], rollout["next", "terminated"] | rollout["next", "truncated"])


def test_set_tasks_changes_rewards_and_survives_partial_resets():
    env = make_task_env("point_nav", torch.zeros(2, 2), horizon=2)
    env.transform[-1].set_tasks(torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
    rollout = env.rollout(4, lambda td: td.set("action", torch.zeros(2, 2)), break_when_any_done=False)
    torch.testing.assert_close(rollout["next", "reward"], -torch.ones(2, 4, 1))


def test_set_tasks_writes_in_place_and_never_into_the_callers_tensor():
    first, second = torch.tensor([[0.1, 0.2], [0.3, 0.4]]), torch.tensor([[-0.1, 0.0], [0.0, -0.1]])
    env = make_task_env("point_nav", first)
    held = env.transform[-1].tasks
    env.transform[-1].set_tasks(second)
    assert env.transform[-1].tasks is held  # same storage: a recorded CUDA graph reads the new tasks
    assert torch.equal(held, second) and torch.equal(first, torch.tensor([[0.1, 0.2], [0.3, 0.4]]))


def test_forward_relabels_a_stored_batch():
    env = make_task_env("point_nav", torch.tensor([[0.1, 0.1]]))
    rollout = env.rollout(3, lambda td: td.set("action", torch.ones(1, 2)), break_when_any_done=False)
    stored = rollout.clone()
    stored["task"] = torch.tensor([[0.0, 0.0]]).expand(1, 3, 2)
    relabelled = env.transform[-1](stored)
    torch.testing.assert_close(relabelled["next", "reward"], -rollout["next", "position"].norm(dim=-1, keepdim=True))


@pytest.mark.parametrize("bad", [torch.zeros(3), torch.zeros(3, 3), torch.zeros(2, 2)])
def test_wrong_task_shape_is_rejected(bad):
    env = make_task_env("point_nav", torch.zeros(3, 2))
    with pytest.raises(ValueError, match="tasks"):
        env.transform[-1].set_tasks(bad)


def test_unknown_family_lists_choices():
    with pytest.raises(ValueError, match="valid choices"):
        get_task_family("humanoid")
    assert set(ENV_NAMES) == {"point_nav", "half_cheetah", "ant"}


def test_non_finite_tasks_are_refused_with_their_position():
    tasks = torch.tensor([[0.1, 0.2], [float("nan"), 0.0]])
    with pytest.raises(ValueError, match=r"tasks: .*1 non-finite, first at index \(1, 0\)"):
        make_task_env("point_nav", tasks)
