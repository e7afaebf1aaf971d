"""Ray jobs get what local workers get: the suite's WANDB_DIR (set after Ray started, it still reaches each task) and
the launcher's prelude, here the import of the user's env module, run before the job."""
import functools
import os
from pathlib import Path

import pytest

from umrl.configs.memory import step_bytes
from umrl.envs.user_envs import import_env_module
from umrl.launch import Job, JobError, LocalLauncher, RayLauncher
from umrl.loggers import wandb_dir_default

ENV_MODULE = str(Path(__file__).resolve().parent / "pendulum_env.py")
IMPORT_ENV = functools.partial(import_env_module, "env_module", ENV_MODULE)  # the suite's prelude for env_module
ASK_ENV = Job(key="env", fn=step_bytes, args=("gym:InvertedPendulum-v5",))  # 4 B x (2 x 4 observations + 1 action)


def test_a_ray_task_gets_the_drivers_wandb_dir_and_env_module(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    monkeypatch.delenv("WANDB_DIR", raising=False)
    ray.init(num_cpus=1, include_dashboard=False)  # its workers start without WANDB_DIR
    try:
        launcher = RayLauncher("local", prelude=IMPORT_ENV)
        ask = Job(key="wandb_dir", fn=os.getenv, args=("WANDB_DIR",))
        with wandb_dir_default(tmp_path / "suite"):
            assert launcher.submit(ask).result(timeout=120) == str(tmp_path / "suite")
        assert launcher.submit(ask).result(timeout=120) is None  # unset again: not left in a reused worker
        assert launcher.submit(ASK_ENV).result(timeout=120) == 36
    finally:
        ray.shutdown()


def test_a_local_worker_runs_the_prelude_that_imports_the_env_module_before_its_jobs(tmp_path):
    for prelude, expected in ((IMPORT_ENV, 36), (None, JobError)):
        launcher = LocalLauncher(1, cwd=tmp_path, prelude=prelude)
        try:
            future = launcher.submit(ASK_ENV)
            if expected is JobError:
                with pytest.raises(JobError, match="KeyError|InvertedPendulum"):
                    future.result(timeout=120)
            else:
                assert future.result(timeout=120) == expected
        finally:
            launcher.shutdown()
