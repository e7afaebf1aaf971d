"""Feeds the recipes, the suite and the Python API bad inputs, and sorts what each does into clear / fine / obscure /
silent.

    python scripts/diagnostics/bad_inputs.py                  # every case, a line each, then the counts per kind
    python scripts/diagnostics/bad_inputs.py --only seed      # the cases whose label contains "seed"
    python scripts/diagnostics/bad_inputs.py --kinds files --jobs 3 --timeout 400   # the file kinds, 3 at a time
    python scripts/diagnostics/bad_inputs.py --kinds other --jobs 2    # cells, logs and reports, non-finite values

A few small runs made first give the cases a real MAML and DIAYN checkpoint to misuse. Each case runs in its own
process under a time limit, in a temporary directory: the first 40 ("old kinds": values, sizes, names, runs of
another kind, the Python API) as a fresh ``python`` command line; the file kinds (special files, hostile-but-hash-
valid trees and metadata, damaged files, full disks, long and odd names) and the other kinds (a meta-test cell's
output holding a file of other settings, a cut one or a folder; an unwritable ``WANDB_DIR``; report columns beyond
K; NaN and inf given to the Python API's constructors) as a snippet in a child forked from the probe once torch and
umrl are imported, in a folder of its own (they make the files a hostile writer could: the
hash in a checkpoint is an integrity check anyone can recompute). A case expects one of three outcomes, and is

- **clear** when it got it: ``refuse`` exits non-zero with a line in umrl's format (``<key>: got …; expected …``,
  a checkpoint's ``cannot read checkpoint <path> (<what>): <why>`` or ``cannot write checkpoint <path>: <why>``,
  a missing one's ``no checkpoint file at <path>``, a cell's ``recomputing the cell <path>: <why>``); ``warn``
  exits 0 having printed such a line (a resume that skipped a bad newest checkpoint, a cell file recomputed);
- **fine** when a ``run`` case (a legal input, or a stray file umrl must leave alone) exits 0;
- **obscure** when it exits non-zero without such a line, or runs past the time limit;
- **silent** when a ``refuse`` or ``warn`` case exits 0 without a word in that format.

The cases are the kinds a new user (and an attacker) tries: values out of range, sizes no machine holds, names that
are paths, checkpoints of another env or method, corrupt or crafted files, misuse of the Python API.
"""
from __future__ import annotations

import argparse
import importlib
import itertools
import os
import re
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import traceback
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
MESSAGE = re.compile(r"\S: got .*; expected "  # a checkpoint's own errors: its file, what it is, why
                     r"|cannot read checkpoint \S+ \([^)]*\): |cannot write checkpoint \S+: "
                     r"|\S+ is not a regular checkpoint file \(|no checkpoint (file )?at \S+"
                     r"|\S+ is in use by |\S+ holds checkpoints of an earlier run"  # run folders' locks
                     r"|recomputing the cell \S+: ")  # a cell's file of other settings, or cut short
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
    kind: str = "old kinds"  # the group its count is reported in
    template: bool = True  # argv is a str.format template run as a command; else a file case: a ``-c`` snippet
    # forked from the probe (:func:`fork_case`), its "{tmp}" replaced and its braces literal


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
    recipe("vime", "advantage.gamma=0", expect="run"),
    recipe("vime", "advantage.lmbda=0", expect="run"),
    suite("protocol.gamma=0", "protocol.lmbda=0", expect="run"),
    recipe("maml", "seed=99999999999999999999"),
    recipe("diayn", "seed=99999999999999999999"),
    recipe("maml", "maml.inner_lr=1e30"),
    recipe("diayn", "optim.alpha=0"),
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
        path = sorted(glob.glob("{tmp}/oracle/checkpoints/step_*.safetensors"))[-1]
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


