"""Process-wide tuning, opt-in: what umrl's command lines and worker processes apply before they start working.

Importing umrl and calling its functions changes nothing outside their arguments. The settings below make the
process faster for umrl's workloads but reach everything else running in it, so only a program that owns the process
applies them: the command lines (:mod:`umrl.cli`), the benchmark suite's worker jobs (:func:`tuned_call`), the
benchmark scripts.
A script of your own may call :func:`tune_process` first thing, or not at all. The torch thread count changes the
rounding, from which runs drift apart, and the speed (the quick start at torch's default count on 2 busy cores: 146 s
of CPU instead of 15 s), so a Python run gives the command line's numbers under the same count:
``with torch_threads(cfg.num_threads):`` around it (:func:`torch_threads`, restored on exit) or
``tune_process(num_threads=...)``.

- ``sys.modules[name] = None`` for optional packages a dependency looks up on every module call
  (:func:`umrl.absent_modules.mark_absent_modules`): up to 12 % of a point_nav collection's wall time.
- glibc keeps freed large blocks for reuse (:func:`umrl.heap.keep_freed_memory`): about a third of the paper-settings
  MAML learning step on 2 cores was page faults without it; the price is a higher resident peak.
- torch's intra-op thread count (``torch.set_num_threads``), e.g. a config's ``num_threads``: the numbers depend on
  it (above).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch

from umrl.absent_modules import mark_absent_modules
from umrl.heap import keep_freed_memory as keep_freed_heap_memory
from umrl.validation import check_int

__all__ = ["torch_threads", "tune_process", "tuned_call"]


def tune_process(*, num_threads: int | None = None, keep_freed_memory: bool = True) -> dict[str, Any]:
    """Apply umrl's process-wide settings (module docstring); idempotent. Returns what was applied.

    Keyword Args:
        num_threads: ``torch.set_num_threads(num_threads)`` (>= 1); ``None`` leaves torch's count.
        keep_freed_memory: raise glibc's mmap and trim thresholds (:func:`umrl.heap.keep_freed_memory`; a no-op
            where the environment sets glibc's malloc or the C library has no ``mallopt``).
    """
    if num_threads is not None:
        num_threads = check_int("num_threads", num_threads, min=1)
    applied: dict[str, Any] = {"absent_modules": mark_absent_modules()}
    applied["kept_freed_memory"] = keep_freed_heap_memory() if keep_freed_memory else False
    if num_threads is not None:
        torch.set_num_threads(num_threads)
        applied["num_threads"] = num_threads
    return applied


@contextmanager
def torch_threads(num_threads: int | None) -> Iterator[None]:
    """Run the block on ``num_threads`` torch intra-op threads (``None``: leave the count), the count before restored
    on exit, also after an error: a run from Python with a config's ``num_threads``, as its command line runs it.

    Example:
        >>> before = torch.get_num_threads()
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
        >>> torch.get_num_threads() == before
        True
    """
    if num_threads is not None:
        num_threads = check_int("num_threads", num_threads, min=1)
    previous = torch.get_num_threads()
    if num_threads is None or num_threads == previous:
        yield
        return
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def tuned_call(fn: Callable, num_threads: int | None, /, *args, **kwargs):
    """``fn(*args, **kwargs)`` after :func:`tune_process` (``num_threads``): a worker process's job, e.g.
    ``Job(fn=tuned_call, args=(run_cell, 1, spec))`` (pickles by reference like ``fn``)."""
    tune_process(num_threads=num_threads)
    return fn(*args, **kwargs)
