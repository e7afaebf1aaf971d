"""Every command the README and the pages under docs/ show (:mod:`doc_commands` reads them) is written as its
program takes it, without running the hours-long ones:

- a recipe or suite command line (``python recipes/<name>.py``, ``umrl <name>``, ``python benchmarks/suite.py``)
  names existing keys, and its config composes in-process as the command composes it and passes the config's checks
  (the tiny profiles' runs are tested in test_recipe_*.py, test_cli.py and test_suite.py);
- a script or module (``python scripts/...``, ``python benchmarks/...``, ``python -m umrl...``) exists and its
  argument parser takes the arguments shown (the script runs up to its ``parse_args``, no further);
- the paths a command reads exist in the repository, except those an earlier command writes (:data:`WRITTEN_EARLIER`,
  each with what writes it); a placeholder (``<dir>``) stands for such a path, a retired name for today's
  (:data:`RETIRED_NAMES`), and ``device=cuda`` is accepted on a machine without CUDA;
- ``python -c`` snippets run (they take milliseconds); ``make`` targets exist in the Makefile; the examples a page
  runs exist and a test runs them; ``python -m pytest`` names existing test files.
The README's Python quick start runs as written (a slow test)."""
import argparse
import contextlib
import fnmatch
import glob
import io
import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from doc_commands import REPO, DocCommand, doc_commands, spell_out
from hydra import compose as hydra_compose
from hydra.core.override_parser.overrides_parser import OverridesParser
from results_history import in_history

from umrl.cli.errors import unknown_key_errors
from umrl.configs import ConfigError, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig
from umrl.configs.suite import SuiteConfig
from umrl.configs.vime import VIMEConfig
from umrl.suite import CONFIG_DIR as SUITE_CONFIG_DIR
from umrl.trainers.config import CONFIG_DIR, compose, config_dir

SCHEMAS = {"diayn": DIAYNConfig, "maml": MAMLConfig, "vime": VIMEConfig, "suite": SuiteConfig}
RECIPE = re.compile(r"recipes/(diayn|maml|vime)\.py|benchmarks/(suite)\.py")
COMMANDS = doc_commands()

SHOWN_FAILING = {
    "umrl maml maml.inner_lrr=0.1": [
        "maml.inner_lrr: got 0.1; expected a key of the maml config (did you mean maml.inner_lr?)"],
}
"""Commands a page shows to demonstrate an error, with the error lines they print."""

USER_FILES = {"python my_env.py"}
"""Commands that run a file of the user's (the page shows how to write it)."""

PLACEHOLDER = "outputs/placeholder"
"""What a placeholder a page writes for a path of the user's (``<dir>``, ``<a copy of the run>``) stands for here;
``<s>`` (a seed) stands for 0."""

RETIRED_NAMES = {"ant_maml_reward": "ant"}
"""Names the code no longer has, in the commands of results made before (each page says at which commit): checked
with today's name (``ant_maml_reward``: removed when ``ant`` took the MAML reference code's goal reward)."""

WRITTEN_EARLIER = {
    # paths (fnmatch patterns) a command reads: what writes them (an earlier command of the page, a long run)
    "outputs/tiny/diayn/point_nav/seed0": "the tiny DIAYN command before it",
    "outputs/suite/ant_gate/cells/ant/*/seed0[*].json": "the ant gate suite command before it",
    "outputs/suite/ref_ant/cells/ant/[*]/seed0[*].json": "the ant reference suite command before it",
    "outputs/diayn/half_cheetah/seed0/checkpoints/step_*.pt": "the HC-D01 DIAYN run (1 M env steps)",
    "outputs/diayn/point_nav/seed0": "the DIAYN run of the block (50 k env steps)",
    "outputs/suite/ref_half_cheetah/cells/half_cheetah/*/seed0-<key>.csv": "the suite command before it",
    "/tmp/ss/*/checkpoints/step_*.safetensors": "second_step.md's MAML runs (the training commands of each block)",
    "results/point_nav/diayn_trained/seed*": "results/README.md's DIAYN commands at 89c011f (git-ignored: 66 MB per run)",
    "results/half_cheetah/diayn_ref_1m/seed[12]": "plan.md's HC-D01 / HC-D2 rows (seed 0 is committed)",
    "results/half_cheetah/uml_diayn_ref/seed[12]": "plan.md's HC-M2 row (seed 0 is committed)",
    "results/half_cheetah/oracle_ref/seed2": "plan.md's HC-M1 row (seeds 0 and 1 are committed)",
    "results/half_cheetah/uml_random_ref/seed2": "plan.md's HC-M1 row (seeds 0 and 1 are committed)",
    "results/ant/*_ref*/seed[012]": "plan.md's AN-D and AN-M rows (not run: the ant gate stopped them)",
    "outputs/suite/trained_skills": "point_nav.md's suite command of that section",
    "outputs/suite/ref3_half_cheetah": "reference_half_cheetah.md's three-seed suite command before it",
    "outputs/suite/ref3_point_nav": "reference_point_nav.md's three-seed suite command before it",
    "outputs/suite/ref3_point_nav_along": "reference_point_nav.md's along-meta-training suite command before it",
    "outputs/suite/pn_skills_2x300": "reference_point_nav.md's 2 x 300 skills suite command before it",
    "/tmp/pn_earlier/*": "reference_point_nav.md's git archive of the earlier defaults' cells (a019296)",
    "outputs/diayn/point_nav/seeds0-1-2/seed[012]": "results/README.md's point_nav DIAYN command (2 x 32) below it",
    f"{PLACEHOLDER}*": "a run the page names by a placeholder (`<dir>`, `<the 200 k DIAYN run>`, `<copy>`)",
}
"""Paths the commands read that the repository does not hold, each with what writes it: a command reading one is
checked up to it (its config composes and passes every other check, its arguments parse, its other paths exist)."""


