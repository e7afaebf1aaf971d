"""Helpers for tests of the Hydra scripts in benchmarks/: import a script, compose its config (recipes are a package:
``from recipes import compose``)."""
import importlib.util
from pathlib import Path

from hydra import compose
from omegaconf import DictConfig

from recipes import config_dir

REPO = Path(__file__).resolve().parents[1]


def load_script(relative_path: str):
    """Import ``REPO/relative_path`` (e.g. ``"recipes/diayn.py"``) as a module."""
    path = REPO / relative_path
    spec = importlib.util.spec_from_file_location(f"umrl_script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compose_config(directory: str, name: str, overrides) -> DictConfig:
    """Compose Hydra config ``name`` from ``REPO/directory`` with ``overrides``."""
    with config_dir(REPO / directory):
        return compose(name, overrides=list(overrides))
