"""DIAYN SAC + discriminator updates per second (2x300 networks, batch 256) against their arithmetic floor.

    python benchmarks/diayn_updates.py                                  # cpu, eager, point_nav and half_cheetah
    python benchmarks/diayn_updates.py --device auto --compile --cudagraphs --repeats 7
    python benchmarks/diayn_updates.py --device cpu --threads 2 --envs point_nav

One update is :class:`umrl.objectives.diayn.DIAYNUpdate` (relabel with the current D, SACLoss + D's cross-entropy,
backward, Adam steps, soft target update) on a batch drawn from a device-resident replay buffer of random
transitions, as in the recipe: ``point_nav`` (obs 2, act 2, 50 skills) and ``half_cheetah`` (obs 17, act 6, 20
skills). Variants: ``eager`` always; ``--compile`` adds ``compile``, ``--cudagraphs`` adds ``cudagraphs``, both add
``compile+cudagraphs``. Each variant gets its own networks from the same seed; their timed repeats (``--updates``
updates each, after ``--warmup`` untimed ones) are interleaved, and the medians of ``--repeats`` are printed with
ratios to ``eager`` from the same run.

The **arithmetic floor** is one update's FLOPs (``torch.utils.flop_counter.FlopCounterMode`` around an eager update:
matmuls of forward and backward; Adam's elementwise work is not counted) divided by the device's matmul rate measured
in the same run, twice: a large ``torch.mm`` (the device's peak) and the update's own dominant GEMM
([batch, 300] @ [300, 300], what these small layers can reach). ``updates/s`` at the floor is 1 / floor.
"""
from __future__ import annotations

import argparse
import statistics

import torch
from tensordict import TensorDict
from torch.utils.flop_counter import FlopCounterMode
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from umrl.envs import ENV_NAMES, get_env_spec
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives.diayn import DIAYNLoss, DIAYNUpdate, make_diayn_optimizers
from umrl.process import tune_process
from umrl.profiling import device_clock, matmul_rate
from umrl.validation import resolve_device

HIDDEN = (300, 300)


def random_transitions(env_name: str, obs_dim: int, act_dim: int, size: int) -> TensorDict:
    """``size`` random transitions (batch ``[size]``, on CPU) with the keys DIAYNLoss reads."""
    g = torch.Generator().manual_seed(0)
    num_skills = get_env_spec(env_name).num_skills
    skill = torch.eye(num_skills)[torch.randint(num_skills, (size,), generator=g)]
    data = TensorDict({
        "observation": torch.randn(size, obs_dim, generator=g), "skill": skill,
        "action": torch.rand(size, act_dim, generator=g) * 2 - 1,
        "next": {"observation": torch.randn(size, obs_dim, generator=g), "skill": skill,
                 "reward": torch.zeros(size, 1), "done": torch.zeros(size, 1, dtype=torch.bool),
                 "terminated": torch.zeros(size, 1, dtype=torch.bool)},
    }, [size])
    return data


class _GlobalOnly:
    """Stands in for FlopCounterMode's per-module tracker, which compares modules with ``==`` in a weak dict and so
    fails on the loss's ``TensorDictParams``; every FLOP is counted under "Global" only."""

    parents = ("Global",)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


