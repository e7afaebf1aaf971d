"""One wandb run per job: sequential train() calls, a failing job, Hydra multirun; every run with its group and job
type; one wandb folder per output tree, which `wandb sync --dry-run` lists whole; the suite's runs with their config
and tables (offline runs read back)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from script_loading import REPO, compose_config, repo_env
from wandb_offline import offline_runs, run_id, sync_dry_run

import umrl.trainers
from umrl import suite
from umrl.configs import validate
from umrl.configs.suite import SuiteConfig
from umrl.launch import Job, LocalLauncher
from umrl.loggers import close_logger, make_logger, wandb_dir_default
from umrl.metatest import iqm, read_rows
from umrl.suite.report import CURVE_COLUMNS
from umrl.trainers import compose

TINY = ["env.horizon=10", "meta_batch_size=2", "trajectories_per_task=3", "policy.hidden=[16]", "progress=false",
        "trpo.cg_iters=3", "logger.backend=wandb"]


@pytest.fixture
def offline_wandb(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "runs"))
    return tmp_path / "runs"


def _by_seed(runs):
    return {json.loads(run.config["seed"]): run for run in runs}


def test_each_train_call_in_one_process_gets_its_own_finished_run(tmp_path, offline_wandb, monkeypatch):
    from umrl.trainers import maml

    results = {seed: maml.train(compose("maml", [*TINY, f"seed={seed}", f"iterations={seed + 1}",
                                                 f"output_dir={tmp_path / str(seed)}"])) for seed in (0, 1)}

    def crash(*args, **kwargs):
        raise RuntimeError("a job that fails after its logger started")

    monkeypatch.setattr(maml, "meta_step", crash)
    with pytest.raises(RuntimeError, match="fails after"):
        maml.train(compose("maml", [*TINY, "seed=2", f"output_dir={tmp_path / '2'}"]))
    runs = _by_seed(offline_runs(offline_wandb))
    assert sorted(runs) == [0, 1, 2] and all(run.finished for run in runs.values())
    for seed, result in results.items():
        run = runs[seed]
        assert run.name == f"maml_oracle_point_nav_seed{seed}"
        assert (run.group, run.job_type) == ("maml_point_nav_oracle", "maml")  # the seeds of one setting together
        assert json.loads(run.config["output_dir"]) == str(tmp_path / str(seed))
        assert len(run.metrics["train/return_pre"]) == seed + 1  # its own iterations, none of the other job's
        assert float(run.metrics["train/return_pre"][-1]) == pytest.approx(result["train/return_pre"])
    assert "train/return_pre" not in runs[2].metrics


def test_hydra_multirun_logs_each_job_to_its_own_run(tmp_path, offline_wandb):
    sweep = tmp_path / "multirun"
    command = [sys.executable, str(REPO / "recipes" / "maml.py"), "-m", "seed=0,1", "iterations=1", *TINY,
               f"output_dir={tmp_path}/seed${{seed}}", f"hydra.sweep.dir={sweep}"]
    out = subprocess.run(command, check=False, capture_output=True, text=True, timeout=600, cwd=tmp_path,
                         env=repo_env())
    assert out.returncode == 0, out.stderr[-2000:]
    runs = _by_seed(offline_runs(offline_wandb))
    assert sorted(runs) == [0, 1]
    assert [len(runs[s].metrics["train/return_pre"]) for s in (0, 1)] == [1, 1]
    assert {(run.group, run.job_type) for run in runs.values()} == {("maml_point_nav_oracle", "maml")}
    assert "maml point_nav finished: iteration 1 | train/return_pre" in out.stdout  # the summary, not a dict
    for job in (0, 1):  # Hydra's per-job log file receives the same summary
        assert "finished: iteration 1" in (sweep / str(job) / "maml.log").read_text()


def test_multirun_files_default_under_outputs():
    with umrl.trainers.config_dir():
        from hydra import compose as hydra_compose

        for name in umrl.trainers.RECIPES:
            cfg = hydra_compose(name, return_hydra_config=True)
            assert cfg.hydra.sweep.dir.startswith(f"outputs/multirun/{name}/"), name


def test_runs_of_one_output_tree_share_one_wandb_folder_that_sync_lists_whole(tmp_path, monkeypatch):
    """Without WANDB_DIR, a run writes to the root of its output_dir's tree (its first folder when relative): the
    runs of outputs/... all land in outputs/wandb, and `wandb sync --dry-run` run there lists every one."""
    monkeypatch.delenv("WANDB_DIR", raising=False)
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.chdir(tmp_path)
    for log_dir, job_type in [("outputs/maml/point_nav/oracle/seed0", "maml"), ("outputs/diayn/point_nav/seed1",
                                                                                   "diayn")]:
        close_logger(make_logger({"backend": "wandb", "group": "g"}, exp_name=job_type, job_type=job_type,
                                 config={"seed": 0}, log_dir=log_dir))
    runs = offline_runs(tmp_path)
    assert len(runs) == 2 and {run.path.parent for run in runs} == {tmp_path / "outputs" / "wandb"}
    assert sync_dry_run(tmp_path / "outputs") == {run_id(run) for run in runs}
    assert sorted(run.job_type for run in runs) == ["diayn", "maml"]


def test_the_suites_wandb_dir_reaches_its_workers_and_never_overrides_the_users(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_DIR", raising=False)
    probe = Job("probe", os.getenv, ("WANDB_DIR",))
    with wandb_dir_default(tmp_path / "suite"):
        launcher = LocalLauncher(1, cwd=tmp_path)
        try:
            assert launcher.submit(probe).result(timeout=120) == str(tmp_path / "suite")
        finally:
            launcher.shutdown()
    assert "WANDB_DIR" not in os.environ
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "mine"))
    with wandb_dir_default(tmp_path / "suite"):
        assert os.environ["WANDB_DIR"] == str(tmp_path / "mine")
    assert os.environ["WANDB_DIR"] == str(tmp_path / "mine")


@pytest.mark.slow
def test_a_suites_runs_sit_in_its_wandb_folder_with_group_job_type_config_and_tables(tmp_path, monkeypatch):
    """A tiny suite (oracle: one MAML pre-training in a worker process, one meta-test cell): every run in
    <output_dir>/wandb, listed by `wandb sync --dry-run` there; one group; the meta-test run carries the suite's
    whole config, its curve as a table of IQM, mean and their CIs per k (equal to those of results.csv's returns), as
    an image of the band, and its rows of the results table; the report run holds every curve row and the figure."""
    monkeypatch.delenv("WANDB_DIR", raising=False)
    monkeypatch.setenv("WANDB_MODE", "offline")
    tiny_maml = ("{iterations: 1, meta_batch_size: 2, trajectories_per_task: 2, env: {horizon: 10}, "
                 "policy: {hidden: [16]}, trpo: {cg_iters: 2}}")
    cfg = validate(compose_config("umrl/suite/config", "suite", [
        f"output_dir={tmp_path}", "methods=[oracle]", "seeds=[0]", "num_tasks=2", "protocol.num_steps=2",
        "protocol.num_trajectories=2", "protocol.horizon=10", "report.steps=[0]", "ablation.enabled=false",
        "launcher.workers=1", "launcher.threads=1", f"+pretrain.maml.overrides={tiny_maml}"]), SuiteConfig)
    suite.run_suite(cfg, log=lambda _: None)
    assert "WANDB_DIR" not in os.environ
    runs = {run.job_type: run for run in offline_runs(tmp_path)}
    assert sorted(runs) == ["maml", "meta_test", "report"]
    assert {run.path.parent for run in runs.values()} == {tmp_path / "wandb"}
    assert sync_dry_run(tmp_path) == {run_id(run) for run in runs.values()}
    assert len({run.group for run in runs.values()}) == 1 and runs["report"].group.startswith("suite-")
    meta_test = runs["meta_test"]
    assert meta_test.name == "oracle_point_nav" and meta_test.finished
    config = {key: json.loads(value) for key, value in meta_test.config.items()}
    assert (config["method"], config["env"], config["methods"], config["num_tasks"]) == ("oracle", "point_nav",
                                                                                         ["oracle"], 2)
    assert config["protocol"]["num_steps"] == 2 and config["launcher"]["workers"] == 1
    curve = meta_test.table("meta_test/curve")
    assert curve["columns"] == CURVE_COLUMNS and [row[:3] for row in curve["data"]] == [
        [k, "point_nav", "oracle"] for k in (0, 1, 2)]
    rows = read_rows([tmp_path / "results.csv"])
    for k, _, _, value, low, high, mean, mean_low, mean_high in curve["data"]:
        returns = np.array([r["return"] for r in rows if r["step"] == k])
        assert value == pytest.approx(float(iqm(returns))) and mean == pytest.approx(float(returns.mean()))
        assert low <= value <= high and mean_low <= mean <= mean_high
    assert len(meta_test.metrics["meta_test/return"]) == 3
    for run, key in ((meta_test, "meta_test/curve_band"), (runs["report"], "report/curves")):
        image = run.path / "files" / run.images[key]  # the run's own copy (the band's figure file was temporary)
        assert not image.is_symlink() and image.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert runs["report"].table("meta_test/curves")["data"] == curve["data"]  # one arm: every curve row is its own
    results = meta_test.table("results")
    by_metric = {record["metric"]: record for record in (dict(zip(results["columns"], row)) for row in results["data"])}
    assert sorted(by_metric) == ["auc", "return_k0", "return_k2"]
    for k in (0, 2):  # the curve's band at k is the summary table's IQM and CI at k
        record = by_metric[f"return_k{k}"]
        assert curve["data"][k][3:6] == pytest.approx([record["iqm"], record["iqm_low"], record["iqm_high"]])
    assert runs["report"].table("results")["data"] == results["data"]  # one arm: the report's table is its rows
