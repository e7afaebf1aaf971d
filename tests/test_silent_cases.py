"""Settings that would run to a clean exit without doing the work asked for are refused before any work."""
import json

import pytest
import torch
from tensordict import TensorDict

import umrl.trainers
from umrl.configs import ConfigError, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.metatest import cell_finished, read_rows, run_matrix, summary_table
from umrl.metatest.results import text_sha256
from umrl.optim.hvp import KLHessian
from umrl.optim.trpo import TRPOStep
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
        validate(umrl.trainers.compose("diayn", [f"output_dir={tmp_path}", *overrides]), DIAYNConfig)
    assert not (tmp_path / "checkpoints").exists()


@pytest.mark.parametrize("num_skills", [0, -3, 2.5, None])
def test_a_random_proposal_needs_at_least_one_skill(num_skills):
    with pytest.raises(ValueError, match=rf"num_skills: got {num_skills}; expected an integer >= 1 with proposal "
                                         r"random"):
        make_proposal("random", "point_nav", num_tasks=2, trajectories_per_task=1, num_skills=num_skills,
                      discriminator_hidden=[8])


def test_trpo_warns_when_a_nan_kl_rejects_the_step():
    params = TensorDict({"w": torch.ones(3, requires_grad=True)}, [])
    target = torch.tensor([2.0, 0.0, -1.0])

    def model_kl():
        return 0.5 * (params["w"] - 1).pow(2).sum()

    def closure():  # a sound surrogate whose measured KL is NaN away from the start
        shift = params["w"] - 1
        return (shift * -target).sum(), model_kl() + torch.where(shift.abs().sum() > 0, torch.nan, 0.0)

    with pytest.warns(RuntimeWarning, match="TRPO step rejected: the KL was not finite at 5 of 5 line-search trials"):
        info = TRPOStep(params, max_kl=0.01, max_backtracks=5, hvp=KLHessian(lambda batch: model_kl()))(closure)
    assert info["accepted"] == 0.0 and info["nonfinite_kl"] == 5
    assert torch.equal(params["w"], torch.ones(3))


HEADER = "method,env,seed,task,step,return\n"
SETTINGS = {"method": "scratch", "env": "point_nav", "seed": 0}


@pytest.mark.parametrize("text, message", [
    ("", "no rows"), (HEADER, "no rows"), (HEADER + "scratch,point_nav,0,0,0,nan\n", "return nan at seed 0"),
    ("method,env\nscratch,point_nav\n", "no column 'seed'"), (HEADER + "scratch,point_nav,0,0,x,1.0\n", "ValueError"),
])
def test_a_bad_cached_cell_is_named_and_recomputed(tmp_path, text, message):
    cell = tmp_path / "seed0-abc.csv"
    cell.write_text(text)  # its JSON records it: the file is as written, and still no table
    cell.with_suffix(".json").write_text(json.dumps({"settings": SETTINGS, "csv_sha256": text_sha256(text)}))
    with pytest.raises(ValueError, match=f"cannot read results file {cell}: .*{message}"):
        read_rows([cell])
    with pytest.warns(UserWarning, match=f"recomputing the cell {cell}: cannot read results file {cell}"):
        assert not cell_finished(cell, SETTINGS)
    assert not cell.exists() and not cell.with_suffix(".json").exists()


def test_a_corrupt_cell_json_is_named_and_recomputed(tmp_path):
    cell = tmp_path / "seed0-abc.csv"
    text = HEADER + "scratch,point_nav,0,0,0,1.5\n"
    cell.write_text(text)
    cell.with_suffix(".json").write_text(json.dumps({"settings": SETTINGS, "csv_sha256": text_sha256(text)}))
    assert cell_finished(cell, SETTINGS) and read_rows([cell])[0]["return"] == 1.5
    cell.with_suffix(".json").write_text('{"lr": 0.0')
    with pytest.warns(UserWarning, match=f"recomputing the cell {cell}: {cell.with_suffix('.json')}: Expecting"):
        assert not cell_finished(cell, SETTINGS)
    assert not cell.exists()


def test_a_nan_or_a_missing_step_in_a_table_is_an_error():
    rows = [{"method": "scratch", "env": "point_nav", "seed": 0, "task": t, "step": k, "return": 1.0,
             "lr_schedule": "constant"} for t in (0, 1) for k in (0, 1)]
    assert run_matrix(rows, env="point_nav", method="scratch").shape == (2, 2)
    rows[3]["return"] = float("nan")
    with pytest.raises(ValueError, match=r"'scratch' on 'point_nav': seed 0, task 1 has non-finite return \{1: nan\}"):
        summary_table(rows)
    with pytest.raises(ValueError, match=r"seed 0, task 1 has steps \[0\], others \[0, 1\]"):
        run_matrix(rows[:3], env="point_nav", method="scratch")
