"""One suite per output_dir (umrl.folder_lock's lock, naming the holder; a killed holder's lock is free at once) and
local workers that stop when their driver is killed."""
import os
import signal
import subprocess
import sys
import time

import pytest
from hydra import compose

from umrl.folder_lock import FolderInUse, claim_run_folder, lock_folder
from umrl.suite import CONFIG_DIR, run_suite
from umrl.trainers import config_dir

DRIVER = """
import sys, time
from pathlib import Path
from umrl.folder_lock import lock_folder
from umrl.launch import Job, LocalLauncher
with lock_folder(sys.argv[1]):
    launcher = LocalLauncher(1, cwd=sys.argv[1])
    launcher.submit(Job(key="sleep", fn=time.sleep, args=(120,), log=Path(sys.argv[1]) / "sleep.log"))
    while not launcher.busy:
        time.sleep(0.05)
    print(next(iter(launcher.busy)).process.pid, flush=True)
    time.sleep(120)
"""


def _gone(pid: int, timeout: float) -> bool:
    """The process ended within ``timeout`` s (a zombie nobody reaps yet counts as ended)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.1)
    return False


def test_a_second_suite_in_the_same_output_dir_refuses(tmp_path):
    with config_dir(CONFIG_DIR):
        cfg = compose("suite", ["profile=tiny", f"output_dir={tmp_path}"])
    with lock_folder(tmp_path) as lock, pytest.raises(FolderInUse, match=rf"output_dir {tmp_path} is in use by this "
                                                                         rf"process \(pid {os.getpid()}"):
        run_suite(cfg)
    assert not lock.held and sorted(p.name for p in tmp_path.iterdir()) == ["run.lock"]  # nothing else written


def test_the_suite_lock_does_not_block_its_jobs_runs(tmp_path):
    """The suite holds its output_dir; its pre-training jobs lock their own folders inside it."""
    with lock_folder(tmp_path):
        run = claim_run_folder(tmp_path / "pretrain" / "maml" / "point_nav" / "seed0-x", resume=False,
                               checkpointers=[])
        assert run.held
        run.release()


def test_workers_exit_when_the_driver_is_killed(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])}
    driver = subprocess.Popen([sys.executable, "-c", DRIVER, str(tmp_path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        worker = int(driver.stdout.readline())
        with pytest.raises(FolderInUse, match=f"in use by pid {driver.pid} on "), lock_folder(tmp_path):
            pass
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        # a worker notices within DRIVER_POLL_S once its imports are done (seconds on a loaded machine)
        assert _gone(worker, timeout=60), f"worker {worker} still running after its driver was killed"
    finally:
        if driver.poll() is None:
            driver.kill()
    with lock_folder(tmp_path):  # the kernel released the killed driver's lock
        pass
