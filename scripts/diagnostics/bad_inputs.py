"""Feeds the recipes, the suite and the Python API bad inputs, and sorts what each does into clear / obscure / silent.

    python scripts/diagnostics/bad_inputs.py                  # every case, a line each, then the counts
    python scripts/diagnostics/bad_inputs.py --only seed      # the cases whose label contains "seed"

Each case runs in a fresh ``python`` process (a recipe or suite command line, or a Python snippet) under a time limit,
in a temporary directory; a few small runs made first give the cases a real MAML and DIAYN checkpoint to misuse.
A case expects one of three outcomes, and is

- **clear** when it got it: ``refuse`` exits non-zero with a line in umrl's format (``<key>: got …; expected …``, or
  a checkpoint's ``cannot read checkpoint <path> (<size> bytes): <why>``);
  ``warn`` exits 0 having printed such a line; ``run`` exits 0 (a legal value that used to crash);
- **obscure** when it exits non-zero without such a line, or runs past the time limit;
- **silent** when a ``refuse`` or ``warn`` case exits 0 without a word in that format.

The cases are the kinds a new user (and an attacker) tries: values out of range, sizes no machine holds, names that
are paths, checkpoints of another env or method, corrupt or crafted files, misuse of the Python API.
"""
from __future__ import annotations

import argparse
import itertools
import os
import re
import subprocess
import sys
import tempfile
import textwrap
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
MESSAGE = re.compile(r"\S: got .*; expected |cannot read checkpoint \S+ \(\d+ bytes\): ")  # a checkpoint's own errors
MAML_TINY = ["+profile=maml_tiny", "iterations=2", "logger.backend=none", "progress=false"]
DIAYN_TINY = ["+profile=diayn_tiny", "logger.backend=none", "progress=false"]
VIME_TINY = ["+profile=vime_tiny", "iterations=1", "logger.backend=none", "progress=false"]
_RUN_DIRS = itertools.count()  # a fresh output_dir per case
SUITE_TINY = ["profile=tiny", "methods=[scratch]", "ablation.enabled=false", "launcher.workers=0"]


@dataclass(frozen=True)
class Case:
    """One bad input: ``argv`` after ``python`` (``{tmp}`` is the probe's directory), the outcome it should have."""

    label: str
    expect: str  # refuse | warn | run
    argv: tuple[str, ...]


def recipe(name: str, *overrides: str, expect: str = "refuse", label: str | None = None) -> Case:
    tiny = {"maml": MAML_TINY, "diayn": DIAYN_TINY, "vime": VIME_TINY}[name]
    out = () if any(o.startswith("output_dir=") for o in overrides) else (f"output_dir={{tmp}}/{name}_{next(_RUN_DIRS)}",)
    argv = ("recipes/" + name + ".py", *tiny, *out, *overrides)
    return Case(label or f"{name} {' '.join(overrides)}", expect, argv)


def suite(*overrides: str, expect: str = "refuse") -> Case:
    argv = ("benchmarks/suite.py", *SUITE_TINY, f"output_dir={{tmp}}/suite_{next(_RUN_DIRS)}", *overrides)
    return Case(f"suite {' '.join(overrides)}", expect, argv)


def snippet(label: str, code: str, expect: str = "refuse") -> Case:
    return Case(label, expect, ("-c", textwrap.dedent(code)))


SETUP = (  # runs the cases misuse: a tiny MAML oracle run, a half_cheetah one, a DIAYN run
    ("recipes/maml.py", *MAML_TINY, "proposal=oracle", "checkpoint.keep_all=true", "output_dir={tmp}/oracle"),
    ("recipes/maml.py", *MAML_TINY, "env.name=half_cheetah", "proposal=random", "num_skills=5", "env.horizon=10",
     "iterations=1", "output_dir={tmp}/cheetah"),
    ("recipes/diayn.py", *DIAYN_TINY, "output_dir={tmp}/diayn"),
)

CRAFTED = """
import pickle, torch
class Payload:
    def __reduce__(self):
        return (open, ("{tmp}/pwned", "w"))
torch.save({{"policy": Payload()}}, "{tmp}/crafted.pt")
"""

