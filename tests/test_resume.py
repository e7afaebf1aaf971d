"""Kill-and-resume: a run stopped at a checkpoint, by a signal between checkpoints, or killed with SIGKILL
mid-iteration, and resumed finishes with parameters bit-identical to an uninterrupted run (every recipe, point_nav and
half_cheetah; at a checkpoint every tensor of the final checkpoint: networks, optimisers, replay buffers with their
trajectory ids, RNGs, env states, DIAYN's episodes in progress; after a signal also every logged training metric);
resumes that would continue a different run are refused; an unreadable latest checkpoint falls back to the previous
one; a DIAYN checkpoint written before episodes were kept resumes with restarted episodes."""
import importlib
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from script_loading import REPO, sigkill_after
from tensordict import TensorDictBase

from umrl.checkpoints.file import read_checkpoint, write_checkpoint
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import ConfigError
from umrl.trainers import compose
from umrl.trainers.diayn import train as train_diayn

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

TINY = {
    "diayn": ["num_skills=3", "env.num_envs=4", "env.horizon=10", "collector.frames_per_batch=40",
              "collector.init_random_frames=40", "optim.updates_per_frame=0.25", "network.hidden=[16,16]",
              "network.discriminator_hidden=[16]", "replay_buffer.size=200", "replay_buffer.batch_size=16",
              "eval.every=80", "eval.episodes_per_skill=1", "checkpoint.every=40"],
    "maml": ["proposal=oracle", "meta_batch_size=2", "trajectories_per_task=3", "env.horizon=10",
             "policy.hidden=[16]", "checkpoint.every=1", "trpo.cg_iters=3"],
    "vime": ["env.num_envs=4", "env.horizon=10", "policy.hidden=[16]", "dynamics.hidden=[8]",
             "dynamics.batch_size=8", "dynamics.updates_per_iteration=2", "dynamics.replay_size=30",
             "dynamics.holdout_size=10", "bonus.num_samples=2", "dynamics.num_samples=2", "checkpoint.every=1"],
}
"""Tiny settings; the replay buffers are small enough to wrap (the FIFO layout must survive the resume)."""
BUDGET = {"diayn": ("collector.total_frames", 80, 160), "maml": ("iterations", 1, 2), "vime": ("iterations", 1, 2)}
"""(budget key, where the first run stops, where both runs end)."""
PARAMS = {"diayn": "loss", "maml": "policy", "vime": "policy"}
"""The checkpoint entry holding every trained parameter (DIAYN's loss: actor, Q-networks and targets, D, alpha)."""


def config(recipe, output_dir, env_name, *overrides):
    return compose(recipe, ["logger.backend=none", "progress=false", f"output_dir={output_dir}",
                            f"env.name={env_name}", *TINY[recipe], *overrides])


