"""A run's checkpoint folder: saving ``step_<N>.safetensors`` files atomically beside the run's ``config.yaml``,
finding the latest, pruning the older ones, and resolving what a user names (a file or a run folder) to a checkpoint
file.

The files are :mod:`umrl.checkpoints.file`'s (safetensors with the state's JSON tree in their metadata, data only,
hash-checked); what a recipe's state holds is :mod:`umrl.checkpoints.format`'s. Files that umrl wrote under their
earlier name, ``step_<N>.pt`` (the same content; every result under ``results/``), are found, loaded, resumed and
pruned as well: the latest checkpoint is the highest step over both names.
"""
from __future__ import annotations

import os
import re
import stat
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from umrl.atomic_write import write_text_atomic
from umrl.checkpoints.file import CheckpointError, file_kind, read_checkpoint, write_checkpoint
from umrl.plain_config import to_container
from umrl.validation import InvalidType

SUFFIX = ".safetensors"
"""The suffix of the checkpoint files :meth:`Checkpointer.save` writes: they are safetensors files."""
LEGACY_SUFFIX = ".pt"
"""The suffix umrl's checkpoints had before :data:`SUFFIX` (the same safetensors content; still read)."""


class Checkpointer:
    """Saves ``state`` dicts as ``<directory>/step_<N>.safetensors`` with the resolved config in
    ``<directory>/config.yaml``.

    Every file is written atomically (a ``.tmp`` then ``os.replace``). The temporary files a killed save left behind
    (``step_<N>.safetensors.tmp``, ``config.yaml.tmp`` and safetensors' own hidden ``.tmp<6 letters or digits>``;
    ``step_<N>.pt.tmp`` from umrl versions that named checkpoints ``.pt``) are removed by the writer: by
    :meth:`remove_stale_tmp`, which the trainers call once they hold their folder's lock
    (:mod:`umrl.folder_lock`), else at its first :meth:`save` or :meth:`load_latest_valid` (a resume). Read-only
    lookups (:meth:`latest`, :func:`resolve_checkpoint`, loaders) never touch them: another run may be writing there.

    A checkpoint is exactly what :meth:`save` writes: an entry whose whole name is ``step_<N>.safetensors`` (or
    ``step_<N>.pt``, the name umrl gave the same files before) and which is a regular file, not a symlink (checked
    with ``os.lstat``, without opening it). Anything else in the folder (``best_step_3.safetensors``, a FIFO, a
    folder or a symlink named ``step_3.safetensors``) is never listed, read or deleted. Where one step has a file
    under each name, the ``.safetensors`` one is the step's checkpoint (a :meth:`save` of that step removes the
    other).

    Args:
        directory: where checkpoints go (created on first save).
        keep_all: keep every checkpoint (meta-training ablations evaluate them all); otherwise only the newest.
    """

    _pattern = re.compile(r"step_([0-9]+)(\.safetensors|\.pt)")
    _tmp_pattern = re.compile(r"step_[0-9]+(\.safetensors|\.pt)\.tmp|config\.yaml\.tmp|\.tmp[A-Za-z0-9]{6}")
    """What a killed :meth:`save` leaves: its own ``.tmp`` files, and the hidden file safetensors writes first (the
    ``tempfile`` crate's ``.tmp`` + 6 random letters or digits, renamed to the ``.safetensors.tmp`` once
    complete)."""

    def __init__(self, directory: str | os.PathLike, keep_all: bool = False):
        self.directory = Path(directory)
        self.keep_all = keep_all
        self._stale_removed = False

    def remove_stale_tmp(self) -> None:
        """Once per writer: delete the temporary files a killed save left in :attr:`directory` (regular files named
        as :meth:`save` and safetensors name them, :attr:`_tmp_pattern`; other ``*.tmp`` entries are not umrl's and
        stay)."""
        if not self._stale_removed and self.directory.is_dir():
            for stale in self.directory.iterdir():
                if self._tmp_pattern.fullmatch(stale.name) and _is_regular_file(stale):
                    stale.unlink()
        self._stale_removed = True

    def _files(self) -> list[tuple[int, Path]]:
        """``(step, path)`` of every checkpoint file under either name, by step, a step's ``.pt`` before its
        ``.safetensors``."""
        if not self.directory.is_dir():
            return []
        found = [(int(m.group(1)), m.group(2) == SUFFIX, p) for p in self.directory.iterdir()
                 if (m := self._pattern.fullmatch(p.name)) and _is_regular_file(p)]
        return [(step, p) for step, _, p in sorted(found)]

    def all(self) -> list[Path]:
        """Every checkpoint on disk, one per step, oldest step first: regular files (not symlinks) named exactly
        ``step_<N>.safetensors`` or ``step_<N>.pt`` (the ``.safetensors`` one where a step has both)."""
        return list({step: path for step, path in self._files()}.values())

    def latest(self) -> Path | None:
        """The checkpoint with the largest step, or ``None``."""
        found = self.all()
        return found[-1] if found else None

    def save(self, state: Mapping[str, Any], step: int, config: Any = None) -> Path:
        """Write ``state`` for ``step`` atomically (a killed save never leaves a broken newest file)."""
        self.remove_stale_tmp()
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"step_{step}{SUFFIX}"
        tmp = path.with_name(path.name + ".tmp")
        write_checkpoint(state, tmp)
        os.replace(tmp, path)
        if config is not None:
            write_text_atomic(self.directory / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(to_container(config))))
        for old_step, old in self._files():
            if old != path and (old_step == step or not self.keep_all):  # this step's .pt is superseded
                old.unlink()
        return path

    def load(self, path: str | os.PathLike | None = None) -> dict:
        """Load ``path`` (default: the latest checkpoint); an unreadable file raises :class:`CheckpointError`."""
        target = Path(path) if path is not None else self.latest()
        if target is None or not target.is_file():
            where = target if target is not None else self.directory
            raise FileNotFoundError(
                f"no checkpoint at {where}: run the recipe once without resume=true, or point to an existing "
                "step_<N>.safetensors (or .pt) file."
            )
        return read_checkpoint(target)

    def load_latest_valid(self, check: Callable[[Any, Path], Any] | None = None) -> tuple[Path, Any]:
        """``(path, state)`` of the newest readable checkpoint, for ``resume=true``: an unreadable newer file is
        skipped with a warning naming it and, once a readable one is found, renamed ``<name>.unreadable`` (else it
        would stay the latest, the one loaders and the suite read); ``FileNotFoundError`` if there is none,
        :class:`CheckpointError` if none can be read (nothing is renamed then). ``check(state, path)`` (a format's
        :meth:`~umrl.checkpoints.CheckpointFormat.check`) returns the state or raises :class:`CheckpointError` for
        content that cannot be the run's (non-finite weights, sizes the tensors do not have): that file is skipped
        too."""
        self.remove_stale_tmp()
        found = self.all()
        if not found:
            return self.load()  # raises FileNotFoundError saying where it looked
        errors = []
        for path in reversed(found):
            try:
                state = read_checkpoint(path)
                if check is not None:
                    state = check(state, path)
            except CheckpointError as e:
                errors.append(str(e))
                warnings.warn(f"skipping unreadable checkpoint {path}; trying the previous one. ({e})", stacklevel=2)
                continue
            for skipped in found[found.index(path) + 1:]:
                skipped.rename(skipped.with_name(skipped.name + ".unreadable"))
                warnings.warn(f"moved the unreadable checkpoint {skipped} aside to {skipped.name}.unreadable; "
                              f"resuming from {path}.", stacklevel=2)
            return path, state
        raise CheckpointError("no readable checkpoint in " f"{self.directory}:\n" + "\n".join(errors))


