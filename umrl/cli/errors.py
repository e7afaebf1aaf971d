"""How the command lines refuse bad input: the clear lines alone, no traceback, exit status 1.

Hydra prints a failing job as ``Error executing job with overrides: [...]``, a traceback, then the exception's
message, and answers a misspelt key with "To append to your config use +key=value". The command lines
(:mod:`umrl.cli`) instead print the :class:`~umrl.configs.ConfigError` lines, ``key: got <value>; expected <what is
accepted>``, a misspelt key getting "did you mean <key>?" (:func:`difflib.get_close_matches` against the config's
keys). ``HYDRA_FULL_ERROR=1``, Hydra's own switch, restores Hydra's behaviour with the full traceback.
"""
from __future__ import annotations

import difflib
import functools
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

from hydra import compose
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override
from hydra.errors import ConfigCompositionException, HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError

from umrl.configs import ConfigError
from umrl.folder_lock import FolderHoldsRun, FolderInUse
from umrl.trainers.config import config_dir
from umrl.validation import Invalid

__all__ = ["full_error_requested", "refuses_bad_config", "unknown_key_errors"]

RENAMED_KEYS: dict[str, dict[str, str]] = {
    "vime": {"trpo.gamma": "advantage.gamma", "trpo.gae_lambda": "advantage.lmbda"},
}
"""Keys a command's config renamed, ``{command: {old key: new key}}``: an old key is answered with its new name."""

OTHER_CONFIG_FLAGS = ("-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir")
"""Hydra's flags that compose another config than the command's own."""


def full_error_requested() -> bool:
    """Whether ``HYDRA_FULL_ERROR=1`` asks for errors raised with their traceback (Hydra's own test of it)."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1"


def refuses_bad_config(main: Callable[[DictConfig], None]) -> Callable[[DictConfig], None]:
    """``main`` (a Hydra task function) ending the process with the message of a :class:`~umrl.configs.ConfigError`
    or of a refused value (:data:`umrl.validation.Invalid`) or output folder (another run's, in use or holding
    checkpoints: :mod:`umrl.folder_lock`), exit status 1, instead of Hydra's report with a
    traceback; unchanged under :func:`full_error_requested`."""
    @functools.wraps(main)  # Hydra names the job after the wrapped function's module
    def refusing(cfg: DictConfig) -> None:
        try:
            main(cfg)
        except (ConfigError, *Invalid, FolderInUse, FolderHoldsRun) as e:
            if full_error_requested():
                raise
            raise SystemExit(str(e)) from None

    return refusing


def unknown_key_errors(directory: str | Path, config_name: str, args: Sequence[str]) -> list[str]:
    """One line for each override in ``args`` (a command line's arguments) that names no key of config
    ``config_name`` in ``directory``, with the closest key if there is one::

        maml.inner_lrr: got 0.1; expected a key of the maml config (did you mean maml.inner_lr?)

    Composes the config as Hydra will (a sweep ``key=a,b`` by its first value). Other composition errors (an
    override Hydra cannot parse, a profile that does not exist) and a command line that names another config
    (``--config-name``, ``--config-path``, ``--config-dir``) return ``[]``: Hydra's own message names them.
    """
    if any(a.split("=")[0] in OTHER_CONFIG_FLAGS for a in args):
        return []
    try:
        overrides = OverridesParser.create().parse_overrides([a for a in args if "=" in a and not a.startswith("-")])
    except HydraException:
        return []
    lines = {override.input_line: _one_value(override) for override in overrides}
    unknown: list[Override] = []
    with config_dir(directory):
        while True:
            try:
                cfg = compose(config_name, overrides=[line for line in lines.values() if line is not None])
                break
            except ConfigCompositionException as e:
                bad = _failed_override(e, [o for o in overrides if lines[o.input_line] is not None])
                if bad is None:
                    return []
                unknown.append(bad)
                lines[bad.input_line] = None
            except HydraException:
                return []
    keys = list(_keys(OmegaConf.to_container(cfg, resolve=False)))
    return [_unknown_key_line(o, keys, config_name) for o in unknown]


def _one_value(override: Override) -> str | None:
    """``override`` as a single-value override (a sweep by its first value), or None if it has no first value."""
    if not override.is_sweep_override():
        return override.input_line
    try:
        return f"{override.get_key_element()}={next(iter(override.sweep_string_iterator()))}"
    except (HydraException, StopIteration):  # e.g. interval(0,1): no values to list
        return None


def _failed_override(error: ConfigCompositionException, overrides: list[Override]) -> Override | None:
    """The override of ``overrides`` whose key ``error`` says is missing, or None for another error."""
    cause = error.__cause__
    if not isinstance(cause, (ConfigAttributeError, ConfigKeyError)) or not cause.full_key:
        return None
    missing = cause.full_key
    return next((o for o in overrides if o.key_or_group == missing or o.key_or_group.startswith(missing + ".")), None)


def _keys(node: Mapping, prefix: str = "") -> Iterator[str]:
    """Every key of a nested mapping as a dotted path, the inner ones too (``maml``, ``maml.inner_lr``)."""
    for key, value in node.items():
        yield f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from _keys(value, f"{prefix}{key}.")


def _unknown_key_line(override: Override, keys: list[str], config_name: str) -> str:
    """The error line of an override whose key is missing: the key whose last part is close to the override's
    (:func:`difflib.get_close_matches`' cutoff), the closest path among them (``inner_lr`` and ``mmal.inner_lr``
    suggest ``maml.inner_lr``, ``envz`` suggests ``envs`` before ``pretrain.vime.overrides.env``), else the keys
    beside it."""
    key, value = override.key_or_group, override.input_line.split("=", 1)[1]
    renamed = RENAMED_KEYS.get(config_name, {}).get(key)
    if renamed is not None:
        return f"{key}: got {value}; expected {renamed} (the key's new name)"
    name = key.rpartition(".")[2]

    def similarity(a: str, b: str) -> float:
        return difflib.SequenceMatcher(None, a, b).ratio()

    candidates = [k for k in keys if not key.startswith(k + ".") and similarity(name, k.rpartition(".")[2]) >= 0.6]
    if candidates:
        closest = max(candidates, key=lambda k: similarity(name, k.rpartition(".")[2]) + similarity(key, k))
        hint = f"did you mean {closest}?"
    else:
        parent = key.rpartition(".")[0] if key.rpartition(".")[0] in keys else ""
        hint = f"one of {', '.join(k for k in keys if k.rpartition('.')[0] == parent)}"
    return f"{key}: got {value}; expected a key of the {config_name} config ({hint})"
