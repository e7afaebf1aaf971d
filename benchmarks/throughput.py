"""Env-step throughput of umrl's CMPs, next to the raw speed of the same simulators, measured in one run.

Usage::

    python benchmarks/throughput.py                  # all envs, 5 repeats
    python benchmarks/throughput.py --quick          # short run (2 repeats, fewer steps)
    python benchmarks/throughput.py --envs half_cheetah --mujoco-batches 800 --repeats 7

Every configuration is timed ``--repeats`` times, interleaved (repeat r of every configuration runs before repeat
r + 1 of any), after one untimed warm-up call, with Python's garbage collector off inside each timed call (as
``timeit``); the table gives the median env steps/s and, per env and batch size,
the ratio to the reference row (``ref``). On a shared machine the absolute numbers are noisy: compare ratios.

Rows, per env and batch size ``B`` (policy = the 2x300 Gaussian MLP of :mod:`umrl.modules.policy`, sampled):

- point_nav: ``env._step`` alone (raw batched torch step), ``env.step`` alone (TorchRL's step), a bare torch loop
  with the policy (``ref``: MLP, sampling, log-prob, point update, stored trajectory), ``env.rollout`` with the
  policy, TorchRL ``Collector`` with the policy.
- half_cheetah / ant: ``mujoco.rollout`` open loop on all threads (``ref``: the physics limit), gymnasium's sync
  vector env stepped bare (random actions, no policy), the ``gym`` backend and the ``batched`` backend with the
  policy (``env.rollout``), and the batched backend alone (random actions); with ``--per-core``, also
  ``mujoco.rollout`` and the batched env on one thread each (per-core efficiency, free of thread scaling).

``--scaling`` prints a thread-scaling table instead, for half_cheetah and ant at ``B = --scaling-batch`` (800): at
1, 2, 4, 8, 16 threads (up to the usable CPUs, or the ``--threads-list``) the physics limit (``mujoco.rollout`` open
loop on that many threads), the batched backend alone (random actions) and with the 2x300 policy (``env.rollout``:
torch on one thread beside the physics, as umrl collects, see :mod:`umrl.envs.threads`; and torch on the same number
of threads as the physics), a candidate collector that is not umrl's ("2 shards": two half batches, one stepping on
a worker thread while the policy samples the other's actions), and their ratios to the limit; next to them the
bounds the policy's own
cost sets: the policy alone (sample for ``B`` observations, torch on one thread) takes ``t_p`` per step against the
limit's ``t_L``, so collecting with policy and physics one after the other (as umrl does) reaches at most
``t_L / (t_L + t_p)`` of the limit ("serial bound"), and with the policy's work perfectly overlapped with the physics
on ``n`` threads at most ``t_L / (t_L + t_p / n)`` ("overlap bound"); then the time to collect one paper-settings
half_cheetah meta-iteration (20 tasks x 40 trajectories x 100 steps, pre- and post-update: 160 k env steps) through
:func:`umrl.rollout.collect` with per-task parameters, on all the threads. The table of the repeats done so far is
printed after each repeat, so a run cut short by a time limit still reports (on 16 cores, 3 repeats of
``--mujoco-steps 100`` took 232 s without the 1-thread rows and over 330 s with them).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import gymnasium
import mujoco
import mujoco.rollout
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from umrl.envs import ENV_NAMES, make_env
from umrl.envs.mujoco_batched import BATCHED_ENVS, MODEL_SPECS
from umrl.envs.threads import torch_threads_beside_physics
from umrl.modules.policy import make_gaussian_policy
from umrl.process import tune_process
from umrl.rollout import collect

warnings.filterwarnings("ignore", message=".*settotalmass.*")

ALL_ENVS = tuple(ENV_NAMES)
NUM_CPUS = len(os.sched_getaffinity(0))
GYM_VEC = "gymnasium sync vector env, bare"

# A benchmark is (env, batch, label, is_reference, setup) where setup() returns run() -> number of env steps.
Bench = tuple[str, int, str, bool, Callable[[], Callable[[], int]]]


def _policy(env):
    return make_gaussian_policy(env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1])


def _rollout(name: str, batch: int, steps: int, backend: str, with_policy: bool):
    def setup():
        env = make_env(name, batch, seed=0, horizon=10**6, backend=backend)
        policy = _policy(env) if with_policy else None

        def run() -> int:
            env.rollout(steps, policy, break_when_any_done=False)
            return batch * steps

        return run

    return setup


def _env_step_only(name: str, batch: int, steps: int, raw: bool):
    """``steps`` calls of the base env's ``_step`` (raw) or ``step`` on a fixed action."""

    def setup():
        env = make_env(name, batch, seed=0, horizon=10**6).base_env
        td = env.reset()
        td["action"] = env.action_spec.rand()
        step = env._step if raw else env.step

        def run() -> int:
            for _ in range(steps):
                step(td)
            return batch * steps

        return run

    return setup


