"""Argument checks shared by the Python API and the config schemas (:mod:`umrl.configs`).

Each helper checks one property of one argument and returns the (normalised) value, or raises an error naming the
argument, the bad value and what is accepted, in one format::

    inner_lr: got nan; expected a finite number > 0

Wrong types raise :class:`InvalidType` (a ``TypeError``), wrong values :class:`InvalidValue` (a ``ValueError``);
both carry ``name``, ``value`` and ``expected`` so :func:`umrl.configs.validate` can gather many into one report.
"""
from __future__ import annotations

import math
import numbers
import os
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

DEVICES = ("cpu", "cuda", "auto")

SEED_MAX = 2**63 - 1
"""The largest seed accepted: ``torch.manual_seed`` takes up to ``2**64 - 1``, and umrl derives further seeds by adding
offsets (DIAYN's evaluation env, the suite's sweep tasks), so seeds stay within int64."""


def describe(value: Any, limit: int = 240) -> str:
    """A short printable form of ``value`` for error messages (tensors by shape and dtype, TensorDicts by batch
    size, modules by class)."""
    if isinstance(value, TensorDictBase):
        return f"a {type(value).__name__} of batch size {list(value.batch_size)}"
    if isinstance(value, torch.nn.Module):
        return f"a {type(value).__name__}"
    if isinstance(value, torch.Tensor) and value.numel() > 1:
        return f"a tensor of shape {list(value.shape)} and dtype {value.dtype}"
    text = repr(value.item() if isinstance(value, torch.Tensor) else value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _Invalid(Exception):
    """``<name>: got <value>[ (<note>)]; expected <expected>``."""

    def __init__(self, name: str, value: Any, expected: str, note: str | None = None):
        self.name, self.value, self.expected, self.note = name, value, expected, note
        super().__init__(self.message())

    def message(self) -> str:
        note = f" ({self.note})" if self.note else ""
        return f"{self.name}: got {describe(self.value)}{note}; expected {self.expected}"


class InvalidValue(_Invalid, ValueError):
    """A value of an accepted type outside what is accepted."""


class InvalidType(_Invalid, TypeError):
    """A value of a type that is not accepted."""


Invalid = (InvalidValue, InvalidType)


def bounds_text(
    gt: float | None = None, ge: float | None = None, lt: float | None = None, le: float | None = None
) -> str:
    """``"> 0"``, ``">= 1"``, ``"in (0, 1]"`` or ``""`` for the given bounds."""
    low, low_open = (gt, True) if gt is not None else (ge, False)
    high, high_open = (lt, True) if lt is not None else (le, False)
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{_bound(low)}, {_bound(high)}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {_bound(low)}"
    if high is not None:
        return f"{'<' if high_open else '<='} {_bound(high)}"
    return ""


def _bound(value: float) -> str:
    """Integers in full (``9223372036854775807``, not ``9.22337e+18``), floats short."""
    return str(value) if isinstance(value, int) else f"{value:g}"


def _in_bounds(value: float, gt: float | None, ge: float | None, lt: float | None, le: float | None) -> bool:
    return not ((gt is not None and value <= gt) or (ge is not None and value < ge)
                or (lt is not None and value >= lt) or (le is not None and value > le))


def check_int(name: str, value: Any, *, min: int | None = None, max: int | None = None) -> int:
    """``value`` as an ``int`` (booleans and non-integral numbers are refused) within ``[min, max]``."""
    expected = " ".join(["an integer", bounds_text(ge=min, le=max)]).strip()
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InvalidType(name, value, expected)
    if not _in_bounds(value, None, min, None, max):
        raise InvalidValue(name, value, expected)
    return int(value)


def check_float(
    name: str,
    value: Any,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
) -> float:
    """``value`` as a finite ``float`` (ints accepted, booleans refused) within the given bounds."""
    expected = " ".join(["a finite number", bounds_text(gt=gt, ge=ge, lt=lt, le=le)]).strip()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InvalidType(name, value, expected)
    if not math.isfinite(value) or not _in_bounds(value, gt, ge, lt, le):
        raise InvalidValue(name, value, expected)
    return float(value)


def check_positive(name: str, value: Any) -> float:
    """``value`` as a finite ``float`` > 0 (learning rates, step sizes, scales)."""
    return check_float(name, value, gt=0)


def check_probability(name: str, value: Any) -> float:
    """``value`` as a finite ``float`` in [0, 1] (discounts, GAE lambda, fractions that may be 0 or 1)."""
    return check_float(name, value, ge=0, le=1)


def check_finite(name: str, value: Any) -> Any:
    """``value`` (a number or a floating/integer tensor) with no NaN or infinite entry, returned unchanged."""
    if not isinstance(value, torch.Tensor):
        return check_float(name, value)
    if value.is_complex() or value.dtype == torch.bool:
        raise InvalidType(name, value, "a real-valued tensor")
    bad = ~torch.isfinite(value)
    if bad.any():
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise InvalidValue(name, value, "finite values only",
                           note=f"{int(bad.sum())} non-finite, first at index {first}: {value[first].item()}")
    return value


def check_not_diverged(values: Mapping[str, Any], where: str) -> None:
    """The training loops' guard: ``FloatingPointError`` naming every tensor of ``values`` (losses, rewards,
    adapted parameters) holding a NaN or an infinity, ``where`` saying which step produced them. Not an argument
    check (:func:`check_finite` is): the inputs were valid and the run diverged."""
    bad = [k for k, v in values.items() if torch.is_tensor(v) and not torch.isfinite(v).all()]
    if bad:
        raise FloatingPointError(
            f"non-finite {bad} in {where}: lower the learning rate or check the inputs; the last checkpoint is intact."
        )


def check_bool(name: str, value: Any) -> bool:
    """``value`` if it is a ``bool`` (``true``/``false`` in a config)."""
    if not isinstance(value, bool):
        raise InvalidType(name, value, "true or false")
    return value


def check_str(name: str, value: Any) -> str:
    """``value`` if it is a non-empty ``str``."""
    if not isinstance(value, str):
        raise InvalidType(name, value, "a non-empty string")
    if not value:
        raise InvalidValue(name, value, "a non-empty string")
    return value


MAX_THREADS = 1024
"""The most torch threads a config may ask for: far above any machine umrl runs on, below the counts at which
OpenMP's runtime aborts the process instead of raising."""

NAME_MAX_BYTES = 255
"""The longest file or folder name (one path component, UTF-8 bytes) Linux file systems accept."""


def check_name(name: str, value: Any) -> str:
    """``value`` if it is a file name (a run's or report's name), not a path: non-empty, without ``/``, ``\\`` or
    NUL, not ``.`` or ``..`` (such a name would write outside the folder it is meant for), and at most
    :data:`NAME_MAX_BYTES` bytes."""
    expected = f"a name without path separators (not '.' or '..'), of at most {NAME_MAX_BYTES} bytes"
    if not isinstance(value, str):
        raise InvalidType(name, value, expected)
    if value in ("", ".", "..") or any(c in value for c in "/\\\0") or len(value.encode()) > NAME_MAX_BYTES:
        raise InvalidValue(name, value, expected)
    return value


def check_seed(name: str, value: Any) -> int:
    """``value`` as a seed: an ``int`` in ``[0, SEED_MAX]`` (:data:`SEED_MAX`)."""
    return check_int(name, value, min=0, max=SEED_MAX)


def check_writable_dir(name: str, value: Any) -> str:
    """``value`` if it is a path (``str``) to a directory this process can write into, or can create: every folder
    name in it at most :data:`NAME_MAX_BYTES` bytes, every part of it that exists a directory and the deepest
    existing one writable. Nothing is created."""
    check_str(name, value)
    path = Path(value).absolute()
    too_long = [part for part in path.parts if len(part.encode()) > NAME_MAX_BYTES]
    if too_long or "\0" in value:
        raise InvalidValue(name, value, f"a path whose every folder name has at most {NAME_MAX_BYTES} bytes (no NUL)",
                           note=f"{len(too_long[0].encode())} bytes in {too_long[0][:40]}..." if too_long else None)
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        fault = "a file" if existing.is_file() else "not a directory"
    elif not os.access(existing, os.W_OK | os.X_OK):
        fault = "not writable"
    else:
        return value
    raise InvalidValue(name, value, "a writable directory", note=fault if existing == path else f"{existing} is {fault}")


def check_choice(name: str, value: Any, choices: Collection) -> Any:
    """``value`` if it is one of ``choices``."""
    try:
        accepted = value in choices
    except TypeError:  # an unhashable value against a set or mapping of choices
        accepted = False
    if not accepted:
        raise InvalidValue(name, value, f"one of {', '.join(repr(c) for c in choices)}")
    return value


def check_path_exists(name: str, value: Any) -> str:
    """``value`` if it is a path (``str``) to an existing file or directory; relative paths are taken from the cwd."""
    check_str(name, value)
    if not Path(value).exists():
        raise InvalidValue(name, value, "an existing file or directory", note=f"{Path(value).absolute()} does not exist")
    return value


def check_list(
    name: str,
    value: Any,
    item: Callable[[str, Any], Any],
    *,
    min_len: int = 0,
    unique: bool = False,
    what: str = "items",
) -> list:
    """``value`` as a ``list`` whose entries pass ``item(f"{name}[i]", entry)``.

    ``min_len`` and ``unique`` constrain the list; ``what`` names the entries in the message (``"integers >= 0"``).
    """
    expected = f"a {'non-empty ' if min_len == 1 else ''}list of {'distinct ' if unique else ''}{what}"
    if min_len > 1:
        expected += f" (at least {min_len})"
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Sequence):
        raise InvalidType(name, value, expected)
    if len(value) < min_len:
        raise InvalidValue(name, value, expected)
    checked = [item(f"{name}[{i}]", entry) for i, entry in enumerate(value)]
    if unique and len(set(map(repr, checked))) < len(checked):
        raise InvalidValue(name, value, expected, note="repeated entries")
    return checked


