"""The one format/version check every checkpoint loader and every ``resume=true`` goes through.

A umrl checkpoint is a dict (stored by :mod:`umrl.checkpoint_file`: data only, hash-checked) with ``"format"`` (a versioned name such as ``"umrl.maml.v1"``),
``"meta"`` (what a loader needs to rebuild the networks) and format-specific entries. :class:`CheckpointFormat` names
one format, the ``meta`` keys its loaders read, and does the saving (stamping ``"format"``) and the checked loading.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from umrl.envs.registry import ENV_NAMES, check_observation_size
from umrl.runtime import Checkpointer, read_checkpoint, resolve_checkpoint, to_container
from umrl.validation import InvalidValue

__all__ = ["CheckpointFormat", "check_budget_left"]


def check_budget_left(key: str, budget: int, done: int, unit: str, run_dir: str | os.PathLike) -> None:
    """Refuse a ``resume=true`` whose budget (config key ``key``, in ``unit``) is not beyond the ``done`` the run in
    ``run_dir`` has already done: there is nothing left to do, and a smaller budget cannot undo what was done."""
    if budget <= done:
        raise InvalidValue(key, budget, f"> {done} to continue it with resume=true",
                           note=f"nothing to do: the run in {run_dir} has already done {done} {unit}")


@dataclass(frozen=True)
class CheckpointFormat:
    """One checkpoint format.

    Attributes:
        name: the versioned tag stored under ``"format"``, e.g. ``"umrl.diayn.v1"``.
        what: the recipe's name for error messages, e.g. ``"DIAYN"``.
        meta_keys: keys every ``state["meta"]`` of this format carries (checked on save).
    """

    name: str
    what: str
    meta_keys: tuple[str, ...]

    def save(self, checkpointer: Checkpointer, step: int, meta: Mapping[str, Any], config: Any = None,
             **entries: Any) -> Path:
        """Write ``{"format": name, "meta": meta, **entries, "config": resolved config}`` as ``step_<step>.pt``
        (the config also beside it as ``config.yaml``); ``meta`` must carry :attr:`meta_keys`."""
        missing = sorted(set(self.meta_keys) - set(meta))
        if missing:
            raise ValueError(f"{self.what} checkpoint meta lacks {missing}; it must carry {list(self.meta_keys)}.")
        state = {"format": self.name, "meta": dict(meta), **entries,
                 "config": to_container(config) if config is not None else None}
        return checkpointer.save(state, step, config)

    def check(self, state: Any, source: str | os.PathLike) -> dict:
        """Return ``state`` if it is a dict of this format whose networks fit their env's observation (where the env is
        registered), else raise ``ValueError`` naming ``source``."""
        if not isinstance(state, dict) or state.get("format") != self.name:
            found = state.get("format") if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"{source} is not a {self.what} checkpoint (format {found!r}, expected {self.name!r}).")
        meta = state.get("meta") or {}
        if meta.get("env") in ENV_NAMES:
            check_observation_size(meta["env"], meta.get("obs_dim"), f"{self.what} checkpoint {source}")
        return state

    def check_run(self, state: dict, name: str, source: str | os.PathLike, why: str, **expected: Any) -> dict:
        """Return ``state`` if its ``meta`` holds the ``expected`` values (``env="point_nav"``, ``proposal="diayn"``),
        else :class:`~umrl.validation.InvalidValue` naming argument ``name`` (its value ``source``), what the
        checkpoint holds and, in ``why``, who expects the rest: a checkpoint of another env or proposal is refused
        before any work (on another env it would fail in a matmul, or on another proposal run silently)."""
        found = {key: state["meta"].get(key) for key in expected}
        if found != expected:
            def run(values: Mapping[str, Any]) -> str:
                return f"a {self.what} run with " + ", ".join(f"{k}={v!r}" for k, v in values.items())

            raise InvalidValue(name, str(source), f"{run(expected)} ({why})", note=run(found))
        return state

    def load(self, path: str | os.PathLike) -> dict:
        """Load and check a checkpoint: a ``step_*.pt`` file, a ``checkpoints/`` folder or a run's output_dir
        (the latest ``step_*.pt``); ``FileNotFoundError`` says what was looked for, ``CheckpointError`` names an
        unreadable file."""
        file = resolve_checkpoint(path)
        return self.check(read_checkpoint(file), file)

    def load_for_resume(self, checkpointer: Checkpointer, meta: Mapping[str, Any],
                        check_config: Callable[[Any], None] | None = None) -> dict:
        """The newest readable checkpoint of ``checkpointer`` (an unreadable newer one is skipped with a warning
        naming it), checked, for a run whose networks are described by ``meta``.

        ``check_config(saved_config)`` runs first (recipes pass ``lambda saved: umrl.configs.check_resume(saved,
        cfg)``: a ``ConfigError`` listing the keys that differ beyond ``RESUME_ALLOW``); then ``ValueError`` if
        ``meta`` differs from the saved one."""
        path, state = checkpointer.load_latest_valid()
        state = self.check(state, path)
        if check_config is not None:
            check_config(state["config"])
        mismatched = {k: (state["meta"].get(k), v) for k, v in meta.items() if state["meta"].get(k) != v}
        if mismatched:
            raise ValueError(f"resume=true with a config that differs from the checkpoint's (saved, now): {mismatched}.")
        return state
