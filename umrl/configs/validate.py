"""Check a composed config against its schema before any work starts; compare a resumed run's config to its saved one.

A schema is a dataclass (usable as a Hydra/OmegaConf structured config) whose fields are declared with the
helpers below: each holds the check of :mod:`umrl.validation` that its value must pass, the annotation gives the
type OmegaConf enforces later and ``Optional[...]`` lets the value be ``null``; nested dataclasses are config
groups. A schema may define ``cross_check(cfg: dict) -> list[str]`` (error lines) for rules that relate several keys; it runs
once every key passed its own check. A schema may define ``notices(cfg: dict) -> list[str]`` for values that
run, but not as written (a budget rounded up, say): each line is a warning once the config passed. Defaults live in the
yaml files, not here (every field is ``MISSING``).
"""
from __future__ import annotations

import dataclasses
import types
import typing
import warnings
from collections.abc import Callable, Collection, Iterable, Mapping
from functools import partial
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from umrl.configs.env_groups import env_defaults
from umrl.validation import (
    Invalid,
    bounds_text,
    check_bool,
    check_choice,
    check_float,
    check_int,
    check_list,
    check_mapping,
    check_name,
    check_path_exists,
    check_seed,
    check_str,
    check_writable_dir,
    resolve_device,
)

_CHECK = "umrl_check"


class ConfigError(ValueError):
    """Every bad key of a config, one ``key: got <value>; expected <what is accepted>`` line each."""

    def __init__(self, schema: str, errors: list[str]):
        errors = list(dict.fromkeys(errors))  # e.g. one reuse path shared by several seeds: said once
        self.errors = errors
        lines = "\n".join(f"  {e}" for e in errors)
        super().__init__(f"invalid config ({schema}, {len(errors)} error{'s' * (len(errors) > 1)}):\n{lines}")


# --- field declarations ----------------------------------------------------------------------------------------------


def checked(check: Callable[[str, Any], Any]) -> Any:
    """A required field whose value must pass ``check(key, value)`` (which returns the value to keep)."""
    return dataclasses.field(default=MISSING, metadata={_CHECK: check})


def group(schema: type) -> Any:
    """A nested config group described by the dataclass ``schema``."""
    return dataclasses.field(default_factory=schema)


def integer(*, min: int | None = None, max: int | None = None) -> Any:
    return checked(partial(check_int, min=min, max=max))


def number(**bounds: float) -> Any:
    """A finite float with ``gt``/``ge``/``lt``/``le`` bounds."""
    return checked(partial(check_float, **bounds))


def boolean() -> Any:
    return checked(check_bool)


def string() -> Any:
    return checked(check_str)


def name() -> Any:
    """A file name, not a path (:func:`umrl.validation.check_name`)."""
    return checked(check_name)


def choice(choices: Collection) -> Any:
    """One of ``choices``, read when checked (a live registry view such as ``umrl.envs.ENV_NAMES`` stays live)."""
    return checked(partial(check_choice, choices=choices))


def device() -> Any:
    """``cpu | cuda | auto``, resolved to the device used (``cuda`` refused without a GPU)."""
    return checked(resolve_device)


def existing_path() -> Any:
    return checked(check_path_exists)


def writable_dir() -> Any:
    """A directory to write into, existing or not (:func:`umrl.validation.check_writable_dir`)."""
    return checked(check_writable_dir)


def seed() -> Any:
    """A seed in ``[0, SEED_MAX]`` (:func:`umrl.validation.check_seed`)."""
    return checked(check_seed)


def mapping() -> Any:
    return checked(check_mapping)


def int_list(*, min: int | None = None, max: int | None = None, min_len: int = 0, unique: bool = False) -> Any:
    what = f"integers {bounds_text(ge=min, le=max)}".strip()
    item = partial(check_int, min=min, max=max)
    return checked(partial(check_list, item=item, min_len=min_len, unique=unique, what=what))


