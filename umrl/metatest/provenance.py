"""What a results file needs to be reproduced: the commit (and whether the tree was dirty), the command, the hardware.

:func:`provenance` returns plain strings, so it can be written into ``summary.md`` or a JSON file as it is.
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
