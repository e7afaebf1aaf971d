"""What identifies a suite result, so a changed config or code never reuses a stale one; state files written atomically.

Every pre-training run and every meta-test cell of the benchmark suite is stored under a :func:`config_key`: a hash
of the resolved config that produced it (a recipe config, a :class:`~umrl.metatest.CellSpec`) and of the code version
(:func:`source_version`). The key is part of the result's path, so a rerun with ``protocol.num_steps`` 2 -> 4 (or
an edited recipe) computes new results beside the old ones instead of reusing them, and a report built from the
current keys never mixes configs. Switching back to a previous config finds its results again.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from umrl.atomic_write import write_text_atomic
from umrl.checkpoints.folder import Checkpointer

KEY_LENGTH = 12
"""Hex digits of a :func:`config_key` (48 bits: a collision among a suite's runs is not a practical concern)."""

UNKEYED = ("output_dir", "logger", "progress", "resume")
"""Top-level recipe keys that do not change what a run computes (where it writes, how it logs, whether it continues
a killed run): left out of a pre-training run's key. Every other key, including ``device`` and ``num_threads`` (both
can change floating-point results), is part of it."""

DONE_MARKER = "suite_complete"
"""The file a pre-training run directory holds once the suite saw the run finish."""

SOURCE_SUFFIXES = (".py", ".yaml")


REPORT_ONLY = ("umrl/metatest/plots.py", "umrl/metatest/provenance.py")
"""Sources that only draw or describe results (no pre-training run or cell executes them): editing them recomputes
nothing."""


def source_version(roots: Iterable[str | os.PathLike], exclude: Iterable[str] = REPORT_ONLY) -> str:
    """A :data:`KEY_LENGTH`-digit hash of every ``*.py`` and ``*.yaml`` file under ``roots`` (folders, or single
    files hashed under their own name; relative path and bytes, in sorted order) but those named in ``exclude``
    (``<root folder name>/<path in it>``): the code a result ran with. Works without git and sees uncommitted
    edits."""
    digest, skip = hashlib.sha256(), set(exclude)
    for root in map(Path, roots):
        if root.is_file():
            files, names = [root], [root.name]
        elif root.is_dir():
            files = sorted(p for p in root.rglob("*") if p.suffix in SOURCE_SUFFIXES and "__pycache__" not in p.parts)
            names = [f"{root.name}/{path.relative_to(root).as_posix()}" for path in files]
        else:
            raise FileNotFoundError(f"source_version: {root} is neither a file nor a directory.")
        for path, name in zip(files, names):
            if name in skip:
                continue
            digest.update(f"{name}\0".encode())
            digest.update(path.read_bytes())
            digest.update(b"\0")
    return digest.hexdigest()[:KEY_LENGTH]


def config_key(values: Mapping[str, Any], code: str) -> str:
    """A :data:`KEY_LENGTH`-digit hash of ``values`` (a plain, resolved config: nested dicts, lists, scalars) and
    the ``code`` version; equal configs give equal keys whatever their key order."""
    text = json.dumps({"config": values, "code": code}, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:KEY_LENGTH]


def keyed_config(values: Mapping[str, Any], unkeyed: Iterable[str] = UNKEYED) -> dict:
    """``values`` without the top-level keys in ``unkeyed`` (what a pre-training run's key is computed from)."""
    skip = set(unkeyed)
    return {k: v for k, v in values.items() if k not in skip}


def write_json_atomic(path: str | os.PathLike, value: Any) -> Path:
    """Write ``value`` as indented JSON through a ``.tmp`` file and ``os.replace``; creates the parent folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(value, indent=1, default=str))
    return path


def remove_stale_tmp(root: str | os.PathLike) -> list[Path]:
    """Delete every ``*.tmp`` under ``root`` (what a killed atomic write left behind; wandb folders are not
    touched); returns the removed paths. Call it only while nothing writes under ``root``."""
    root = Path(root)
    if not root.is_dir():
        return []
    stale = [p for p in root.rglob("*.tmp") if p.is_file() and "wandb" not in p.relative_to(root).parts]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def latest_step(run_dir: str | os.PathLike) -> int | None:
    """The step of the newest ``<run_dir>/checkpoints/step_<N>.pt`` (None without one)."""
    latest = Checkpointer(Path(run_dir) / "checkpoints").latest()
    return None if latest is None else int(latest.stem.split("_")[-1])


def mark_done(run_dir: str | os.PathLike) -> None:
    """Write the run's :data:`DONE_MARKER` (atomically, with the time)."""
    write_text_atomic(Path(run_dir) / DONE_MARKER, time.strftime("%Y-%m-%dT%H:%M:%S"))


def run_finished(run_dir: str | os.PathLike, budget: int) -> bool:
    """Whether the pre-training run in ``run_dir`` finished: its :data:`DONE_MARKER` exists, or its newest checkpoint
    is at a step ``>= budget`` (the run did all its work but was killed before the marker, e.g. during a final
    evaluation after its last checkpoint; the marker is then written)."""
    if (Path(run_dir) / DONE_MARKER).exists():
        return True
    step = latest_step(run_dir)
    if step is None or step < budget:
        return False
    mark_done(run_dir)
    return True


__all__ = [
    "DONE_MARKER",
    "KEY_LENGTH",
    "UNKEYED",
    "config_key",
    "keyed_config",
    "latest_step",
    "mark_done",
    "remove_stale_tmp",
    "run_finished",
    "source_version",
    "write_json_atomic",
]