def number_list(*, min_len: int = 0, **bounds: float) -> Any:
    what = f"finite numbers {bounds_text(**bounds)}".strip()
    return checked(partial(check_list, item=partial(check_float, **bounds), min_len=min_len, what=what))


def choice_list(choices: Collection, *, min_len: int = 0, unique: bool = True) -> Any:
    """A list of entries of ``choices`` (read when checked, like :func:`choice`)."""

    def check(name: str, value: Any) -> list:
        what = f"names from {', '.join(repr(c) for c in choices)}"
        item = partial(check_choice, choices=choices)
        return check_list(name, value, item, min_len=min_len, unique=unique, what=what)

    return checked(check)


# --- validation ------------------------------------------------------------------------------------------------------


def _optional(annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    return origin in (typing.Union, types.UnionType) and type(None) in typing.get_args(annotation)


def _read(node: DictConfig, key: str) -> Any:
    """``node[key]`` with interpolations resolved, containers as plain Python lists/dicts."""
    value = node[key]
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _check_group(node: DictConfig, schema: type, prefix: str, errors: list[str], partial: bool = False) -> dict:
    hints = typing.get_type_hints(schema)
    fields = {f.name: f for f in dataclasses.fields(schema)}
    out: dict[str, Any] = {}
    for key in node:
        if key not in fields:
            errors.append(f"{prefix}{key}: unexpected key; expected one of the keys of {schema.__name__}: "
                          f"{', '.join(fields)}")
    for name, field in fields.items():
        path = f"{prefix}{name}"
        if name not in node:
            if not partial:
                errors.append(f"{path}: missing; {schema.__name__} requires it")
            continue
        annotation = hints[name]
        if dataclasses.is_dataclass(annotation):
            sub = node[name]
            if not isinstance(sub, DictConfig):
                errors.append(f"{path}: got {sub!r}; expected a group of keys {[f.name for f in dataclasses.fields(annotation)]}")
            else:
                out[name] = _check_group(sub, annotation, f"{path}.", errors, partial)
            continue
        try:
            value = _read(node, name)
        except OmegaConfBaseException as e:
            errors.append(f"{path}: cannot be read ({type(e).__name__}: {str(e).splitlines()[0]})")
            continue
        if value is None and _optional(annotation):
            out[name] = None
            continue
        try:
            out[name] = field.metadata[_CHECK](path, value)
        except Invalid as e:
            if _optional(annotation):
                e.expected = f"null or {e.expected}"
            errors.append(e.message())
    return out


def validate(cfg: DictConfig | Mapping, schema: type) -> DictConfig:
    """Check every key of ``cfg`` against ``schema`` and return the config to run with.

    Raises :class:`ConfigError` listing every bad, missing or unexpected key (never a bare ``TypeError`` or an
    OmegaConf dump); warns (``UserWarning``) each of the schema's ``notices``. The returned config is ``schema`` as an
    OmegaConf structured config (struct mode: a later typo or wrong type is refused) holding ``cfg``'s values with
    interpolations resolved and ``device`` resolved to ``cpu``/``cuda``.
    """
    node = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg))
    errors: list[str] = []
    values = _check_group(node, schema, "", errors)
    cross_check = getattr(schema, "cross_check", None)
    if not errors and cross_check is not None:
        errors += cross_check(values)
    if errors:
        raise ConfigError(schema.__name__, errors)
    for notice in getattr(schema, "notices", lambda _: [])(values):
        warnings.warn(notice, stacklevel=2)
    return OmegaConf.merge(OmegaConf.structured(schema), values)


def check_partial(values: Mapping, schema: type, prefix: str = "") -> list[str]:
    """Errors for the keys present in ``values`` (a subset of ``schema``'s, e.g. a suite's recipe overrides), each
    checked as :func:`validate` would; missing keys are fine, unknown ones are errors; no cross-checks."""
    errors: list[str] = []
    _check_group(OmegaConf.create(dict(values)), schema, prefix, errors, partial=True)
    return errors


# --- resume ----------------------------------------------------------------------------------------------------------