def check_keys(name: str, value: Any, keys: Sequence, expected: str) -> TensorDictBase:
    """``value`` if it is a TensorDict holding every key of ``keys`` (nested keys as tuples); the note names the
    missing ones. ``expected`` says what the batch is (``"transitions with the keys [...]"``)."""
    if not isinstance(value, TensorDictBase):
        raise InvalidType(name, value, expected)
    missing = [key for key in keys if value.get(key, None) is None]
    if missing:
        raise InvalidValue(name, value, expected, note=f"no {', '.join(map(repr, missing))}")
    return value


def check_mapping(name: str, value: Any) -> dict:
    """``value`` as a ``dict`` with string keys (free-form settings such as Hydra overrides)."""
    if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
        raise InvalidType(name, value, "a mapping with string keys")
    return dict(value)


def resolve_device(name: str, value: Any) -> str:
    """``"cpu"`` or ``"cuda"`` for a device setting in :data:`DEVICES`; ``"auto"`` picks CUDA when available.

    ``"cuda"`` without a CUDA device is refused (the choices that work here are ``cpu`` and ``auto``).
    """
    check_choice(name, value, DEVICES)
    cuda = torch.cuda.is_available()
    if value == "cuda" and not cuda:
        raise InvalidValue(name, value, "one of 'cpu', 'auto'", note="no CUDA device is available on this machine")
    if value == "auto":
        return "cuda" if cuda else "cpu"
    return value