CASES = [
    # values out of range, or legal values that used to fail deep inside
    recipe("maml", "advantage.gamma=0", expect="run"),
    recipe("maml", "advantage.lmbda=0", expect="run"),
    recipe("vime", "trpo.gamma=0", expect="run"),
    recipe("vime", "trpo.gae_lambda=0", expect="run"),
    suite("protocol.gamma=0", "protocol.lmbda=0", expect="run"),
    recipe("maml", "seed=99999999999999999999"),
    recipe("diayn", "seed=99999999999999999999"),
    recipe("maml", "maml.inner_lr=1e30"),
    recipe("diayn", "optim.alpha=0"),
    recipe("diayn", "optim.compile=true"),
    recipe("maml", "proposal=oracle", "num_skills=7"),
    recipe("diayn", "collector.init_random_frames=100000"),
    recipe("diayn", "optim.updates_per_frame=1e-9"),
    recipe("diayn", "collector.total_frames=100", "collector.init_random_frames=0", "collector.frames_per_batch=400",
           "replay_buffer.batch_size=32", expect="warn"),
    suite("launcher.ray_address=foo"),
    suite("seeds=[99999999999999999999]"),
    # sizes no machine can hold
    recipe("maml", "trajectories_per_task=1000000000000"),
    recipe("diayn", "replay_buffer.size=100000000000"),
    recipe("vime", "dynamics.replay_size=100000000000"),
    suite("protocol.num_trajectories=1000000000000"),
    # output places and names
    recipe("maml", "output_dir={tmp}/afile", label="maml output_dir=<a file>"),
    recipe("vime", "output_dir={tmp}/afile/run", label="vime output_dir=<below a file>"),
    recipe("maml", "logger.backend=csv", "logger.exp_name=../../x"),
    suite("profile_name=../../../x"),
    suite("methods=[diayn_init]", "pretrain.diayn.reuse='runs/{{seed.__class__.__mro__}}'"),
    # checkpoints of another env or method, resumes that cannot continue
    suite("methods=[uml_diayn]", "pretrain.maml.reuse='{tmp}/oracle'"),
    suite("methods=[diayn_init]", "pretrain.diayn.reuse='{tmp}/diayn'", "++pretrain.diayn.overrides.num_skills=7"),
    recipe("maml", "proposal=oracle", "resume=true", "iterations=1", "output_dir={tmp}/oracle",
           label="maml resume=true iterations=1 of a 2-iteration run"),
    snippet("run_cell(uml_diayn) of an oracle run", """
        from umrl.metatest import CellSpec, run_cell
        run_cell(CellSpec(method="uml_diayn", env="point_nav", seed=0, output="{tmp}/cell_a.csv",
                          checkpoint="{tmp}/oracle"))"""),
    snippet("run_cell(uml_random) of a half_cheetah run on point_nav", """
        from umrl.metatest import CellSpec, run_cell
        run_cell(CellSpec(method="uml_random", env="point_nav", seed=0, output="{tmp}/cell_b.csv",
                          checkpoint="{tmp}/cheetah"))"""),
    # files that are damaged or crafted
    snippet("a checkpoint with 64 bytes zeroed", """
        import glob
        from umrl.checkpoints import load_maml_policy
        path = sorted(glob.glob("{tmp}/oracle/checkpoints/step_*.pt"))[-1]
        data = bytearray(open(path, "rb").read()); mid = len(data) // 2; data[mid:mid + 64] = bytes(64)
        open("{tmp}/zeroed.pt", "wb").write(data)
        load_maml_policy("{tmp}/zeroed.pt")"""),
    snippet("a crafted .pt given to load_maml_policy", CRAFTED + """
from umrl.checkpoints import load_maml_policy
try:
    load_maml_policy("{tmp}/crafted.pt")
finally:
    import os; assert not os.path.exists("{tmp}/pwned"), "the crafted file ran code"
"""),
    snippet("a crafted .pt given to export_skills", CRAFTED + """
import runpy, sys, os
sys.argv = ["export_skills", "{tmp}/crafted.pt", "{tmp}/skills_out"]
try:
    runpy.run_module("umrl.checkpoints.export_skills", run_name="__main__")
finally:
    assert not os.path.exists("{tmp}/pwned"), "the crafted file ran code"
"""),
    # the Python API
    snippet("collect with a None policy", """
        from umrl.envs import make_env
        from umrl.rollout import collect
        collect(make_env("point_nav", 4, horizon=5), None, num_tasks=2, horizon=5)"""),
    snippet("collect with a policy of another width", """
        from umrl.envs import make_env
        from umrl.modules import make_gaussian_policy
        from umrl.rollout import collect
        collect(make_env("point_nav", 4, horizon=5), make_gaussian_policy(3, 2, hidden=[8]), num_tasks=2, horizon=5)"""),
    snippet("collect(horizon=0)", """
        from umrl.envs import make_env
        from umrl.modules import make_gaussian_policy
        from umrl.rollout import collect
        collect(make_env("point_nav", 4, horizon=5), make_gaussian_policy(2, 2, hidden=[8]), num_tasks=2, horizon=0)"""),
    snippet("make_task_env with a list", """
        from umrl.envs import make_task_env
        make_task_env("point_nav", [0.1, 0.2])"""),
    snippet("make_proposal('random', num_skills=0)", """
        from umrl.proposals import make_proposal
        make_proposal("random", "point_nav", num_tasks=2, trajectories_per_task=2, horizon=5, num_skills=0)"""),
    snippet("DIAYNLoss on a batch without skill", """
        import torch
        from tensordict import TensorDict
        from umrl.modules import make_discriminator, make_skill_actor, make_skill_qvalue
        from umrl.objectives import DIAYNLoss
        loss = DIAYNLoss(make_skill_actor(2, 4, 2, hidden=(8,)), make_skill_qvalue(2, 4, 2, hidden=(8,)),
                         make_discriminator(2, 4, hidden=(8,)), num_skills=4)
        loss(TensorDict({{"observation": torch.zeros(8, 2), "action": torch.zeros(8, 2),
                         "next": {{"observation": torch.zeros(8, 2), "done": torch.zeros(8, 1, dtype=torch.bool),
                                  "terminated": torch.zeros(8, 1, dtype=torch.bool)}}}}, [8]))"""),
    snippet("make_env(device='cuda') without CUDA", """
        import torch
        from umrl.envs import make_env
        if torch.cuda.is_available():
            raise SystemExit("umrl: got a CUDA device; expected a machine without one (case not applicable)")
        make_env("point_nav", 2, device="cuda")"""),
]