# ---- files that cannot lie: special, hostile-but-hash-valid, damaged files; full disks; long and odd names ---------
# These snippets are plain Python (no str.format: "{tmp}" is the only placeholder). Each works in its own folder
# CASE under the probe's directory and starts with FILES, the helpers that make the files a hostile writer could.
FILES = '''
import json, math, os, shutil, subprocess, sys
from pathlib import Path
import safetensors.torch, torch
from umrl import checkpoints
from umrl.checkpoints.file import FILE_FORMAT, content_hash, read_checkpoint, write_checkpoint
from umrl.checkpoints import DIAYN_FORMAT, MAML_FORMAT, VIME_FORMAT
from umrl.checkpoints.folder import Checkpointer
TMP = Path("{tmp}")
CASE = TMP / "case_%d"
CASE.mkdir()

def write_tree(path, tree_json, tensors=None):
    """Any JSON tree in umrl's container, its hash recomputed: what anyone who can write the file can make."""
    tensors = tensors or {"t0": torch.zeros(3)}
    safetensors.torch.save_file(tensors, str(path), metadata={
        "format": FILE_FORMAT, "tree": tree_json, "sha256": content_hash(tree_json, tensors)})
    return path

def latest(run):
    return Checkpointer(TMP / run / "checkpoints").latest()

def tiny(kind, hidden=(16,)):
    """(format, meta, entries) of a small point_nav checkpoint of ``kind`` (DIAYN, MAML or VIME)."""
    from umrl.modules import make_discriminator, make_gaussian_policy, make_skill_actor
    from umrl.modules.bnn import BayesianDynamics
    if kind == "DIAYN":
        return DIAYN_FORMAT, {"env": "point_nav", "obs_dim": 2, "act_dim": 2, "num_skills": 4, "hidden": list(hidden),
                              "discriminator_hidden": [16], "discriminator_observation_key": ["observation"],
                              "discriminator_input_dims": None}, {
            "actor": make_skill_actor(2, 4, 2, hidden=hidden).state_dict(),
            "discriminator": make_discriminator(2, 4, hidden=(16,)).state_dict(), "counters": {"frames": 1}}
    if kind == "MAML":
        return MAML_FORMAT, {"env": "point_nav", "proposal": "random", "obs_dim": 2, "act_dim": 2,
                             "hidden": list(hidden), "init_std": 1.0, "inner_lr": 0.1, "num_inner_steps": 1,
                             "first_order": False, "num_tasks": 2, "trajectories_per_task": 2, "horizon": 10,
                             "num_skills": 4}, {
            "policy": make_gaussian_policy(2, 2, hidden=hidden, init_std=1.0).state_dict()}
    return VIME_FORMAT, {"env": "point_nav", "obs_dim": 2, "act_dim": 2, "policy_hidden": list(hidden),
                         "policy_init_std": 1.0, "dynamics_hidden": [8], "prior_std": 0.5, "likelihood_std": 0.5}, {
        "policy": make_gaussian_policy(2, 2, hidden=hidden, init_std=1.0).state_dict(),
        "dynamics": BayesianDynamics(2, 2, hidden=(8,)).state_dict()}

def save(fmt, meta, entries, folder=None, step=1):
    return fmt.save(Checkpointer(folder or CASE, keep_all=True), step, meta, **entries)

def relay(argv, **kwargs):
    """Run ``python argv`` (a recipe), print what it printed, exit with its code."""
    proc = subprocess.run([sys.executable, *argv], capture_output=True, text=True, **kwargs)
    print(proc.stdout + proc.stderr)
    sys.exit(proc.returncode)
'''
_FILE_CASES = itertools.count()


def file_case(kind: str, label: str, body: str, expect: str = "refuse") -> Case:
    """A snippet of ``kind`` (the group its count is reported in): :data:`FILES`, then ``body`` (dedented)."""
    code = FILES % next(_FILE_CASES) + textwrap.dedent(body)
    return Case(label, expect, ("-c", code), kind=kind, template=False)


LOADERS = {"DIAYN": ["load_diayn_checkpoint", "load_discriminator", "load_skill_policy"],
           "MAML": ["load_maml_checkpoint", "load_maml_policy"],
           "VIME": ["load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy"]}
SPECIAL = {"a FIFO": "os.mkfifo(path)", "a folder": "path.mkdir()", "a symlink to /dev/zero": "path.symlink_to('/dev/zero')"}
MAML_RESUME = ("recipes/maml.py", *MAML_TINY, "proposal=oracle", "checkpoint.keep_all=true", "iterations=3",
               "resume=true")


def maml_resume_with(plant: str) -> str:
    """A body: copy the probe's oracle MAML run, run ``plant`` (``path`` is its checkpoints/step_9.pt), resume it."""
    return f"""
        shutil.copytree(TMP / "oracle", CASE / "run")
        path = CASE / "run" / "checkpoints" / "step_9.pt"
        {plant}
        relay([*{MAML_RESUME!r}, f"output_dir={{CASE / 'run'}}"])"""


def special_file_cases() -> list[Case]:
    cases = []
    for what, make in SPECIAL.items():
        for loaders in LOADERS.values():
            for loader in loaders:
                cases.append(file_case("special files", f"{loader}(<{what} named step_5.pt>)", f"""
                    path = CASE / "step_5.pt"; {make}
                    getattr(checkpoints, {loader!r})(path)"""))
        cases.append(file_case("special files", f"load_maml_policy(<run whose newest step_999.pt is {what}>)", f"""
            shutil.copytree(TMP / "oracle", CASE / "run")
            path = CASE / "run" / "checkpoints" / "step_999.pt"; {make}
            checkpoints.load_maml_policy(CASE / "run")""", expect="run"))
        cases.append(file_case("special files", f"maml resume=true of a run holding {what} named step_9.pt",
                               maml_resume_with(make), expect="run"))
    cases.append(file_case("special files", "run_cell(oracle) of a run whose newest step_999.pt is a FIFO", """
        from umrl.metatest import AdaptationConfig, CellSpec, run_cell
        shutil.copytree(TMP / "oracle", CASE / "run")
        os.mkfifo(CASE / "run" / "checkpoints" / "step_999.pt")
        run_cell(CellSpec(method="oracle", env="point_nav", seed=0, output=str(CASE / "cell.csv"), num_tasks=2,
                          checkpoint=str(CASE / "run"), protocol=AdaptationConfig(num_steps=1, num_trajectories=2)))""",
        expect="run"))
    cases.append(file_case("special files", "load_maml_policy(<a symlink to a real checkpoint>)", """
        (CASE / "step_1.pt").symlink_to(latest("oracle"))
        checkpoints.load_maml_policy(CASE / "step_1.pt")""", expect="run"))
    cases.append(file_case("special files", "load_maml_policy(<a dangling symlink named step_1.pt>)", """
        (CASE / "step_1.pt").symlink_to(CASE / "gone.pt")
        checkpoints.load_maml_policy(CASE / "step_1.pt")"""))
    return cases


