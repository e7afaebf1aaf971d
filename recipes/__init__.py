"""umrl's training recipes, importable and scriptable.

Each recipe module (:mod:`recipes.diayn`, :mod:`recipes.maml`, :mod:`recipes.vime`) has ``train(cfg) -> dict`` (the
final metrics and the ``"checkpoint"`` path) and ``main``, its ``@hydra.main`` command line
(``python recipes/<name>.py key=value ...``). From Python, compose the config with the same override syntax::

    from recipes import compose
    from recipes.maml import train

    result = train(compose("maml", ["proposal=random", "iterations=10", "logger.backend=none"]))

or in one call ``recipes.train("maml", [...])``. Configs live in ``recipes/config/<name>.yaml``.
"""
from __future__ import annotations

import importlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

CONFIG_DIR = Path(__file__).resolve().parent / "config"
RECIPES = ("diayn", "maml", "vime")

__all__ = ["CONFIG_DIR", "RECIPES", "compose", "config_dir", "register_help_text", "train"]


@contextmanager
def config_dir(directory: str | Path = CONFIG_DIR) -> Iterator[None]:
    """Hydra's compose API initialised on ``directory``, also inside a running ``@hydra.main`` (whose global Hydra
    state is set aside and restored)."""
    outer = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(directory), version_base="1.3"):
            yield
    finally:  # initialize_config_dir swaps the GlobalHydra singleton: look it up again
        GlobalHydra.instance().clear()
        if outer is not None:
            GlobalHydra.instance().initialize(outer)


def _check_name(name: str) -> None:
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; valid choices: {list(RECIPES)}.")


def compose(name: str, overrides: Sequence[str] = ()) -> DictConfig:
    """The config of recipe ``name`` with command-line style ``overrides`` (``["env.name=ant", "seed=3"]``); a
    misspelt key fails here, as on the command line."""
    _check_name(name)
    with config_dir():
        return hydra_compose(name, overrides=list(overrides))


def train(name: str, overrides: Sequence[str] = ()) -> dict:
    """Run recipe ``name`` in this process: ``recipes.<name>.train(compose(name, overrides))``."""
    _check_name(name)
    return importlib.import_module(f"recipes.{name}").train(compose(name, overrides))


def register_help_text(directory: str | Path = CONFIG_DIR) -> None:
    """Make ``${umrl_config_text:<name>}`` the text of ``<directory>/<name>.yaml`` as written, comments included: the
    scripts' ``--help`` (their ``hydra.help.template``) shows every key with its comment. The scripts call it under
    ``if __name__ == "__main__"``, before Hydra reads ``--help``."""
    def text(name: str) -> str:
        return (Path(directory) / f"{name}.yaml").read_text().replace("$", "$$")  # Hydra fills the template with
        # string.Template, where "$$" is a literal "$"

    OmegaConf.register_new_resolver("umrl_config_text", text, replace=True)
