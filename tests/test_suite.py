"""Benchmark suite: planning, skipping finished cells, resuming a killed run, the Ray launcher (cache keys,
validation and failures: test_suite_cache.py)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from script_loading import compose_config

import umrl.trainers
from umrl import suite
from umrl.checkpoints import MAML_FORMAT
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import ConfigError, validate
from umrl.configs.suite import SuiteConfig, pretrain_seeds
from umrl.launch import RayLauncher, run_jobs
from umrl.metatest import read_rows, write_rows
from umrl.metatest.results import text_sha256

REPO = Path(__file__).resolve().parents[1]

TINY = ["num_tasks=2", "protocol.num_steps=1", "protocol.num_trajectories=2", "protocol.horizon=10", "report.steps=[0]",
        "logger.backend=none", "ablation.enabled=false", "launcher.threads=1"]


def _cfg(tmp_path, *overrides):
    cfg = compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", *TINY, *overrides])
    return validate(cfg, SuiteConfig)


def test_plan_dependencies_and_shared_pretraining(tmp_path):
    cfg = _cfg(tmp_path, "seeds=[0,1]", "pretrain_seeds=0", "methods=[uml_diayn,diayn_init,scratch]")
    jobs = {job.key: job for job in suite.plan(cfg, group="g", code="code")}
    # one DIAYN and one MAML(diayn) run shared by both seeds; MAML(diayn) waits for DIAYN
    assert sorted(k for k in jobs if k.startswith("pretrain")) == [
        "pretrain/diayn/point_nav/seed0", "pretrain/maml_diayn/point_nav/seed0"]
    assert jobs["pretrain/maml_diayn/point_nav/seed0"].deps == ("pretrain/diayn/point_nav/seed0",)
    assert jobs["cell/point_nav/uml_diayn/seed1"].deps == ("pretrain/maml_diayn/point_nav/seed0",)
    assert jobs["cell/point_nav/diayn_init/seed1"].deps == ("pretrain/diayn/point_nav/seed0",)
    assert jobs["cell/point_nav/scratch/seed0"].deps == ()
    # the trainer's own train through the package API, with composed overrides (no command line)
    job = jobs["pretrain/maml_diayn/point_nav/seed0"]
    assert job.fn.__module__ == "umrl.trainers" and job.args[0] == "maml"
    runs = suite.plan_pretraining(cfg, "g", "code")
    diayn_dir = runs["diayn", "point_nav", 0].run_dir
    assert {"proposal=diayn", "checkpoint.keep_all=true", "resume=false", "device=cpu",
            f"diayn_checkpoint={diayn_dir}"} <= set(job.args[1])
    # a checkpoint in the run dir makes the recipe resume instead of starting over
    assert diayn_dir.name == "seed0"  # the seed's folder in the DIAYN job's, whose checkpoints a resume reads
    (diayn_dir.parent / "checkpoints").mkdir(parents=True)
    (diayn_dir.parent / "checkpoints" / "step_10.pt").write_bytes(b"")
    assert "resume=true" in suite.plan_pretraining(cfg, "g", "code")["diayn", "point_nav", 0].overrides


def test_an_envs_diayn_seeds_pretrain_in_one_job(tmp_path):
    """Two pre-training seeds: one DIAYN job trains both (seeds=[0,1]), each seed's MAML(diayn) and DIAYN-init cells
    wait for it and read that seed's folder in it; the job is done when both seeds are."""
    cfg = _cfg(tmp_path, "seeds=[0,1]", "pretrain_seeds=[0,1]", "methods=[uml_diayn,diayn_init]")
    jobs = {job.key: job for job in suite.plan(cfg, group="g", code="code")}
    assert sorted(k for k in jobs if k.startswith("pretrain/diayn")) == ["pretrain/diayn/point_nav/seeds0-1"]
    job = jobs["pretrain/diayn/point_nav/seeds0-1"]
    assert "seeds=[0,1]" in job.args[1] and not job.done()
    runs = suite.plan_pretraining(cfg, "g", "code")
    first, second = runs["diayn", "point_nav", 0].run_dir, runs["diayn", "point_nav", 1].run_dir
    assert (first.name, second.name) == ("seed0", "seed1") and first.parent == second.parent
    for seed, run_dir in ((0, first), (1, second)):
        assert jobs[f"pretrain/maml_diayn/point_nav/seed{seed}"].deps == ("pretrain/diayn/point_nav/seeds0-1",)
        assert f"diayn_checkpoint={run_dir}" in jobs[f"pretrain/maml_diayn/point_nav/seed{seed}"].args[1]
        assert jobs[f"cell/point_nav/diayn_init/seed{seed}"].deps == ("pretrain/diayn/point_nav/seeds0-1",)


