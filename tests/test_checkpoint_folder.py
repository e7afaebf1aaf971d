"""A run's checkpoint folder (:mod:`umrl.checkpoints.folder`): saving, pruning, listing, resolving, falling back."""
import os
import re
import signal
from contextlib import contextmanager

import pytest
import torch

from umrl.checkpoints.file import CheckpointError
from umrl.checkpoints.folder import Checkpointer, resolve_checkpoint


def test_checkpointer_keeps_latest_or_all_and_writes_config(tmp_path):
    latest_only = Checkpointer(tmp_path / "a")
    for step in (1, 10, 5):
        latest_only.save({"step": step}, step, config={"seed": 3})
    assert [p.name for p in latest_only.all()] == ["step_5.safetensors"]
    assert (tmp_path / "a" / "config.yaml").read_text().strip() == "seed: 3"

    keep = Checkpointer(tmp_path / "b", keep_all=True)
    for step in (2, 10, 7):
        keep.save({"step": step}, step)
    assert [p.name for p in keep.all()] == ["step_2.safetensors", "step_7.safetensors", "step_10.safetensors"]
    assert keep.load()["step"] == 10 and keep.load(keep.all()[0])["step"] == 2
    assert resolve_checkpoint(tmp_path / "b") == keep.latest()
    assert not list((tmp_path / "b").glob("*.tmp"))


def test_missing_checkpoint_fails_with_a_clear_message(tmp_path):
    with pytest.raises(FileNotFoundError, match="resume=true"):
        Checkpointer(tmp_path / "none").load()
    with pytest.raises(FileNotFoundError, match="step_"):
        resolve_checkpoint(tmp_path / "none")


def _as_legacy(path):
    """``path`` renamed ``step_<N>.pt``, as umrl named the same files before."""
    return path.rename(path.with_suffix(".pt"))


