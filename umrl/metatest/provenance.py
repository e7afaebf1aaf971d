"""What a results file needs to be reproduced: the commit (and whether the tree was dirty), the command, the hardware,
and the inputs it read, named so that the file means the same on another machine.

:func:`provenance` returns plain strings, so it can be written into ``summary.md`` or a JSON file as it is.
:func:`relative_path` is how a result file names a file it was made from (a cell's ``"checkpoint"``): relative to
the folder of the result file itself, not to the repository or the current directory, so the name holds no machine
path and still resolves when the results and the runs they read are moved or committed together, inside the
repository or outside it (``results/point_nav/meta_test_ref/seed0/oracle.json`` names
``../../oracle_ref/seed0``). Read one back with :func:`resolve_recorded_path`.
"""
from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]


def git_commit(repo: str | os.PathLike = REPO) -> str:
    """``<sha>`` of ``HEAD``, suffixed ``-dirty`` when tracked files differ from it; ``unknown`` outside a git tree."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, check=True).stdout.strip()

    try:
        sha = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return f"{sha}-dirty" if dirty else sha


def relative_path(path: str | os.PathLike, result_file: str | os.PathLike) -> str:
    """``path`` (absolute, or relative to the current directory) relative to the folder of ``result_file``, with
    ``/`` separators: ``relative_path("results/pn/oracle_ref/seed0", "results/pn/meta_test/seed0/oracle.json")`` is
    ``"../../oracle_ref/seed0"``."""
    folder = os.path.dirname(os.path.abspath(result_file))
    return Path(os.path.relpath(os.path.abspath(path), folder)).as_posix()


def resolve_recorded_path(recorded: str, result_file: str | os.PathLike) -> Path:
    """The file a result file names with :func:`relative_path` (an absolute path, as older files hold, is kept)."""
    return Path(result_file).parent / recorded


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else :func:`platform.processor`)."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def provenance(*, command: str, wall_seconds: float, job_threads: int) -> dict[str, str]:
    """``commit``, ``command``, ``cpu``, ``cores``, ``torch threads``, ``gpu``, ``software`` and ``wall time``.

    ``job_threads`` is the torch thread count each job sets; ``cores`` are the CPUs this process may use out of the
    machine's total.
    """
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    return {
        "commit": git_commit(),
        "command": command,
        "cpu": cpu_model(),
        "cores": f"{usable} usable of {os.cpu_count()}",
        "torch threads": f"{job_threads} per job (driver: {torch.get_num_threads()})",
        "gpu": gpu,
        "software": f"python {sys.version.split()[0]}, torch {torch.__version__}, {platform.platform()}",
        "wall time": f"{wall_seconds:.0f} s",
    }