def test_a_maml_override_the_inner_step_cannot_take_fails_before_any_run(tmp_path):
    cfg = _cfg(tmp_path, "seeds=[0]", "methods=[uml_random]", "++pretrain.maml.overrides.trpo.hvp=analytic",
               "+pretrain.maml.overrides.maml.task_loop=true")
    with pytest.raises(ConfigError, match=r"pretrain.maml \(maml_random, point_nav, seed 0\): maml.task_loop: got True; "
                                          "expected null with trpo.hvp=analytic"):
        suite.plan_pretraining(cfg, "g", "code")


def test_every_pretraining_run_gets_the_launchers_thread_count(tmp_path):
    cfg = _cfg(tmp_path, "seeds=[0]", "methods=[uml_diayn,vime_init]", "launcher.threads=3")
    runs = suite.plan_pretraining(cfg, "g", "code")
    assert {kind for kind, _, _ in runs} == {"diayn", "maml_diayn", "vime"}
    for run in runs.values():
        assert umrl.trainers.compose(run.run.recipe, list(run.overrides)).num_threads == 3


def test_independent_pretraining_per_seed_and_both_sgd_schedules(tmp_path):
    cfg = _cfg(tmp_path, "seeds=[0,1]", "pretrain_seeds=null", "methods=[uml_random,scratch]",
               "protocol.sgd_schedule=[reference,constant]")
    jobs = {job.key: job for job in suite.plan(cfg, group="g")}
    # pretrain_seeds null: each meta-test seed has its own pre-training run
    assert sorted(k for k in jobs if k.startswith("pretrain")) == [
        "pretrain/maml_random/point_nav/seed0", "pretrain/maml_random/point_nav/seed1"]
    assert jobs["cell/point_nav/uml_random/seed1"].deps == ("pretrain/maml_random/point_nav/seed1",)
    # the SGD method gets one cell per schedule, Adam's scratch one
    assert sorted(k for k in jobs if k.startswith("cell/")) == [
        "cell/point_nav/scratch/seed0", "cell/point_nav/scratch/seed1",
        "cell/point_nav/uml_random/seed0", "cell/point_nav/uml_random/seed0/constant",
        "cell/point_nav/uml_random/seed1", "cell/point_nav/uml_random/seed1/constant"]
    ref = jobs["cell/point_nav/uml_random/seed1"].args[0]
    assert ref.protocol.sgd_schedule == "reference" and Path(ref.output).name.startswith("seed1-")
    constant = jobs["cell/point_nav/uml_random/seed1/constant"].args[0]
    assert constant.protocol.sgd_schedule == "constant" and Path(constant.output).name.startswith("seed1.constant-")
    assert "/maml_random/point_nav/seed1-" in ref.checkpoint
    explicit = _cfg(tmp_path, "seeds=[0,1]", "pretrain_seeds=[7,8]", "methods=[uml_random]")
    assert "pretrain/maml_random/point_nav/seed8" in {j.key for j in suite.plan(explicit, group="g")}
    with pytest.raises(ConfigError, match=r"pretrain_seeds: got \[7\].*a list of 2 integers"):
        _cfg(tmp_path, "seeds=[0,1]", "pretrain_seeds=[7]", "methods=[uml_random]")
    with pytest.raises(ConfigError, match=r"protocol.sgd_schedule: got 'halving'.*constant"):
        _cfg(tmp_path, "methods=[uml_random]", "protocol.sgd_schedule=halving")