TREES = {  # label: the JSON tree of a hash-valid file
    "a JSON tree nested 100,000 deep": '"[" * 100_000 + "]" * 100_000',
    "a TensorDict whose batch size its tensors lack":
        'json.dumps({"__tensordict__": {"x": {"__tensor__": "t0"}}, "batch_size": [7]})',
    "a negative TensorDict batch size": 'json.dumps({"__tensordict__": {}, "batch_size": [-1]})',
    "an object-dtype array": 'json.dumps({"__ndarray__": "t0", "dtype": "O"})',
    "a 400 MB-per-element string dtype": 'json.dumps({"__ndarray__": "t0", "dtype": "<U100000000"})',
    "a tuple tag holding a number": 'json.dumps({"__tuple__": 5})',
    "an unhashable dict key": 'json.dumps({"__dict__": [[[1], 2]]})',
    "a torch.Size beyond int64": 'json.dumps({"__size__": [10**30]})',
    "an integer of 5,000 digits": '"1" + "0" * 5000',
    "a numpy scalar of text": 'json.dumps({"__npscalar__": "x", "dtype": "<f8"})',
    "an unknown torch dtype": 'json.dumps({"__dtype__": "Tensor"})',
    "a tensor name the file lacks": 'json.dumps({"format": "umrl.maml.v1", "policy": {"__tensor__": "t9"}})',
}


def hostile_tree_cases() -> list[Case]:
    cases = [file_case("hostile trees", f"load_maml_policy(<{label}, hash valid>)", f"""
        path = write_tree(CASE / "step_1.pt", {tree})
        checkpoints.load_maml_policy(path)""") for label, tree in TREES.items()]
    for label in ("a JSON tree nested 100,000 deep", "a TensorDict whose batch size its tensors lack",
                  "an object-dtype array"):
        cases.append(file_case("hostile trees", f"maml resume=true whose newest file holds {label}",
                               maml_resume_with(f"write_tree(path, {TREES[label]})"), expect="warn"))
    return cases


DAMAGES = {  # label: statements changing ``meta`` / ``entries`` of tiny(kind) (``width`` names its hidden key)
    "a NaN weight": "w = next(iter(entries.values())); k = next(iter(w)); w[k] = w[k].clone().fill_(math.nan)",
    "infinite weights": "w = next(iter(entries.values())); k = next(iter(w)); w[k] = torch.full_like(w[k], math.inf)",
    "a NaN setting": "meta[setting] = math.nan",
    "an infinite setting": "meta[setting] = math.inf",
    "two 100,000-wide layers in a small file": "meta[width] = [100_000, 100_000]",
    "a width of zero": "meta[width] = [0]",
    "a negative width": "meta[width] = [-16]",
    "a text width": "meta[width] = ['16']",
    "a boolean width": "meta[width] = [True]",
    "a fractional width": "meta[width] = [16.5]",
    "a width beyond 2**20": "meta[width] = [2**20 + 1]",
    "a million layers": "meta[width] = [1] * 1_000_000",
    "weights of other shapes than the meta's": "meta[width] = [8]",
    "a meta that is a list": "meta = [1, 2]",
    "a meta without its width key": "del meta[width]",
}
NETWORK_LOADER = {"DIAYN": "load_skill_policy", "MAML": "load_maml_policy", "VIME": "load_vime_policy"}
WIDTH = {"DIAYN": "hidden", "MAML": "hidden", "VIME": "policy_hidden"}
SETTING = {"DIAYN": "num_skills", "MAML": "inner_lr", "VIME": "prior_std"}