def _written_earlier(path: str) -> bool:
    """A path :data:`WRITTEN_EARLIER` lists, or one under a run folder that is in git history only (the history
    pages' runs: ``git checkout <commit> -- results/<folder>`` brings one back; results/README.md lists them)."""
    return any(fnmatch.fnmatchcase(path, pattern) for pattern in WRITTEN_EARLIER) or in_history(path)


def _allowed(error: str) -> bool:
    """A config error that names a path written earlier, or ``device=cuda`` on a machine without CUDA."""
    if error.startswith("device: got 'cuda' (no CUDA device") and not torch.cuda.is_available():
        return True
    named = re.findall(r"got '([^']*)'|(/\S+) (?:does not exist|has no checkpoint)", error)
    paths = [str(Path(p).relative_to(REPO)) if p.startswith(str(REPO)) else p for pair in named for p in pair if p]
    return any(_written_earlier(p) for p in paths)


def _fill(word: str) -> str:
    """A command's word with its placeholders and retired names replaced (:data:`PLACEHOLDER`,
    :data:`RETIRED_NAMES`)."""
    word = re.sub(r"<[^<>]+>", PLACEHOLDER, word.replace("<s>", "0"))
    for old, new in RETIRED_NAMES.items():
        word = re.sub(rf"\b{old}\b", new, word)
    return word


def _id(command: DocCommand) -> str:
    return f"{command.page}:{' '.join(command.argv)[:80]}"


def _of_kind(*kinds: str) -> list[DocCommand]:
    """The commands of these kinds, each command line once (at its first page)."""
    unique: dict[tuple[str, ...], DocCommand] = {}
    for command in COMMANDS:
        if _kind(command) in kinds:
            unique.setdefault(command.argv, command)
    return list(unique.values())


def _kind(command: DocCommand) -> str:
    program, *args = command.argv
    shown = " ".join(command.argv)
    if shown in USER_FILES:
        return "user file"
    if program == "make":
        return "make"
    if program == "umrl" or (args and RECIPE.fullmatch(args[0])):
        return "config"
    if args[:2] == ["-m", "pytest"]:
        return "pytest"
    if args[:1] == ["-c"]:
        return "snippet"
    if args and args[0].startswith("examples/"):
        return "example"
    return "script"


def test_every_shown_command_is_of_a_checked_kind():
    kinds = {_kind(c) for c in COMMANDS}
    assert kinds == {"config", "script", "pytest", "snippet", "make", "example", "user file"}, kinds
    assert {"README.md", "docs/quickstart.md", "docs/own_env.md", "docs/results/plan.md"} <= {c.page for c in COMMANDS}
    assert len(COMMANDS) > 100


def _first_values(overrides: list[str]) -> list[str]:
    """Hydra overrides with a sweep (``seed=0,1``) replaced by its first value."""
    parsed = OverridesParser.create().parse_overrides(overrides)
    return [f"{o.get_key_element()}={next(iter(o.sweep_string_iterator()))}" if o.is_sweep_override()
            else o.input_line for o in parsed]


@pytest.mark.parametrize("command", _of_kind("config"), ids=_id)
def test_a_recipe_or_suite_command_composes_and_passes_its_checks(command, monkeypatch):
    monkeypatch.chdir(REPO)  # the pages' relative paths are the repository root's
    program, *args = [_fill(word) for word in command.argv]
    name = args.pop(0) if program == "umrl" else next(g for g in RECIPE.fullmatch(args.pop(0)).groups() if g)
    kinds = "".join("o" if "=" in a and not a.startswith("-") else "f" for a in args)
    # argparse reads the overrides as one positional list: a flag between two of them ends it (exit status 2)
    assert not re.search(r"of+o", kinds), f"{command}: a flag between two overrides"
    shown = " ".join(command.argv)
    if shown in SHOWN_FAILING:
        assert unknown_key_errors(CONFIG_DIR, name, args) == SHOWN_FAILING[shown]
        return
    if "--help" in args:
        return
    # a config of a run's own folder (`--config-path=<copy>/checkpoints`): its overrides are checked on the default
    config_paths = [a.split("=", 1)[1] for a in args if a.startswith("--config-path=")]
    assert all(_written_earlier(path) for path in config_paths), f"{command}: {config_paths}"
    overrides = _first_values([a for a in args if "=" in a and not a.startswith("-")])
    if name == "suite":
        with config_dir(SUITE_CONFIG_DIR):
            cfg = hydra_compose("suite", overrides=overrides)
    else:
        cfg = compose(name, overrides)  # as the recipe: the env's config group follows env.name
    try:
        validate(cfg, SCHEMAS[name])
    except ConfigError as e:
        left = [error for error in e.errors if not _allowed(error)]
        assert not left, f"{command}: {left}"


