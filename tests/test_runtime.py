"""Recipe runtime: checkpoints, loggers, seeding, NaN guard."""
import os
import re
import signal
from contextlib import contextmanager

import pytest
import torch

from umrl.runtime import (
    Checkpointer,
    CheckpointError,
    check_finite,
    close_logger,
    log_metrics,
    make_logger,
    resolve_checkpoint,
    seed_everything,
)


def test_checkpointer_keeps_latest_or_all_and_writes_config(tmp_path):
    latest_only = Checkpointer(tmp_path / "a")
    for step in (1, 10, 5):
        latest_only.save({"step": step}, step, config={"seed": 3})
    assert [p.name for p in latest_only.all()] == ["step_5.pt"]
    assert (tmp_path / "a" / "config.yaml").read_text().strip() == "seed: 3"

    keep = Checkpointer(tmp_path / "b", keep_all=True)
    for step in (2, 10, 7):
        keep.save({"step": step}, step)
    assert [p.name for p in keep.all()] == ["step_2.pt", "step_7.pt", "step_10.pt"]
    assert keep.load()["step"] == 10 and keep.load(keep.all()[0])["step"] == 2
    assert resolve_checkpoint(tmp_path / "b") == keep.latest()
    assert not list((tmp_path / "b").glob("*.tmp"))


def test_missing_checkpoint_fails_with_a_clear_message(tmp_path):
    with pytest.raises(FileNotFoundError, match="resume=true"):
        Checkpointer(tmp_path / "none").load()
    with pytest.raises(FileNotFoundError, match="step_"):
        resolve_checkpoint(tmp_path / "none")


def test_nan_guard_names_the_bad_loss():
    check_finite({"loss_a": torch.tensor(1.0)}, "ok")
    with pytest.raises(FloatingPointError, match="loss_b"):
        check_finite({"loss_a": torch.tensor(1.0), "loss_b": torch.tensor(float("nan"))}, "update 3")


def test_seed_everything_reproduces_draws():
    seed_everything(7)
    a = torch.rand(3)
    seed_everything(7)
    assert torch.equal(a, torch.rand(3))


def test_csv_logger_writes_scalars(tmp_path):
    logger = make_logger({"backend": "csv"}, exp_name="exp", config={"lr": 0.1}, log_dir=tmp_path)
    log_metrics(logger, {"train/x": 1.5}, step=3)
    files = list((tmp_path / "csv").rglob("*.csv"))
    assert any("1.5" in f.read_text() for f in files)
    assert make_logger({"backend": "none"}, exp_name="exp") is None
    with pytest.raises(ValueError, match="valid choices"):
        make_logger({"backend": "tensorboardx"}, exp_name="exp")


def test_wandb_defaults_to_an_offline_run(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    logger = make_logger({"backend": "wandb", "group": "g"}, exp_name="exp", config={"lr": 0.1})
    log_metrics(logger, {"train/x": 1.0}, step=0)
    assert logger.experiment.settings.mode == "offline" and logger.experiment.group == "g"
    assert "WANDB_MODE" not in os.environ  # the mode is this run's, not the process's (a later job may be online)
    close_logger(logger)
    assert list((tmp_path / "wandb").glob("offline-run-*"))


def test_wandb_runs_land_under_the_output_dir(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_DIR", raising=False)
    seen = {}
    monkeypatch.setattr("umrl.runtime.get_logger", lambda backend, **kwargs: seen.update(kwargs))
    make_logger({"backend": "wandb"}, exp_name="exp", log_dir=tmp_path / "run")
    assert seen["logger_name"] == str(tmp_path / "run") and (tmp_path / "run").is_dir()  # -> <output_dir>/wandb
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "elsewhere"))
    make_logger({"backend": "wandb"}, exp_name="exp", log_dir=tmp_path / "run")
    assert seen["logger_name"] == str(tmp_path / "elsewhere")


