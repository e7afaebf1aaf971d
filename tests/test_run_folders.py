"""Runs and their folders: one run per output_dir (a second is refused naming the holder), a fresh run never writes
into an earlier run's folder, a killed save's temporary files are removed on the next start, and names and paths are
checked before Hydra or a trainer writes anything."""
import os
import signal
import subprocess
import sys
import time

import pytest
from omegaconf import OmegaConf
from script_loading import REPO, repo_env

from umrl.configs import ConfigError
from umrl.configs.callbacks import OutputDirCheck
from umrl.folder_lock import FolderHoldsRun, FolderInUse, FolderLock
from umrl.trainers import DIAYNTrainer, MAMLTrainer, VIMETrainer, compose

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

TRAINERS = {"diayn": DIAYNTrainer, "maml": MAMLTrainer, "vime": VIMETrainer}
TINY = {
    "diayn": ["num_skills=3", "env.num_envs=4", "env.horizon=10", "collector.frames_per_batch=40",
              "collector.init_random_frames=40", "collector.total_frames=80", "network.hidden=[16,16]",
              "network.discriminator_hidden=[16]", "replay_buffer.size=200", "replay_buffer.batch_size=16",
              "eval.episodes_per_skill=1"],
    "maml": ["proposal=oracle", "meta_batch_size=2", "trajectories_per_task=3", "env.horizon=10", "policy.hidden=[16]",
             "trpo.cg_iters=3", "iterations=2"],
    "vime": ["env.num_envs=4", "env.horizon=10", "policy.hidden=[16]", "dynamics.hidden=[8]", "dynamics.batch_size=8",
             "dynamics.updates_per_iteration=2", "bonus.num_samples=2", "dynamics.num_samples=2", "iterations=2"],
}


def config(recipe, output_dir, *overrides):
    return compose(recipe, ["logger.backend=none", "progress=false", f"output_dir={output_dir}", *TINY[recipe],
                            *overrides])


def listing(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_mtime_ns) for p in folder.rglob("*") if p.name != "run.lock")


@pytest.mark.parametrize(("recipe", "where"), [("diayn", "checkpoints"), ("diayn", "seed0/checkpoints"),
                                               ("maml", "checkpoints"), ("vime", "checkpoints")])
def test_a_fresh_run_into_an_earlier_runs_folder_is_refused_before_any_work(tmp_path, recipe, where):
    earlier = tmp_path / where / "step_40.pt"
    earlier.parent.mkdir(parents=True)
    earlier.write_bytes(b"an earlier run's checkpoint")
    before = listing(tmp_path)
    with pytest.raises(FolderHoldsRun, match=rf"output_dir {tmp_path} holds checkpoints of an earlier run "
                                             rf"\({earlier}\): pass resume=true to continue it, or choose another "
                                             "output_dir"):
        TRAINERS[recipe](config(recipe, tmp_path))
    assert listing(tmp_path) == before  # nothing written, nothing removed
    FolderLock(tmp_path).acquire().release()  # and the folder is free again


def test_a_second_trainer_in_a_folder_in_use_is_refused_and_close_frees_it(tmp_path):
    first = MAMLTrainer(config("maml", tmp_path))
    first.setup()  # writes checkpoint 0, which the resumed run below starts from
    with pytest.raises(FolderInUse, match=rf"output_dir {tmp_path} is in use by this process \(pid {os.getpid()} "):
        MAMLTrainer(config("maml", tmp_path, "resume=true"))
    first.close()
    MAMLTrainer(config("maml", tmp_path, "resume=true")).close()


def test_the_command_line_refuses_a_folder_in_use_before_hydra_writes(tmp_path):
    (tmp_path / "hydra" / ".hydra").mkdir(parents=True)
    (tmp_path / "hydra" / ".hydra" / "config.yaml").write_text("the running run's config\n")
    before = listing(tmp_path)
    with FolderLock(tmp_path):
        proc = subprocess.run([sys.executable, str(REPO / "recipes" / "maml.py"), f"output_dir={tmp_path}",
                               "logger.backend=none"], check=False, capture_output=True, text=True, timeout=120,
                              cwd=tmp_path, env=repo_env(HYDRA_FULL_ERROR="0"))
    assert proc.returncode == 1, proc.stderr
    assert f"output_dir {tmp_path} is in use by pid {os.getpid()} on " in proc.stderr
    assert "Traceback" not in proc.stderr
    assert listing(tmp_path) == before


def hydra_config(tmp_path, **values):
    return OmegaConf.create({**values, "hydra": {"run": {"dir": "${output_dir}/hydra"}}})