class _Parsed(Exception):
    """Raised by the patched ``parse_args``: the script took its arguments."""


def _stop_after_parsing(monkeypatch) -> None:
    parse_args = argparse.ArgumentParser.parse_args

    def parse_and_stop(self, args=None, namespace=None):
        raise _Parsed(parse_args(self, args, namespace))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_and_stop)


def _paths(args: list[str]) -> list[str]:
    """The repository-relative or /tmp paths in ``args`` (also after ``=`` or ``@``), braces expanded."""
    found = []
    for arg in args:
        for path in re.findall(r"(?:^|[=@])((?:results|outputs|docs|examples|tests|/tmp)/[^\s\"']*|results$)", arg):
            path = re.sub(r":[a-z]+$", "", path.replace("{seed}", "*"))  # per-seed template, `PATH:init` suffix
            found += spell_out(path, r"\{([^{}]*,[^{}]*)\}", ",")  # shell braces
    return found


def _missing(paths: list[str]) -> list[str]:
    return [p for p in paths if not _written_earlier(p) and not glob.glob(str(REPO / p))]


def _synopsis_forms(args: list[str]) -> list[list[str]]:
    """``args``, or for a synopsis (``OLD NEW [--relocate FROM=TO]``) the forms without and with its optional
    part."""
    if not any(a.startswith("[") for a in args):
        return [args]
    without, depth = [], 0
    for a in args:
        depth += a.startswith("[")
        if not depth:
            without.append(a)
        depth -= a.endswith("]")
    return [without, [a.strip("[]") for a in args]]


@pytest.mark.parametrize("command", _of_kind("script"), ids=_id)
def test_a_script_takes_the_arguments_shown_and_its_inputs_exist(command, monkeypatch):
    _, *args = command.argv
    _stop_after_parsing(monkeypatch)
    for argv in _synopsis_forms(args):
        is_module = argv[0] == "-m"
        if is_module:
            argv = argv[1:]  # python -m MODULE ARGS: sys.argv is [MODULE, ARGS]
        else:
            assert (REPO / argv[0]).is_file(), f"{command}: no file {argv[0]}"
        monkeypatch.setattr(sys, "argv", argv)
        with pytest.raises(_Parsed):
            try:
                if is_module:
                    runpy.run_module(argv[0], run_name="__main__", alter_sys=False)
                else:
                    runpy.run_path(str(REPO / argv[0]), run_name="__main__")
            except SystemExit as e:
                pytest.fail(f"{command}: its parser refused the arguments (exit status {e.code})")
    assert _missing(_paths(args)) == [], command


def test_no_path_listed_as_written_earlier_is_in_the_repository():
    read = {p for c in COMMANDS for p in _paths(list(c.argv))}
    present = [p for p in read if _written_earlier(p) and glob.glob(str(REPO / p))]
    assert not present, f"listed as written earlier but in the repository (take it off the list): {present}"


@pytest.mark.parametrize("command", _of_kind("snippet"), ids=_id)
def test_a_python_snippet_runs(command):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(command.argv[2], "<doc snippet>", "exec"), {"__name__": "__main__"})  # noqa: S102 -- the docs' own
    assert out.getvalue().strip(), command


def test_make_targets_shown_exist():
    targets = re.findall(r"^([\w-]+):", (REPO / "Makefile").read_text(), flags=re.MULTILINE)
    shown = {target for c in _of_kind("make") for target in c.argv[1:] or targets[:1]}  # bare `make`: the first
    assert {"setup", "run", "test"} <= shown <= set(targets), shown - set(targets)


def test_examples_shown_exist_and_a_test_runs_them():
    tests = "".join(p.read_text() for p in (REPO / "tests").glob("test_*.py"))
    for command in _of_kind("example"):
        path = command.argv[1]
        assert (REPO / path).is_file(), command
        assert path.split("/")[-1] in tests, f"{command}: no test runs {path}"


def test_pytest_commands_name_existing_tests():
    for command in _of_kind("pytest"):
        files = [a.split("::")[0] for a in command.argv if a.split("/")[0] == "tests"]
        assert files and all((REPO / f).exists() for f in files), command


@pytest.mark.slow
def test_the_readme_python_quick_start_runs_as_written(tmp_path):
    """The README's snippet, in a fresh folder (it writes under outputs/): it prints the mean return at k = 0..3."""
    text = (REPO / "README.md").read_text()
    snippet = next(block for block in re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)
                   if "train(\"diayn\"" in block)
    out = subprocess.run([sys.executable, "-c", snippet], check=False, cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    values = re.findall(r"-?\d+\.\d+", out.stdout.strip().splitlines()[-1])
    assert len(values) == 4, out.stdout
