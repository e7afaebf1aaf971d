"""Keep freed CPU memory in the process, so the next large tensor reuses it instead of page-faulting fresh memory.

glibc's ``malloc`` serves every request above its mmap threshold (at most 32 MB unless set) with a new ``mmap`` and
unmaps it on ``free``. The MAML learning step allocates and frees hundreds of tensors that size (one ``[T, N·H, 300]``
activation is 240 MB at the paper's point_nav settings), so the kernel zero-fills every one of them again, 4 KB per
page fault, serialised on the process's memory map. On the 2-core machine that kernel time was about a third of the
paper-settings learning step (README, "Latest performance figures"). :func:`keep_freed_memory` raises glibc's mmap
and trim thresholds (``mallopt``) so large blocks come from the heap and stay there once freed; results are
unchanged (only where tensors live changes).

The price is resident memory: the heap keeps its high-water mark and fragments, so a process's peak RSS grows
(measured in the README). umrl's command lines and the suite's workers apply it at start
(:func:`umrl.process.tune_process`); library calls never do. To keep
glibc's behaviour or choose your own, set glibc's own ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` or a
``glibc.malloc`` entry of ``GLIBC_TUNABLES`` in the environment: umrl then leaves ``malloc`` alone.
"""
from __future__ import annotations

import ctypes
import os

__all__ = ["USER_MALLOC_SETTINGS", "keep_freed_memory"]

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
_LIMIT = 2**31 - 1  # mallopt takes an int: blocks above 2 GiB still get their own mmap

USER_MALLOC_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
"""glibc environment variables that mean the user chose the malloc settings (as does ``glibc.malloc`` in
``GLIBC_TUNABLES``)."""


def keep_freed_memory() -> bool:
    """Make glibc keep freed blocks of any size below 2 GiB in the heap for reuse; process-wide, idempotent.

    Returns whether the setting was applied: ``False`` where the C library has no ``mallopt`` (macOS, Windows) or
    rejects it, and when the environment already sets glibc's malloc (see :data:`USER_MALLOC_SETTINGS`).
    """
    if any(name in os.environ for name in USER_MALLOC_SETTINGS) or "glibc.malloc" in os.environ.get(
        "GLIBC_TUNABLES", ""
    ):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library already loaded into this process
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # the trim threshold first: were the mmap threshold raised alone, freed heap tops would still be returned
    return bool(mallopt(M_TRIM_THRESHOLD, _LIMIT)) and bool(mallopt(M_MMAP_THRESHOLD, _LIMIT))
