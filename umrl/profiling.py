"""Timing on any device (the recipes' ``time/`` metrics, TRPO's phases, the benchmarks): a clock that waits for
queued device work, the matmul rate that turns a FLOP count into an arithmetic floor, and the FLOP counter."""
from __future__ import annotations

import time

import torch
from torch.utils.benchmark import Timer
from torch.utils.flop_counter import FlopCounterMode, bmm_flop, mm_flop

__all__ = ["device_clock", "flop_counter", "matmul_rate"]


def _accumulated_bmm_flop(self_shape, a_shape, b_shape, *args, **kwargs) -> int:
    return bmm_flop(a_shape, b_shape)


def _accumulated_mm_flop(self_shape, a_shape, b_shape, *args, **kwargs) -> int:
    return mm_flop(a_shape, b_shape)


def flop_counter() -> FlopCounterMode:
    """A silent ``FlopCounterMode`` that also counts the in-place matmuls (``baddbmm_``, ``addmm_``), which torch's
    own table leaves out."""
    aten = torch.ops.aten
    return FlopCounterMode(display=False, custom_mapping={aten.baddbmm_: _accumulated_bmm_flop,
                                                          aten.addmm_: _accumulated_mm_flop})


def device_clock(device: torch.device) -> float:
    """Wait for the work queued on ``device`` (CUDA), then read ``time.perf_counter()``."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def matmul_rate(device: torch.device, m: int, k: int, n: int, *, min_run_time: float = 0.2) -> float:
    """Median FLOP/s of a float32 ``[m, k] @ [k, n]`` ``torch.mm`` on ``device`` at the current thread count
    (``torch.utils.benchmark.Timer``: it synchronises CUDA and picks the repeat count)."""
    a, b = torch.randn(m, k, device=device), torch.randn(k, n, device=device)
    timer = Timer("torch.mm(a, b)", globals={"torch": torch, "a": a, "b": b}, num_threads=torch.get_num_threads())
    return 2 * m * k * n / timer.blocked_autorange(min_run_time=min_run_time).median