def test_reference_profile_runs_k100_both_schedules_independent_pretraining():
    cfg = validate(compose_config("umrl/suite/config", "suite", ["profile=reference"]), SuiteConfig)
    assert cfg.protocol.num_steps == 100 and list(cfg.protocol.sgd_schedule) == ["reference", "constant"]
    assert cfg.pretrain_seeds is None
    assert pretrain_seeds(cfg) == list(cfg.seeds)
    quick = compose_config("umrl/suite/config", "suite", ["profile=quick"])
    assert pretrain_seeds(quick) == [0, 0, 0] and quick.protocol.sgd_schedule == "reference"


def test_removed_profile_name_lists_the_profiles():
    with pytest.raises(Exception, match=r"(?s)profile/paper.*quick.*reference"):
        compose_config("umrl/suite/config", "suite", ["profile=paper"])


def test_existing_cell_is_skipped(tmp_path):
    cfg = _cfg(tmp_path, "methods=[scratch]", "seeds=[0,1]", "launcher.workers=0")
    planted = [{"method": "scratch", "env": "point_nav", "seed": 0, "task": t, "step": k, "return": 123.0,
                "lr_schedule": "constant"}
               for k in range(2) for t in range(2)]
    jobs = suite.plan(cfg, group="g", code=suite.code_version())
    cell = next(j for j in jobs if j.key == "cell/point_nav/scratch/seed0").args[0]
    existing = write_rows(planted, cell.output)
    with existing.open(newline="") as f:  # a finished cell records its settings and its CSV's hash beside it
        existing.with_suffix(".json").write_text(json.dumps({
            "method": "scratch", "env": "point_nav", "lr": 0.01, "lr_schedule": "constant",
            "settings": cell.settings(), "csv_sha256": text_sha256(f.read())}, default=str))
    suite.run_suite(cfg, log=lambda _: None)
    assert read_rows([existing]) == planted  # untouched
    rows = read_rows([tmp_path / "results.csv"])
    assert {r["seed"] for r in rows} == {0, 1}
    assert all(r["return"] == 123.0 for r in rows if r["seed"] == 0)  # the planted cell was used, not recomputed
    assert all(r["return"] != 123.0 for r in rows if r["seed"] == 1)
    assert (tmp_path / "summary.md").exists() and (tmp_path / "curves.png").exists()


