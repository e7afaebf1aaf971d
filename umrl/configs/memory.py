"""Memory preflight: refuse, before any work, sizes whose largest allocations cannot fit in the memory of the device
they go to.

The estimate is a cheap lower bound, not a dry run: the float32 observation, next observation and action of every
env step or transition a run stores at once (what else a recipe stores per step only adds to it). A size is refused
when that bound alone exceeds what the device has available now; anything below may still run out later.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from umrl.envs import get_env_spec
from umrl.validation import InvalidValue, resolve_device

FLOAT_BYTES = 4
_UNITS = ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB")


@dataclass(frozen=True)
class Allocation:
    """``value`` (the config key ``key``'s) items of ``item_bytes`` each, held at once; ``what`` names them in a
    message (``"replay buffer"``) and ``given`` the other keys the item size depends on (``"with env.horizon=100"``)."""

    key: str
    value: int
    item_bytes: int
    what: str
    given: str = ""

    @property
    def bytes(self) -> int:
        return self.value * self.item_bytes


def step_bytes(env_name: str, extra_floats: int = 0) -> int:
    """Lower bound of the bytes one stored env step of ``env_name`` takes: its float32 observation, next observation
    and action, plus ``extra_floats`` (e.g. DIAYN's skill one-hots)."""
    spec = get_env_spec(env_name)
    return FLOAT_BYTES * (2 * spec.obs_dim + spec.act_dim + extra_floats)


def available_memory(device: str) -> int | None:
    """Bytes that can still be allocated on ``device`` (``cpu``, ``cuda`` or ``auto``): the GPU's free memory, Linux's
    ``MemAvailable``, else the physical memory; ``None`` where neither can be read."""
    if resolve_device("device", device) == "cuda":
        return torch.cuda.mem_get_info()[0]
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def format_bytes(count: float) -> str:
    """``1.5e12`` -> ``"1.364 TiB"``."""
    unit = 0
    while count >= 1024 and unit < len(_UNITS) - 1:
        count, unit = count / 1024, unit + 1
    return f"{count:.4g} {_UNITS[unit]}"


def allocation_errors(allocations: Sequence[Allocation], device: str) -> list[str]:
    """The error of the largest of ``allocations`` when together they exceed :func:`available_memory` on ``device``
    (none if it is unknown), with the most that key could take next to the others (named when the largest alone
    would fit)."""
    available = available_memory(device)
    total = sum(a.bytes for a in allocations)
    if available is None or total <= available:
        return []
    big = max(allocations, key=lambda a: a.bytes)
    room = max(0, available - (total - big.bytes)) // big.item_bytes
    note = f"≈ {format_bytes(big.bytes)} of {big.what}"
    if big.bytes <= available:  # too much only with the others
        note += f", {format_bytes(total)} with {', '.join(a.key for a in allocations if a is not big)}"
    where = "free on the GPU" if resolve_device("device", device) == "cuda" else "available"
    given = f" {big.given}" if big.given else ""
    return [InvalidValue(big.key, big.value, f"at most {room}{given} on this machine ({format_bytes(available)} {where})",
                         note=note).message()]
