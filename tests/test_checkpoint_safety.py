"""Checkpoint files are data: a crafted pickle runs nothing through any loader or resume, a changed byte is an error
naming the file, and only ``umrl.checkpoints.convert`` (with a warning) reads the old torch.save files."""
import os
import pathlib
import pickle
import warnings

import numpy as np
import pytest
import torch
from tensordict import TensorDict

import umrl.trainers
from umrl import checkpoints
from umrl.checkpoints import MAML_FORMAT
from umrl.checkpoints.convert import convert_checkpoint
from umrl.checkpoints.export_skills import main as export_skills
from umrl.checkpoints.file import CheckpointError, LegacyCheckpointError, read_checkpoint, write_checkpoint
from umrl.checkpoints.folder import Checkpointer
from umrl.proposals import make_proposal

LOADERS = ["load_diayn_checkpoint", "load_discriminator", "load_skill_policy", "load_maml_checkpoint",
           "load_maml_policy", "load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy"]


class _Touch:
    """Unpickling it creates ``marker``: what a crafted checkpoint could do with any code."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return pathlib.Path.touch, (pathlib.Path(self.marker),)


def _malicious(directory, marker, step=5, fmt="umrl.maml.v1"):
    (directory / "checkpoints").mkdir(parents=True, exist_ok=True)
    path = directory / "checkpoints" / f"step_{step}.pt"
    torch.save({"format": fmt, "meta": {}, "payload": _Touch(marker)}, path)
    return path


@pytest.mark.parametrize("loader", LOADERS)
def test_no_loader_unpickles(tmp_path, loader):
    marker = tmp_path / "marker"
    path = _malicious(tmp_path / "run", marker)
    for source in (path, tmp_path / "run"):
        with pytest.raises(LegacyCheckpointError, match=f"{path}.*torch.save pickle.*umrl.checkpoints.convert"):
            getattr(checkpoints, loader)(source)
    assert not marker.exists()


def test_diayn_checkpoint_and_export_do_not_unpickle(tmp_path):
    marker = tmp_path / "marker"
    path = _malicious(tmp_path / "run", marker, fmt="umrl.diayn.v1")
    with pytest.raises(LegacyCheckpointError, match=str(path)):
        make_proposal("diayn", "point_nav", num_tasks=2, trajectories_per_task=1, diayn_checkpoint=tmp_path / "run")
    with pytest.raises(LegacyCheckpointError, match=str(path)):
        export_skills([str(tmp_path / "run"), str(tmp_path / "copy")])
    assert not marker.exists()


@pytest.mark.parametrize("recipe", ["diayn", "maml", "vime"])
def test_resume_does_not_unpickle(tmp_path, recipe):
    marker = tmp_path / "marker"
    path = _malicious(tmp_path, marker, fmt=f"umrl.{recipe}.v1")
    extra = ["iterations=1"] if recipe != "diayn" else []
    overrides = ["logger.backend=none", "progress=false", "resume=true", f"output_dir={tmp_path}", *extra]
    with pytest.warns(UserWarning, match="skipping unreadable"), \
            pytest.raises(CheckpointError, match=f"(?s)no readable checkpoint.*{path}.*torch.save pickle"):
        umrl.trainers.train(recipe, overrides)
    assert not marker.exists()


def test_state_round_trips_exactly(tmp_path):
    state = {"w": torch.arange(6.0).reshape(2, 3), "b": torch.tensor([True, False]), "n": np.arange(3, dtype=np.uint32),
             "rng": ("MT19937", np.arange(4, dtype=np.uint32), 2, 0, 0.0), "opt": {0: {"step": torch.tensor(3.0)}},
             "td": TensorDict({"obs": torch.ones(4, 2), ("next", "r"): torch.zeros(4, 1)}, batch_size=[4]),
             "nan": float("nan"), "size": torch.Size([2]), "dtype": torch.float64, "x": np.float32(1.5),
             "__tensor__": "not a tag"}
    write_checkpoint(state, tmp_path / "s.pt")
    out = read_checkpoint(tmp_path / "s.pt")
    assert torch.equal(out["w"], state["w"]) and out["b"].dtype == torch.bool
    assert out["n"].dtype == np.uint32 and out["rng"][1].dtype == np.uint32 and out["rng"][0] == "MT19937"
    assert isinstance(out["rng"], tuple) and list(out["opt"]) == [0]
    assert torch.equal(out["td"]["next", "r"], torch.zeros(4, 1)) and out["td"].batch_size == torch.Size([4])
    assert np.isnan(out["nan"]) and out["size"] == torch.Size([2]) and out["dtype"] is torch.float64
    assert out["x"].dtype == np.float32 and out["__tensor__"] == "not a tag"
    with pytest.raises(TypeError, match=r"entry \.obj is a .*_Touch"):
        write_checkpoint({"obj": _Touch(tmp_path / "m")}, tmp_path / "bad.pt")


@pytest.mark.parametrize("damage", ["flip", "zero64"])
def test_a_changed_byte_is_an_error_naming_the_file_and_resume_falls_back(tmp_path, damage):
    checkpointer = Checkpointer(tmp_path, keep_all=True)
    checkpointer.save({"w": torch.arange(1000.0), "config": {"seed": 0}}, 1)
    bad = checkpointer.save({"w": torch.arange(1000.0) + 1, "config": {"seed": 0}}, 2)
    data = bytearray(bad.read_bytes())
    middle = len(data) // 2
    if damage == "flip":
        data[middle] ^= 0x01
    else:
        data[middle - 32:middle + 32] = bytes(64)
    bad.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=f"cannot read checkpoint {bad}.*hash mismatch"):
        checkpointer.load(bad)
    with (pytest.warns(UserWarning, match=f"skipping unreadable checkpoint {bad}"),
          pytest.warns(UserWarning, match=f"moved the unreadable checkpoint {bad} aside")):
        path, state = checkpointer.load_latest_valid()
    assert path.name == "step_1.safetensors" and state["w"][1] == 1


def test_a_changed_header_byte_is_an_error(tmp_path):
    path = MAML_FORMAT.save(Checkpointer(tmp_path), 1, dict.fromkeys(MAML_FORMAT.meta_keys, 1), {"seed": 7},
                            policy={"w": torch.ones(3)})
    data = path.read_bytes()
    path.write_bytes(data.replace(b'\\"seed\\":7', b'\\"seed\\":8'))
    assert path.read_bytes() != data
    with pytest.raises(CheckpointError, match=f"{path}.*hash mismatch"):
        checkpoints.load_maml_checkpoint(path)


def test_convert_reads_a_trusted_old_file_with_a_warning_and_strips_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    old = tmp_path / "old" / "step_3.pt"
    old.parent.mkdir()
    torch.save({"format": "umrl.maml.v1", "meta": {"env": "point_nav", "obs_dim": 2}, "policy": {"w": torch.ones(2)},
                "rng": {"numpy": ("MT19937", np.arange(3, dtype=np.uint32), 0, 0, 0.0)},
                "config": {"output_dir": "/tmp/somewhere/seed0", "diayn_checkpoint": "/work/x/diayn/seed0-abc"}}, old)
    with pytest.raises(ValueError, match="absolute paths.*diayn_checkpoint"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        convert_checkpoint(old, tmp_path / "new")
    with pytest.warns(UserWarning, match="unpickles.*only checkpoints you trust"):
        written = convert_checkpoint(old, tmp_path / "new", {"/work/x/diayn/seed0-abc": "results/diayn/seed0"})
    assert written == tmp_path / "new" / "checkpoints" / "step_3.safetensors"
    state = read_checkpoint(written)  # a stand-in policy: the format's network checks would refuse it
    assert state["config"] == {"output_dir": "new", "diayn_checkpoint": "results/diayn/seed0"}
    assert state["rng"]["numpy"][1].dtype == np.uint32 and torch.equal(state["policy"]["w"], torch.ones(2))
    assert "/tmp" not in (tmp_path / "new" / "checkpoints" / "config.yaml").read_text()
    assert os.path.exists(old)


def test_a_suite_cell_does_not_unpickle_a_reused_run(tmp_path):
    from umrl.metatest import CellSpec, run_cell

    marker = tmp_path / "marker"
    path = _malicious(tmp_path / "run", marker)
    spec = CellSpec(method="oracle", env="point_nav", seed=0, output=str(tmp_path / "cell.csv"),
                    checkpoint=str(tmp_path / "run"), num_tasks=1)
    with pytest.raises(LegacyCheckpointError, match=str(path)):
        run_cell(spec)
    assert not marker.exists() and not (tmp_path / "cell.csv").exists()


def test_convert_refuses_a_file_that_would_run_code(tmp_path):
    marker = tmp_path / "marker"
    path = _malicious(tmp_path / "run", marker)
    with pytest.raises(pickle.UnpicklingError), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        convert_checkpoint(path, tmp_path / "new")
    assert not marker.exists()
