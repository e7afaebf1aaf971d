"""Trainers as library objects: step by step equals train(); state_dict / load_state_dict continue a run."""
import torch

from umrl.trainers import MAMLTrainer, VIMETrainer, compose

TINY = ["proposal=random", "env.horizon=8", "meta_batch_size=2", "trajectories_per_task=2", "policy.hidden=[8]",
        "num_skills=3", "logger.backend=none", "progress=false", "trpo.cg_iters=3", "iterations=2"]


def _trainer(directory, *overrides) -> MAMLTrainer:
    return MAMLTrainer(compose("maml", [*TINY, f"output_dir={directory}", *overrides]))


def test_steps_and_state_dict_continue_the_run_bit_for_bit(tmp_path):
    reference = _trainer(tmp_path / "reference")
    result = reference.train()
    reference.close()
    assert result["iteration"] == 2 and reference.done

    first = _trainer(tmp_path / "split")
    metrics = first.step()
    assert first.iteration == 1 and first.env_steps == metrics["time/env_steps"] == 2 * 2 * 2 * 8
    state = first.state_dict()
    first.close()
    second = _trainer(tmp_path / "other")  # a fresh run elsewhere, then the saved state
    second.load_state_dict(state)
    second.step()
    second.close()
    for key, value in reference.policy.state_dict().items():
        assert torch.equal(value, second.policy.state_dict()[key]), key
    assert second.iteration == 2 and second.env_steps == reference.env_steps


VIME_TINY = ["env.name=point_nav", "env.num_envs=4", "env.horizon=10", "policy.hidden=[8]", "dynamics.hidden=[8]",
             "dynamics.updates_per_iteration=2", "dynamics.batch_size=8", "logger.backend=none", "progress=false",
             "iterations=2"]


def test_vime_trainer_steps_and_state_dict_continue_the_run_bit_for_bit(tmp_path):
    reference = VIMETrainer(compose("vime", [*VIME_TINY, f"output_dir={tmp_path / 'reference'}"]))
    reference.train()
    reference.close()
    first = VIMETrainer(compose("vime", [*VIME_TINY, f"output_dir={tmp_path / 'split'}"]))
    metrics = first.step()
    assert metrics["train/frames"] == 4 * 10 and not first.done
    state = first.state_dict()
    first.close()
    second = VIMETrainer(compose("vime", [*VIME_TINY, f"output_dir={tmp_path / 'other'}"]))
    second.load_state_dict(state)
    second.step()
    second.close()
    assert second.done
    for mine, theirs in ((second.policy, reference.policy), (second.dynamics, reference.dynamics)):
        for key, value in theirs.state_dict().items():
            assert torch.equal(value, mine.state_dict()[key]), key