def hostile_metadata_cases() -> list[Case]:
    cases = []
    for kind, loader in NETWORK_LOADER.items():
        for label, damage in DAMAGES.items():
            cases.append(file_case("hostile metadata", f"{loader}(<{label}, hash valid>)", f"""
                fmt, meta, entries = tiny({kind!r}); width, setting = {WIDTH[kind]!r}, {SETTING[kind]!r}
                {damage}
                write_checkpoint({{"format": fmt.name, "meta": meta, **entries, "config": None}}, CASE / "step_1.pt")
                getattr(checkpoints, {loader!r})(CASE)"""))
    cases.append(file_case("hostile metadata", "load_maml_policy(<27 kB: ant, two 100,000-wide layers>)", """
        fmt, meta, entries = tiny("MAML")
        save(fmt, {**meta, "env": "ant", "obs_dim": 105, "act_dim": 8, "hidden": [100_000, 100_000]}, entries)
        checkpoints.load_maml_policy(CASE)"""))
    cases.append(file_case("hostile metadata", "run_cell(oracle) of a checkpoint with a NaN inner_lr", """
        from umrl.metatest import CellSpec, run_cell
        state = read_checkpoint(latest("oracle")); state["meta"]["inner_lr"] = math.nan
        save(MAML_FORMAT, state["meta"], {k: v for k, v in state.items() if k not in ("format", "meta")}, step=2)
        run_cell(CellSpec(method="oracle", env="point_nav", seed=0, output=str(CASE / "cell.csv"), num_tasks=2,
                          checkpoint=str(CASE)))"""))
    cases.append(file_case("hostile metadata", "maml resume=true whose newest file has a NaN inner_lr", maml_resume_with(
        """state = read_checkpoint(latest("oracle")); state["meta"]["inner_lr"] = math.nan
        save(MAML_FORMAT, state["meta"], {k: v for k, v in state.items() if k not in ("format", "meta")},
             folder=path.parent, step=9)"""), expect="warn"))
    cases.append(file_case("hostile metadata", "diayn resume=true whose newest program state has a NaN weight", f"""
        from umrl.checkpoints.diayn import DIAYN_SEEDS_FORMAT
        shutil.copytree(TMP / "diayn", CASE / "run")
        state = read_checkpoint(latest(CASE / "run"))
        name = next(k for k, v in state["loss"].items() if v.is_floating_point())
        state["loss"][name] = state["loss"][name].clone().fill_(math.nan)
        save(DIAYN_SEEDS_FORMAT, state["meta"], {{k: v for k, v in state.items() if k not in ("format", "meta")}},
             folder=CASE / "run" / "checkpoints", step=10**6)
        relay(["recipes/diayn.py", *{DIAYN_TINY!r}, "resume=true", "collector.total_frames=4000",
               f"output_dir={{CASE / 'run'}}"])""", expect="warn"))
    return cases


DAMAGED = {  # label: statements turning ``data`` (the bytes of a real MAML checkpoint) into a damaged file
    "an empty file": "data = b''",
    "7 bytes": "data = data[:7]",
    "the 8-byte length only": "data = data[:8]",
    "cut at half": "data = data[:len(data) // 2]",
    "the last byte cut": "data = data[:-1]",
    "a header length beyond the file": "data = (len(data) * 2).to_bytes(8, 'little') + data[8:]",
    "a header that is not JSON": "n = int.from_bytes(data[:8], 'little'); data = data[:8] + b'{' + b'x' * (n - 1) + data[8 + n:]",
    "a byte flipped in the tree": "i = data.index(b'tree') + 40; data = data[:i] + bytes([data[i] ^ 1]) + data[i + 1:]",
    "a byte flipped in the tensor data": "data = data[:-9] + bytes([data[-9] ^ 0xFF]) + data[-8:]",
    "garbage appended": "data = data + os.urandom(1000)",
    "random bytes": "data = os.urandom(4096)",
    "a text file": "data = b'step 1: not a checkpoint' * 10",
    "a gzip file": "import gzip; data = gzip.compress(data)",
}


def damaged_file_cases() -> list[Case]:
    cases = [file_case("damaged files", f"load_maml_policy(<{label}>)", f"""
        data = latest("oracle").read_bytes()
        {damage}
        (CASE / "step_1.pt").write_bytes(data)
        checkpoints.load_maml_policy(CASE / "step_1.pt")""") for label, damage in DAMAGED.items()]
    cases.append(file_case("damaged files", "maml resume=true whose newest file is cut at half", maml_resume_with(
        """data = latest("oracle").read_bytes(); path.write_bytes(data[:len(data) // 2])"""), expect="warn"))
    return cases


# a small disk: a private tmpfs in a user+mount namespace (gone with the process), else a file-size limit
FULL = '''
import resource
DISK = CASE / "disk"; DISK.mkdir()
TMPFS = subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0
def on_full_disk(argv, size="48k"):
    if TMPFS:
        cmd = ["unshare", "-rm", "sh", "-c", f'mount -t tmpfs -o size={size} tmpfs "{DISK}" && exec "$0" "$@"',
               sys.executable, *argv]
        proc = subprocess.run(cmd, capture_output=True, text=True)
    else:
        limit = lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (48 * 1024, 48 * 1024))
        proc = subprocess.run([sys.executable, *argv], capture_output=True, text=True, preexec_fn=limit)
    print(proc.stdout + proc.stderr)
    sys.exit(proc.returncode)
'''


