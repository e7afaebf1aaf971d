"""One run per folder: a run (a trainer, the suite) holds an OS lock on ``<folder>/run.lock`` while it writes there.

The lock is ``fcntl.flock`` on a file opened with ``O_CREAT``. The kernel drops it when the holding process ends,
however it ends (``kill -9`` too), so a lock is never stale and a dead holder never blocks anyone. The file is never
deleted (a deleted lock file lets two processes each lock a file of that name) and its content, the holder's pid,
host and start time written once the lock is held, is read only to name the holder in a refusal: it decides
nothing. A lock belongs to one folder: the suite's lock does not cover the runs its jobs write in its subfolders.

A process that has not released a folder cannot lock it a second time (a second trainer into the folder of one not
yet closed is refused, naming this process). The one hand-over is :func:`reserve_folder`: a Hydra callback locks
the folder before Hydra writes into it (:mod:`umrl.configs.callbacks`), and the run the script then starts there
takes that lock over (:func:`lock_folder`).
"""
from __future__ import annotations

import fcntl
import functools
import os
import socket
import stat
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol, Self

from umrl.validation import InvalidValue

__all__ = ["LOCK_NAME", "FolderHoldsRun", "FolderInUse", "FolderLock", "claim_run_folder", "lock_folder",
           "releases_folder_on_error", "reserve_folder"]

LOCK_NAME = "run.lock"
"""The lock file's name inside the locked folder."""

_HOLDER_BYTES = 256
"""The most of a lock file read for the refusal message (its content is written by umrl, but trusted for nothing)."""

_reserved: dict[str, FolderLock] = {}
"""Locks this process took for a run it is about to start (:func:`reserve_folder`), by real folder path."""


class FolderInUse(RuntimeError):
    """Another process (or another run of this one) holds the folder's lock; the message names the holder."""


class FolderHoldsRun(FileExistsError):
    """A fresh run (``resume=false``) was pointed at a folder holding an earlier run's checkpoints."""


class FolderLock:
    """The lock of ``folder`` (``<folder>/run.lock``); ``key`` is the setting that named the folder, for messages.

    :meth:`acquire` takes it or raises :class:`FolderInUse`; :meth:`release` (idempotent) gives it back; as a
    context manager it holds the lock for the block (one already held, e.g. :func:`lock_folder`'s, is kept)."""

    def __init__(self, folder: str | os.PathLike, key: str = "output_dir"):
        self.folder, self.key = Path(folder), key
        self._fd: int | None = None

    @property
    def path(self) -> Path:
        return self.folder / LOCK_NAME

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> Self:
        """Create the folder if needed and lock it, then record this process as the holder."""
        self.folder.mkdir(parents=True, exist_ok=True)
        try:  # a symlink is refused (O_NOFOLLOW); a FIFO opens without waiting (O_NONBLOCK) and is refused below
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
        except OSError as err:
            raise self._bad_lock_file(err.strerror or str(err)) from None
        try:
            mode = os.fstat(fd).st_mode
            if not stat.S_ISREG(mode):
                raise self._bad_lock_file("not a regular file")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise FolderInUse(f"{self.key} {self.folder} is in use by {_holder(fd)}; choose another "
                                  f"{self.key} or wait") from None
        except BaseException:
            os.close(fd)
            raise
        started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {started}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Give the lock back (the file stays, emptied); nothing to do if it is not held."""
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.ftruncate(fd, 0)
            os.close(fd)  # closing the only descriptor of the open file releases the flock

    def _bad_lock_file(self, why: str) -> InvalidValue:
        return InvalidValue(self.key, str(self.folder), f"a folder whose {LOCK_NAME} is a regular file umrl can "
                            "open, or absent", note=f"{self.path}: {why}")

    def __enter__(self) -> Self:
        return self if self.held else self.acquire()

    def __exit__(self, *exc_info: object) -> None:
        self.release()


def _holder(fd: int) -> str:
    """Who holds the lock, as its holder wrote it (``pid N on <host> since <time>``), for a message only."""
    text = os.pread(fd, _HOLDER_BYTES, 0).decode(errors="replace").strip()
    if not text.startswith("pid ") or not text.isprintable():
        return "another process (it has not written its pid yet)"
    if text.split()[1] == str(os.getpid()) and socket.gethostname() in text:
        return f"this process ({text}): close the trainer that writes there first"
    return text


def _key(folder: str | os.PathLike) -> str:
    return os.path.realpath(folder)


def reserve_folder(lock: FolderLock) -> FolderLock:
    """Keep ``lock`` (held) for the run this process is about to start in its folder: the next :func:`lock_folder`
    of that folder in this process takes it over instead of being refused. Returns it (release it when the run
    ends; releasing twice is harmless)."""
    _reserved[_key(lock.folder)] = lock
    return lock


def lock_folder(folder: str | os.PathLike, key: str = "output_dir") -> FolderLock:
    """The lock of ``folder``, held: the one this process reserved for it (:func:`reserve_folder`), else newly
    acquired (:class:`FolderInUse` if another holds it)."""
    reserved = _reserved.pop(_key(folder), None)
    if reserved is not None and reserved.held:
        return reserved
    return FolderLock(folder, key).acquire()


class _Checkpoints(Protocol):
    def all(self) -> list[Path]: ...

    def remove_stale_tmp(self) -> None: ...


def claim_run_folder(folder: str | os.PathLike, *, resume: bool, checkpointers: Sequence[_Checkpoints]) -> FolderLock:
    """Lock a trainer's ``output_dir`` (:func:`lock_folder`), then, holding it: refuse a fresh run (``resume``
    false) where ``checkpointers`` find an earlier run's checkpoints (:class:`FolderHoldsRun`), and remove the
    temporary files an interrupted save left in their folders (no other run can be writing there now)."""
    lock = lock_folder(folder)
    try:
        earlier = [path for checkpointer in checkpointers for path in checkpointer.all()]
        if earlier and not resume:
            raise FolderHoldsRun(f"output_dir {lock.folder} holds checkpoints of an earlier run ({earlier[-1]}"
                                 f"{f' and {len(earlier) - 1} more' if len(earlier) > 1 else ''}): pass "
                                 "resume=true to continue it, or choose another output_dir")
        for checkpointer in checkpointers:
            checkpointer.remove_stale_tmp()
    except BaseException:
        lock.release()
        raise
    return lock


def releases_folder_on_error(init: Callable) -> Callable:
    """Decorate a trainer's ``__init__`` that sets ``self.folder_lock``: if construction fails after the folder was
    locked, the lock is released before the error propagates (a notebook can retry in the same folder)."""

    @functools.wraps(init)
    def wrapper(self, *args: Any, **kwargs: Any) -> None:
        try:
            init(self, *args, **kwargs)
        except BaseException:
            lock = getattr(self, "folder_lock", None)
            if lock is not None:
                lock.release()
            raise

    return wrapper
