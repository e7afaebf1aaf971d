"""umrl.profiling: the benchmarks' device clock and matmul rate."""
import torch

from umrl.profiling import device_clock, matmul_rate


def test_device_clock_advances_and_matmul_rate_is_a_plausible_flop_rate():
    cpu = torch.device("cpu")
    start = device_clock(cpu)
    rate = matmul_rate(cpu, 64, 32, 16, min_run_time=0.05)
    assert device_clock(cpu) > start
    assert 1e6 < rate < 1e14  # FLOP/s: above a megaflop, below any CPU's peak