def test_the_callback_refuses_a_fresh_run_into_a_finished_runs_folder(tmp_path):
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "step_2.pt").write_bytes(b"")
    with pytest.raises(SystemExit, match="holds checkpoints of an earlier run"):
        OutputDirCheck().on_run_start(config=hydra_config(tmp_path, output_dir=str(tmp_path), resume=False))
    callback = OutputDirCheck()
    callback.on_run_start(config=hydra_config(tmp_path, output_dir=str(tmp_path), resume=True))
    callback.on_run_end(config=None)
    assert not (tmp_path / "hydra").exists()


def test_the_trainer_takes_over_the_lock_the_callback_took(tmp_path):
    callback = OutputDirCheck()
    callback.on_run_start(config=hydra_config(tmp_path, output_dir=str(tmp_path), resume=False))
    trainer = MAMLTrainer(config("maml", tmp_path))  # the run the command line starts: not refused
    assert trainer.folder_lock is callback.lock
    with pytest.raises(FolderInUse):
        FolderLock(tmp_path).acquire()
    trainer.close()
    callback.on_run_end(config=None)
    FolderLock(tmp_path).acquire().release()


@pytest.mark.parametrize(("key", "value", "message"), [
    ("profile_name", "../../../x", r"profile_name: got '\.\./\.\./\.\./x'; expected a name without path separators"),
    ("profile_name", "p" * 300, r"profile_name: got 'p{20,}.*; expected a name .* of at most 255 bytes"),
    ("logger.exp_name", "e" * 256, r"logger.exp_name: got 'e{20,}.*; expected a name .* of at most 255 bytes"),
])
def test_names_are_refused_before_hydra_writes(tmp_path, key, value, message):
    values = {"output_dir": str(tmp_path / "outputs" / "suite" / value.replace("/", "_"))}
    cfg = hydra_config(tmp_path, **values)
    OmegaConf.update(cfg, key, value)
    with pytest.raises(SystemExit, match=message):
        OutputDirCheck().on_run_start(config=cfg, config_name="suite")
    assert list(tmp_path.iterdir()) == []


def test_a_folder_name_over_255_bytes_is_refused_before_any_work(tmp_path):
    long = tmp_path / ("d" * 300) / "run"
    with pytest.raises(ConfigError, match=r"output_dir: got .* \(300 bytes in d{40}\.\.\.\); expected a path whose "
                                          "every folder name has at most 255 bytes"):
        MAMLTrainer(config("maml", long))
    with pytest.raises(SystemExit, match="output_dir: got .*expected a path whose every folder name"):
        OutputDirCheck().on_run_start(config=hydra_config(tmp_path, output_dir=str(long)))
    assert list(tmp_path.iterdir()) == []


KILLED_SAVE = """
import sys, torch
from umrl.checkpoints.folder import Checkpointer
Checkpointer(sys.argv[1]).save({"weights": torch.zeros(%d)}, 1)
"""


def killed_save(directory, numel=20_000_000, attempts=5):
    """Kill -9 a process while it saves a checkpoint of ``numel`` floats into ``directory``; the names it left."""
    for _ in range(attempts):
        proc = subprocess.Popen([sys.executable, "-c", KILLED_SAVE % numel, str(directory)])
        while proc.poll() is None and not (directory.is_dir() and any(directory.iterdir())):
            time.sleep(0.001)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        left = sorted(p.name for p in directory.iterdir())
        if proc.returncode == -signal.SIGKILL and not any(name.startswith("step_") for name in left):
            return left
        for path in directory.iterdir():
            path.unlink()
        numel *= 2  # the save finished first: a bigger one
    pytest.fail("no save could be killed half-way")


def test_a_killed_saves_temporary_files_are_removed_on_the_next_start(tmp_path):
    checkpoints = tmp_path / "checkpoints"
    left = killed_save(checkpoints)
    assert len(left) == 1 and left[0].startswith(".tmp")  # safetensors' hidden file, before it became step_1.pt.tmp
    for name in ("step_3.pt.tmp", "config.yaml.tmp"):  # a save killed after safetensors' rename
        (checkpoints / name).write_bytes(b"partial")
    for name in ("notes.tmp", ".tmp-mine.txt"):  # not umrl's: stays
        (checkpoints / name).write_text("someone else's")
    trainer = VIMETrainer(config("vime", tmp_path))  # a fresh run: no checkpoint there, so it may start
    assert sorted(p.name for p in checkpoints.iterdir()) == [".tmp-mine.txt", "notes.tmp"]
    trainer.close()
