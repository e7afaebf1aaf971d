"""The command lines the README and the user docs show are written as their commands take them: each names an
existing command, every override names a key of its config, and the composed config passes the config's checks
(a composition, not a run: the tiny profiles' runs are tested in test_recipe_*.py, test_cli.py and test_suite.py).
The README's Python quick start runs as written."""
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose
from hydra.core.override_parser.overrides_parser import OverridesParser

from umrl.cli.errors import unknown_key_errors
from umrl.configs import ConfigError, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig
from umrl.configs.suite import SuiteConfig
from umrl.configs.vime import VIMEConfig
from umrl.suite import CONFIG_DIR as SUITE_CONFIG_DIR
from umrl.trainers.config import CONFIG_DIR, config_dir

REPO = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "docs/quickstart.md", "docs/own_env.md"]
COMMAND = re.compile(r"^(?:python (?:recipes/(diayn|maml|vime)\.py|benchmarks/(suite)\.py)|umrl (diayn|maml|vime|suite))"
                     r"(?:\s+(.*))?$")
SCHEMAS = {"diayn": DIAYNConfig, "maml": MAMLConfig, "vime": VIMEConfig, "suite": SuiteConfig}
# a value that names the output of an earlier command on the page (a fresh tree does not hold it)
NEEDS_EARLIER_RUN = ("diayn_checkpoint",)


def code_blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", text, flags=re.DOTALL)


def doc_commands() -> list[tuple[str, str]]:
    """``(page, command line)`` for every umrl command in the pages' bash blocks (comments cut, continuations
    joined)."""
    found = []
    for page in PAGES:
        for block in code_blocks((REPO / page).read_text(), "bash"):
            for line in block.replace("\\\n", " ").splitlines():
                line = re.split(r"\s+#", line.strip(), maxsplit=1)[0].strip()
                if COMMAND.match(line):
                    found.append((page, line))
    return found


def first_values(overrides: list[str]) -> list[str]:
    """Hydra overrides with a sweep (``seed=0,1``) replaced by its first value."""
    parsed = OverridesParser.create().parse_overrides(overrides)
    return [f"{o.get_key_element()}={next(iter(o.sweep_string_iterator()))}" if o.is_sweep_override()
            else o.input_line for o in parsed]


def test_the_pages_show_commands():
    pages = {page for page, _ in doc_commands()}
    assert {"README.md", "docs/quickstart.md"} <= pages


@pytest.mark.parametrize("page, line", doc_commands())
def test_a_documented_command_composes_and_passes_its_checks(page, line):
    match = COMMAND.match(line)
    command = next(group for group in match.groups()[:3] if group)
    args = shlex.split(match.group(4) or "")
    kinds = "".join("o" if "=" in a and not a.startswith("-") else "f" for a in args)
    # argparse reads the overrides as one positional list: a flag between two of them ends it (exit status 2)
    assert not re.search(r"of+o", kinds), f"{page}: {line}: a flag between two overrides"
    directory = SUITE_CONFIG_DIR if command == "suite" else CONFIG_DIR
    assert unknown_key_errors(directory, command, args) == [], line
    if "--help" in args:
        return
    overrides = first_values([a for a in args if "=" in a and not a.startswith("-")])
    with config_dir(directory):
        cfg = compose(command, overrides=overrides)
    try:
        validate(cfg, SCHEMAS[command])
    except ConfigError as e:
        left = [error for error in e.errors if not error.startswith(NEEDS_EARLIER_RUN)]
        assert not left, f"{page}: {line}: {left}"


@pytest.mark.slow
def test_the_readme_python_quick_start_runs_as_written(tmp_path):
    """The README's snippet, in a fresh folder (it writes under outputs/): it prints the mean return at k = 0..3."""
    snippet = next(block for block in code_blocks((REPO / "README.md").read_text(), "python")
                   if "train(\"diayn\"" in block)
    out = subprocess.run([sys.executable, "-c", snippet], check=False, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    values = re.findall(r"-?\d+\.\d+", out.stdout.strip().splitlines()[-1])
    assert len(values) == 4, out.stdout