def _batched_one_thread(name: str, batch: int, steps: int):
    """The batched env (no StepCounter) stepped on one thread with a fixed random action: per-core efficiency."""

    def setup():
        env = BATCHED_ENVS[name](batch, seed=0, num_threads=1)
        td = env.reset()
        td["action"] = env.action_spec.rand()

        def run() -> int:
            for _ in range(steps):
                env.step(td)
            return batch * steps

        return run

    return setup


def _bare_point_loop(batch: int, steps: int):
    """The reference for point_nav: the policy's own modules and the point update, no TorchRL env in between."""

    def setup():
        net = (
            _policy(make_env("point_nav", 1)).module[0].module
        )  # MLP + state-independent scale -> (loc, scale)

        def run() -> int:
            pos = torch.zeros(batch, 2)
            obs, actions, log_probs = [], [], []
            for _ in range(steps):
                loc, scale = net(pos)
                action = loc + scale * torch.randn_like(loc)
                log_probs.append(torch.distributions.Normal(loc, scale).log_prob(action).sum(-1))
                obs.append(pos)
                actions.append(action)
                pos = pos + 0.1 * action.clamp(-1.0, 1.0)
            torch.stack(obs, 1), torch.stack(actions, 1), torch.stack(log_probs, 1)
            return batch * steps

        return run

    return setup


def _collector(name: str, batch: int, steps: int):
    def setup():
        env = make_env(name, batch, seed=0, horizon=10**6)
        collector = Collector(
            env,
            _policy(env),
            frames_per_batch=batch * steps,
            total_frames=-1,
            auto_register_policy_transforms=False,
        )
        batches = iter(collector)

        def run() -> int:
            return next(batches).numel()

        return run

    return setup


def _physics_limit(name: str, batch: int, steps: int, threads: int):
    """``mujoco.rollout`` of ``batch`` copies for ``steps`` env steps (frame_skip substeps each), random controls."""

    def setup():
        model = BATCHED_ENVS[name](1).model
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        data = mujoco.MjData(model)
        state0 = np.empty((batch, mujoco.mj_stateSize(model, spec)))
        mujoco.mj_getState(model, data, state0[0], spec)
        state0[:] = state0[0]
        nstep = MODEL_SPECS[name].frame_skip * steps
        rng = np.random.default_rng(0)
        control = np.repeat(
            rng.uniform(-1, 1, (batch, steps, model.nu)), MODEL_SPECS[name].frame_skip, axis=1
        )
        out_state = np.empty((batch, nstep, state0.shape[1]))
        out_sensor = np.empty((batch, nstep, model.nsensordata))
        pool = mujoco.rollout.Rollout(nthread=threads if threads > 1 else 0)
        datas = [mujoco.MjData(model) for _ in range(max(threads, 1))]
        models = [model] * batch

        def run() -> int:
            pool.rollout(
                models,
                datas,
                state0,
                control,
                nstep=nstep,
                state=out_state,
                sensordata=out_sensor,
                skip_checks=True,
            )
            return batch * steps

        return run

    return setup


def _bare_gym_vector(name: str, batch: int, steps: int):
    def setup():
        spec = MODEL_SPECS[name]
        # gymnasium's own autoreset (a terminated Ant copy restarts), as a user of the bare vector env would step it
        envs = gymnasium.make_vec(spec.gym_id, num_envs=batch, vectorization_mode="sync", **spec.gym_kwargs)
        envs.reset(seed=0)
        actions = (
            np.random.default_rng(0).uniform(-1, 1, (steps, *envs.action_space.shape)).astype(np.float32)
        )

        def run() -> int:
            for action in actions:
                envs.step(action)
            return batch * steps

        return run

    return setup


