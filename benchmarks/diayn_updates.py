"""DIAYN's training loop for S seeds in one program: aggregate seed-updates/s against the arithmetic floor.

    python benchmarks/diayn_updates.py                                   # half_cheetah, S = 1 3 6, cpu, eager
    python benchmarks/diayn_updates.py --threads 2 --seeds 1 3 6 --repeats 7
    python benchmarks/diayn_updates.py --threads 2 --seeds 1 3 6 --repeats 5 --compile   # eager and compiled
    python benchmarks/diayn_updates.py --device cuda --seeds 1 4 8 --compile --cudagraphs

What is timed is :meth:`umrl.trainers.diayn.DIAYNTrainer.step` at the recipe's defaults (2x300 networks, batch 128,
one env copy per seed): one env step of every seed, then one fused update of all seeds, as in a run, with the env
stepping, the acting, the replay writes and samples included (``loop``), after the warm-up; and the update alone on
the same trainer's replay samples (``update``). One seed-update is one seed's SAC + discriminator update, so a
step of S seeds is S seed-updates. Beside them, ``sacloss`` is one seed's update through TorchRL's ``SACLoss``
(:class:`umrl.objectives.diayn.DIAYNUpdate`, the one-seed implementation) on the same sizes, update only. Variants
are built from the same seeds and their timed repeats (``--steps`` steps each) interleaved; medians of
``--repeats`` are printed, with ratios to S = 1 eager from the same run. ``--compile`` adds the variants with
``optim.compile=true`` (on a CPU: the hand-derived gradients compiled, :class:`StackedDIAYNUpdate`); ``setup s`` is a
variant's construction and warm-up (``--warmup`` steps after the random ones), which includes the compilation.

The **arithmetic floor** is one seed-update's FLOPs (``torch.utils.flop_counter.FlopCounterMode`` around one update
of one seed: the matmuls of forward and backward; Adam's element-wise work is not counted) divided by the matmul rate
of the update's own dominant GEMM ([batch, 300] @ [300, 300], ``torch.mm``), measured in every repeat of the same
run (median; its range is printed): ``floor seed-upd/s`` = rate / FLOPs, and ``of floor`` = seed-updates/s / that. Batched matmuls of several seeds can run above
that one-matrix rate, so ``of floor`` can exceed 1 at large S.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from umrl.envs import ENV_NAMES
from umrl.objectives.diayn import DIAYNUpdate, make_diayn_optimizers
from umrl.process import tune_process
from umrl.profiling import device_clock, matmul_rate
from umrl.trainers import compose
from umrl.trainers.diayn import DIAYNTrainer
from umrl.validation import resolve_device


class _GlobalOnly:
    """Stands in for FlopCounterMode's per-module tracker, which compares modules with ``==`` in a weak dict and so
    fails on TensorDict parameters; every FLOP is counted under "Global" only."""

    parents = ("Global",)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def count_flops(fn, *args) -> int:
    """Matmul FLOPs of ``fn(*args)`` (forward and backward)."""
    counter = FlopCounterMode(display=False)
    counter.mod_tracker = _GlobalOnly()
    with counter:
        fn(*args)
    return counter.get_total_flops()


class Variant:
    """A :class:`DIAYNTrainer` of ``num_seeds`` seeds, warmed up past its first updates."""

    def __init__(self, env_name: str, num_seeds: int, args, output_dir: Path, *, compile: bool,
                 cudagraphs: bool):
        self.name = "+".join(["eager"] * (not compile and not cudagraphs) + ["compile"] * compile
                             + ["cudagraphs"] * cudagraphs)
        self.num_seeds, self.device = num_seeds, torch.device(args.device)
        overrides = [
            f"env.name={env_name}", f"seeds=[{','.join(str(args.seed + s) for s in range(num_seeds))}]",
            f"device={args.device}", f"replay_buffer.batch_size={args.batch_size}",
            f"replay_buffer.size={args.buffer_size}", f"collector.init_random_frames={args.batch_size}",
            f"network.hidden=[{args.hidden},{args.hidden}]",
            f"network.discriminator_hidden=[{args.hidden},{args.hidden}]",
            "collector.total_frames=1000000000", "eval.every=1000000000", "checkpoint.every=1000000000",
            "log_every=1000000000", f"optim.compile={compile}", f"optim.cudagraphs={cudagraphs}",
            "logger.backend=none", "progress=false", f"output_dir={output_dir / f'{self.name}_S{num_seeds}'}",
        ]
        start = time.perf_counter()
        self.trainer = DIAYNTrainer(compose("diayn", overrides))
        self.steps(args.batch_size + args.warmup)  # the random warm-up, then compilation or capture
        self.setup_s = time.perf_counter() - start

    def steps(self, n: int) -> float:
        """Seconds for ``n`` trainer steps (device work included)."""
        start = device_clock(self.device)
        for _ in range(n):
            self.trainer.step()
        return device_clock(self.device) - start

    def updates(self, n: int) -> float:
        """Seconds for ``n`` updates on fresh replay samples (device work included)."""
        start = device_clock(self.device)
        for _ in range(n):
            self.trainer.update(self.trainer.replay.sample())
        return device_clock(self.device) - start


class SACLossVariant:
    """One seed's update through TorchRL's ``SACLoss`` (:class:`DIAYNUpdate`) on a replay sample of ``source``."""

    def __init__(self, source: Variant, args):
        trainer = source.trainer
        loss = trainer.seed_losses[0]
        loss.make_value_estimator(gamma=trainer.cfg.optim.gamma)
        self.update = DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=3e-4, discriminator_lr=3e-4), tau=0.01)
        self.sample = lambda: trainer.replay.sample()[0].exclude("action_noise", ("next", "action_noise")).set(
            ("next", "reward"), torch.zeros(args.batch_size, 1, device=source.device)).set(
            ("next", "done"), torch.zeros(args.batch_size, 1, dtype=torch.bool, device=source.device))
        self.device = source.device

    def updates(self, n: int) -> float:
        start = device_clock(self.device)
        for _ in range(n):
            self.update(self.sample())
        return device_clock(self.device) - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument("--envs", nargs="+", default=["half_cheetah"], choices=sorted(ENV_NAMES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 3, 6], help="numbers of seeds S to measure")
    parser.add_argument("--compile", action="store_true", help="also measure torch.compile'd updates")
    parser.add_argument("--cudagraphs", action="store_true", help="also measure CUDA-graph-captured updates")
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--hidden", type=int, default=300, help="width of the 2-layer networks")
    parser.add_argument("--buffer-size", type=int, default=100_000)
    parser.add_argument("--steps", type=int, default=100, help="trainer steps (and updates) per timed repeat")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps after the random warm-up")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.device = resolve_device("--device", args.device)
    device = torch.device(args.device)
    if args.cudagraphs and device.type != "cuda":
        raise SystemExit(f"--cudagraphs needs --device cuda (or auto on a GPU machine); got device {device}.")
    tune_process(num_threads=args.threads)  # as the recipes run
    modes = [(False, False)] + [(True, False)] * args.compile + [(False, True)] * args.cudagraphs
    modes += [(True, True)] * (args.compile and args.cudagraphs)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    gemm = f"[{args.batch_size},{args.hidden}]@[{args.hidden},{args.hidden}]"
    with tempfile.TemporaryDirectory() as tmp:
        for env_name in args.envs:
            variants = [Variant(env_name, s, args, Path(tmp), compile=c, cudagraphs=g) for c, g in modes
                        for s in args.seeds]
            one_seed = next((v for v in variants if v.num_seeds == 1 and v.name == "eager"), None)
            probe = one_seed or Variant(env_name, 1, args, Path(tmp), compile=False, cudagraphs=False)
            flops = count_flops(probe.trainer.update, probe.trainer.replay.sample())
            sacloss = SACLossVariant(probe, args)
            loops = {id(v): [] for v in variants}
            updates = {id(v): [] for v in variants}
            sac_times, rates = [], []
            for _ in range(args.repeats):  # the GEMM rate too: a shared machine's speed drifts between minutes
                rates.append(matmul_rate(device, args.batch_size, args.hidden, args.hidden))
                for variant in variants:
                    loops[id(variant)].append(variant.steps(args.steps))
                    updates[id(variant)].append(variant.updates(args.steps))
                sac_times.append(sacloss.updates(args.steps))
            rate = statistics.median(rates)
            floor = rate / flops
            print(f"device {name}; batch {args.batch_size}, networks 2x{args.hidden}; {gemm} matmul "
                  f"{rate / 1e9:.1f} GFLOP/s (median of {args.repeats}, {min(rates) / 1e9:.1f}-"
                  f"{max(rates) / 1e9:.1f}); {flops / 1e9:.3f} GFLOP per seed-update")
            print(f"{'env':<13} {'variant':<19} {'S':>3} {'loop s-upd/s':>13} {'update s-upd/s':>15} {'of floor':>9} "
                  f"{'vs S=1':>7} {'floor s-upd/s':>14} {'setup s':>8}")
            base = None
            for variant in variants:
                loop = args.steps * variant.num_seeds / statistics.median(loops[id(variant)])
                update = args.steps * variant.num_seeds / statistics.median(updates[id(variant)])
                base = loop if base is None and variant.num_seeds == min(args.seeds) else base
                print(f"{env_name:<13} {variant.name:<19} {variant.num_seeds:>3} {loop:>13.1f} {update:>15.1f} "
                      f"{loop / floor:>9.2f} {loop / base:>6.2f}x {floor:>14.0f} {variant.setup_s:>8.1f}")
            sac = args.steps / statistics.median(sac_times)
            print(f"{env_name:<13} {'sacloss (1 seed)':<19} {1:>3} {'':>13} {sac:>15.1f} {sac / floor:>9.2f} "
                  f"{'':>7} {floor:>14.0f}")


if __name__ == "__main__":
    main()
