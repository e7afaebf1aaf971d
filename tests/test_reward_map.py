"""Reward maps of 2-D skill discriminators: shapes, territories = argmax D, the statistics on a known geometry."""
import math
import runpy
import sys
from pathlib import Path

import pytest
import torch
from tensordict.nn import TensorDictModule

from umrl.modules.discriminator import make_discriminator
from umrl.reward_map import reward_map, reward_map_stats

GOALS = torch.tensor([[0.3, 0.1], [-0.4, 0.2], [0.1, 0.45], [0.4, -0.3]])


def compass_discriminator(scale=1.0):
    """Linear logits scale * (x, -x, y, -y): skill 0 owns +x, 1 owns -x, 2 owns +y, 3 owns -y (cones at 45°)."""
    linear = torch.nn.Linear(2, 4)
    with torch.no_grad():
        linear.weight.copy_(scale * torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]))
        linear.bias.zero_()
    return TensorDictModule(linear, in_keys=["observation"], out_keys=["skill_logits"])


def test_shapes_rewards_and_territories_follow_the_discriminator():
    d = make_discriminator(2, 5, hidden=(16,), seed=0)
    rmap = reward_map(d, GOALS, radius=3.0, resolution=11, num_angles=8, num_radii=6)
    assert rmap.grid.shape == (11, 11, 2) and rmap.grid_rewards.shape == (11, 11, 5)
    assert rmap.territory.shape == (11, 11) and rmap.inner_territory.shape == (11, 11)
    assert rmap.ray_rewards.shape == (8, 6, 5) and rmap.goal_rewards.shape == (11, 11, 5)
    assert rmap.eval_goal_rewards.shape == (4, 5) and rmap.num_skills == 5
    assert rmap.grid[0, 0].tolist() == [-3.0, -3.0] and rmap.grid[0, -1].tolist() == [3.0, -3.0]
    torch.testing.assert_close(rmap.radii[-1], torch.tensor(3.0))
    with torch.no_grad():
        logits = d.module(rmap.grid)
    torch.testing.assert_close(rmap.grid_rewards, torch.log_softmax(logits, -1) + math.log(5))
    assert torch.equal(rmap.territory, logits.argmax(-1))
    # r_z + log p(z) is a log-probability: D sums to one over skills
    torch.testing.assert_close((rmap.ray_rewards - math.log(5)).exp().sum(-1), torch.ones(8, 6))


def test_stats_on_a_known_geometry():
    rmap = reward_map(compass_discriminator(), GOALS, radius=10.0, resolution=41, num_angles=16, num_radii=11)
    assert rmap.territory[20, 30] == 0 and rmap.territory[20, 10] == 1  # (5, 0) -> +x, (-5, 0) -> -x
    assert rmap.territory[30, 20] == 2 and rmap.territory[10, 20] == 3
    stats = reward_map_stats(rmap)
    assert stats["num_skills"] == 4
    assert stats["edge_fraction"] == 1.0  # linear logits: every skill's best point is as far out as possible
    assert stats["skills_near_origin"] == 4
    assert stats["skills_at_eval_goals"] == 3  # the goals point +x, -x, +y and +x
    assert 0 < stats["goal_square_range"] < stats["disc_range"]
    assert stats["disc_min"] < 0 < stats["disc_max"] <= math.log(4)
    flat = reward_map_stats(reward_map(compass_discriminator(0.0), GOALS, radius=10.0, resolution=5, num_radii=5))
    assert flat["disc_range"] == 0 and flat["edge_fraction"] == 0  # D uniform: r = 0, the first point is "best"


def test_bad_inputs():
    d = compass_discriminator()
    with pytest.raises(ValueError, match="radius must be positive"):
        reward_map(d, GOALS, radius=0.0)
    with pytest.raises(ValueError, match=r"eval_goals must have shape \[N, 2\]"):
        reward_map(d, GOALS[:, :1], radius=1.0)
    with pytest.raises(ValueError, match="resolution"):
        reward_map(d, GOALS, radius=1.0, resolution=1)


def test_cli_maps_random_and_diayn_discriminators_and_draws_them(tiny_diayn_checkpoint, tmp_path, monkeypatch, capsys):
    directory, discriminator = tiny_diayn_checkpoint
    out = tmp_path / "maps"
    monkeypatch.setattr(sys, "argv", ["reward_map.py", "--random-seeds", "1", "--hidden", "16", "--num-skills",
                                      "4", "--resolution", "21", "--diayn-checkpoint", str(directory),
                                      "--out", str(out)])
    runpy.run_path(str(Path(__file__).parents[1] / "scripts" / "diagnostics" / "reward_map.py"), run_name="__main__")
    printed = capsys.readouterr().out
    for name in ("random_xavier_seed1", "diayn_diayn"):
        assert name in printed
        for figure in (f"territories_{name}.png", f"rays_{name}.png"):
            assert (out / figure).stat().st_size > 1000
    # the checkpoint's row is the loaded discriminator's
    from umrl.envs.tasks import get_task_family

    expected = reward_map_stats(reward_map(discriminator, get_task_family("point_nav").eval_tasks(), radius=10.0,
                                           resolution=21))
    row = next(line for line in printed.splitlines() if line.startswith("diayn_diayn")).split()[1:]
    assert float(row[5]) == pytest.approx(expected["edge_fraction"], abs=1e-3)
    assert int(float(row[6])) == expected["skills_near_origin"]
