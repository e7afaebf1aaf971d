"""Helpers for tests of the Hydra scripts in benchmarks/ and recipes/: import a script, compose its config (the
trainers' configs compose from the library: ``from umrl.trainers import compose``), kill a running one."""
import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from hydra import compose
from omegaconf import DictConfig

from umrl.configs.env_groups import with_env_group
from umrl.trainers import config_dir

REPO = Path(__file__).resolve().parents[1]


def repo_env(**extra: str) -> dict[str, str]:
    """This process's environment for a subprocess that imports umrl from ``REPO``: ``REPO`` first on
    ``PYTHONPATH``, the entries already there kept (a machine whose packages come from ``PYTHONPATH``), plus
    ``extra``."""
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, **extra}


def load_script(relative_path: str):
    """Import ``REPO/relative_path`` (e.g. ``"benchmarks/suite.py"``) as module ``umrl_script_<stem>``, once per
    session: it is registered in ``sys.modules`` (its dataclasses resolve their annotations there) and reused."""
    path = REPO / relative_path
    name = f"umrl_script_{path.stem}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name]


def compose_config(directory: str, name: str, overrides) -> DictConfig:
    """Compose Hydra config ``name`` from ``REPO/directory`` with ``overrides`` (a recipe's per-env defaults chosen
    from ``env.name``, as :func:`umrl.trainers.compose` does)."""
    with config_dir(REPO / directory):
        return compose(name, overrides=with_env_group(name, overrides))


def sigkill_after(script_args: list[str], checkpoint: Path, timeout: float = 120.0) -> None:
    """Run ``python <script_args>`` from ``REPO``, SIGKILL it as soon as ``checkpoint`` exists, and check that it was
    killed (not finished) and wrote ``checkpoint`` in ``timeout`` seconds."""
    proc = subprocess.Popen([sys.executable, *script_args], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + timeout
        while not checkpoint.exists() and proc.poll() is None:
            assert time.monotonic() < deadline, f"the script wrote no {checkpoint.name} within {timeout:.0f} s"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run finished before it could be killed"
