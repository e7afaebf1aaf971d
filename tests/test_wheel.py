"""umrl as a library install: the wheel holds the package, its configs (the suite's too) and the ``umrl`` console
script; installed into a fresh venv without network, ``umrl maml`` runs from a folder outside the checkout, and
the Python path (``umrl.trainers.train`` under ``umrl.process.torch_threads(cfg.num_threads)``) gives its numbers.

The fresh venv has no pip and no dependencies of its own: the wheel goes in with ``pip --python <venv> install
--no-deps --no-index`` and a ``.pth`` file puts this interpreter's site-packages (torch, torchrl, ...) after the
venv's own, so ``umrl`` is the wheel's (that folder's editable umrl hook is a ``.pth`` file of its own, which Python
reads only in a site directory).
"""
import os
import shutil
import subprocess
import sys
import sysconfig

import pytest
import torch
from hydra import compose as hydra_compose
from script_loading import REPO

import umrl.trainers
from umrl.checkpoints import load_maml_checkpoint
from umrl.process import torch_threads
from umrl.trainers import config_dir

TINY = ["+profile=maml_tiny", "iterations=2", "logger.backend=none", "progress=false"]


def _run(command, **kwargs):
    proc = subprocess.run(command, check=False, capture_output=True, text=True, timeout=600, **kwargs)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def _install_wheel(tmp_path):
    """Build the wheel from a copy of the package's files, install it into a fresh venv; returns the venv's
    ``bin`` and ``site-packages`` folders."""
    source = tmp_path / "source"
    shutil.copytree(REPO / "umrl", source / "umrl", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, source / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    _run([*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", "-w", str(tmp_path / "dist"),
          str(source)])
    (wheel,) = (tmp_path / "dist").glob("umrl-*.whl")
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    _run([*pip, "--python", str(venv / "bin" / "python"), "install", "--no-deps", "--no-index", "-q", str(wheel)])
    site = venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    (site / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return venv / "bin", site


@pytest.mark.slow
def test_the_installed_console_script_runs_a_recipe_outside_the_checkout_as_python_does(tmp_path):
    bin_dir, site = _install_wheel(tmp_path)
    assert (site / "umrl" / "suite" / "config" / "profile" / "tiny.yaml").is_file()
    with config_dir(site / "umrl" / "suite" / "config"):  # the installed suite config composes
        assert hydra_compose("suite", ["profile=tiny"]).profile_name == "tiny"

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "HYDRA_FULL_ERROR")}
    out = _run([str(bin_dir / "umrl"), "maml", *TINY, f"output_dir={tmp_path / 'cli'}"], cwd=elsewhere,
               env={**env, "WANDB_MODE": "disabled"})
    assert "maml point_nav finished: iteration 2" in out.stdout
    assert (site / "umrl" / "cli" / "__pycache__").is_dir()  # the wheel's umrl ran, not the checkout's
    assert not (elsewhere / "outputs").exists()

    overrides = [*TINY, f"output_dir={tmp_path / 'python'}"]
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # a caller's count other than the config's num_threads=1
    try:
        with torch_threads(umrl.trainers.compose("maml", overrides).num_threads):
            umrl.trainers.train("maml", overrides)
    finally:
        torch.set_num_threads(before)
    cli, python = load_maml_checkpoint(tmp_path / "cli"), load_maml_checkpoint(tmp_path / "python")
    assert cli["iteration"] == python["iteration"] == 2 and cli["env_steps"] == python["env_steps"]
    assert cli["policy"].keys() == python["policy"].keys()
    for name, value in cli["policy"].items():
        assert torch.equal(value, python["policy"][name]), name
