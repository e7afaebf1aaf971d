"""Jobs and launchers (umrl.launch): dependencies, failures reported with the job's log, no shared-memory leftovers."""
import os
import time
from pathlib import Path

import pytest

from umrl.launch import InlineLauncher, Job, LocalLauncher, run_jobs
from umrl.metatest import CellSpec, run_cell


def test_failed_job_blocks_dependants_only():
    def boom():
        raise RuntimeError("no")

    ran = []
    jobs = [Job("a", boom), Job("b", ran.append, args=("b",), deps=("a",)),
            Job("c", ran.append, args=("c",))]
    succeeded, failed = run_jobs(jobs, InlineLauncher(), log=lambda _: None)
    assert succeeded == {"c"} and ran == ["c"]
    assert "RuntimeError: no" in failed["a"] and "blocked" in failed["b"]


def test_failed_job_prints_its_error_and_log_tail(tmp_path):
    spec = CellSpec(method="uml_random", env="point_nav", seed=0, output=str(tmp_path / "cell.csv"),
                    checkpoint=str(tmp_path / "no_such_run"))
    job = Job("cell/x", run_cell, args=(spec,), what="meta-test of uml_random", log=tmp_path / "x.log")
    launcher = LocalLauncher(1, cwd=tmp_path)
    printed = []
    try:
        succeeded, failed = run_jobs([job], launcher, log=printed.append)
    finally:
        launcher.shutdown()
    assert not succeeded and "FileNotFoundError" in failed["cell/x"]
    text = "\n".join(printed)
    assert "[fail] cell/x (meta-test of uml_random)" in text and "error: JobError: FileNotFoundError" in text
    assert f"last lines of {tmp_path / 'x.log'}" in text and "| Traceback" in text  # the worker's traceback


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/<pid>/maps")
def test_local_workers_hold_no_shared_memory_semaphores(tmp_path):
    """A suite killed with SIGKILL cannot clean up: the local launcher must not create named semaphores
    (``/dev/shm/sem.mp-*``, what multiprocessing pools leave behind) at all."""
    def semaphores(pid):
        return {line.split()[-1] for line in Path(f"/proc/{pid}/maps").read_text().splitlines() if "sem.mp-" in line}

    before = semaphores(os.getpid())
    launcher = LocalLauncher(1, cwd=tmp_path)
    try:
        future = launcher.submit(Job("sleep", time.sleep, args=(3,)))
        deadline = time.time() + 60
        while not launcher.busy and time.time() < deadline:
            time.sleep(0.05)
        (worker,) = launcher.busy
        assert semaphores(worker.process.pid) == set()
        assert semaphores(os.getpid()) == before
        future.result(timeout=120)
    finally:
        launcher.shutdown()
