"""A rerun with the default output_dir gets a folder of its own (umrl.run_folders): ``seed0``, then ``seed0-2``, ...;
two runs started at once never pick the same folder; resume=true continues the latest run and names it; an
output_dir the command line names keeps the refusal; MAML's default diayn_checkpoint follows the latest DIAYN run."""
import os
import subprocess
import sys

import pytest
from omegaconf import OmegaConf
from racing import FORK, run_racers
from script_loading import repo_env

from umrl.configs.callbacks import OutputDirCheck
from umrl.folder_lock import FolderLock
from umrl.run_folders import claim_default_run_folder, latest_run, named_keys, place_default_run

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def earlier_run(folder, step=5, where="checkpoints"):
    (folder / where).mkdir(parents=True, exist_ok=True)
    (folder / where / f"step_{step}.safetensors").write_bytes(b"an earlier run's checkpoint")
    return folder


def test_a_fresh_run_takes_the_first_free_folder_after_the_latest_run(tmp_path):
    base = tmp_path / "seed0"
    lock, note = claim_default_run_folder(base, resume=False)
    assert lock.folder == base and note is None
    lock.release()
    earlier_run(base, where="seed0/checkpoints")  # a DIAYN program's seed checkpoints hold a run too
    lock, note = claim_default_run_folder(base, resume=False)
    assert lock.folder == tmp_path / "seed0-2"
    assert note == f"output_dir {base} holds an earlier run: this run writes to {tmp_path / 'seed0-2'} " \
                   "(output_dir=<folder> chooses the folder)"
    with FolderLock(tmp_path / "seed0-3"):  # another process's run, before its first checkpoint: skipped
        second, _ = claim_default_run_folder(base, resume=False)
    assert second.folder == tmp_path / "seed0-4"
    lock.release()
    second.release()
    earlier_run(tmp_path / "seed0-10")
    (tmp_path / "seed0-x").mkdir()  # not of the family
    earlier_run(tmp_path / "seed01")
    assert latest_run(base) == tmp_path / "seed0-10"
    lock, _ = claim_default_run_folder(base, resume=False)
    assert lock.folder == tmp_path / "seed0-11"  # after the latest run, never between earlier ones
    lock.release()


def test_resume_continues_the_latest_run_and_names_its_folder_and_step(tmp_path):
    base = tmp_path / "seed0"
    lock, note = claim_default_run_folder(base, resume=True)  # nothing to continue: the folder itself, silently
    assert (lock.folder, note) == (base, None)
    lock.release()
    earlier_run(base, step=40)
    earlier_run(tmp_path / "seed0-2", step=7)
    earlier_run(tmp_path / "seed0-2", step=12)
    lock, note = claim_default_run_folder(base, resume=True)
    assert lock.folder == tmp_path / "seed0-2"
    assert note == f"resume=true: continuing the run in {tmp_path / 'seed0-2'} from step 12"
    lock.release()


TRIALS = 10


def _race(bases, start, picked, racer):
    """One racer: for each family, wait for the other racer, claim a folder, hold it until both have picked."""
    for trial, base in enumerate(bases):
        start.wait()
        lock, _ = claim_default_run_folder(base, resume=False)
        picked[2 * trial + racer] = int(lock.folder.name.rpartition("-")[2])
        start.wait()
        lock.release()


def test_two_runs_started_at_once_pick_different_folders(tmp_path):
    bases = [earlier_run(tmp_path / f"trial{i}" / "seed0") for i in range(TRIALS)]
    start, picked = FORK.Barrier(2), FORK.Array("i", 2 * TRIALS)
    run_racers(_race, [(bases, start, picked, i) for i in range(2)])
    assert [sorted(picked[2 * t:2 * t + 2]) for t in range(TRIALS)] == [[2, 3]] * TRIALS


def recipe_config(output_dir, overrides, **values):
    return OmegaConf.create({"output_dir": str(output_dir), "resume": False, **values,
                             "hydra": {"run": {"dir": "${output_dir}/hydra"}, "overrides": {"task": overrides}}})


def test_the_callback_moves_a_default_rerun_and_refuses_a_named_folder(tmp_path, capsys):
    base = earlier_run(tmp_path / "seed0")
    cfg = recipe_config(base, ["+profile=maml_tiny"])  # a profile's output_dir is a default too
    callback = OutputDirCheck()
    callback.on_run_start(config=cfg)
    assert cfg.output_dir == str(tmp_path / "seed0-2") and cfg.hydra.run.dir == str(tmp_path / "seed0-2" / "hydra")
    assert capsys.readouterr().out == f"output_dir {base} holds an earlier run: this run writes to " \
                                      f"{tmp_path / 'seed0-2'} (output_dir=<folder> chooses the folder)\n"
    callback.on_run_end(config=cfg)
    with pytest.raises(SystemExit, match="holds checkpoints of an earlier run"):
        OutputDirCheck().on_run_start(config=recipe_config(base, [f"output_dir={base}"]))


