"""Smoke tests of recipes/vime.py: a tiny run completes, checkpoints, resumes; the policy loader; coverage."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import ProbabilisticActor

from umrl.checkpoints import load_vime_checkpoint, load_vime_dynamics, load_vime_policy
from umrl.checkpoints.file import write_checkpoint
from umrl.resume_state import load_replay_buffer_state
from umrl.trainers import compose

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def load_recipe():
    import umrl.trainers.vime

    return umrl.trainers.vime


def tiny_config(output_dir, *overrides):
    return compose("vime", [
            "logger.backend=none", "progress=false", f"output_dir={output_dir}", "iterations=2",
            "env.num_envs=4", "env.horizon=10", "policy.hidden=[16,16]", "dynamics.updates_per_iteration=3",
            "dynamics.batch_size=8", "dynamics.holdout_fraction=0.25", "checkpoint.every=1", *overrides,
    ])


def stored_transitions(state) -> int:
    """Transitions in a checkpoint's replay + held-out buffers (:func:`umrl.resume_state.replay_buffer_state`)."""
    total = 0
    for key in ("replay", "holdout"):
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
        load_replay_buffer_state(buffer, state[key])
        total += len(buffer)
    return total


def test_run_checkpoint_resume_and_load(tmp_path):
    recipe = load_recipe()
    result = recipe.train(tiny_config(tmp_path))
    assert result["coverage/cells"] > 0 and result["coverage/initial_cells"] > 0
    assert result["bonus/intrinsic_mean"] > 0 and result["train/frames"] == 80
    assert (tmp_path / "figures" / "coverage.png").stat().st_size > 1000
    first = load_vime_checkpoint(tmp_path)
    assert first["counters"] == {"iteration": 2, "frames": 80}
    assert stored_transitions(first) == 80
    assert not first["median_history"][-2:].isnan().any()

    resumed = recipe.train(tiny_config(tmp_path, "resume=true", "iterations=3"))
    second = load_vime_checkpoint(tmp_path)
    assert second["counters"] == {"iteration": 3, "frames": 120}
    assert second["initial_coverage"] == first["initial_coverage"]
    assert resumed["coverage/cumulative_cells"] >= second["initial_coverage"]["cells"]
    assert stored_transitions(second) == 120
    assert resumed["coverage/initial_cells"] == result["coverage/initial_cells"]
    # the bonus normaliser was restored, then moved by one batch
    torch.testing.assert_close(second["median_history"][:-1], first["median_history"][1:], equal_nan=True)

    policy = load_vime_policy(tmp_path / "checkpoints")
    assert isinstance(policy, ProbabilisticActor)
    for name, value in policy.state_dict().items():
        torch.testing.assert_close(value, second["policy"][name])
    td = policy(TensorDict({"observation": torch.zeros(5, 2)}, [5]))
    assert td["action"].shape == (5, 2) and td["action_log_prob"].shape == (5,)
    dynamics = load_vime_dynamics(tmp_path)
    assert dynamics.input_rms.count.item() > 100  # the running statistics travel with the checkpoint
    (tmp_path / "figures" / "coverage.png").unlink()
    recipe.train(tiny_config(tmp_path, "resume=true", "iterations=4"))
    assert (tmp_path / "figures" / "coverage.png").stat().st_size > 1000  # a resumed run draws it too

    with pytest.raises(ValueError, match="nothing to do"):
        recipe.train(tiny_config(tmp_path, "resume=true", "iterations=3"))


def test_resume_without_checkpoint_and_bad_config(tmp_path):
    recipe = load_recipe()
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        recipe.train(tiny_config(tmp_path, "resume=true"))
    with pytest.raises(ValueError, match="holdout_fraction"):
        recipe.train(tiny_config(tmp_path, "dynamics.holdout_fraction=0"))
    control = recipe.train(tiny_config(tmp_path / "control", "bonus.shuffle=true", "iterations=1"))
    assert control["bonus/intrinsic_return"] == pytest.approx(control["bonus/intrinsic_mean"] * 10, rel=1e-4)
    write_checkpoint({"format": "other"}, tmp_path / "step_1.pt")
    with pytest.raises(ValueError, match="not a VIME checkpoint"):
        load_vime_policy(tmp_path / "step_1.pt")


def test_state_coverage_counts_cells_and_velocity_ranges():
    from umrl.skill_coverage import cumulative_coverage, state_coverage

    xy = torch.tensor([[[0.01, 0.01], [0.05, 0.02], [0.15, 0.0], [-0.05, 0.3]]])  # [N=1, H=4, 2]
    mask = torch.tensor([[True, True, True, False]])
    batch = TensorDict({("next", "position"): xy, "mask": mask}, [1, 4])
    cov = state_coverage(batch, "point_nav", cell_size=0.1)
    assert cov["cells"] == 2 and cov["area"] == pytest.approx(0.02)
    assert cov["max_distance"] == pytest.approx(0.15)
    vel = TensorDict({("next", "x_velocity"): torch.linspace(-1, 3, 101).reshape(1, 101, 1),
                      "mask": torch.ones(1, 101, dtype=torch.bool)}, [1, 101])
    cov = state_coverage(vel, "half_cheetah")
    assert cov["velocity_range"] == pytest.approx(4.0)
    assert cov["velocity_range_p5_p95"] == pytest.approx(3.6, rel=1e-4)
    with pytest.raises(ValueError, match="valid choices"):
        state_coverage(batch, "cartpole")
    seen, cum = cumulative_coverage(None, batch, "point_nav", cell_size=0.1)
    assert cum["cumulative_cells"] == 2
    batch["next", "position"] = xy + 1.0
    seen, cum = cumulative_coverage(seen, batch, "point_nav", cell_size=0.1)
    assert cum["cumulative_cells"] == 4 and seen.shape == (4, 2)
    seen, cum = cumulative_coverage(None, vel, "half_cheetah")
    assert cum["cumulative_velocity_range"] == pytest.approx(4.0)
