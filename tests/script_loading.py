"""Helpers for tests of the Hydra scripts in benchmarks/ and recipes/: import a script, compose its config (the
trainers' configs compose from the library: ``from umrl.trainers import compose``)."""
import importlib.util
import sys
from pathlib import Path

from hydra import compose
from omegaconf import DictConfig

from umrl.trainers import config_dir

REPO = Path(__file__).resolve().parents[1]


def load_script(relative_path: str):
    """Import ``REPO/relative_path`` (e.g. ``"benchmarks/suite.py"``) as module ``umrl_script_<stem>``, once per
    session: it is registered in ``sys.modules`` (its dataclasses resolve their annotations there) and reused."""
    path = REPO / relative_path
    name = f"umrl_script_{path.stem}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name]


def compose_config(directory: str, name: str, overrides) -> DictConfig:
    """Compose Hydra config ``name`` from ``REPO/directory`` with ``overrides``."""
    with config_dir(REPO / directory):
        return compose(name, overrides=list(overrides))
