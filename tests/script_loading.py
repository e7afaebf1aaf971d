"""Helpers for tests of the Hydra scripts in recipes/ and benchmarks/: import a script, compose its config."""
import importlib.util
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

REPO = Path(__file__).resolve().parents[1]


def load_script(relative_path: str):
    """Import ``REPO/relative_path`` (e.g. ``"recipes/diayn.py"``) as a module."""
    path = REPO / relative_path
    spec = importlib.util.spec_from_file_location(f"umrl_script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compose_config(config_dir: str, name: str, overrides) -> DictConfig:
    """Compose Hydra config ``name`` from ``REPO/config_dir`` with ``overrides``."""
    with initialize_config_dir(config_dir=str(REPO / config_dir), version_base="1.3"):
        return compose(name, overrides=list(overrides))
