"""umrl.profiling: the benchmarks' device clock, matmul rate and FLOP counter."""
import torch

from umrl.profiling import device_clock, flop_counter, matmul_rate


def test_device_clock_advances_and_matmul_rate_is_a_plausible_flop_rate():
    cpu = torch.device("cpu")
    start = device_clock(cpu)
    rate = matmul_rate(cpu, 64, 32, 16, min_run_time=0.05)
    assert device_clock(cpu) > start
    assert 1e6 < rate < 1e14  # FLOP/s: above a megaflop, below any CPU's peak


def test_flop_counter_counts_in_place_matmuls_like_their_out_of_place_forms():
    a, b, c = torch.randn(4, 10, 5), torch.randn(4, 5, 6), torch.randn(4, 10, 6)
    x, y, z = torch.randn(10, 3), torch.randn(3, 5), torch.randn(10, 5)
    counts = []
    for in_place in (False, True):
        with flop_counter() as counter:
            if in_place:
                c.clone().baddbmm_(a, b)
                z.clone().addmm_(x, y)
            else:
                torch.baddbmm(c, a, b)
                torch.addmm(z, x, y)
        counts.append(counter.get_total_flops())
    assert counts == [2 * 4 * 10 * 5 * 6 + 2 * 10 * 3 * 5] * 2