def max_param_diff(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max((a[k].double() - b[k].double()).abs().max().item() for k in a)


def leaves(value, path: str = ""):
    """``(path, leaf)`` for every tensor, array and plain value of a checkpoint (TensorDicts entry by entry)."""
    if isinstance(value, TensorDictBase):
        for key, leaf in value.items(include_nested=True, leaves_only=True):
            yield f"{path}/{key}", leaf
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from leaves(item, f"{path}/{key}")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from leaves(item, f"{path}[{i}]")
    else:
        yield path, value


def leaf_diff(a, b) -> float:
    """max |a - b| over a tensor's or array's entries (NaN where both are NaN counts as equal; a changed shape or
    dtype is inf), 0 or inf for other leaves."""
    if isinstance(a, (torch.Tensor, np.ndarray)):
        a, b = torch.as_tensor(a), torch.as_tensor(b)
        if a.shape != b.shape or a.dtype != b.dtype:
            return float("inf")
        a, b = a.double(), b.double()
        differ = (a != b) & ~(a.isnan() & b.isnan())
        return (a - b).abs()[differ].nan_to_num(float("inf")).max().item() if differ.any() else 0.0
    return 0.0 if a == b else float("inf")


def checkpoint_diffs(a: dict, b: dict) -> dict[str, float]:
    """``path -> max |a - b|`` for every leaf of two checkpoints but their configs (whose output_dir differ)."""
    a, b = dict(leaves({**a, "config": None})), dict(leaves({**b, "config": None}))
    assert a.keys() == b.keys(), sorted(set(a) ^ set(b))
    return {path: leaf_diff(a[path], b[path]) for path in a}


@pytest.mark.parametrize("env_name", ["point_nav", "half_cheetah"])
@pytest.mark.parametrize("recipe", ["diayn", "maml", "vime"])
def test_resume_at_a_checkpoint_is_bit_identical(tmp_path, recipe, env_name):
    train = importlib.import_module(f"umrl.trainers.{recipe}").train
    key, stop, end = BUDGET[recipe]
    whole = train(config(recipe, tmp_path / "whole", env_name, f"{key}={end}"))
    train(config(recipe, tmp_path / "split", env_name, f"{key}={stop}"))
    resumed = train(config(recipe, tmp_path / "split", env_name, f"{key}={end}", "resume=true"))
    diffs = checkpoint_diffs(read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"]))
    assert {path: d for path, d in diffs.items() if d != 0} == {}
    assert any(path.startswith(f"/{PARAMS[recipe]}/") for path in diffs)
    if recipe == "diayn":  # the replay and the seed's own generator continue across the resume
        assert {"/replay/rows/observation", "/rng/generators/seed0"} <= set(diffs)


def test_diayn_resume_keeps_the_random_policy_score(tmp_path):
    """The random policy is scored once, by the initial discriminator: a resumed run reports that score and logs no
    second ``eval/random_*`` row (rescoring with the trained discriminator would change it)."""
    overrides = ("logger.backend=csv", "eval.episodes_per_skill=4")
    whole = train_diayn(config("diayn", tmp_path / "whole", "point_nav", "collector.total_frames=160", *overrides))
    train_diayn(config("diayn", tmp_path / "split", "point_nav", "collector.total_frames=80", *overrides))
    resumed = train_diayn(config("diayn", tmp_path / "split", "point_nav", "collector.total_frames=160",
                                 "resume=true", *overrides))
    random_metrics = {key: value for key, value in whole.items() if key.startswith("eval/random_")}
    assert random_metrics and random_metrics == {key: resumed[key] for key in random_metrics}
    logged = list((tmp_path / "split").rglob("random_final_state_accuracy.csv"))
    assert len(logged) == 1 and len(logged[0].read_text().split()) == 1, logged


def test_sigkill_mid_iteration_then_resume_is_bit_identical(tmp_path):
    """A MAML run killed with SIGKILL while meta-training (after its 2nd checkpoint), resumed in-process."""
    overrides = ["logger.backend=none", "progress=false", "env.name=point_nav", *TINY["maml"], "iterations=6"]
    killed = tmp_path / "killed"
    sigkill_after(["recipes/maml.py", *overrides, f"output_dir={killed}"], killed / "checkpoints" / "step_2.safetensors")
    assert Checkpointer(killed / "checkpoints").latest().name != "step_6.safetensors"

    from umrl.trainers.maml import train

    resumed = train(compose("maml", [*overrides, f"output_dir={killed}", "resume=true"]))
    whole = train(compose("maml", [*overrides, f"output_dir={tmp_path / 'whole'}"]))
    a, b = read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"])
    assert a["iteration"] == b["iteration"] == 6
    assert max_param_diff(a["policy"], b["policy"]) == 0.0


def logged_rows(run_dir) -> dict[str, list[tuple[int, str]]]:
    """``metric -> [(step, value)]`` of a run's CSV logs (``time/`` metrics: steps only, their values are clocks)."""
    rows = {}
    for scalars in (run_dir / "csv").rglob("scalars"):
        for file in sorted(scalars.rglob("*.csv")):
            name = file.relative_to(scalars).with_suffix("").as_posix()
            lines = [line.split(",", 1) for line in file.read_text().splitlines()]
            rows[name] = [(int(step), "" if name.startswith("time/") else value) for step, value in lines]
    return rows


def test_resume_drops_the_rows_logged_past_the_checkpoint(tmp_path):
    """A run killed after logging iterations 3 and 4 but before saving them resumes from its checkpoint 2; its CSV
    logs then hold each iteration once, as the uninterrupted run's (not 3 and 4 twice)."""
    from umrl.trainers.maml import train

    def cfg(folder, iterations, *overrides):
        return config("maml", tmp_path / folder, "point_nav", "logger.backend=csv", f"iterations={iterations}",
                      *overrides)

    train(cfg("split", 4))
    for step in (3, 4):
        (tmp_path / "split" / "checkpoints" / f"step_{step}.safetensors").unlink()
    train(cfg("split", 6, "resume=true"))
    train(cfg("whole", 6))
    logged, expected = logged_rows(tmp_path / "split"), logged_rows(tmp_path / "whole")
    assert [step for step, _ in expected["time/learn_s"]] == list(range(1, 7))
    assert any(name.startswith("train/") for name in expected)
    assert logged == expected


def test_resume_falls_back_past_a_truncated_checkpoint(tmp_path):
    from umrl.trainers.maml import train

    def cfg(*overrides):
        return config("maml", tmp_path, "point_nav", *overrides)

    train(cfg("iterations=2"))
    latest = Checkpointer(tmp_path / "checkpoints").latest()
    latest.write_bytes(latest.read_bytes()[:100])
    with pytest.warns(UserWarning, match=f"skipping unreadable checkpoint {latest}"):
        result = train(cfg("iterations=3", "resume=true"))
    assert result["iteration"] == 3


@pytest.mark.parametrize(("recipe", "change", "message"), [
    ("maml", "seed=5", "seed: checkpoint has 0, this run has 5"),
    ("maml", "trpo.max_kl=0.5", "trpo.max_kl: checkpoint has 0.01, this run has 0.5"),
    ("maml", "env.horizon=12", "env.horizon: checkpoint has 10, this run has 12"),
    ("diayn", "optim.lr=0.5", "optim.lr: checkpoint has 0.0003, this run has 0.5"),
])
def test_resume_with_a_changed_config_is_refused_with_the_keys(tmp_path, recipe, change, message):
    train = importlib.import_module(f"umrl.trainers.{recipe}").train
    key, stop, _ = BUDGET[recipe]
    train(config(recipe, tmp_path, "point_nav", f"{key}={stop}"))
    with pytest.raises(ConfigError, match=message):
        train(config(recipe, tmp_path, "point_nav", f"{key}={stop * 2}", "resume=true", change))


def test_diayn_resume_may_change_the_checkpoint_schedule(tmp_path):
    """``checkpoint.every`` changes nothing but when checkpoints are written (the episodes go on through them): a
    resume with another one writes on the new schedule from the resume on and finishes as the uninterrupted run."""
    whole = train_diayn(config("diayn", tmp_path / "whole", "point_nav", "collector.total_frames=160",
                               "checkpoint.every=80"))
    train_diayn(config("diayn", tmp_path / "split", "point_nav", "collector.total_frames=80", "checkpoint.every=80",
                       "checkpoint.keep_all=true"))
    resumed = train_diayn(config("diayn", tmp_path / "split", "point_nav", "collector.total_frames=160",
                                 "checkpoint.every=40", "checkpoint.keep_all=true", "resume=true"))
    assert [p.name for p in Checkpointer(tmp_path / "split" / "checkpoints").all()] == [
        "step_80.safetensors", "step_120.safetensors", "step_160.safetensors"]
    a, b = read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"])
    assert [path for path, d in checkpoint_diffs(a, b).items() if d != 0] == ["/counters/next_checkpoint"]
    assert (a["counters"]["next_checkpoint"], b["counters"]["next_checkpoint"]) == (240, 200)


def test_diayn_checkpoint_without_episodes_resumes_with_them_restarted(tmp_path):
    """A program checkpoint written before DIAYN kept its episodes in progress (built here by dropping them) still
    resumes: the episodes restart, with a warning, and the run reaches its budget. Episodes that do not fit the
    env are refused, naming the file and what differs."""
    from umrl.trainers.diayn import DIAYNTrainer

    train_diayn(config("diayn", tmp_path, "half_cheetah", "collector.total_frames=80"))
    latest = Checkpointer(tmp_path / "checkpoints").latest()
    state = read_checkpoint(latest)
    del state["episodes"]["carry"]["skill"]
    write_checkpoint(state, latest)
    unfit = (f"cannot resume from {latest}: the saved episodes in progress do not fit this run's env: carry "
             "entries {'skill': None} where it has {'skill': '\\[4, 3\\] float32'}")
    with pytest.raises(ValueError, match=unfit):
        DIAYNTrainer(config("diayn", tmp_path, "half_cheetah", "collector.total_frames=120", "resume=true"))
    del state["episodes"], state["envs"]["train"]["base_env"]["episodes"]
    write_checkpoint(state, latest)
    with pytest.warns(UserWarning, match="holds no episodes in progress .* they restart here"):
        trainer = DIAYNTrainer(config("diayn", tmp_path, "half_cheetah", "collector.total_frames=120",
                                      "resume=true"))
    try:
        assert trainer._carry["step_count"].eq(0).all()
        assert trainer.train()["train/frames"] == 120
    finally:
        trainer.close()


def signal_at_step(trainer, signum: int, step: int) -> None:
    """Make ``trainer`` send ``signum`` to this process as its ``step``-th call of ``step()`` (from 1) begins."""
    original, calls = trainer.step, []

    def step_then_signal():
        calls.append(step)
        if len(calls) == step:
            os.kill(os.getpid(), signum)  # handled before the step runs: the step in progress still completes
        return original()

    trainer.step = step_then_signal


DIAYN_OFF_SCHEDULE = ("collector.total_frames=48", "collector.frames_per_batch=4", "collector.init_random_frames=16",
                      "env.horizon=7", "log_every=16", "checkpoint.every=20")
"""One step of each of 4 copies per batch, 7 steps an episode: the scheduled checkpoint (frame 20) and the stop
(frame 24) both cut episodes, the stop also a logging interval (every 16 frames), and updates run on both sides."""
STOPS = {"diayn": ("collector.total_frames", 48, DIAYN_OFF_SCHEDULE, 6, "step_24.safetensors"),
         "maml": ("iterations", 4, ("checkpoint.every=100",), 2, "step_2.safetensors"),
         "vime": ("iterations", 4, ("checkpoint.every=100",), 2, "step_2.safetensors")}
"""(budget key, budget, settings, the step during which the signal comes, the checkpoint it writes): every stop
falls between scheduled checkpoints."""


def logged_training_metrics(trainer) -> list:
    """``(progress, metrics)`` of every :meth:`~umrl.trainers.base.Trainer.log` call of ``trainer`` from now on,
    without the timings (``time/``)."""
    rows = []
    trainer.register_op("post_log", lambda t, metrics: rows.append(
        (t.progress, {k: v for k, v in metrics.items() if not k.startswith("time/")})))
    return rows


@pytest.mark.parametrize(("recipe", "env_name", "seeds"), [
    ("diayn", "point_nav", ()), ("diayn", "half_cheetah", ("seeds=[0,1]",)), ("maml", "point_nav", ()),
    ("vime", "point_nav", ())], ids=["diayn-point_nav", "diayn-half_cheetah-S2", "maml", "vime"])
def test_sigterm_saves_the_step_in_progress_and_the_resumed_run_is_exact(tmp_path, capsys, recipe, env_name, seeds):
    module = importlib.import_module(f"umrl.trainers.{recipe}")
    trainer_class = getattr(module, f"{recipe.upper()}Trainer")
    key, budget, settings, stop_step, saved = STOPS[recipe]
    overrides = (f"{key}={budget}", *settings, *seeds)
    stopped = tmp_path / "stopped"
    handler = signal.getsignal(signal.SIGTERM)
    trainer = trainer_class(config(recipe, stopped, env_name, *overrides))
    logged = logged_training_metrics(trainer)
    signal_at_step(trainer, signal.SIGTERM, stop_step)
    with pytest.raises(SystemExit) as stop:
        trainer.train()
    trainer.close()
    assert stop.value.code == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is handler  # restored
    latest = Checkpointer(stopped / "checkpoints").latest()
    assert latest.name == saved
    assert capsys.readouterr().err.splitlines()[-1] == str(stop.value)  # the one line, also the exception's text
    assert str(stop.value).startswith("stopped by SIGTERM ") and f"saved {latest};" in str(stop.value)

    def finish(output_dir, *more):
        trainer = trainer_class(config(recipe, output_dir, env_name, *overrides, *more))
        rows = logged_training_metrics(trainer)
        try:
            return trainer.train(), rows
        finally:
            trainer.close()

    resumed, logged_after = finish(stopped, "resume=true")
    whole, logged_whole = finish(tmp_path / "whole")
    diffs = checkpoint_diffs(read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"]))
    assert {path: d for path, d in diffs.items() if d != 0} == {}
    assert any(path.startswith(f"/{PARAMS[recipe]}/") for path in diffs)
    assert logged + logged_after == logged_whole
    if recipe == "diayn":  # the stop cut episodes whose returns are logged after it
        assert {"/episodes/carry/step_count", "/envs/train/base_env/episodes/" + (
            "position" if env_name == "point_nav" else "state")} <= set(diffs)
        assert any(key.endswith("train/episode_return") for _, metrics in logged_after for key in metrics)


def test_sigint_on_the_command_line_saves_and_ends_with_one_line(tmp_path):
    """Ctrl-C during ``recipes/maml.py``: the meta-iteration in progress is finished and saved, the process ends
    with status 130 and one line, no traceback."""
    overrides = ["logger.backend=none", "progress=false", "env.name=point_nav", *TINY["maml"], "iterations=1000",
                 f"output_dir={tmp_path}"]
    proc = subprocess.Popen([sys.executable, "recipes/maml.py", *overrides], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (tmp_path / "checkpoints" / "step_1.safetensors").exists() and proc.poll() is None:
            assert time.monotonic() < deadline, "no first meta-iteration within 120 s"
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)  # train() runs: its handler is installed
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "Traceback" not in err + out
    last = err.strip().splitlines()[-1]
    latest = Checkpointer(tmp_path / "checkpoints").latest()
    iteration = int(latest.stem.split("_")[1])
    assert 1 <= iteration < 1000
    assert last == (f"stopped by SIGINT after meta-iteration {iteration} of 1000; saved {latest}; continue with "
                    "resume=true (same output_dir)")
