"""Settings that would run to a clean exit without doing the work asked for are refused before any work."""
import pytest

import recipes
from umrl.configs import ConfigError, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.proposals import make_proposal


@pytest.mark.parametrize("overrides, message", [
    (["collector.total_frames=1000", "collector.init_random_frames=1000"],
     r"collector.init_random_frames: got 1000 \(no update would run\); expected an integer < collector.total_frames"),
    (["optim.updates_per_frame=1e-9"], r"optim.updates_per_frame: got 1e-09 \(no update would run\)"),
    (["collector.total_frames=100", "collector.init_random_frames=0", "replay_buffer.batch_size=256"],
     r"replay_buffer.batch_size: got 256 \(no update would run\); expected an integer <= collector.total_frames"),
])
def test_diayn_without_a_single_update_is_refused(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate(recipes.compose("diayn", [f"output_dir={tmp_path}", *overrides]), DIAYNConfig)
    assert not (tmp_path / "checkpoints").exists()


@pytest.mark.parametrize("num_skills", [0, -3, 2.5])
def test_a_random_proposal_needs_at_least_one_skill(num_skills):
    with pytest.raises(ValueError, match=rf"num_skills: got {num_skills}; expected null \(the env's default\) or an "
                                         r"integer >= 1"):
        make_proposal("random", "point_nav", num_tasks=2, trajectories_per_task=1, num_skills=num_skills)