def build_benchmarks(args) -> list[Bench]:
    benches: list[Bench] = []
    if "point_nav" in args.envs:
        steps = 100 if args.quick else args.point_steps
        for b in args.point_batches:
            benches += [
                (
                    "point_nav",
                    b,
                    "env._step alone (raw torch)",
                    False,
                    _env_step_only("point_nav", b, steps, True),
                ),
                (
                    "point_nav",
                    b,
                    "env.step alone (TorchRL)",
                    False,
                    _env_step_only("point_nav", b, steps, False),
                ),
                ("point_nav", b, "bare torch loop + policy", True, _bare_point_loop(b, steps)),
                (
                    "point_nav",
                    b,
                    "env.rollout + policy",
                    False,
                    _rollout("point_nav", b, steps, "default", True),
                ),
                ("point_nav", b, "Collector + policy", False, _collector("point_nav", b, steps)),
            ]
    for name in ("half_cheetah", "ant"):
        if name not in args.envs:
            continue
        for b in args.mujoco_batches:
            steps = max(2, (args.mujoco_steps // (4 if name == "ant" else 1)) // (4 if args.quick else 1))
            benches += [
                (
                    name,
                    b,
                    f"mujoco.rollout open loop, {args.threads} thr",
                    True,
                    _physics_limit(name, b, steps, args.threads),
                ),
                (name, b, GYM_VEC, False, _bare_gym_vector(name, b, steps)),
                (name, b, "gym backend + policy", False, _rollout(name, b, steps, "gym", True)),
                (name, b, "batched backend + policy", False, _rollout(name, b, steps, "batched", True)),
                (name, b, "batched backend alone", False, _rollout(name, b, steps, "batched", False)),
            ]
            if args.per_core:
                benches += [
                    (name, b, "mujoco.rollout open loop, 1 thr", False, _physics_limit(name, b, steps, 1)),
                    (name, b, "batched env.step alone, 1 thr", False, _batched_one_thread(name, b, steps)),
                ]
    return benches


def run_benchmarks(benches: list[Bench], repeats: int,
                   after_repeat: Callable[[dict[int, list[float]]], None] | None = None) -> dict[int, list[float]]:
    """Median-ready steps/s: ``{bench index: [steps/s per repeat]}``, configurations interleaved; ``after_repeat``
    is called with the rates so far after every repeat."""
    runs = {}
    for i, (*_, setup) in enumerate(benches):
        runs[i] = setup()
        runs[i]()  # warm-up, untimed
    rates: dict[int, list[float]] = {i: [] for i in runs}
    for r in range(repeats):
        print(f"repeat {r + 1}/{repeats}", file=sys.stderr, flush=True)
        for i, run in runs.items():
            gc.disable()  # as timeit does: a collection of earlier garbage would land in one timed call
            try:
                start = time.perf_counter()
                n = run()
                rates[i].append(n / (time.perf_counter() - start))
            finally:
                gc.enable()
        if after_repeat is not None:
            after_repeat(rates)
    return rates


def format_table(benches: list[Bench], rates: dict[int, list[float]]) -> str:
    """One row per configuration: median, spread, ratio to the ``ref`` row and, for MuJoCo, to bare gymnasium."""
    medians = [statistics.median(rates[i]) for i in range(len(benches))]
    ref = {(e, b): medians[i] for i, (e, b, _, is_ref, _) in enumerate(benches) if is_ref}
    gym_vec = {(e, b): medians[i] for i, (e, b, label, *_) in enumerate(benches) if label.startswith(GYM_VEC)}
    header = f"{'env':<13}{'B':>6}  {'configuration':<36}{'median steps/s':>15}{'min .. max':>26}"
    lines = [header + f"{'x ref':>7}{'x gym vec':>11}"]
    for i, (env, b, label, is_ref, _) in enumerate(benches):
        spread = f"{min(rates[i]):,.0f} .. {max(rates[i]):,.0f}"
        ratio = "ref" if is_ref else f"{medians[i] / ref[(env, b)]:.2f}"
        vs_gym = f"{medians[i] / gym_vec[(env, b)]:.2f}" if (env, b) in gym_vec else "-"
        lines.append(f"{env:<13}{b:>6}  {label:<36}{medians[i]:>15,.0f}{spread:>26}{ratio:>7}{vs_gym:>11}")
    return "\n".join(lines)


def _batched(name: str, batch: int, steps: int, threads: int, policy_threads: str | None):
    """The batched backend on ``threads`` threads, ``env.rollout`` alone (``policy_threads=None``) or with the
    policy, torch on one thread beside the physics as umrl collects (``"umrl"``) or on ``threads`` (``"all"``)."""

    def setup():
        env = BATCHED_ENVS[name](batch, seed=0, num_threads=threads)
        policy = _policy(env) if policy_threads else None
        beside = torch_threads_beside_physics if policy_threads == "umrl" else contextlib.nullcontext

        def run() -> int:
            torch.set_num_threads(threads)
            with beside(env):
                env.rollout(steps, policy, break_when_any_done=False)
            return batch * steps

        return run

    return setup


def _two_shards(name: str, batch: int, steps: int, threads: int):
    """A candidate collector, not umrl's: two envs of ``batch / 2`` copies on ``threads`` physics threads each, one
    shard's ``env.step`` on a worker thread (MuJoCo releases the GIL) while the main thread samples the other shard's
    actions, torch on one thread. It measures how much of the policy's cost overlapping hides ("overlap bound").
    (TorchRL's ``AsyncEnvPool(backend="threading")`` would be the pool, but in torchrl 0.14.1 its per-env send
    fails for envs with a batch size of their own.)"""

    def setup():
        envs = [BATCHED_ENVS[name](batch // 2, seed=i, num_threads=threads) for i in range(2)]
        policy, worker = _policy(envs[0]), ThreadPoolExecutor(1)

        def run() -> int:
            torch.set_num_threads(threads)
            with torch_threads_beside_physics(envs[0]):
                tds = [policy(env.reset()) for env in envs]
                stepping = worker.submit(envs[0].step, tds[0])
                for t in range(steps):
                    last = t + 1 == steps
                    for i in (0, 1):  # shard i's step ends; shard 1 - i steps while shard i's actions are sampled
                        stepped = stepping.result()
                        if i == 0 or not last:
                            stepping = worker.submit(envs[1 - i].step, tds[1 - i])
                        if not last:  # as env.rollout: one policy call per step
                            tds[i] = policy(step_mdp(stepped))
            return 2 * (batch // 2) * steps

        return run

    return setup


def _policy_only(name: str, batch: int, steps: int):
    """The 2x300 policy sampling actions for ``batch`` observations of ``name``, ``steps`` times, torch on one thread."""

    def setup():
        env = BATCHED_ENVS[name](batch, seed=0, num_threads=1)
        policy, td = _policy(env), env.reset()

        def run() -> int:
            torch.set_num_threads(1)
            for _ in range(steps):
                policy(td)
            return batch * steps

        return run

    return setup


def scaling_table(args, repeats: int) -> str:
    """Thread-scaling rows per (env, threads): physics limit, batched alone, batched + policy, ratios. The table of
    the repeats done so far is printed after each one, so a run stopped by a time limit still reports."""
    batch = args.scaling_batch
    threads = args.threads_list or [t for t in (1, 2, 4, 8, 16, 32, 64) if t <= NUM_CPUS]
    benches: list[Bench] = []
    for name in ("half_cheetah", "ant"):
        steps = max(2, (args.mujoco_steps // (4 if name == "ant" else 1)) // (4 if args.quick else 1))
        for t in threads:
            benches += [
                (name, t, "limit", True, _physics_limit(name, batch, steps, t)),
                (name, t, "alone", False, _batched(name, batch, steps, t, None)),
                (name, t, "policy", False, _batched(name, batch, steps, t, "umrl")),
                (name, t, "policy, torch all", False, _batched(name, batch, steps, t, "all")),
                (name, t, "two shards", False, _two_shards(name, batch, steps, t)),
                (name, t, "policy only", False, _policy_only(name, batch, steps)),
            ]

    def table(rates: dict[int, list[float]]) -> str:
        done = len(rates[0])
        med = {(e, t, label): statistics.median(rates[i]) for i, (e, t, label, *_) in enumerate(benches)}
        lines = [
            f"thread scaling, B={batch}, env steps/s (medians of {done} interleaved repeats"
            + ("" if done == repeats else f", {repeats - done} to go") + ")",
            f"{'env':<13}{'threads':>8}{'mujoco.rollout limit':>22}{'batched alone':>15}{'batched + policy':>18}"
            + f"{'alone/limit':>13}{'policy/limit':>14}{'torch all thr/limit':>21}{'2 shards/limit':>16}"
            + f"{'serial bound':>14}"
            + f"{'overlap bound':>15}",
        ]
        for name, t in dict.fromkeys((e, t) for e, t, *_ in benches):
            limit, alone, policy, policy_all, shards, policy_only = (
                med[(name, t, k)]
                for k in ("limit", "alone", "policy", "policy, torch all", "two shards", "policy only")
            )
            t_limit, t_policy = 1 / limit, 1 / policy_only  # seconds per env step of each, same batch
            lines.append(
                f"{name:<13}{t:>8}{limit:>22,.0f}{alone:>15,.0f}{policy:>18,.0f}{alone / limit:>13.2f}"
                f"{policy / limit:>14.2f}{policy_all / limit:>21.2f}{shards / limit:>16.2f}"
                f"{t_limit / (t_limit + t_policy):>14.2f}"
                f"{t_limit / (t_limit + t_policy / t):>15.2f}"
            )
        return "\n".join(lines)

    def report(rates: dict[int, list[float]]) -> None:
        if len(rates[0]) < repeats:
            print(table(rates), flush=True)

    return table(run_benchmarks(benches, repeats, after_repeat=report))


def meta_iteration_collection(threads: int, repeats: int, num_tasks: int = 20, per_task: int = 40,
                              horizon: int = 100) -> tuple[float, int]:
    """Median seconds to collect a paper-settings half_cheetah meta-iteration (pre- and post-update batches)."""
    torch.set_num_threads(threads)
    env = TransformedEnv(
        BATCHED_ENVS["half_cheetah"](num_tasks * per_task, seed=0, num_threads=threads), StepCounter(horizon)
    )
    policy = _policy(env)
    params = TensorDict.from_module(policy).data.expand(num_tasks).clone()  # per-task (adapted) parameters
    times = []
    for _ in range(repeats + 1):  # the first is a warm-up
        start = time.perf_counter()
        for p in (None, params):
            collect(env, policy, num_tasks=num_tasks, horizon=horizon, params=p)
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:]), 2 * num_tasks * per_task * horizon


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", choices=ALL_ENVS, default=list(ALL_ENVS))
    parser.add_argument("--quick", action="store_true", help="2 repeats and fewer steps per repeat")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--point-batches", type=int, nargs="+", default=[100, 800, 4000])
    parser.add_argument("--point-steps", type=int, default=200)
    parser.add_argument("--mujoco-batches", type=int, nargs="+", default=[20, 800])
    parser.add_argument("--mujoco-steps", type=int, default=40, help="env steps per repeat (ant: a quarter)")
    parser.add_argument(
        "--threads", type=int, default=NUM_CPUS, help="mujoco.rollout threads (physics limit)"
    )
    parser.add_argument(
        "--per-core", action="store_true", help="add 1-thread rows: mujoco.rollout and the batched env alone"
    )
    parser.add_argument("--torch-threads", type=int, default=1, help="torch intra-op threads (policy)")
    parser.add_argument("--scaling", action="store_true", help="the thread-scaling table (see the docstring)")
    parser.add_argument("--scaling-batch", type=int, default=800, help="B of the thread-scaling table")
    parser.add_argument(
        "--threads-list", type=int, nargs="+", default=None, help="thread counts of the scaling table"
    )
    args = parser.parse_args()
    tune_process()  # as the recipes run
    if args.scaling:
        repeats = 2 if args.quick else args.repeats
        print(f"umrl thread scaling: {NUM_CPUS} CPUs usable")
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            print(scaling_table(args, repeats))
            seconds, steps = meta_iteration_collection(max(args.threads_list or [NUM_CPUS]), repeats)
        print(f"half_cheetah meta-iteration collection (umrl.rollout.collect, per-task params): {steps:,} env steps "
              f"in {seconds:.2f} s ({steps / seconds:,.0f} steps/s), {max(args.threads_list or [NUM_CPUS])} threads")
        return
    torch.set_num_threads(args.torch_threads)
    repeats = 2 if args.quick else args.repeats
    torch.manual_seed(0)
    benches = build_benchmarks(args)
    print(
        f"umrl throughput: {NUM_CPUS} CPUs usable, torch threads {torch.get_num_threads()}, "
        f"{repeats} interleaved repeats, medians; ratios are to the 'ref' row of the same env and B."
    )
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        rates = run_benchmarks(benches, repeats)
    print(format_table(benches, rates))


if __name__ == "__main__":
    main()