@pytest.mark.parametrize("damage", ["truncated", "empty", "garbage"])
def test_unreadable_checkpoint_is_named_and_resume_falls_back(tmp_path, damage):
    checkpointer = Checkpointer(tmp_path, keep_all=True)
    checkpointer.save({"w": torch.arange(1000.0)}, 1)
    bad = checkpointer.save({"w": torch.arange(1000.0) + 1}, 2)
    data = bad.read_bytes()
    bad.write_bytes({"truncated": data[: len(data) // 2], "empty": b"", "garbage": b"not a checkpoint"}[damage])
    with pytest.raises(CheckpointError, match=f"cannot read checkpoint {bad}"):
        checkpointer.load(bad)
    with (pytest.warns(UserWarning, match=f"skipping unreadable checkpoint {bad}"),
          pytest.warns(UserWarning, match=f"moved the unreadable checkpoint {bad} aside to step_2.pt.unreadable")):
        path, state = checkpointer.load_latest_valid()
    assert path.name == "step_1.pt" and state["w"][0] == 0
    assert checkpointer.latest() == path and bad.with_name("step_2.pt.unreadable").exists()  # what loaders read
    (tmp_path / "step_1.pt").write_bytes(b"")
    with pytest.warns(UserWarning), pytest.raises(CheckpointError, match="no readable checkpoint"):
        checkpointer.load_latest_valid()


def test_stale_tmp_files_are_removed_and_config_is_written_atomically(tmp_path):
    Checkpointer(tmp_path).save({"x": 1}, 1, config={"seed": 0})
    (tmp_path / "step_2.pt.tmp").write_bytes(b"half a save")
    (tmp_path / "config.yaml.tmp").write_text("half")
    assert resolve_checkpoint(tmp_path).name == "step_1.pt"  # a read-only lookup: another run may be writing
    assert len(list(tmp_path.glob("*.tmp"))) == 2
    checkpointer = Checkpointer(tmp_path)
    path, _ = checkpointer.load_latest_valid()  # the writer, resuming
    assert not list(tmp_path.glob("*.tmp"))
    assert path.name == "step_1.pt" and checkpointer.latest().name == "step_1.pt"
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


def test_only_files_named_exactly_step_n_pt_are_checkpoints_and_others_are_never_pruned(tmp_path):
    for name in ("backup_step_100.pt", "best_step_1200.pt", "step_100.pt.bak", "step_1e3.pt"):
        (tmp_path / name).write_bytes(b"kept by the user")
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save({"x": 1}, 3)
    assert checkpointer.latest().name == "step_3.pt" and resolve_checkpoint(tmp_path).name == "step_3.pt"
    checkpointer.save({"x": 2}, 5)  # keep_all=False prunes step_3.pt, and nothing else
    assert [p.name for p in checkpointer.all()] == ["step_5.pt"]
    for name in ("backup_step_100.pt", "best_step_1200.pt", "step_100.pt.bak", "step_1e3.pt"):
        assert (tmp_path / name).read_bytes() == b"kept by the user"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_special_files_named_like_checkpoints_are_never_listed_read_or_removed(tmp_path):
    checkpointer = Checkpointer(tmp_path)
    real = checkpointer.save({"x": 5}, 5)
    os.mkfifo(tmp_path / "step_9.pt")  # reading it would block forever
    (tmp_path / "step_7.pt").mkdir()
    (tmp_path / "step_7.pt" / "notes").write_text("a folder")
    os.symlink("/dev/zero", tmp_path / "step_8.pt")  # reading it would never end
    assert checkpointer.all() == [real] and checkpointer.latest() == real
    with _within(10):
        assert resolve_checkpoint(tmp_path) == real
        assert checkpointer.load()["x"] == 5
        assert Checkpointer(tmp_path).load_latest_valid() == (real, {"x": 5})
        checkpointer.save({"x": 6}, 6)  # prunes step_5.pt only
    assert [p.name for p in checkpointer.all()] == ["step_6.pt"]
    assert (tmp_path / "step_9.pt").exists() and (tmp_path / "step_7.pt" / "notes").read_text() == "a folder"
    assert os.readlink(tmp_path / "step_8.pt") == "/dev/zero"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_resolving_a_special_file_given_explicitly_fails_before_opening_it(tmp_path):
    real = Checkpointer(tmp_path).save({"x": 5}, 5)
    os.mkfifo(tmp_path / "step_9.pt")
    (tmp_path / "step_7.pt").mkdir()
    os.symlink("/dev/zero", tmp_path / "step_8.pt")
    with _within(10):
        for name, kind in (("step_9.pt", "a FIFO"), ("step_7.pt", "a folder"), ("step_8.pt", "a character device")):
            message = f"{tmp_path / name} is not a regular checkpoint file ({kind})"
            with pytest.raises(CheckpointError, match=re.escape(message)):
                resolve_checkpoint(tmp_path / name)
    os.symlink(real, tmp_path / "chosen.pt")  # a symlink to a regular file, named by the user, is followed
    assert resolve_checkpoint(tmp_path / "chosen.pt") == tmp_path / "chosen.pt"


def test_stale_tmp_cleanup_removes_only_the_files_save_writes(tmp_path):
    Checkpointer(tmp_path).save({"x": 1}, 1, config={"seed": 0})
    (tmp_path / "step_2.pt.tmp").write_bytes(b"half a save")
    (tmp_path / "config.yaml.tmp").write_text("half")
    (tmp_path / "notes.tmp").write_text("the user's")
    (tmp_path / "step_3.pt.tmp").mkdir()
    (tmp_path / "elsewhere").write_text("a target")
    os.symlink(tmp_path / "elsewhere", tmp_path / "step_4.pt.tmp")
    Checkpointer(tmp_path).save({"x": 5}, 5)
    assert sorted(p.name for p in tmp_path.glob("*.tmp")) == ["notes.tmp", "step_3.pt.tmp", "step_4.pt.tmp"]
    assert (tmp_path / "step_3.pt.tmp").is_dir() and (tmp_path / "step_4.pt.tmp").read_text() == "a target"

def test_replay_buffer_state_keeps_only_filled_rows_and_round_trips_through_wraps():
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from umrl.runtime import load_replay_buffer_state, replay_buffer_state

    def make():
        return TensorDictReplayBuffer(storage=LazyTensorStorage(7), batch_size=2)

    def rows(start, n):
        return TensorDict({"x": torch.arange(start, start + n, dtype=torch.float32)}, [n])

    buffer = make()
    buffer.extend(rows(0, 3))
    state = replay_buffer_state(buffer)
    assert state["_storage"]["rows"]["x"].tolist() == [0, 1, 2]  # not the 7 allocated rows
    assert state["_storage"]["rows"]["x"].untyped_storage().nbytes() == 3 * 4  # a copy, not a view of them
    buffer.extend(rows(10, 6))  # wraps: the write cursor passes the end
    restored = make()
    load_replay_buffer_state(restored, replay_buffer_state(buffer))
    for b in (buffer, restored):
        b.extend(rows(100, 2))
    assert restored.storage[:7]["x"].tolist() == buffer.storage[:7]["x"].tolist()
    assert len(restored) == len(buffer) == 7
