"""One wandb run per job: sequential train() calls, a failing job, Hydra multirun (offline runs read back)."""
import json
import os
import subprocess
import sys

import pytest
from script_loading import REPO
from wandb_offline import offline_runs

import recipes
from recipes import compose

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
    from recipes import maml

    results = {seed: maml.train(compose("maml", [*TINY, f"seed={seed}", f"iterations={seed + 1}",
                                                 f"output_dir={tmp_path / str(seed)}"])) for seed in (0, 1)}

    def crash(*args, **kwargs):
        raise RuntimeError("a job that fails after its logger started")

    monkeypatch.setattr(maml, "meta_iteration", crash)
    with pytest.raises(RuntimeError, match="fails after"):
        maml.train(compose("maml", [*TINY, "seed=2", f"output_dir={tmp_path / '2'}"]))
    runs = _by_seed(offline_runs(offline_wandb))
    assert sorted(runs) == [0, 1, 2] and all(run.finished for run in runs.values())
    for seed, result in results.items():
        run = runs[seed]
        assert run.name == f"maml_oracle_point_nav_seed{seed}"
        assert json.loads(run.config["output_dir"]) == str(tmp_path / str(seed))
        assert len(run.metrics["train/return_pre"]) == seed + 1  # its own iterations, none of the other job's
        assert float(run.metrics["train/return_pre"][-1]) == pytest.approx(result["train/return_pre"])
    assert "train/return_pre" not in runs[2].metrics


def test_hydra_multirun_logs_each_job_to_its_own_run(tmp_path, offline_wandb):
    sweep = tmp_path / "multirun"
    command = [sys.executable, str(REPO / "recipes" / "maml.py"), "-m", "seed=0,1", "iterations=1", *TINY,
               f"output_dir={tmp_path}/seed${{seed}}", f"hydra.sweep.dir={sweep}"]
    out = subprocess.run(command, check=False, capture_output=True, text=True, timeout=600, cwd=tmp_path,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    assert out.returncode == 0, out.stderr[-2000:]
    runs = _by_seed(offline_runs(offline_wandb))
    assert sorted(runs) == [0, 1]
    assert [len(runs[s].metrics["train/return_pre"]) for s in (0, 1)] == [1, 1]
    assert "maml point_nav finished: iteration 1 | train/return_pre" in out.stdout  # the summary, not a dict
    for job in (0, 1):  # Hydra's per-job log file receives the same summary
        assert "finished: iteration 1" in (sweep / str(job) / "maml.log").read_text()


def test_multirun_files_default_under_outputs():
    with recipes.config_dir():
        from hydra import compose as hydra_compose

        for name in recipes.RECIPES:
            cfg = hydra_compose(name, return_hydra_config=True)
            assert cfg.hydra.sweep.dir.startswith(f"outputs/multirun/{name}/"), name
