"""Each recipe's per-env defaults: the Hydra config group ``<recipe>_env`` chosen from ``env.name``.

A recipe whose defaults depend on the env (DIAYN's episode length, budget, skill count and widths; MAML's iterations
and its random proposal's discriminator) lists the group in its yaml's ``defaults``; one file per built-in env
(``umrl/configs/diayn_env/point_nav.yaml``, ...) holds that env's values with their sources, and ``default.yaml`` those
of an env umrl does not ship (``env.name=gym:<EnvId>``). The composed config holds the values the run uses, so
``--cfg job`` shows them.

A user keeps typing ``env.name=half_cheetah``: :func:`with_env_group` turns it into the group choice
(``diayn_env=half_cheetah``) for the command lines (:func:`umrl.cli.run`) and :func:`umrl.trainers.compose`; an
explicit choice (``diayn_env=ant``) is left alone. Each built-in env's file sets ``env.name`` too, so a sweep
``-m env.name=point_nav,ant`` becomes ``-m diayn_env=point_nav,ant`` and each job gets its env's defaults.

Example:
    >>> with_env_group("diayn", ["env.name=ant", "seed=3"])
    ['env.name=ant', 'seed=3', 'diayn_env=ant']
    >>> env_defaults("maml", "half_cheetah")["iterations"]
    475
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import cache
from pathlib import Path

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import OmegaConf

CONFIG_DIR = Path(__file__).resolve().parent

ENV_GROUPS = {"diayn": "diayn_env", "maml": "maml_env"}
"""``{recipe: its per-env group}``; a recipe not listed (VIME) has no env-dependent defaults."""

GENERIC = "default"
"""The group choice of an env without its own file (a user's ``gym:<EnvId>``)."""

__all__ = ["ENV_GROUPS", "GENERIC", "env_defaults", "env_group_choice", "with_env_group", "with_env_group_argv"]


def env_group_choice(recipe: str, env_name: str) -> str:
    """The ``<recipe>_env`` choice for ``env_name``: its own file, else :data:`GENERIC`."""
    return env_name if (CONFIG_DIR / ENV_GROUPS[recipe] / f"{env_name}.yaml").is_file() else GENERIC


@cache
def _group_file(recipe: str, choice: str) -> dict:
    return OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / ENV_GROUPS[recipe] / f"{choice}.yaml"))


def env_defaults(recipe: str, env_name: str) -> dict:
    """The values ``recipe``'s group file holds for ``env_name`` (nested as in the recipe's config), e.g. for a
    report that compares a run's budget with the reference's; read-only (a copy)."""
    return OmegaConf.to_container(OmegaConf.create(_group_file(recipe, env_group_choice(recipe, env_name))))


def with_env_group(recipe: str, overrides: Sequence[str]) -> list[str]:
    """``overrides`` (Hydra's command-line syntax) with ``recipe``'s group chosen from their ``env.name``.

    Unchanged when the recipe has no group, no override sets ``env.name`` (the yaml's default env and group
    agree), an override chooses the group itself, or Hydra cannot parse them (Hydra reports that). A single
    ``env.name=X`` adds ``<group>=X`` (or ``<group>=default``); a sweep over built-in envs is replaced by the
    same sweep of the group, whose files set ``env.name``.

    Raises:
        ValueError: a sweep of ``env.name`` that mixes built-in envs and others (one command per kind).
    """
    overrides = list(overrides)
    group = ENV_GROUPS.get(recipe)
    if group is None:
        return overrides
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException:
        return overrides
    if any(o.key_or_group.lstrip("+~") == group for o in parsed):
        return overrides
    setting = [(i, o) for i, o in enumerate(parsed) if o.key_or_group == "env.name" and not o.is_delete()]
    if not setting:
        return overrides
    index, override = setting[-1]
    if not override.is_sweep_override():
        return [*overrides, f"{group}={env_group_choice(recipe, str(override.value()))}"]
    names = [str(v) for v in override.sweep_string_iterator()]
    choices = [env_group_choice(recipe, name) for name in names]
    if all(choice == GENERIC for choice in choices):
        return [*overrides, f"{group}={GENERIC}"]
    if GENERIC in choices:
        raise ValueError(f"{override.input_line}: a sweep of env.name over built-in envs and others; run one command "
                         f"for the built-in envs ({', '.join(n for n, c in zip(names, choices) if c != GENERIC)}) and "
                         "one per other env.")
    return [*overrides[:index], f"{group}={','.join(names)}", *overrides[index + 1:]]


def with_env_group_argv(recipe: str, argv: Sequence[str]) -> list[str]:
    """A command line's arguments ``argv`` with :func:`with_env_group` applied to its overrides (the ``key=value``
    arguments); flags (``-m``, ``--cfg job``) keep their places."""
    is_override = ["=" in a and not a.startswith("-") for a in argv]
    overrides = [a for a, o in zip(argv, is_override) if o]
    grouped = with_env_group(recipe, overrides)
    if grouped == overrides:
        return list(argv)
    return [a for a, o in zip(argv, is_override) if not o] + grouped
