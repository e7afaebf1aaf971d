"""One suite per output_dir (a lock naming the holder's pid, a dead holder's taken over) and local workers that
stop when their driver is killed."""
import os
import signal
import subprocess
import sys
import time

import pytest

from umrl.launch import DirectoryLocked, directory_lock

DRIVER = """
import sys, time
from pathlib import Path
from umrl.launch import Job, LocalLauncher, directory_lock
with directory_lock(sys.argv[1]):
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
    with directory_lock(tmp_path) as lock:
        assert lock.read_text() == str(os.getpid())
        with pytest.raises(DirectoryLocked, match=rf"output_dir: got .*in use by another suite \(pid {os.getpid()}"), \
                directory_lock(tmp_path):
            pass
    assert not lock.exists()


def test_a_stale_lock_is_taken_over_with_a_warning(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / "suite.lock").write_text(str(dead.pid))
    with pytest.warns(UserWarning, match=f"taking over the stale lock .* of pid {dead.pid}"), \
            directory_lock(tmp_path) as lock:
        assert lock.read_text() == str(os.getpid())


def test_workers_exit_when_the_driver_is_killed(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])}
    driver = subprocess.Popen([sys.executable, "-c", DRIVER, str(tmp_path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        worker = int(driver.stdout.readline())
        with pytest.raises(DirectoryLocked, match=f"pid {driver.pid}"), directory_lock(tmp_path):
            pass
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        assert _gone(worker, timeout=10), f"worker {worker} still running after its driver was killed"
    finally:
        if driver.poll() is None:
            driver.kill()
    with pytest.warns(UserWarning, match="stale lock"), directory_lock(tmp_path):
        pass