RESUME_ALLOW = (
    "device",
    "optim.compile",
    "optim.cudagraphs",
    "cudagraphs",
    "iterations",
    "collector.total_frames",
    "checkpoint.every",
    "checkpoint.keep_all",
    "logger",
    "progress",
    "resume",
    "output_dir",
)
"""Keys that may change when a run resumes: where and how it computes (``device``: checkpoints load on any device;
DIAYN's ``optim.compile`` / ``optim.cudagraphs``), the total budget (``iterations``, ``collector.total_frames``), how
often checkpoints are written and kept, logging, the progress bar, ``resume`` itself and ``output_dir`` (a moved run).
Every other key (seed, env, widths, skill counts, learning rates, TRPO settings...) must match the
checkpoint's saved config: changing it would silently continue a different run. An entry covers its sub-keys."""

RESUME_ADDED = {"compile": False, "network.discriminator_input_dims": None, "env.module": None,
                "policy.learn_std": True}
"""Keys added to a recipe after runs were saved without them, with the value that computes what those runs computed:
a checkpoint's config that lacks one matches a run with that value (MAML's ``compile``, DIAYN's whole-observation
discriminator, no ``env.module``, MAML's learned std)."""

RESUME_FROM_ENV = {"num_skills": "diayn", "default_num_skills": "maml", "discriminator_hidden": "maml"}
"""Keys whose env default runs saved before the per-env config groups (:mod:`umrl.configs.env_groups`) left out of
their config (DIAYN's ``num_skills`` saved as null, MAML's ``default_num_skills`` and ``discriminator_hidden``
absent), with the recipe whose group holds that default: such a checkpoint matches a run with the env's default."""

_ABSENT = "<absent>"


def _flatten(values: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(values, Mapping):
        out: dict[str, Any] = {}
        for key, value in values.items():
            out.update(_flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: values}


def _as_plain(cfg: DictConfig | Mapping) -> dict:
    return OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else dict(cfg)


def resume_diff(
    saved_cfg: DictConfig | Mapping, cfg: DictConfig | Mapping, allow: Iterable[str] = RESUME_ALLOW
) -> dict[str, tuple[Any, Any]]:
    """``{key: (saved value, new value)}`` for every dotted key whose value differs between a checkpoint's saved
    config and the resumed run's config, except keys under an entry of ``allow`` (see :data:`RESUME_ALLOW`).

    A key present on one side only shows ``"<absent>"`` on the other, unless the checkpoint lacks a key of
    :data:`RESUME_ADDED` that the run sets to the value listed there, or a key of :data:`RESUME_FROM_ENV`. Empty
    when the resume is faithful.
    """
    allow = tuple(allow)
    saved, new = _flatten(_as_plain(saved_cfg)), _flatten(_as_plain(cfg))
    diff = {}
    for key in sorted(saved.keys() | new.keys()):
        if any(key == a or key.startswith(f"{a}.") for a in allow):
            continue
        before, after = saved.get(key, _ABSENT), new.get(key, _ABSENT)
        if before is _ABSENT and key in RESUME_ADDED and after == RESUME_ADDED[key]:
            continue
        if before in (None, _ABSENT) and key in RESUME_FROM_ENV and after == _env_default(key, new["env.name"]):
            continue
        if before != after:
            diff[key] = (before, after)
    return diff


def _env_default(key: str, env_name: str) -> Any:
    return env_defaults(RESUME_FROM_ENV[key], env_name).get(key, _ABSENT)


def check_resume(saved_cfg: DictConfig | Mapping, cfg: DictConfig | Mapping, allow: Iterable[str] = RESUME_ALLOW) -> None:
    """Refuse (:class:`ConfigError`) a resume whose config differs from the checkpoint's beyond ``allow``."""
    diff = resume_diff(saved_cfg, cfg, allow)
    if diff:
        errors = [f"{key}: checkpoint has {a!r}, this run has {b!r}" for key, (a, b) in diff.items()]
        errors.append(f"resume only with the checkpoint's values for these keys (allowed to change: {', '.join(allow)})")
        raise ConfigError("resume", errors)