def full_disk_cases() -> list[Case]:
    def case(label: str, body: str, expect: str = "refuse") -> Case:
        return file_case("full disks", label, FULL + textwrap.dedent(body), expect)

    return [
        case("maml recipe onto a full disk", f"""
            on_full_disk(["recipes/maml.py", *{MAML_TINY!r}, f"output_dir={{DISK}}/run"])"""),
        case("diayn recipe onto a full disk", f"""
            on_full_disk(["recipes/diayn.py", *{DIAYN_TINY!r}, f"output_dir={{DISK}}/run"])"""),
        case("vime recipe onto a full disk", f"""
            on_full_disk(["recipes/vime.py", *{VIME_TINY!r}, f"output_dir={{DISK}}/run"])"""),
        case("export_skills onto a full disk", """
            on_full_disk(["-m", "umrl.checkpoints.export_skills", str(TMP / "diayn"), str(DISK / "skills")],
                         size="8k")"""),
        case("Checkpointer.save onto a full disk", """
            on_full_disk(["-c", "import torch; from umrl.checkpoints.folder import Checkpointer; "
                          f"Checkpointer({str(DISK)!r}).save({{'w': torch.zeros(100_000)}}, 1)"])"""),
        case("a full disk leaves no partial file", """
            on_full_disk(["-c", "import torch, os; from umrl.checkpoints.file import write_checkpoint\\n"
                          f"try:\\n    write_checkpoint({{'w': torch.zeros(100_000)}}, {str(DISK / 'x.pt')!r})\\n"
                          f"finally:\\n    assert not os.path.exists({str(DISK / 'x.pt')!r}), 'a partial file stayed'"])"""),
    ]


def odd_name_cases() -> list[Case]:
    def case(label: str, body: str, expect: str = "refuse") -> Case:
        return file_case("long and odd names", label, body, expect)

    copy = 'shutil.copytree(TMP / "oracle", CASE / name)\ncheckpoints.load_maml_policy(CASE / name)'
    return [
        case("load_maml_policy(<a 300-byte folder name>)", """
            checkpoints.load_maml_policy(CASE / ("x" * 300) / "step_1.pt")"""),
        case("load_maml_policy(<a 300-byte file name>)", """
            checkpoints.load_maml_policy(CASE / ("step_" + "1" * 295 + ".pt"))"""),
        case("load_maml_policy(<a path with a NUL byte>)", """
            checkpoints.load_maml_policy(str(CASE) + "/step_1.pt\\x00.txt")"""),
        case("load_maml_policy(<a symlink loop named step_1.pt>)", """
            (CASE / "step_1.pt").symlink_to(CASE / "step_1.pt")
            checkpoints.load_maml_policy(CASE / "step_1.pt")"""),
        case("load_maml_policy(<a run folder with a newline in its name>)", "name = 'a\\nb'\n" + copy, "run"),
        case("load_maml_policy(<a run folder named in unicode>)", "name = 'Prüfpunkt ✓ 检查点'\n" + copy, "run"),
        case("load_maml_policy(<a run folder with spaces and quotes>)", "name = 'a \"b\" \\'c\\''\n" + copy, "run"),
        case("load_maml_policy(<a path through ..>)", """
            checkpoints.load_maml_policy(TMP / "diayn" / ".." / "oracle")""", "run"),
        case("load_maml_policy(<a 255-byte step_<N>.pt name in a run>)", """
            shutil.copytree(TMP / "oracle", CASE / "run")
            shutil.copy(latest("oracle"), CASE / "run" / "checkpoints" / ("step_" + "9" * 247 + ".pt"))
            checkpoints.load_maml_policy(CASE / "run")""", "run"),
        case("export_skills to a 300-byte folder name", """
            from umrl.checkpoints.export_skills import main
            main([str(TMP / "diayn"), str(CASE / ("y" * 300))])"""),
        case("load_maml_policy(<a folder without a checkpoint>)", """
            (CASE / "empty" / "checkpoints").mkdir(parents=True)
            checkpoints.load_maml_policy(CASE / "empty")"""),
    ]


def folder_lock_cases() -> list[Case]:
    """The run folder's lock (:mod:`umrl.folder_lock`): its file made into something else, a second holder."""
    def case(label: str, body: str, expect: str = "refuse") -> Case:
        return file_case("folder locks", label, body, expect)

    acquire = "from umrl.folder_lock import FolderLock\nFolderLock(CASE).acquire()"
    return [
        case("FolderLock.acquire() where run.lock is a FIFO", "os.mkfifo(CASE / 'run.lock')\n" + acquire),
        case("FolderLock.acquire() where run.lock is a folder", "(CASE / 'run.lock').mkdir()\n" + acquire),
        case("FolderLock.acquire() where run.lock is a symlink to /dev/zero",
             "(CASE / 'run.lock').symlink_to('/dev/zero')\n" + acquire),
        case("FolderLock.acquire() while another process holds it", """
            from umrl.folder_lock import FolderLock
            with FolderLock(CASE):
                relay(["-c", f"from umrl.folder_lock import FolderLock; FolderLock({str(CASE)!r}).acquire()"])"""),
        case("maml resume=true into a folder another process holds", f"""
            from umrl.folder_lock import FolderLock
            shutil.copytree(TMP / "oracle", CASE / "run")
            with FolderLock(CASE / "run"):
                relay([*{MAML_RESUME!r}, f"output_dir={{CASE / 'run'}}"])"""),
        case("maml fresh run (resume=false) into a finished run's folder", f"""
            shutil.copytree(TMP / "oracle", CASE / "run")
            relay(["recipes/maml.py", *{MAML_TINY!r}, "proposal=oracle", f"output_dir={{CASE / 'run'}}"])"""),
    ]