def _is_regular_file(path: Path) -> bool:
    """Whether ``path`` itself is a regular file (a symlink is not), judged by ``os.lstat``: nothing is opened."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:  # gone meanwhile, or unreadable metadata
        return False


def checkpoint_path(path: Any) -> Path:
    """``path`` as a :class:`~pathlib.Path`; :class:`~umrl.validation.InvalidType` naming it when it is no path."""
    if not isinstance(path, (str, os.PathLike)):
        raise InvalidType("path", path, "a checkpoint file or run directory (a str or os.PathLike)")
    return Path(path)


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """``path`` if it is a checkpoint file, else the latest checkpoint (:meth:`Checkpointer.latest`) inside the
    directory ``path`` (or its ``checkpoints/`` subfolder). Raises ``FileNotFoundError`` saying what was looked for, and
    :class:`CheckpointError`, before opening anything, for a ``path`` that is neither a regular file (a symlink to
    one is followed) nor a folder, or is a folder named like a checkpoint.

    >>> resolve_checkpoint("/dev/null")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    umrl.checkpoints.file.CheckpointError: /dev/null is not a regular checkpoint file (a character device); ...
    """
    path = checkpoint_path(path)
    try:
        mode = os.stat(path).st_mode  # follows a symlink the user named, opens nothing
    except FileNotFoundError:
        mode = None
    except (OSError, ValueError) as e:  # a name too long, a loop of symlinks, a NUL byte: no file can be there
        raise CheckpointError(f"cannot read checkpoint {str(path)!r} (not opened): "
                              f"{e.strerror if isinstance(e, OSError) else e}.") from e
    if mode is not None and stat.S_ISREG(mode):
        return path
    if mode is not None and (not stat.S_ISDIR(mode) or Checkpointer._pattern.fullmatch(path.name)):
        raise CheckpointError(f"{path} is not a regular checkpoint file ({file_kind(mode)}); "
                              "give a step_<N>.safetensors (or .pt) file or a run folder.")
    for directory in (path, path / "checkpoints"):
        latest = Checkpointer(directory).latest()
        if latest is not None:
            return latest
    raise FileNotFoundError(f"no checkpoint file at {path} (looked for step_*.safetensors and step_*.pt in it and "
                            f"in {path / 'checkpoints'}).")
