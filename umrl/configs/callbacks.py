"""Hydra callbacks of the command lines (``hydra.callbacks`` in the recipes' and the suite's yaml): checks that must
run before Hydra itself writes.

Hydra creates ``hydra.run.dir`` (``${output_dir}/hydra``) and writes its files there before it calls the script's
``main``, where the schemas check the config: an ``output_dir`` that is a file or not writable would fail there
with a bare ``OSError``, a ``profile_name`` like ``../../x`` would be refused only after Hydra wrote outside
``outputs/suite``, and a second run into a folder in use, or a fresh run into a finished run's folder, would
overwrite that run's Hydra files.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, read_write

from umrl.checkpoints.folder import Checkpointer
from umrl.configs.validate import ConfigError
from umrl.folder_lock import (
    FolderHoldsRun,
    FolderInUse,
    FolderLock,
    claim_run_folder,
    lock_folder,
    reserve_folder,
)
from umrl.run_folders import named_keys, place_default_run, resume_line
from umrl.validation import Invalid, check_name, check_writable_dir

NAME_KEYS = ("profile_name", "logger.exp_name")
"""Keys that become folder names (the suite's output folder, the CSV logger's); checked where present."""

PATH_KEYS = ("output_dir", "hydra.run.dir")
"""Folders Hydra or the run write into."""


class OutputDirCheck(Callback):
    """Before Hydra writes anything for a run (``-m`` runs are checked by their schemas and trainers, once Hydra made
    their own directories): refuse names that are paths or too long (:data:`NAME_KEYS`,
    :func:`umrl.validation.check_name`) and folders that cannot be written or have a name over 255 bytes
    (:data:`PATH_KEYS`, :func:`umrl.validation.check_writable_dir`), then lock ``output_dir`` (a folder in use by
    another run is refused, naming its holder; a recipe's fresh run, ``resume=false``, into a folder holding
    checkpoints too: :func:`umrl.folder_lock.claim_run_folder`) and keep the lock for the run the script starts
    there (:func:`umrl.folder_lock.reserve_folder`), releasing it when the run ends. A recipe's ``output_dir``
    the command line leaves at its default is a family of folders instead: a rerun gets the next one,
    ``resume=true`` continues the latest, and the line saying so is printed (:mod:`umrl.run_folders`).

    A refusal ends the process (``SystemExit`` with the :class:`~umrl.configs.ConfigError` message, status 1):
    Hydra turns any ``Exception`` a callback raises into a warning and carries on."""

    def __init__(self) -> None:
        self.lock: FolderLock | None = None

    def on_run_start(self, config: DictConfig, config_name: str | None = None, **kwargs: Any) -> None:
        errors = []
        for key in NAME_KEYS:
            value = OmegaConf.select(config, key)
            try:
                if value is not None:  # None: a key this config does not have
                    check_name(key, value)
            except Invalid as e:
                errors.append(e.message())
        for key in PATH_KEYS:
            try:
                check_writable_dir(key, OmegaConf.select(config, key))
            except Invalid as e:
                errors.append(e.message())
                break  # hydra.run.dir lies in output_dir: the first fault is the one to fix
        if errors:
            raise SystemExit(str(ConfigError(config_name or "command line", errors)))
        resume, overrides = OmegaConf.select(config, "resume"), OmegaConf.select(config, "hydra.overrides.task")
        named = named_keys(overrides) if overrides is not None else {"output_dir"}  # no command line: as named
        notes: list[str] = []
        try:
            if resume is None:  # the suite: it always resumes
                lock = lock_folder(config.output_dir)
            else:  # a recipe: a rerun into its default folder gets a folder of its own (umrl.run_folders)
                with read_write(config):
                    lock, notes = place_default_run(config, named)
                if lock is None:
                    out = config.output_dir
                    lock = claim_run_folder(out, resume=resume is True,
                                            checkpointers=[Checkpointer(Path(out) / "checkpoints")])
                    line = resume_line(out) if resume is True else None
                    notes += [line] if line else []
        except (FolderInUse, FolderHoldsRun, *Invalid) as e:
            raise SystemExit(str(e)) from None
        for note in notes:  # Hydra's logging starts with the job: printed
            print(note, flush=True)
        self.lock = reserve_folder(lock)

    def on_run_end(self, config: DictConfig, config_name: str | None = None, **kwargs: Any) -> None:
        if self.lock is not None:  # the run took it over and may have released it already: release is idempotent
            self.lock.release()