@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
@pytest.mark.parametrize("damage", ["truncated", "empty", "garbage"])
def test_unreadable_checkpoint_is_named_and_resume_falls_back(tmp_path, damage, suffix):
    checkpointer = Checkpointer(tmp_path, keep_all=True)
    first = checkpointer.save({"w": torch.arange(1000.0)}, 1)
    bad = checkpointer.save({"w": torch.arange(1000.0) + 1}, 2)
    if suffix == ".pt":
        first, bad = _as_legacy(first), _as_legacy(bad)
    data = bad.read_bytes()
    bad.write_bytes({"truncated": data[: len(data) // 2], "empty": b"", "garbage": b"not a checkpoint"}[damage])
    with pytest.raises(CheckpointError, match=f"cannot read checkpoint {bad}"):
        checkpointer.load(bad)
    with (pytest.warns(UserWarning, match=f"skipping unreadable checkpoint {bad}"),
          pytest.warns(UserWarning, match=f"moved the unreadable checkpoint {bad} aside to step_2{suffix}.unreadable")):
        path, state = checkpointer.load_latest_valid()
    assert path == first and state["w"][0] == 0
    assert checkpointer.latest() == path and bad.with_name(f"step_2{suffix}.unreadable").exists()  # what loaders read
    first.write_bytes(b"")
    with pytest.warns(UserWarning), pytest.raises(CheckpointError, match="no readable checkpoint"):
        checkpointer.load_latest_valid()


def test_stale_tmp_files_are_removed_and_config_is_written_atomically(tmp_path):
    Checkpointer(tmp_path).save({"x": 1}, 1, config={"seed": 0})
    (tmp_path / "step_2.safetensors.tmp").write_bytes(b"half a save")
    (tmp_path / "step_3.pt.tmp").write_bytes(b"half a save by an earlier umrl")
    (tmp_path / "config.yaml.tmp").write_text("half")
    assert resolve_checkpoint(tmp_path).name == "step_1.safetensors"  # a read-only lookup: another run may write
    assert len(list(tmp_path.glob("*.tmp"))) == 3
    checkpointer = Checkpointer(tmp_path)
    path, _ = checkpointer.load_latest_valid()  # the writer, resuming
    assert not list(tmp_path.glob("*.tmp"))
    assert path.name == "step_1.safetensors" and checkpointer.latest().name == "step_1.safetensors"
    assert "seed: 0" in (tmp_path / "config.yaml").read_text()


@contextmanager
def _within(seconds):
    """Fail instead of hanging: a blocked ``open`` of a FIFO is interrupted by the alarm."""
    def expire(signum, frame):
        raise TimeoutError(f"still blocked after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


NOT_CHECKPOINTS = ("backup_step_100.pt", "best_step_1200.safetensors", "step_100.pt.bak", "step_100.safetensors.bak",
                   "step_1e3.pt", "step_1e3.safetensors", "step_7.pth", "step_7.safetensor", "step_7.PT")


def test_only_files_named_exactly_step_n_safetensors_or_pt_are_checkpoints_and_others_are_never_pruned(tmp_path):
    for name in NOT_CHECKPOINTS:
        (tmp_path / name).write_bytes(b"kept by the user")
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save({"x": 1}, 3)
    assert checkpointer.latest().name == "step_3.safetensors"
    assert resolve_checkpoint(tmp_path).name == "step_3.safetensors"
    checkpointer.save({"x": 2}, 5)  # keep_all=False prunes step_3.safetensors, and nothing else
    assert [p.name for p in checkpointer.all()] == ["step_5.safetensors"]
    for name in NOT_CHECKPOINTS:
        assert (tmp_path / name).read_bytes() == b"kept by the user"


def test_a_new_checkpoint_is_a_safetensors_file_that_torch_load_reads_as_such(tmp_path):
    """The name says what the file is: safetensors' reader opens it and finds umrl's metadata, and ``torch.load``
    dispatches on the suffix to safetensors (no unpickling, no advice to set ``weights_only=False``)."""
    from safetensors import safe_open

    from umrl.checkpoints.file import FILE_FORMAT

    path = Checkpointer(tmp_path).save({"w": torch.arange(3.0), "step": 4}, 4)
    assert path.name == "step_4.safetensors"
    with safe_open(str(path), "pt") as file:
        assert file.metadata()["format"] == FILE_FORMAT and list(file.keys()) == ["t0"]
    assert torch.equal(torch.load(path)["t0"], torch.arange(3.0))


def test_legacy_pt_checkpoints_are_listed_loaded_resumed_and_pruned_beside_new_ones(tmp_path):
    """A run written while checkpoints were named ``step_<N>.pt`` (the same files), continued by this umrl: the
    latest is the highest step over both names, a step written under both names counts once (the new name), and
    pruning removes either name."""
    keep = Checkpointer(tmp_path / "all", keep_all=True)
    for step in (0, 10, 20):
        _as_legacy(keep.save({"step": step}, step))
    assert [p.name for p in keep.all()] == ["step_0.pt", "step_10.pt", "step_20.pt"]
    assert keep.latest().name == "step_20.pt" and resolve_checkpoint(tmp_path / "all").name == "step_20.pt"
    path, state = keep.load_latest_valid()  # resume=true of the old run
    assert path.name == "step_20.pt" and state == {"step": 20} and keep.load()["step"] == 20
    keep.save({"step": 20}, 20)  # a step saved again: the .pt of that step is superseded, earlier ones stay
    keep.save({"step": 30}, 30)
    assert [p.name for p in keep.all()] == ["step_0.pt", "step_10.pt", "step_20.safetensors", "step_30.safetensors"]
    assert sorted(p.name for p in (tmp_path / "all").iterdir() if p.name != "config.yaml") == [
        "step_0.pt", "step_10.pt", "step_20.safetensors", "step_30.safetensors"]

    latest_only = Checkpointer(tmp_path / "latest")
    _as_legacy(latest_only.save({"step": 50}, 50))
    assert latest_only.latest().name == "step_50.pt"  # a higher .pt step beats a lower .safetensors one
    (tmp_path / "latest" / "step_40.safetensors").write_bytes((tmp_path / "latest" / "step_50.pt").read_bytes())
    assert latest_only.latest().name == "step_50.pt"
    latest_only.save({"step": 60}, 60)
    assert [p.name for p in (tmp_path / "latest").iterdir()] == ["step_60.safetensors"]

    both = Checkpointer(tmp_path / "both", keep_all=True)
    new = both.save({"step": 7, "name": "new"}, 7)
    (tmp_path / "both" / "step_7.pt").write_bytes(new.read_bytes())  # e.g. a copy made by hand
    assert both.all() == [new] and resolve_checkpoint(tmp_path / "both") == new


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
def test_special_files_named_like_checkpoints_are_never_listed_read_or_removed(tmp_path, suffix):
    checkpointer = Checkpointer(tmp_path)
    real = checkpointer.save({"x": 5}, 5)
    os.mkfifo(tmp_path / f"step_9{suffix}")  # reading it would block forever
    (tmp_path / f"step_7{suffix}").mkdir()
    (tmp_path / f"step_7{suffix}" / "notes").write_text("a folder")
    os.symlink("/dev/zero", tmp_path / f"step_8{suffix}")  # reading it would never end
    assert checkpointer.all() == [real] and checkpointer.latest() == real
    with _within(10):
        assert resolve_checkpoint(tmp_path) == real
        assert checkpointer.load()["x"] == 5
        assert Checkpointer(tmp_path).load_latest_valid() == (real, {"x": 5})
        checkpointer.save({"x": 6}, 6)  # prunes step_5.safetensors only
    assert [p.name for p in checkpointer.all()] == ["step_6.safetensors"]
    assert (tmp_path / f"step_9{suffix}").exists()
    assert (tmp_path / f"step_7{suffix}" / "notes").read_text() == "a folder"
    assert os.readlink(tmp_path / f"step_8{suffix}") == "/dev/zero"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
def test_resolving_a_special_file_given_explicitly_fails_before_opening_it(tmp_path, suffix):
    real = Checkpointer(tmp_path).save({"x": 5}, 5)
    os.mkfifo(tmp_path / f"step_9{suffix}")
    (tmp_path / f"step_7{suffix}").mkdir()
    os.symlink("/dev/zero", tmp_path / f"step_8{suffix}")
    with _within(10):
        for stem, kind in (("step_9", "a FIFO"), ("step_7", "a folder"), ("step_8", "a character device")):
            name = stem + suffix
            message = f"{tmp_path / name} is not a regular checkpoint file ({kind})"
            with pytest.raises(CheckpointError, match=re.escape(message)):
                resolve_checkpoint(tmp_path / name)
    os.symlink(real, tmp_path / "chosen.pt")  # a symlink to a regular file, named by the user, is followed
    assert resolve_checkpoint(tmp_path / "chosen.pt") == tmp_path / "chosen.pt"


def test_stale_tmp_cleanup_removes_only_the_files_save_writes(tmp_path):
    Checkpointer(tmp_path).save({"x": 1}, 1, config={"seed": 0})
    (tmp_path / "step_2.safetensors.tmp").write_bytes(b"half a save")
    (tmp_path / "step_6.pt.tmp").write_bytes(b"half a save by an earlier umrl")
    (tmp_path / "config.yaml.tmp").write_text("half")
    (tmp_path / "notes.tmp").write_text("the user's")
    (tmp_path / "step_3.pt.tmp").mkdir()
    (tmp_path / "elsewhere").write_text("a target")
    os.symlink(tmp_path / "elsewhere", tmp_path / "step_4.pt.tmp")
    Checkpointer(tmp_path).save({"x": 5}, 5)
    assert sorted(p.name for p in tmp_path.glob("*.tmp")) == ["notes.tmp", "step_3.pt.tmp", "step_4.pt.tmp"]
    assert (tmp_path / "step_3.pt.tmp").is_dir() and (tmp_path / "step_4.pt.tmp").read_text() == "a target"
