"""Checkpoint files named for what they are (``step_<N>.safetensors``), and the runs written while umrl named the
same files ``step_<N>.pt`` (the committed results, a run in progress) read, resumed and pruned as before."""
import importlib
import re
import shutil
from pathlib import Path

import pytest
import torch
from test_resume import BUDGET, checkpoint_diffs, config

from umrl import checkpoints
from umrl.checkpoints.file import read_checkpoint
from umrl.checkpoints.folder import Checkpointer, resolve_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

REPO = Path(__file__).resolve().parents[1]


def _rename_to_pt(run_dir: Path) -> list[str]:
    """Rename every checkpoint of ``run_dir`` (the seeds' folders too) ``step_<N>.pt``, as umrl wrote them before."""
    renamed = []
    for path in sorted(run_dir.rglob("step_*.safetensors")):
        path.rename(path.with_suffix(".pt"))
        renamed.append(str(path.with_suffix(".pt").relative_to(run_dir)))
    return renamed


@pytest.mark.parametrize("recipe", ["diayn", "maml"])
def test_a_run_written_with_pt_names_resumes_to_the_numbers_of_an_uninterrupted_run(tmp_path, recipe):
    """DIAYN (seed folders beside the resume file, only the newest kept) and MAML (every checkpoint kept)."""
    train = importlib.import_module(f"umrl.trainers.{recipe}").train
    key, stop, end = BUDGET[recipe]
    whole = train(config(recipe, tmp_path / "whole", "point_nav", f"{key}={end}"))
    assert Path(whole["checkpoint"]).name == f"step_{end}.safetensors"
    train(config(recipe, tmp_path / "split", "point_nav", f"{key}={stop}"))
    assert _rename_to_pt(tmp_path / "split")
    resumed = train(config(recipe, tmp_path / "split", "point_nav", f"{key}={end}", "resume=true"))
    diffs = checkpoint_diffs(read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"]))
    assert {path: d for path, d in diffs.items() if d != 0} == {}
    left = sorted(str(p.relative_to(tmp_path / "split")) for p in (tmp_path / "split").rglob("step_*"))
    if recipe == "maml":  # keeps every checkpoint: the old ones under their old names
        assert left == ["checkpoints/step_0.pt", "checkpoints/step_1.pt", "checkpoints/step_2.safetensors"]
    else:  # keeps the newest only: the .pt files are pruned
        assert left == ["checkpoints/step_160.safetensors", "seed0/checkpoints/step_160.safetensors"]


def _step(path: Path) -> int:
    return int(re.fullmatch(r"step_([0-9]+)\.pt", path.name).group(1))


def test_committed_results_with_pt_names_resolve_to_their_highest_step_and_load(tmp_path):
    """The highest step by number (``step_140.pt`` after ``step_80.pt``), read by the loaders as before: a committed
    MAML run, and committed DIAYN skills renamed as the exports before ``.safetensors`` named them."""
    maml_run = REPO / "results" / "half_cheetah" / "uml_random_ref" / "seed0"
    files = list((maml_run / "checkpoints").glob("step_*.pt"))
    assert len(files) > 2 and resolve_checkpoint(maml_run) == max(files, key=_step)
    assert Checkpointer(maml_run / "checkpoints").all() == sorted(files, key=_step)
    saved = read_checkpoint(max(files, key=_step))
    policy, inner_lr = checkpoints.load_maml_policy(maml_run)
    assert inner_lr == saved["meta"]["inner_lr"] and saved["meta"]["env"] == "half_cheetah"
    assert all(torch.equal(value, saved["policy"][key]) for key, value in policy.state_dict().items())
    diayn_run = Path(shutil.copytree(REPO / "results" / "point_nav" / "diayn_2x32" / "seed0", tmp_path / "skills"))
    assert _rename_to_pt(diayn_run) == ["checkpoints/step_50000.pt"]
    _, num_skills, obs_dim = checkpoints.load_skill_policy(diayn_run)
    saved = read_checkpoint(resolve_checkpoint(diayn_run))
    assert resolve_checkpoint(diayn_run).suffix == ".pt" and (num_skills, obs_dim) == (saved["meta"]["num_skills"], 2)
