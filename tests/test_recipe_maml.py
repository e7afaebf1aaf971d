"""recipes/maml.py smoke tests: two meta-iterations per proposal on tiny settings, kept checkpoints, resume."""
import pytest
import torch

from umrl.checkpoints import load_maml_checkpoint, load_maml_policy
from umrl.checkpoints.folder import Checkpointer
from umrl.modules import policy_log_std
from umrl.trainers import compose
from umrl.trainers.maml import train

TINY = ["env.horizon=10", "meta_batch_size=2", "trajectories_per_task=3", "policy.hidden=[16]",
        "logger.backend=none", "progress=false", "checkpoint.every=1", "trpo.cg_iters=3"]


def _cfg(tmp_path, *overrides):
    return compose("maml", [*TINY, f"output_dir={tmp_path}", *overrides])


@pytest.mark.parametrize("proposal", ["oracle", "random", "diayn"])
def test_two_iterations_per_proposal(tmp_path, proposal, tiny_diayn_checkpoint):
    diayn, _ = tiny_diayn_checkpoint
    out = tmp_path / "maml"
    skills = ["num_skills=4"] if proposal == "random" else []  # diayn's come from the checkpoint, oracle has none
    result = train(_cfg(out, f"proposal={proposal}", "iterations=2", f"diayn_checkpoint={diayn}", *skills))
    assert result["iteration"] == 2
    for key in ("train/return_pre", "train/return_post", "train/kl", "train/improvement", "time/collect_s",
                "time/learn_s", "time/env_steps_per_s", "train/reward_mean"):
        assert torch.isfinite(torch.tensor(result[key])), key
    assert 0 < result["time/cg_s"] < result["time/direction_s"] < result["time/learn_s"]  # the step's parts nest
    assert result["train/kl"] <= 0.01
    files = Checkpointer(out / "checkpoints").all()
    assert [p.name for p in files] == ["step_0.safetensors", "step_1.safetensors", "step_2.safetensors"]
    initial = load_maml_checkpoint(files[0])
    assert initial["iteration"] == 0 and initial["env_steps"] == 0  # the ablation's "before meta-training" point
    state = load_maml_checkpoint(out)
    assert state["meta"]["proposal"] == proposal and state["iteration"] == 2
    policy, inner_lr = load_maml_policy(out)
    assert inner_lr == 0.1 and policy.module[0].module[0][0].out_features == 16
    assert result["train/log_std"] == policy_log_std(policy).mean().item()  # logged after the meta-step


def test_analytic_hvp_gives_the_autograd_runs_numbers(tmp_path):
    """trpo.hvp=analytic computes gauss_newton's product by hand: the same run to float rounding."""
    runs = {hvp: train(_cfg(tmp_path / hvp, "iterations=2", f"trpo.hvp={hvp}", "maml.inner_lr=0.5",
                            "policy.hidden=[16,16]")) for hvp in ("gauss_newton", "analytic")}
    for key in ("train/return_pre", "train/return_post", "train/kl", "train/improvement", "train/step_norm",
                "train/log_std", "train/backtracks"):
        assert runs["analytic"][key] == pytest.approx(runs["gauss_newton"][key], rel=1e-4, abs=1e-6), key
    assert runs["analytic"]["train/step_norm"] > 0


def test_resume_continues_from_the_latest_checkpoint(tmp_path):
    train(_cfg(tmp_path, "iterations=1"))
    first = load_maml_checkpoint(tmp_path)
    result = train(_cfg(tmp_path, "iterations=2", "resume=true"))
    assert result["iteration"] == 2
    second = load_maml_checkpoint(tmp_path)
    assert second["env_steps"] == 2 * first["env_steps"]
    assert len(Checkpointer(tmp_path / "checkpoints").all()) == 3  # steps 0, 1, 2: resuming writes no second step_0
    for budget in (1, 2):  # a budget the checkpoint already reached: refused, as DIAYN and VIME refuse it
        with pytest.raises(ValueError, match=rf"iterations: got {budget} \(nothing to do: the run in {tmp_path} has "
                                             r"already done 2 iterations\); expected > 2"):
            train(_cfg(tmp_path, f"iterations={budget}", "resume=true"))
    with pytest.raises(ValueError, match="maml.inner_lr: checkpoint has 0.1, this run has 0.2"):
        train(_cfg(tmp_path, "iterations=3", "resume=true", "maml.inner_lr=0.2"))


def test_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="diayn_checkpoint: .*proposal=diayn needs it"):
        train(_cfg(tmp_path, "proposal=diayn", f"diayn_checkpoint={tmp_path / 'nowhere'}"))
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        train(_cfg(tmp_path / "fresh", "resume=true"))