def test_the_default_diayn_checkpoint_follows_the_latest_diayn_run(tmp_path):
    diayn = earlier_run(tmp_path / "diayn" / "seed0")
    cfg = OmegaConf.create({"proposal": "diayn", "diayn_checkpoint": str(diayn), "resume": False,
                            "output_dir": str(tmp_path / "maml")})
    lock, notes = place_default_run(cfg, set())
    assert cfg.diayn_checkpoint == str(diayn) and notes == []  # one run: its folder, silently
    lock.release()
    earlier_run(tmp_path / "diayn" / "seed0-2")
    lock, notes = place_default_run(cfg, set())
    assert cfg.diayn_checkpoint == str(tmp_path / "diayn" / "seed0-2")
    assert notes == [f"diayn_checkpoint: the latest DIAYN run of its default folder, {tmp_path / 'diayn' / 'seed0-2'}"]
    lock.release()
    cfg.diayn_checkpoint = str(diayn)
    assert place_default_run(cfg, {"diayn_checkpoint", "output_dir"}) == (None, [])  # named: used as given
    assert cfg.diayn_checkpoint == str(diayn)


def test_named_keys_are_the_keys_an_override_sets():
    assert named_keys(["output_dir=a", "+seed=1", "++resume=true", "~logger.group", "+profile=maml_tiny"]) == \
        {"output_dir", "seed", "resume", "profile"}


TINY_MAML = ["+profile=maml_tiny", "proposal=random", "iterations=1", "meta_batch_size=2", "trajectories_per_task=2",
             "env.horizon=5", "logger.backend=none", "progress=false"]


def umrl_command(cwd, *args):
    env = repo_env(HYDRA_FULL_ERROR="0")
    out = subprocess.run([sys.executable, "-m", "umrl", *args], capture_output=True, text=True, timeout=600,
                         check=False, cwd=cwd, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def test_a_rerun_and_a_rerun_sweep_keep_every_earlier_run(tmp_path):
    """On the command line: a single rerun (Hydra's files too) and each job of a rerun ``-m`` sweep land in new
    folders; the earlier runs' files are untouched."""
    family = tmp_path / "outputs" / "tiny" / "maml" / "point_nav" / "random"
    earlier = earlier_run(family / "seed0")
    (earlier / "hydra").mkdir()
    (earlier / "hydra" / "maml.log").write_text("the earlier run's log\n")
    out = umrl_command(tmp_path, "maml", *TINY_MAML)
    assert out.stdout.splitlines()[0] == ("output_dir outputs/tiny/maml/point_nav/random/seed0 holds an earlier run: "
                                          "this run writes to outputs/tiny/maml/point_nav/random/seed0-2 "
                                          "(output_dir=<folder> chooses the folder)")
    assert (family / "seed0-2" / "checkpoints" / "step_1.safetensors").is_file()
    assert (family / "seed0-2" / "hydra" / ".hydra" / "config.yaml").is_file()
    assert (earlier / "hydra" / "maml.log").read_text() == "the earlier run's log\n"
    assert sorted(p.name for p in (earlier / "checkpoints").iterdir()) == ["step_5.safetensors"]
    umrl_command(tmp_path, "maml", "-m", *TINY_MAML, "seed=0,1", f"hydra.sweep.dir={tmp_path / 'multirun'}")
    assert sorted(p.name for p in family.iterdir()) == ["seed0", "seed0-2", "seed0-3", "seed1"]
    assert (family / "seed0-3" / "checkpoints" / "step_1.safetensors").is_file()
    assert (family / "seed1" / "checkpoints" / "step_1.safetensors").is_file()


def test_resume_into_a_named_folder_names_the_step_it_continues_from(tmp_path, capsys):
    folder = earlier_run(tmp_path / "run", step=30)
    callback = OutputDirCheck()
    callback.on_run_start(config=recipe_config(folder, [f"output_dir={folder}", "resume=true"], resume=True))
    callback.on_run_end(config=None)
    assert capsys.readouterr().out == f"resume=true: continuing the run in {folder} from step 30\n"


def test_the_python_path_keeps_an_earlier_run_as_the_command_line_does(tmp_path, monkeypatch, capsys):
    import umrl.trainers

    monkeypatch.chdir(tmp_path)  # the default output_dir is relative to the working folder
    overrides = ["+profile=maml_tiny", "iterations=1", "logger.backend=none", "progress=false"]
    first = umrl.trainers.train("maml", overrides)
    second = umrl.trainers.train("maml", overrides)
    first_dir, second_dir = (os.path.dirname(os.path.dirname(r["checkpoint"])) for r in (first, second))
    assert second_dir == first_dir + "-2" and os.path.isfile(first["checkpoint"])  # the first run is kept
    assert f"this run writes to {second_dir}" in capsys.readouterr().out
    resumed = umrl.trainers.train("maml", [*overrides, "iterations=2", "resume=true"])
    assert os.path.dirname(os.path.dirname(resumed["checkpoint"])) == second_dir  # the latest run continues
