"""Where a recipe's run goes when its command line leaves ``output_dir`` at its default: a rerun never overwrites.

A recipe's default ``output_dir`` (``outputs/diayn/<env>/seed<s>``, a profile's own) names a family of run folders:
the folder itself, then ``<folder>-2``, ``<folder>-3``, ... (``ls -v`` lists them in the order the runs started). A
folder *holds a run* when it holds checkpoints (``checkpoints/step_*.safetensors`` or ``.pt``, or a DIAYN
seed's ``seed<s>/checkpoints/``).

- A fresh run (``resume=false``) takes the first folder after the family's latest run that it can lock
  (:mod:`umrl.folder_lock`) and that holds no run: two runs started at once lock different folders.
- ``resume=true`` continues the family's latest run. When none holds a run yet it names the folder itself, and the
  trainer then stops with a ``FileNotFoundError`` (nothing to resume: run once without ``resume=true``).
- MAML's ``proposal=diayn`` with its default ``diayn_checkpoint`` reads the latest run of that DIAYN family.

An ``output_dir`` (or ``diayn_checkpoint``) the command line names is used as it is: a fresh run into a folder
holding checkpoints is refused (:func:`umrl.folder_lock.claim_run_folder`). The command lines apply this
(:class:`umrl.configs.callbacks.OutputDirCheck` for a run, :func:`umrl.cli.recipe.sweep_job_folder` for each
``-m`` job) and :func:`umrl.trainers.train` apply this; the trainer classes take ``output_dir`` as given.
"""
from __future__ import annotations

import itertools
import os
import re
from collections.abc import Collection, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from umrl.checkpoints.folder import Checkpointer
from umrl.folder_lock import FolderInUse, FolderLock

__all__ = ["claim_default_run_folder", "latest_run", "named_keys", "place_default_run", "resume_line",
           "run_checkpoints", "run_folder"]


def named_keys(overrides: Sequence[str]) -> set[str]:
    """The config keys a command line's Hydra ``overrides`` set (``+output_dir=x`` and ``output_dir=x`` both name
    ``output_dir``; ``+profile=maml_tiny`` names ``profile``, not the keys the profile sets)."""
    return {line.split("=", 1)[0].lstrip("+~") for line in overrides if "=" in line}


def run_folder(base: str | os.PathLike, run: int) -> Path:
    """The folder of run number ``run`` (1, 2, ...) of ``base``'s family: ``base`` itself, then ``<base>-<run>``."""
    base = Path(base)
    return base if run == 1 else base.with_name(f"{base.name}-{run}")


def run_checkpoints(folder: str | os.PathLike) -> list[Path]:
    """The checkpoints a run left in ``folder``: its own (``checkpoints/``) and a DIAYN program's per seed
    (``seed<s>/checkpoints/``)."""
    folder = Path(folder)
    seeds = sorted(folder.glob("seed*/checkpoints")) if folder.is_dir() else []
    return [path for directory in [folder / "checkpoints", *seeds] for path in Checkpointer(directory).all()]


def _runs(base: Path) -> list[int]:
    """The numbers of the folders of ``base``'s family that hold a run, ascending."""
    numbered = re.compile(re.escape(base.name) + r"-([0-9]+)")
    siblings = os.listdir(base.parent) if base.parent.is_dir() else []
    found = [1] + [int(m.group(1)) for name in siblings if (m := numbered.fullmatch(name)) and int(m.group(1)) >= 2]
    return sorted(n for n in set(found) if run_checkpoints(run_folder(base, n)))


def latest_run(base: str | os.PathLike) -> Path | None:
    """The folder of the latest run of ``base``'s family (the highest number holding checkpoints), or None."""
    runs = _runs(Path(base))
    return run_folder(base, runs[-1]) if runs else None


def resume_line(folder: str | os.PathLike) -> str | None:
    """The line a ``resume=true`` run in ``folder`` prints: the folder and the step it continues from (None when the
    folder holds no run to continue)."""
    if not run_checkpoints(folder):
        return None
    latest = Checkpointer(Path(folder) / "checkpoints").latest()
    step = f"step {latest.stem.removeprefix('step_')}" if latest else "its seeds' last checkpoints"
    return f"resume=true: continuing the run in {folder} from {step}"


def claim_default_run_folder(base: str | os.PathLike, *, resume: bool) -> tuple[FolderLock, str | None]:
    """Lock the folder of ``base``'s family a run with the default ``output_dir`` writes to (module docstring):
    returns the held lock and the line that says where the run goes when that is not ``base`` itself or when it
    resumes (None otherwise). ``resume``: a latest run another process holds raises
    :class:`~umrl.folder_lock.FolderInUse`; a fresh run skips every folder another process holds."""
    base = Path(base)
    runs = _runs(base)
    if resume:
        folder = run_folder(base, runs[-1]) if runs else base
        lock = FolderLock(folder).acquire()
        return lock, resume_line(folder)
    for run in itertools.count(runs[-1] + 1 if runs else 1):
        folder = run_folder(base, run)
        try:
            lock = FolderLock(folder).acquire()
        except FolderInUse:
            continue
        if not run_checkpoints(folder):
            note = None if run == 1 else (f"output_dir {base} holds an earlier run: this run writes to {folder} "
                                          "(output_dir=<folder> chooses the folder)")
            return lock, note
        lock.release()  # a run that finished between the listing and the lock
    raise AssertionError("unreachable: itertools.count never ends")


def place_default_run(cfg: DictConfig, named: Collection[str]) -> tuple[FolderLock | None, list[str]]:
    """Apply this module's rules to a recipe config whose command line named the keys ``named`` (:func:`named_keys`):
    with ``output_dir`` not named, lock the run's folder (:func:`claim_default_run_folder`) and set
    ``cfg.output_dir`` to it; with ``proposal=diayn`` and ``diayn_checkpoint`` not named, point ``diayn_checkpoint``
    at the latest run of its family. ``cfg`` must be writable. Returns the held lock (None when ``output_dir`` was
    named: the caller claims it) and the lines that say what changed."""
    notes = []
    if (OmegaConf.select(cfg, "proposal") == "diayn" and "diayn_checkpoint" not in named
            and OmegaConf.select(cfg, "diayn_checkpoint") is not None):
        latest = latest_run(cfg.diayn_checkpoint)
        if latest is not None and latest != Path(cfg.diayn_checkpoint):
            cfg.diayn_checkpoint = str(latest)
            notes.append(f"diayn_checkpoint: the latest DIAYN run of its default folder, {latest}")
    if "output_dir" in named:
        return None, notes
    lock, note = claim_default_run_folder(cfg.output_dir, resume=bool(cfg.resume))
    if lock.folder != Path(cfg.output_dir):
        cfg.output_dir = str(lock.folder)
    return lock, [*notes, *([note] if note else [])]
