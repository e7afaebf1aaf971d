"""Process-wide tuning, opt-in: what umrl's command lines and worker processes apply before they start working.

Importing umrl and calling its functions changes nothing outside their arguments. The settings below make the
process faster for umrl's workloads but reach everything else running in it, so only a program that owns the process
applies them: the recipes' ``main``, the benchmark suite's worker jobs (:func:`tuned_call`), the benchmark scripts.
A script of your own may call :func:`tune_process` first thing, or not at all (results are the same, only the speed
and the thread count's low digits differ).

- ``sys.modules[name] = None`` for optional packages a dependency looks up on every module call
  (:func:`umrl.absent_modules.mark_absent_modules`): up to 12 % of a point_nav collection's wall time.
- glibc keeps freed large blocks for reuse (:func:`umrl.heap.keep_freed_memory`): about a third of the paper-settings
  MAML learning step on 2 cores was page faults without it; the price is a higher resident peak.
- torch's intra-op thread count (``torch.set_num_threads``), e.g. a config's ``num_threads``: the low digits of the
  numbers depend on it.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from umrl.absent_modules import mark_absent_modules
from umrl.heap import keep_freed_memory as keep_freed_heap_memory
from umrl.validation import check_int

__all__ = ["tune_process", "tuned_call"]


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


def tuned_call(fn: Callable, num_threads: int | None, /, *args, **kwargs):
    """``fn(*args, **kwargs)`` after :func:`tune_process` (``num_threads``): a worker process's job, e.g.
    ``Job(fn=tuned_call, args=(run_cell, 1, spec))`` (pickles by reference like ``fn``)."""
    tune_process(num_threads=num_threads)
    return fn(*args, **kwargs)