FILE_CASES = [*special_file_cases(), *hostile_tree_cases(), *hostile_metadata_cases(), *damaged_file_cases(),
              *full_disk_cases(), *odd_name_cases(), *folder_lock_cases()]


# ---- the remaining kinds: meta-test cells, where logs and reports go, non-finite values of the Python API --------
CELL = """
from dataclasses import replace
from umrl.metatest import AdaptationConfig, CellSpec, run_cell
cell = CellSpec(method="scratch", env="point_nav", seed=0, output=str(CASE / "cell.csv"), num_tasks=2,
                protocol=AdaptationConfig(num_steps=1, num_trajectories=2, horizon=5))
"""


def cell_cases() -> list[Case]:
    """What a cell's ``output`` may already hold: a file of other settings or cut short (named and recomputed),
    something that is no file (refused before any work)."""
    def case(label: str, body: str, expect: str = "refuse") -> Case:
        return file_case("meta-test cells", label, CELL + textwrap.dedent(body), expect)

    return [
        case("run_cell over a finished cell of another K", """
            run_cell(replace(cell, protocol=replace(cell.protocol, num_steps=2)))
            run_cell(cell)""", "warn"),
        case("run_cell over a finished cell of other tasks", """
            run_cell(replace(cell, num_tasks=3))
            run_cell(cell)""", "warn"),
        case("run_cell over a finished cell of another method", """
            run_cell(replace(cell, method="oracle", checkpoint=str(TMP / "oracle")))
            run_cell(cell)""", "warn"),
        case("run_cell over a cell csv cut at a row's end", """
            run_cell(cell)
            text = open(cell.output, newline="").read()
            open(cell.output, "w", newline="").write(text[:text.rindex("\\r\\n", 0, len(text) - 2) + 2])
            run_cell(cell)""", "warn"),
        case("run_cell over a cell an older umrl wrote (no settings recorded)", """
            run_cell(cell)
            info = json.loads((CASE / "cell.json").read_text())
            (CASE / "cell.json").write_text(json.dumps({k: v for k, v in info.items() if k != "settings"}))
            run_cell(cell)""", "warn"),
        case("run_cell where output is a folder", """
            (CASE / "cell.csv").mkdir()
            run_cell(cell)"""),
        case("run_cell where output is a FIFO", """
            os.mkfifo(CASE / "cell.csv")
            run_cell(cell)"""),
        case("run_cell where the cell's .json is a folder", """
            (CASE / "cell.json").mkdir()
            run_cell(cell)"""),
        case("run_cell whose output folder is a file", """
            (CASE / "afile").write_text("not a folder")
            run_cell(replace(cell, output=str(CASE / "afile" / "cell.csv")))"""),
    ]


def logging_cases() -> list[Case]:
    """Where metrics and tables go: an unwritable ``WANDB_DIR`` (wandb would write to /tmp instead), report columns
    beyond K."""
    def case(label: str, body: str, expect: str = "refuse") -> Case:
        return file_case("logs and reports", label, body, expect)

    wandb_env = 'env={**os.environ, "WANDB_DIR": str(CASE / "afile" / "below")}'
    return [
        case("maml logger.backend=wandb with WANDB_DIR below a file", f"""
            (CASE / "afile").write_text("not a folder")
            relay(["recipes/maml.py", *{MAML_TINY!r}, "logger.backend=wandb", f"output_dir={{CASE / 'run'}}"],
                  {wandb_env})"""),
        case("suite logger.backend=wandb with WANDB_DIR below a file", f"""
            (CASE / "afile").write_text("not a folder")
            relay(["benchmarks/suite.py", *{SUITE_TINY!r}, "logger.backend=wandb", f"output_dir={{CASE / 'suite'}}"],
                  {wandb_env})"""),
        case("suite report.steps=[0,1,5] with protocol.num_steps=1", f"""
            relay(["benchmarks/suite.py", *{SUITE_TINY!r}, "logger.backend=none", "protocol.num_steps=1",
                   "num_tasks=2", "protocol.num_trajectories=2", "protocol.horizon=5", "report.steps=[0,1,5]",
                   f"output_dir={{CASE / 'suite'}}"])""", "warn"),
    ]