def run(argv: tuple[str, ...], tmp: str, timeout: float) -> tuple[int | None, str, float]:
    """``(returncode or None on timeout, stdout + stderr, seconds)`` of ``python argv`` with ``{tmp}`` filled in."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "WANDB_MODE": "disabled", "HYDRA_FULL_ERROR": "0"}
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, *(a.format(tmp=tmp) for a in argv)], check=False, cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=timeout)
        return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - start
    except subprocess.TimeoutExpired as err:
        out = (err.stdout or b"").decode(errors="replace") + (err.stderr or b"").decode(errors="replace")
        return None, out, time.perf_counter() - start


def verdict(expect: str, returncode: int | None, output: str) -> tuple[str, str]:
    """``(clear | obscure | silent, the line that decided it)`` of one case's outcome."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    said = next((line for line in reversed(lines) if MESSAGE.search(line)), "")  # the last, the one raised
    last = lines[-1] if lines else ""
    if returncode is None:
        return "obscure", "timed out: " + last
    if returncode != 0:
        return ("clear", said) if expect == "refuse" and said else ("obscure", last)
    if expect == "run":
        return "clear", "ran"
    return ("clear", said) if expect == "warn" and said else ("silent", "exit 0: " + (said or last))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", default="", help="run only the cases whose label contains this text")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per case (a case past it is obscure)")
    args = parser.parse_args()
    counts: Counter[str] = Counter()
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "afile").write_text("not a directory")
        for argv in SETUP:
            code, out, _ = run(argv, tmp, 600)
            if code != 0:
                raise SystemExit(f"setup run failed: {' '.join(argv)}\n{out[-2000:]}")
        for case in CASES:
            if args.only not in case.label:
                continue
            code, out, seconds = run(case.argv, tmp, args.timeout)
            kind, line = verdict(case.expect, code, out)
            counts[kind] += 1
            print(f"{kind:8s} {seconds:6.1f}s  {case.label}\n{'':17s}{line[:300]}", flush=True)
    print(" ".join(f"{kind}: {counts[kind]}" for kind in ("clear", "obscure", "silent")), f"of {sum(counts.values())}")


if __name__ == "__main__":
    main()
