"""Seeding and the random state of a run: every generator a faithful resume restores, and blocks that draw without
moving the training's generators."""
from __future__ import annotations

import random
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch


def seed_everything(seed: int) -> torch.Generator:
    """Seed Python, NumPy and torch; return a torch generator seeded with ``seed`` for explicit sampling."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def rng_state(**generators: torch.Generator) -> dict:
    """Every random generator a run draws from: ``{"torch", "cuda" (when available), "numpy", "python",
    "generators": {name: state}}`` for the explicit ``generators`` (restore with :func:`set_rng_state`)."""
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
             "generators": {name: g.get_state() for name, g in generators.items()}}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any], **generators: torch.Generator) -> None:
    """Restore what :func:`rng_state` captured, including the states of the named ``generators``."""
    missing = sorted(set(generators) - set(state["generators"]))
    if missing:
        raise KeyError(f"the saved RNG state has no generator {missing}; it holds {sorted(state['generators'])}.")
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    for name, generator in generators.items():
        generator.set_state(state["generators"][name])


@contextmanager
def isolated_rng() -> Iterator[None]:
    """Run a block (evaluation, figures) without moving the torch/CUDA global generators the training draws from."""
    with torch.random.fork_rng(devices=range(torch.cuda.device_count()) if torch.cuda.is_available() else []):
        yield