NON_FINITE = {  # the constructor, a call with the value x
    "DIAYNLoss(alpha_init=nan)": "diayn_loss(alpha_init=x)",
    "DIAYNLoss(target_entropy=inf)": "diayn_loss(target_entropy=x, fixed_alpha=False)",
    "make_diayn_optimizers(lr=nan)": "make_diayn_optimizers(diayn_loss(), lr=x, discriminator_lr=1e-3)",
    "DIAYNUpdate(tau=nan)": "DIAYNUpdate(diayn_loss(), {}, tau=x)",
    "make_gaussian_policy(init_std=nan)": "make_gaussian_policy(2, 2, hidden=[8], init_std=x)",
    "BayesianDynamics(prior_std=nan)": "BayesianDynamics(2, 2, prior_std=x)",
    "BayesianDynamics(init_std=inf)": "BayesianDynamics(2, 2, init_std=x)",
    "VIMEBonus(eta=nan)": "VIMEBonus(BayesianDynamics(2, 2), eta=x)",
    "AdaptationConfig(gamma=nan)": "AdaptationConfig(gamma=x)",
    "AdaptationConfig(lmbda=nan)": "AdaptationConfig(lmbda=x)",
    "sgd_lr_factor('swept', 1, later_factor=nan)": "sgd_lr_factor('swept', 1, x)",
    "TaskAdapter(lr=nan)": "TaskAdapter(make_gaussian_policy(2, 2, hidden=[8]), "
                           "make_eval_env('point_nav', torch.zeros(2, 2), 2, seed=0, horizon=5), 2, optimizer='sgd', lr=x)",
    "goal_within(tolerance=nan)": "goal_within(x)",
}
NON_FINITE_IMPORTS = """
from umrl.envs.tasks import goal_within
from umrl.metatest.protocol import AdaptationConfig, TaskAdapter, make_eval_env, sgd_lr_factor
from umrl.modules import make_discriminator, make_gaussian_policy, make_skill_actor, make_skill_qvalue
from umrl.modules.bnn import BayesianDynamics
from umrl.objectives import DIAYNLoss
from umrl.objectives.diayn import DIAYNUpdate, make_diayn_optimizers
from umrl.transforms.vime_bonus import VIMEBonus
def diayn_loss(**kwargs):
    return DIAYNLoss(make_skill_actor(2, 4, 2, hidden=(8,)), make_skill_qvalue(2, 4, 2, hidden=(8,)),
                     make_discriminator(2, 4, hidden=(8,)), num_skills=4, **kwargs)
"""


def non_finite_cases() -> list[Case]:
    """A NaN or an infinity given to the Python API's constructors."""
    return [file_case("non-finite values", label, NON_FINITE_IMPORTS
                      + f"x = math.{'inf' if label.endswith('inf)') else 'nan'}\n{call}\n")
            for label, call in NON_FINITE.items()]


OTHER_CASES = [*cell_cases(), *logging_cases(), *non_finite_cases()]


ENV = {"PYTHONPATH": str(REPO), "WANDB_MODE": "disabled", "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}
"""The environment of every case (one OpenMP thread: no thread pool exists when a file case is forked)."""


def run(argv: tuple[str, ...], tmp: str, timeout: float) -> tuple[int | None, str, float]:
    """``(returncode or None on timeout, stdout + stderr, seconds)`` of ``python argv`` with ``{tmp}`` filled in."""
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, *(a.format(tmp=tmp) for a in argv)], check=False, cwd=REPO,
                              env={**os.environ, **ENV}, capture_output=True, text=True, timeout=timeout)
        return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - start
    except subprocess.TimeoutExpired as err:
        out = (err.stdout or b"").decode(errors="replace") + (err.stderr or b"").decode(errors="replace")
        return None, out, time.perf_counter() - start


PRELOAD = ("torch", "safetensors.torch", "umrl.checkpoints", "umrl.metatest", "umrl.loggers")
"""Imported once by the probe before the file cases, whose processes are forked from it (seconds each instead of
the ~5 CPU-seconds every ``python -c`` spends importing torch and umrl)."""


@dataclass
class Forked:
    """A file case running in a child forked from the probe: its pid, where its output goes, when it started."""

    case: Case
    pid: int
    output: Any
    start: float


def fork_case(case: Case, tmp: str) -> Forked:
    """Start ``case`` (a ``-c`` snippet) in a forked child that runs it as ``python -c`` would: ``__main__``
    globals, cwd the repository, stdout and stderr to a file, exit status 1 on an exception (its traceback
    printed), the ``SystemExit`` code otherwise."""
    output = tempfile.TemporaryFile("w+")  # noqa: SIM115 -- outlives this call: finished() reads and closes it
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid:
        return Forked(case, pid, output, time.perf_counter())
    status = 1
    try:  # the child: never returns into the probe
        os.dup2(output.fileno(), 1)
        os.dup2(output.fileno(), 2)
        sys.stdout = open(1, "w", buffering=1, closefd=False)  # noqa: SIM115 -- the child's streams until it exits
        sys.stderr = open(2, "w", buffering=1, closefd=False)  # noqa: SIM115 -- (a caller may have replaced both)
        os.chdir(REPO)
        sys.argv = ["-c"]
        code = case.argv[1].replace("{tmp}", tmp)
        exec(compile(code, "<string>", "exec"), {"__name__": "__main__"})  # noqa: S102 -- the probe's own case, as python -c
        status = 0
    except SystemExit as exit_:
        status = exit_.code if isinstance(exit_.code, int) else 0 if exit_.code is None else 1
        if not isinstance(exit_.code, int | None):
            print(exit_.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 -- reported as python reports an uncaught one
        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)


