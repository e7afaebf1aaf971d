"""The suite's cache keyed by config and code, its marker window, atomic state, validation before work and
printed failures (benchmarks/suite.py, umrl/metatest/cache.py)."""
import os

import pytest
from script_loading import compose_config

import umrl.trainers
from umrl import suite
from umrl.configs import ConfigError, validate
from umrl.configs.suite import SuiteConfig
from umrl.metatest import read_rows
from umrl.metatest.cache import DONE_MARKER, config_key, remove_stale_tmp, source_version, write_json_atomic

TINY = ["num_tasks=2", "protocol.num_steps=1", "protocol.num_trajectories=2", "protocol.horizon=10",
        "report.steps=[0]", "logger.backend=none", "ablation.enabled=false", "launcher.threads=1",
        "launcher.workers=0", "seeds=[0]", "pretrain_seeds=0"]
TINY_DIAYN = {"env.num_envs": 4, "env.horizon": 10, "collector.frames_per_batch": 40, "collector.total_frames": 120,
              "collector.init_random_frames": 40, "optim.updates_per_frame": 0.25, "network.hidden": "[16]",
              "network.discriminator_hidden": "[16]", "replay_buffer.batch_size": 16, "eval.every": 80,
              "eval.episodes_per_skill": 2, "checkpoint.every": 80, "num_skills": 3}


def _cfg(tmp_path, *overrides):
    return compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", *TINY, *overrides])


def _quiet(_):
    return None


def test_keys_follow_config_and_code(tmp_path):
    assert config_key({"a": 1, "b": [1, 2]}, "c0") == config_key({"b": [1, 2], "a": 1}, "c0")
    assert config_key({"a": 1}, "c0") != config_key({"a": 2}, "c0")
    assert config_key({"a": 1}, "c0") != config_key({"a": 1}, "c1")
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "m.py").write_text("x = 1\n")
    before = source_version([tmp_path / "pkg"])
    assert source_version([tmp_path / "pkg"]) == before
    (tmp_path / "pkg" / "m.py").write_text("x = 2\n")
    assert source_version([tmp_path / "pkg"]) != before
    edited = source_version([tmp_path / "pkg"], exclude=["pkg/plots.py"])
    (tmp_path / "pkg" / "plots.py").write_text("colour = 'red'\n")  # drawing code: recomputes nothing
    assert source_version([tmp_path / "pkg"], exclude=["pkg/plots.py"]) == edited
    assert source_version([tmp_path / "pkg"], exclude=[]) != edited


def test_changed_k_recomputes_and_the_table_never_mixes(tmp_path):
    suite.run_suite(_cfg(tmp_path, "methods=[scratch]"), log=_quiet)
    first = list((tmp_path / "cells").rglob("*.csv"))
    assert len(first) == 1 and {r["step"] for r in read_rows([tmp_path / "results.csv"])} == {0, 1}
    stamp = first[0].stat().st_mtime_ns

    suite.run_suite(_cfg(tmp_path, "methods=[scratch]", "protocol.num_steps=2"), log=_quiet)
    cells = list((tmp_path / "cells").rglob("*.csv"))
    assert len(cells) == 2  # K=2 got its own cell; the K=1 cell stays, untouched
    assert first[0].stat().st_mtime_ns == stamp
    rows = read_rows([tmp_path / "results.csv"])
    assert {r["step"] for r in rows} == {0, 1, 2} and len(rows) == 2 * 3  # 2 tasks x k=0..2, no K=1 rows
    assert "num_steps: 2" in (tmp_path / "summary.md").read_text()
    assert "num_steps: 2" in (tmp_path / "config.yaml").read_text()

    log = []
    suite.run_suite(_cfg(tmp_path, "methods=[scratch]"), log=log.append)  # back to K=1: found again
    assert any(line.startswith("[skip] cell/point_nav/scratch/seed0") for line in log)
    assert first[0].stat().st_mtime_ns == stamp and {r["step"] for r in read_rows([tmp_path / "results.csv"])} == {0, 1}


def test_changed_recipe_override_gets_a_new_pretraining_run(tmp_path):
    base = _cfg(tmp_path, "methods=[uml_random]")
    runs = suite.plan_pretraining(validate(base, SuiteConfig), "g", "code")
    other = _cfg(tmp_path, "methods=[uml_random]", "++pretrain.maml.overrides.iterations=3")
    changed = suite.plan_pretraining(validate(other, SuiteConfig), "g", "code")
    logging_only = _cfg(tmp_path, "methods=[uml_random]", "logger.backend=csv")
    same = suite.plan_pretraining(validate(logging_only, SuiteConfig), "g", "code")
    key = ("maml_random", "point_nav", 0)
    assert runs[key].run_dir != changed[key].run_dir and runs[key].run_dir == same[key].run_dir
    assert suite.plan_pretraining(validate(base, SuiteConfig), "g", "code2")[key].run_dir != runs[key].run_dir


