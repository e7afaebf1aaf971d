"""point_nav: docs/protocol.md semantics, specs, partial resets."""
import re

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from umrl.envs import make_env
from umrl.envs.point_nav import PointNavEnv


@pytest.mark.parametrize("num_envs", [1, 5])
def test_specs(num_envs):
    check_env_specs(make_env("point_nav", num_envs, seed=0))


def test_starts_at_origin_and_clips_and_scales_actions():
    env = make_env("point_nav", 3)
    td = env.reset()
    assert torch.equal(td["observation"], torch.zeros(3, 2))
    action = torch.tensor([[0.5, -0.25], [3.0, -7.0], [-1.0, 1.0]])
    out = env.step(td.set("action", action))["next"]
    expected = torch.tensor([[0.05, -0.025], [0.1, -0.1], [-0.1, 0.1]])
    torch.testing.assert_close(out["observation"], expected)
    torch.testing.assert_close(out["position"], expected)
    assert torch.equal(out["reward"], torch.zeros(3, 1)), "the CMP itself is reward-free"
    assert not out["done"].any()


def test_horizon_truncates_at_100_steps():
    env = make_env("point_nav", 2)
    rollout = env.rollout(150, lambda td: td.set("action", torch.ones(2, 2)), break_when_any_done=True)
    assert rollout.shape == (2, 100)
    assert rollout["next", "truncated"][:, -1].all() and not rollout["next", "terminated"].any()
    assert not rollout["next", "done"][:, :-1].any()
    torch.testing.assert_close(rollout["next", "position"][:, -1], torch.full((2, 2), 10.0))


def test_partial_reset_resets_only_masked_copies():
    env = PointNavEnv(3)
    td = env.reset()
    for _ in range(4):
        td = env.step(td.set("action", torch.ones(3, 2)))["next"].clone()
    td["_reset"] = torch.tensor([[False], [True], [False]])
    reset = env.reset(td)
    torch.testing.assert_close(reset["observation"], torch.tensor([[0.4, 0.4], [0.0, 0.0], [0.4, 0.4]]))


def test_partial_resets_inside_a_rollout_are_independent():
    env = make_env("point_nav", 2, horizon=3)
    rollout = env.rollout(7, lambda td: td.set("action", torch.ones(2, 2)), break_when_any_done=False)
    # each copy restarts from the origin after 3 steps: positions cycle 0.1, 0.2, 0.3
    torch.testing.assert_close(rollout["next", "position"][0, :, 0], torch.tensor([0.1, 0.2, 0.3, 0.1, 0.2, 0.3, 0.1]))


def test_rollouts_are_reproducible_with_a_seed():
    def run(seed):
        env = make_env("point_nav", 4, seed=seed)
        torch.manual_seed(seed)
        return env.rollout(20)["next", "observation"]

    assert torch.equal(run(3), run(3))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"name": "point_navv"}, "valid choices"),
        ({"name": "point_nav", "num_envs": 0}, re.escape("num_envs: got 0; expected an integer >= 1")),
        ({"name": "point_nav", "num_envs": -3}, re.escape("num_envs: got -3; expected an integer >= 1")),
        ({"name": "point_nav", "horizon": 0}, re.escape("horizon: got 0; expected an integer >= 1")),
        ({"name": "point_nav", "horizon": 2.5}, re.escape("horizon: got 2.5; expected an integer >= 1")),
        ({"name": "ant", "backend": "brax"}, re.escape("backend: got 'brax'; expected one of 'default'")),
    ],
)
def test_bad_input_is_rejected_with_a_clear_message(kwargs, match):
    with pytest.raises((TypeError, ValueError), match=match):
        make_env(**kwargs)