def finished(run_: Forked, timeout: float) -> tuple[int | None, str, float] | None:
    """``run``'s ``(returncode or None on timeout, output, seconds)`` once ``run_`` ended (killed past ``timeout``),
    else ``None``."""
    seconds = time.perf_counter() - run_.start
    pid, status = os.waitpid(run_.pid, os.WNOHANG)
    if not pid and seconds <= timeout:
        return None
    if not pid:
        os.kill(run_.pid, signal.SIGKILL)
        os.waitpid(run_.pid, 0)
    run_.output.seek(0)
    text = run_.output.read()
    run_.output.close()
    return (os.waitstatus_to_exitcode(status) if pid else None), text, seconds


def run_forked(cases: list[Case], tmp: str, timeout: float, jobs: int) -> Iterator[tuple[Case, tuple]]:
    """``(case, run's result)`` of every case, in order, ``jobs`` children at a time."""
    for name in PRELOAD:
        importlib.import_module(name)
    pending, running, done = list(cases), [], {}
    while pending or running:
        while pending and len(running) < jobs:
            running.append(fork_case(pending.pop(0), tmp))
        for run_ in list(running):
            if (result := finished(run_, timeout)) is not None:
                running.remove(run_)
                done[id(run_.case)] = result
        while cases and id(cases[0]) in done:
            case = cases.pop(0)
            yield case, done.pop(id(case))
        time.sleep(0.05)

def verdict(expect: str, returncode: int | None, output: str) -> tuple[str, str]:
    """``(clear | fine | obscure | silent, the line that decided it)`` of one case's outcome."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    said = next((line for line in reversed(lines) if MESSAGE.search(line)), "")  # the last, the one raised
    last = lines[-1] if lines else ""
    if returncode is None:
        return "obscure", "timed out: " + last
    if returncode != 0:
        return ("clear", said) if expect == "refuse" and said else ("obscure", last)
    if expect == "run":
        return "fine", "ran"
    return ("clear", said) if expect == "warn" and said else ("silent", "exit 0: " + (said or last))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", default="", help="run only the cases whose label contains this text")
    parser.add_argument("--kinds", choices=("all", "old", "files", "other"), default="all",
                        help="old: the first 40 cases; files: the file kinds (special, hostile, damaged, full disk, "
                             "odd names); other: meta-test cells, logs and reports, non-finite values")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per case (a case past it is obscure)")
    parser.add_argument("--jobs", type=int, default=1, help="cases run at once (each in its own folder)")
    args = parser.parse_args()
    cases = {"all": [*CASES, *FILE_CASES, *OTHER_CASES], "old": CASES, "files": FILE_CASES,
             "other": OTHER_CASES}[args.kinds]
    counts: Counter[tuple[str, str]] = Counter()
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "afile").write_text("not a directory")
        for argv in SETUP:
            code, out, _ = run(argv, tmp, 600)
            if code != 0:
                raise SystemExit(f"setup run failed: {' '.join(argv)}\n{out[-2000:]}")
        chosen = [case for case in cases if args.only in case.label]
        with ThreadPoolExecutor(args.jobs) as pool:  # each case is its own process: threads only wait
            old = [case for case in chosen if case.template]
            outcomes = [*zip(old, pool.map(lambda case: run(case.argv, tmp, args.timeout), old))]
        os.environ.update(ENV)  # for the forked file cases and the recipes they start
        outcomes = itertools.chain(outcomes, run_forked([c for c in chosen if not c.template], tmp, args.timeout,
                                                        args.jobs))
        for case, (code, out, seconds) in outcomes:
            verdict_kind, line = verdict(case.expect, code, out)
            counts[case.kind, verdict_kind] += 1
            print(f"{verdict_kind:8s} {seconds:6.1f}s  [{case.kind}] {case.label}\n{'':17s}{line[:300]}", flush=True)
    verdicts = ("clear", "fine", "obscure", "silent")
    for kind in dict.fromkeys(kind for kind, _ in counts):
        print(f"{kind + ':':20s}", " ".join(f"{v}: {counts[kind, v]}" for v in verdicts),
              f"of {sum(counts[kind, v] for v in verdicts)}")
    print(f"{'all:':20s}", " ".join(f"{v}: {sum(n for (_, w), n in counts.items() if w == v)}" for v in verdicts),
          f"of {sum(counts.values())}")

if __name__ == "__main__":
    main()
