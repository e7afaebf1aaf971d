"""SIGTERM and SIGINT during training: finish the current step, save, stop with one line.

The trainers' ``train()`` loops run inside :func:`stop_requests`: while it is active the first SIGTERM or SIGINT
only sets a flag, the loop ends after the step in progress (an env step batch, a meta-iteration), the trainer writes
a checkpoint and raises :class:`TrainingStopped`, a ``SystemExit`` with status 128 + the signal's number (143 for
SIGTERM, 130 for SIGINT: the shell's and schedulers' convention for "ended by this signal", so a ``&&`` chain or a
job system sees a run that did not finish) after printing one line to stderr: no traceback. ``resume=true`` continues
from that checkpoint. A second signal stops at once (``KeyboardInterrupt``, nothing more saved).

The handlers exist only inside the block, in the main thread (elsewhere signals cannot be handled and the block
changes nothing); the previous handlers are restored when it ends. Importing umrl or building a trainer changes no
signal handling.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = ["STOP_SIGNALS", "StopRequest", "TrainingStopped", "stop_requests"]

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class TrainingStopped(SystemExit):
    """A training loop stopped by ``signum`` after saving ``checkpoint``; exit status ``128 + signum``."""

    def __init__(self, signum: int, message: str, checkpoint: str | os.PathLike | None):
        super().__init__(128 + signum)
        self.signum, self.message, self.checkpoint = signum, message, checkpoint

    def __str__(self) -> str:
        return self.message


class StopRequest:
    """Whether a stop signal arrived inside :func:`stop_requests` (true once one did); ``signum`` is its number."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __bool__(self) -> bool:
        return self.signum is not None

    def handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt(f"{signal.Signals(signum).name} again: stopped at once")
        self.signum = signum

    def stopped(self, where: str, checkpoint: str | os.PathLike | None) -> TrainingStopped:
        """Print the one-line message (``where`` the run stopped, the ``checkpoint`` it saved) and return the
        exception to raise."""
        name = signal.Signals(self.signum).name
        message = (f"stopped by {name} {where}; saved {checkpoint}; continue with resume=true (same output_dir)")
        print(message, file=sys.stderr, flush=True)
        return TrainingStopped(self.signum, message, checkpoint)


@contextmanager
def stop_requests(signals: tuple[int, ...] = STOP_SIGNALS) -> Iterator[StopRequest]:
    """Inside the block, ``signals`` set the yielded :class:`StopRequest` instead of ending the process (main
    thread only; elsewhere the request never becomes true); the previous handlers come back when it ends."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = {signum: signal.signal(signum, request.handle) for signum in signals}
    try:
        yield request
    finally:
        for signum, handler in previous.items():  # None: a handler set outside Python, which cannot be restored
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