def test_run_killed_after_its_last_checkpoint_counts_as_finished(tmp_path):
    """The marker window: the DIAYN run wrote its checkpoint at the final step, then died (e.g. in its final
    evaluation) before the suite wrote the completion marker; the restarted suite must finish, not fail."""
    overrides = [f"++pretrain.diayn.overrides.{k}={v}" for k, v in TINY_DIAYN.items()]
    cfg = _cfg(tmp_path, "methods=[diayn_init]", "skill_trajectories=1", *overrides)
    run = suite.plan_pretraining(validate(cfg, SuiteConfig), "g", suite.code_version())["diayn", "point_nav", 0]
    umrl.trainers.train("diayn", run.overrides)  # the run's own work, done outside the suite: no marker
    checkpoint = run.run_dir / "checkpoints" / "step_120.safetensors"
    assert checkpoint.is_file() and not (run.run_dir / DONE_MARKER).exists()
    stamp = checkpoint.stat().st_mtime_ns

    log = []
    suite.run_suite(cfg, log=log.append)
    assert "[skip] pretrain/diayn/point_nav/seed0: already done" in log
    assert checkpoint.stat().st_mtime_ns == stamp and (run.run_dir / DONE_MARKER).exists()
    assert {r["method"] for r in read_rows([tmp_path / "results.csv"])} == {"diayn_init"}


def test_state_files_are_atomic_and_stale_tmp_removed(tmp_path, monkeypatch):
    state = write_json_atomic(tmp_path / "state.json", {"group": "a"})

    def killed(*args):
        raise KeyboardInterrupt("killed between writing the .tmp and replacing")

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        write_json_atomic(state, {"group": "b"})
    monkeypatch.undo()
    assert state.read_text() == '{\n "group": "a"\n}'  # the old content, whole
    stale = [tmp_path / "state.json.tmp", tmp_path / "cells" / "point_nav" / "x.csv.tmp",
             tmp_path / "pretrain" / "diayn" / "checkpoints" / "step_5.pt.tmp"]
    kept = tmp_path / "wandb" / "run.tmp"
    for path in [*stale[1:], kept]:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("partial")
    assert sorted(remove_stale_tmp(tmp_path)) == sorted(stale)
    assert not any(p.exists() for p in stale) and kept.exists()


def test_suite_writes_state_atomically(tmp_path):
    (tmp_path / "cells").mkdir(parents=True)
    (tmp_path / "cells" / "left.csv.tmp").write_text("partial")
    log = []
    suite.run_suite(_cfg(tmp_path, "methods=[scratch]"), log=log.append)
    assert any(line.startswith("[clean] removed") for line in log)
    assert not list(tmp_path.rglob("*.tmp"))
    for name in ("suite_state.json", "timings.json", "config.yaml", "summary.md", "results.csv"):
        assert (tmp_path / name).is_file()


def test_every_bad_input_is_listed_before_any_work(tmp_path):
    out = tmp_path / "out"
    cfg = _cfg(out, "seeds=[]", "launcher.workers=-1", "device=gpu", f"pretrain.maml.reuse='{tmp_path}/nothing/{{env}}'")
    with pytest.raises(ConfigError) as info:
        suite.run_suite(cfg, log=_quiet)
    message = str(info.value)
    for expected in ("seeds: got []", "launcher.workers: got -1", "device: got 'gpu'"):
        assert expected in message
    assert not out.exists()  # nothing started

    missing = _cfg(out, "methods=[uml_random]", f"pretrain.maml.reuse='{tmp_path}/nothing/{{env}}'")
    with pytest.raises(ConfigError, match=r"pretrain.maml.reuse: .*has no checkpoint"):
        suite.run_suite(missing, log=_quiet)
    # a key the recipe does not have fails when its config is composed, before any job
    bad = _cfg(out, "methods=[uml_random]", "++pretrain.maml.overrides.trpo.max_kll=0.1")
    with pytest.raises(ConfigError, match=r"max_kll"):
        suite.run_suite(bad, log=_quiet)
    assert not (out / "pretrain").exists() and not (out / "cells").exists()