def check_device(name: str, value: Any) -> torch.device:
    """``value`` (a ``torch.device`` or its name, or ``"auto"``, see :func:`resolve_device`) as a ``torch.device``;
    a CUDA device is refused where none (or not that index) is available, like ``"cuda"`` in a config."""
    if isinstance(value, str) and value in DEVICES:
        return torch.device(resolve_device(name, value))
    try:
        device = torch.device(value)
    except (RuntimeError, TypeError):
        raise InvalidValue(name, value, "a torch.device or one of 'cpu', 'cuda', 'auto'") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if not count:
            raise InvalidValue(name, value, "one of 'cpu', 'auto'", note="no CUDA device is available on this machine")
        if device.index is not None and device.index >= count:
            raise InvalidValue(name, value, f"a CUDA device index below {count}",
                               note=f"this machine has {count} CUDA device{'s' if count > 1 else ''}")
    return device


__all__ = [
    "DEVICES",
    "SEED_MAX",
    "Invalid",
    "InvalidType",
    "InvalidValue",
    "bounds_text",
    "check_bool",
    "check_choice",
    "check_device",
    "check_finite",
    "check_float",
    "check_int",
    "check_keys",
    "check_list",
    "check_mapping",
    "check_not_diverged",
    "check_path_exists",
    "check_positive",
    "check_probability",
    "check_seed",
    "check_str",
    "check_writable_dir",
    "resolve_device",
]