def test_killed_suite_completes_on_restart(tmp_path):
    # cells long enough (~1 s each on a quiet 2-core machine) for the kill to land between the first and the last
    cmd = [sys.executable, str(REPO / "benchmarks" / "suite.py"), f"output_dir={tmp_path}", *TINY,
           "protocol.num_steps=30", "protocol.horizon=100", "num_tasks=4", "protocol.num_trajectories=10",
           "methods=[scratch]", "seeds=[0,1,2,3]", "launcher.workers=1"]
    env = {**os.environ, "WANDB_MODE": "disabled"}
    first = subprocess.Popen(cmd, cwd=REPO, env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    deadline = time.time() + 90
    while not (finished := list((tmp_path / "cells").rglob("seed*.csv"))) and time.time() < deadline \
            and first.poll() is None:
        time.sleep(0.05)
    os.killpg(first.pid, signal.SIGKILL)  # the suite and its workers die mid-run
    first.wait()
    finished = {c: c.stat().st_mtime_ns for c in (tmp_path / "cells").rglob("seed*.csv")}
    assert finished and len(finished) < 4, "the kill should land between the first and the last cell"
    assert not (tmp_path / "results.csv").exists()
    subprocess.run(cmd, cwd=REPO, env=env, check=True, capture_output=True, timeout=120)
    assert len(list((tmp_path / "cells").rglob("seed*.csv"))) == 4
    assert {c: c.stat().st_mtime_ns for c in finished} == finished  # finished cells were not recomputed
    assert {r["seed"] for r in read_rows([tmp_path / "results.csv"])} == {0, 1, 2, 3}


def test_ray_launcher_runs_two_cells(tmp_path):
    ray = pytest.importorskip("ray")
    cfg = _cfg(tmp_path, "methods=[scratch]", "seeds=[0,1]")
    jobs = [j for j in suite.plan(cfg, group="g") if j.key.startswith("cell/")]
    assert len(jobs) == 2
    ray.init(num_cpus=2, include_dashboard=False, runtime_env={"env_vars": {"WANDB_MODE": "disabled"}})
    try:
        succeeded, failed = run_jobs(jobs, RayLauncher("local"), log=lambda _: None)
    finally:
        ray.shutdown()
    assert not failed and succeeded == {j.key for j in jobs}
    assert {r["seed"] for r in read_rows(tmp_path.rglob("seed*.csv"))} == {0, 1}


def test_reuse_templates_point_the_plan_at_finished_runs(tmp_path):
    for proposal in ("random", "oracle"):
        meta = {**dict.fromkeys(MAML_FORMAT.meta_keys, 1), "env": "point_nav", "proposal": proposal, "obs_dim": 2}
        MAML_FORMAT.save(Checkpointer(tmp_path / "runs" / proposal / "point_nav" / "checkpoints"), 5, meta)
    template = f"{tmp_path}/runs/{{proposal}}/{{env}}"
    cfg = _cfg(tmp_path / "out", "seeds=[0]", "methods=[uml_random,oracle]", f"pretrain.maml.reuse='{template}'")
    runs = suite.plan_pretraining(cfg, "g", "code")
    for proposal in ("random", "oracle"):
        run = runs[f"maml_{proposal}", "point_nav", 0]
        assert run.reused and run.run_dir == tmp_path / "runs" / proposal / "point_nav"


def test_the_ablation_meta_tests_its_baselines_once_per_seed_at_its_k(tmp_path):
    cfg = _cfg(tmp_path, "seeds=[0]", "methods=[oracle,diayn_init]", "ablation.enabled=true",
               "ablation.methods=[oracle]", "ablation.baselines=[scratch,diayn_init]", "ablation.num_steps=3")
    runs = suite.plan_pretraining(cfg, "g", "code")
    assert suite.plan_ablation(cfg, runs, "code") == []  # no checkpoint yet: no baseline read against nothing
    checkpoints = runs["maml_oracle", "point_nav", 0].run_dir / "checkpoints"
    checkpoints.mkdir(parents=True)
    for step in (0, 5, 10):
        (checkpoints / f"step_{step}.pt").write_bytes(b"")
    jobs = {job.key: job.args[0] for job in suite.plan_ablation(cfg, runs, "code")}
    assert sorted(jobs) == ["ablation/point_nav/diayn_init/seed0", "ablation/point_nav/oracle/seed0/iter0",
                            "ablation/point_nav/oracle/seed0/iter10", "ablation/point_nav/oracle/seed0/iter5",
                            "ablation/point_nav/scratch/seed0"]
    scratch, diayn_init = jobs["ablation/point_nav/scratch/seed0"], jobs["ablation/point_nav/diayn_init/seed0"]
    assert scratch.checkpoint is None and scratch.protocol.num_steps == 3 and "iteration" not in scratch.extra
    assert diayn_init.checkpoint == str(runs["diayn", "point_nav", 0].run_dir)
    assert jobs["ablation/point_nav/oracle/seed0/iter5"].extra == {"iteration": 5}
    # scratch needs no pre-training run; a baseline that does must be among the methods
    _cfg(tmp_path, "seeds=[0]", "methods=[oracle]", "ablation.enabled=true", "ablation.methods=[oracle]")
    with pytest.raises(ConfigError, match=r"ablation.baselines: got \['diayn_init'\] \(.* would have no "
                                          r"pre-training run\); expected methods that need no "
                                          r"pre-training \(scratch\) or are also listed in methods \(oracle\)"):
        _cfg(tmp_path, "seeds=[0]", "methods=[oracle]", "ablation.enabled=true", "ablation.methods=[oracle]",
             "ablation.baselines=[diayn_init]")
