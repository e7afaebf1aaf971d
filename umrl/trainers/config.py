"""The trainers' configs: composed by name from the defaults in ``umrl/configs/<name>.yaml`` with Hydra overrides.

The yaml files ship with the package (the one place each default lives; the schemas beside them,
:mod:`umrl.configs.maml` etc., say what is accepted); an env's defaults are the recipe's group file for it,
chosen from ``env.name`` (:mod:`umrl.configs.env_groups`). The recipes' command lines read the same files
(``@hydra.main(config_path="pkg://umrl.configs")``).

Example:
    >>> cfg = compose("maml", ["proposal=random", "env.horizon=7"])
    >>> cfg.proposal, cfg.env.horizon
    ('random', 7)
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

import umrl.configs
from umrl.configs.env_groups import with_env_group
from umrl.metatest.method_table import RECIPES

CONFIG_DIR = Path(umrl.configs.__file__).resolve().parent
"""Where the trainers' default configs live (``diayn.yaml``, ``maml.yaml``, ``vime.yaml``)."""

__all__ = ["CONFIG_DIR", "RECIPES", "check_name", "compose", "config_dir", "register_help_text"]


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


def check_name(name: str) -> None:
    """Refuse a name that is not one of :data:`~umrl.metatest.RECIPES`."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; valid choices: {list(RECIPES)}.")


def compose(name: str, overrides: Sequence[str] = ()) -> DictConfig:
    """The config of trainer ``name`` with command-line style ``overrides`` (``["env.name=ant", "seed=3"]``: ant's
    defaults, :func:`~umrl.configs.env_groups.with_env_group`); a misspelt key fails here, as on the command line."""
    check_name(name)
    with config_dir():
        return hydra_compose(name, overrides=with_env_group(name, overrides))


def register_help_text(directory: str | Path = CONFIG_DIR) -> None:
    """Make ``${umrl_config_text:<name>}`` the text of ``<directory>/<name>.yaml`` as written, comments included: the
    command lines' ``--help`` (their ``hydra.help.template``) shows every key with its comment. The command lines
    (:func:`umrl.cli.run`) call it before Hydra reads ``--help``."""
    def text(name: str) -> str:
        return (Path(directory) / f"{name}.yaml").read_text().replace("$", "$$")  # Hydra fills the template with
        # string.Template, where "$$" is a literal "$"

    OmegaConf.register_new_resolver("umrl_config_text", text, replace=True)
