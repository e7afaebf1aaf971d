"""The configs' ``env.module`` and ``env.name`` checks: a user's module registers its envs before the name is checked.

``env.module`` names a Python module (``my_pkg.my_env``) or a ``.py`` file (``examples/own_env.py``) whose import
calls :func:`~umrl.envs.register_env`; the recipes' schemas check it before ``env.name``, so ``env.name`` may be an
env it registers. Only the command line (or the config given to ``train``) names a module: a checkpoint's saved
config is never imported from.
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

from umrl.envs.registry import ENV_NAMES
from umrl.validation import InvalidValue, check_str

__all__ = ["check_env_name", "env_module_source", "import_env_module"]

_FILE_MODULES: dict[Path, ModuleType] = {}
"""Modules imported from a file path, by resolved path: a second config naming the same file imports it once."""


def import_env_module(name: str, value: Any) -> str:
    """Import ``value``, a dotted module name or a path to a ``.py`` file (relative to the working directory), once
    per process, and return it; an error naming ``name`` if it cannot be found or its import fails."""
    check_str(name, value)
    expected = "an importable module (my_pkg.my_env) or a .py file that registers envs with umrl.envs.register_env"
    try:
        if value.endswith(".py"):
            path = Path(value).resolve()
            if path not in _FILE_MODULES:
                if not path.is_file():
                    raise InvalidValue(name, value, expected, note=f"{path} is not a file")
                spec = importlib.util.spec_from_file_location(f"umrl_env_module_{path.stem}", path)
                module = importlib.util.module_from_spec(spec)
                sys.modules[spec.name] = module  # dataclasses and pickling look the module up by name
                spec.loader.exec_module(module)
                _FILE_MODULES[path] = module
        else:
            importlib.import_module(value)
    except InvalidValue:
        raise
    except Exception as e:
        raise InvalidValue(name, value, expected, note=f"importing it raised {type(e).__name__}: {e}") from e
    return value


def env_module_source(value: str) -> Path:
    """Where the source of ``value`` (as :func:`import_env_module` takes it) lives: the ``.py`` file itself, a
    dotted module's file, or its package's folder when it names a package (the code a result made on its envs ran
    with, for cache keys)."""
    if value.endswith(".py"):
        return Path(value).resolve()
    spec = importlib.util.find_spec(value)
    if spec is None or spec.origin is None:
        raise InvalidValue("env_module", value, "an importable module with a source file")
    origin = Path(spec.origin)
    return origin.parent if spec.submodule_search_locations else origin


def check_env_name(name: str, value: Any) -> str:
    """``value`` if it is a registered env (:data:`~umrl.envs.ENV_NAMES`, read now); for an unregistered
    ``gym:<EnvId>`` the error says whether gymnasium knows the id and how to register its task family."""
    check_str(name, value)
    if value in ENV_NAMES:
        return value
    registered = ", ".join(map(repr, ENV_NAMES))
    if value.startswith("gym:"):
        from umrl.envs.gym_cmp import check_gym_id  # gymnasium and MuJoCo: imported for gym names only

        gym_id = value[len("gym:"):]
        try:
            check_gym_id(name, gym_id)
        except InvalidValue as e:
            raise InvalidValue(name, value, f"gym:<EnvId> with {e.expected}", note=e.note) from None
        raise InvalidValue(name, value, f"one of {registered}, or a gym:<EnvId> registered with its task family",
                           note=f"gymnasium has {gym_id}, but no task family is registered for it: set env.module to "
                                f"a module that calls register_env(gym_env_spec({gym_id!r}, ...)), docs/own_env.md")
    raise InvalidValue(name, value, f"one of {registered}, or gym:<EnvId> registered by env.module (docs/own_env.md)")