class Variant:
    """One loss + optimisers + DIAYNUpdate (with its compile / cudagraphs options) and its replay buffer."""

    def __init__(self, name: str, env_name: str, obs_dim: int, act_dim: int, args, device: torch.device):
        self.name, self.device, self.batch_size = name, device, args.batch_size
        torch.manual_seed(args.seed)
        k = get_env_spec(env_name).num_skills
        loss = DIAYNLoss(make_skill_actor(obs_dim, k, act_dim, hidden=HIDDEN),
                         make_skill_qvalue(obs_dim, k, act_dim, hidden=HIDDEN),
                         make_discriminator(obs_dim, k, hidden=HIDDEN), num_skills=k)
        self.loss = loss.make_value_estimator(gamma=0.99).to(device)
        cudagraphs = "cudagraphs" in name
        optimizers = make_diayn_optimizers(self.loss, lr=3e-4, discriminator_lr=3e-4, capturable=cudagraphs)
        self.update = DIAYNUpdate(self.loss, optimizers, tau=0.01, compile="compile" in name, cudagraphs=cudagraphs)
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(args.buffer_size, device=device),
                                             batch_size=args.batch_size)
        self.buffer.extend(random_transitions(env_name, obs_dim, act_dim, args.buffer_size))

    def run(self, n: int) -> float:
        """Seconds for ``n`` sample + update steps (device work included)."""
        start = device_clock(self.device)
        for _ in range(n):
            out = self.update(self.buffer.sample())
        out["loss_qvalue"].item()  # one host sync per timing, as a recipe checking its losses once per batch
        return device_clock(self.device) - start

    def flops(self) -> int:
        """FLOPs of one eager update (forward + backward matmuls)."""
        counter = FlopCounterMode(display=False)
        counter.mod_tracker = _GlobalOnly()
        with counter:
            self.update._step(self.buffer.sample())
        return counter.get_total_flops()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument("--envs", nargs="+", default=["point_nav", "half_cheetah"], choices=sorted(ENV_NAMES))
    parser.add_argument("--compile", action="store_true", help="also measure torch.compile'd updates")
    parser.add_argument("--cudagraphs", action="store_true", help="also measure CUDA-graph-captured updates")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--buffer-size", type=int, default=100_000)
    parser.add_argument("--updates", type=int, default=50, help="updates per timed repeat")
    parser.add_argument("--warmup", type=int, default=10, help="untimed updates per variant (compile, capture)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    device = torch.device(resolve_device("--device", args.device))
    if args.cudagraphs and device.type != "cuda":
        raise SystemExit(f"--cudagraphs needs --device cuda (or auto on a GPU machine); got device {device}.")
    if args.threads:
        torch.set_num_threads(args.threads)
    tune_process()  # as the recipes run
    names = ["eager"] + (["compile"] if args.compile else []) + (["cudagraphs"] if args.cudagraphs else [])
    names += ["compile+cudagraphs"] if args.compile and args.cudagraphs else []
    peak = matmul_rate(device, 4096, 4096, 4096) if device.type == "cuda" else matmul_rate(device, 1024, 1024, 1024)
    small = matmul_rate(device, args.batch_size, HIDDEN[0], HIDDEN[1])
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(f"device {name}; batch {args.batch_size}, networks 2x{HIDDEN[0]}; matmul rate: peak {peak / 1e9:.1f} "
          f"GFLOP/s, [{args.batch_size},{HIDDEN[0]}]@[{HIDDEN[0]},{HIDDEN[1]}] {small / 1e9:.1f} GFLOP/s")
    print(f"{'env':<13} {'variant':<19} {'updates/s':>10} {'vs eager':>9} {'GFLOP/upd':>10} "
          f"{'floor@peak upd/s':>17} {'floor@gemm upd/s':>17}")
    for env_name in args.envs:
        env_spec = get_env_spec(env_name)
        obs_dim, act_dim = env_spec.obs_dim, env_spec.act_dim
        variants = [Variant(n, env_name, obs_dim, act_dim, args, device) for n in names]
        flops = variants[0].flops()
        for variant in variants:
            variant.run(args.warmup)
        times = {v.name: [] for v in variants}
        for _ in range(args.repeats):
            for variant in variants:
                times[variant.name].append(variant.run(args.updates))
        eager_rate = args.updates / statistics.median(times["eager"])
        for variant in variants:
            rate = args.updates / statistics.median(times[variant.name])
            print(f"{env_name:<13} {variant.name:<19} {rate:>10.1f} {rate / eager_rate:>8.2f}x {flops / 1e9:>10.3f} "
                  f"{peak / flops:>17.0f} {small / flops:>17.0f}")


if __name__ == "__main__":
    main()
