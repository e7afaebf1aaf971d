"""Timing on any device, for the benchmarks: a clock that waits for queued device work, and the matmul rate that
turns a FLOP count into an arithmetic floor."""
from __future__ import annotations

import statistics
import time

import torch

__all__ = ["device_clock", "matmul_rate"]


def device_clock(device: torch.device) -> float:
    """Wait for the work queued on ``device`` (CUDA), then read ``time.perf_counter()``."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def matmul_rate(device: torch.device, m: int, k: int, n: int, repeats: int = 5) -> float:
    """Median FLOP/s of a float32 ``[m, k] @ [k, n]`` ``torch.mm`` on ``device`` at the current thread count (each
    timing repeats the product up to ~2 GFLOP, so small shapes are not lost in the clock's resolution)."""
    a, b = torch.randn(m, k, device=device), torch.randn(k, n, device=device)
    flops = 2 * m * k * n
    inner = max(1, int(2e9 // flops))
    torch.mm(a, b)
    times = []
    for _ in range(repeats):
        start = device_clock(device)
        for _ in range(inner):
            torch.mm(a, b)
        times.append((device_clock(device) - start) / inner)
    return flops / statistics.median(times)
