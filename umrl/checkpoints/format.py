"""The one format/version check every checkpoint loader and every ``resume=true`` goes through.

A umrl checkpoint is a dict (stored by :mod:`umrl.checkpoints.file`: data only, hash-checked) with ``"format"`` (a
versioned name such as ``"umrl.maml.v1"``), ``"meta"`` (what a loader needs to rebuild the networks) and
format-specific entries. :class:`CheckpointFormat` names one format, the ``meta`` keys its loaders read and the
networks it holds (:class:`Network`), and does the saving (stamping ``"format"``) and the checked loading.

A file's hash proves nothing about who wrote it, so the checked loading treats the state as untrusted: every number
in ``meta`` and every weight must be finite, the layer widths ``meta`` describes must be whole numbers in
[1, :data:`MAX_WIDTH`] whose weights the file actually holds (checked before any network is built, so a few bytes
cannot ask for gigabytes), and each network must load into the module ``meta`` describes. A failure is a
:class:`~umrl.checkpoints.file.CheckpointError` naming the file and the key, and ``resume=true`` falls back to the
previous checkpoint.
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any

import torch

from umrl.checkpoints.file import CheckpointError, read_checkpoint
from umrl.checkpoints.folder import Checkpointer, checkpoint_path, resolve_checkpoint
from umrl.envs.registry import ENV_NAMES, check_observation_size
from umrl.plain_config import to_container
from umrl.rng import isolated_rng
from umrl.validation import InvalidValue

__all__ = ["MAX_LAYERS", "MAX_WIDTH", "CheckpointFormat", "Network", "check_budget_left"]

MAX_WIDTH = 2**20
"""The largest layer width (observation, action, skill or hidden size) a checkpoint's ``meta`` may name."""
MAX_LAYERS = 64
"""The most layer widths (input, hidden layers, output) one network of a checkpoint may have."""


def check_budget_left(key: str, budget: int, done: int, unit: str, run_dir: str | os.PathLike) -> None:
    """Refuse a ``resume=true`` whose budget (config key ``key``, in ``unit``) is not beyond the ``done`` the run in
    ``run_dir`` has already done: there is nothing left to do, and a smaller budget cannot undo what was done."""
    if budget <= done:
        raise InvalidValue(key, budget, f"> {done} to continue it with resume=true",
                           note=f"nothing to do: the run in {run_dir} has already done {done} {unit}")


@dataclass(frozen=True)
class Network:
    """A network a checkpoint holds as a state dict under ``entry``.

    Attributes:
        entry: the checkpoint's key, e.g. ``"policy"``.
        build: ``build(meta)`` makes the module (untrained) the state dict loads into.
        widths: ``widths(meta)``: its layer widths ``[in, *hidden, out]``; the products of neighbours are a lower
            bound of the weights it holds, checked against the file before ``build`` allocates them.
    """

    entry: str
    build: Callable[[Mapping[str, Any]], torch.nn.Module]
    widths: Callable[[Mapping[str, Any]], Sequence[Any]]


def _nonfinite(value: Any, key: str) -> Iterator[tuple[str, Any]]:
    """``(key, value)`` of every non-finite float and every tensor holding one in ``value`` (nested mappings,
    lists and tuples)."""
    if isinstance(value, float) and not math.isfinite(value):
        yield key, value
    elif isinstance(value, torch.Tensor) and value.is_floating_point() and not torch.isfinite(value).all():
        yield key, f"a {list(value.shape)} tensor with {int((~torch.isfinite(value)).sum())} non-finite values"
    elif isinstance(value, Mapping):
        for k, v in value.items():
            yield from _nonfinite(v, f"{key}.{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from _nonfinite(v, f"{key}[{i}]")


def _numel(value: Any) -> int:
    """How many tensor elements ``value`` (a state dict, possibly nested) holds."""
    if isinstance(value, torch.Tensor):
        return value.numel()
    if isinstance(value, Mapping):
        return sum(_numel(v) for v in value.values())
    return 0


@dataclass(frozen=True)
class CheckpointFormat:
    """One checkpoint format.

    Attributes:
        name: the versioned tag stored under ``"format"``, e.g. ``"umrl.diayn.v1"``.
        what: the recipe's name for error messages, e.g. ``"DIAYN"``.
        meta_keys: keys every ``state["meta"]`` of this format carries (checked on save).
        networks: the networks its loaders build (checked: sizes, finite weights, a state dict that loads).
        weights: other entries whose tensors must be finite (e.g. a stacked loss's state dict).
        locate: maps a path a user gives (a run's folder) to the one :meth:`load` reads (e.g. a DIAYN run's seed
            folder); None: the path itself.
    """

    name: str
    what: str
    meta_keys: tuple[str, ...]
    networks: tuple[Network, ...] = ()
    weights: tuple[str, ...] = ()
    locate: Callable[[Path], Path] | None = None

    def save(self, checkpointer: Checkpointer, step: int, meta: Mapping[str, Any], config: Any = None,
             **entries: Any) -> Path:
        """Write ``{"format": name, "meta": meta, **entries, "config": resolved config}`` as ``step_<step>.safetensors``
        (the config also beside it as ``config.yaml``); ``meta`` must carry :attr:`meta_keys`."""
        missing = sorted(set(self.meta_keys) - set(meta))
        if missing:
            raise ValueError(f"{self.what} checkpoint meta lacks {missing}; it must carry {list(self.meta_keys)}.")
        state = {"format": self.name, "meta": dict(meta), **entries,
                 "config": to_container(config) if config is not None else None}
        return checkpointer.save(state, step, config)

    def check(self, state: Any, source: str | os.PathLike) -> dict:
        """Return ``state`` if it is a dict of this format whose networks fit their env's observation (where the env is
        registered), else raise ``ValueError`` naming ``source``; content that cannot be what umrl wrote (see the
        module) raises its subclass :class:`~umrl.checkpoints.file.CheckpointError`."""
        if not isinstance(state, dict) or state.get("format") != self.name:
            found = state.get("format") if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"{source} is not a {self.what} checkpoint (format {found!r}, expected {self.name!r}).")
        meta = state.get("meta")
        if not isinstance(meta, dict):
            raise CheckpointError(f"{self._unusable(source)}meta is a {type(meta).__name__}; expected a dict.")
        if meta.get("env") in ENV_NAMES:
            check_observation_size(meta["env"], meta.get("obs_dim"), f"{self.what} checkpoint {source}")
        checked = {"meta": meta, **{entry: state.get(entry) for entry in self._weight_entries()}}
        for key, value in _nonfinite(checked, ""):
            raise CheckpointError(f"{self._unusable(source)}{key[1:]} = {value}; expected finite values (a diverged "
                                  "or tampered file; delete it to resume from the previous checkpoint).")
        for network in self.networks:
            if state.get(network.entry) is not None:
                self._check_network(network, state, source)
        return state

    def build(self, state: Mapping[str, Any], entry: str) -> torch.nn.Module:
        """The network stored under ``entry`` of a checkpoint :meth:`check` accepted, with its weights loaded."""
        network = next(n for n in self.networks if n.entry == entry)
        module = network.build(state["meta"])
        module.load_state_dict(state[entry])
        return module

    def _unusable(self, source: str | os.PathLike) -> str:
        """The start of a :class:`~umrl.checkpoints.file.CheckpointError` about what ``source`` holds."""
        return f"cannot read checkpoint {source} (a {self.what} checkpoint): "

    def _weight_entries(self) -> tuple[str, ...]:
        return (*(n.entry for n in self.networks), *self.weights)

    def _check_network(self, network: Network, state: Mapping[str, Any], source: str | os.PathLike) -> None:
        """Sizes first (nothing allocated), then a real build into which the state dict must load."""
        where = f"{self._unusable(source)}{network.entry}"
        try:
            widths = list(network.widths(state["meta"]))
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"{where}: its meta does not describe the network ({type(e).__name__}: {e}).") from e
        bad = [w for w in widths if isinstance(w, bool) or not isinstance(w, int) or not 1 <= w <= MAX_WIDTH]
        if bad or not 2 <= len(widths) <= MAX_LAYERS:
            shown = f"{widths[:MAX_LAYERS]}{' ...' if len(widths) > MAX_LAYERS else ''}"
            raise CheckpointError(f"{where}: layer widths {shown} from its meta; expected 2 to {MAX_LAYERS} whole "
                                  f"numbers in [1, {MAX_WIDTH}].")
        needed = sum(a * b for a, b in pairwise(widths))
        held = _numel(state[network.entry])
        if needed > held:
            raise CheckpointError(f"{where}: its meta describes layers {widths} of at least {needed} weights, but the "
                                  f"file holds {held}; refused before building it.")
        try:
            with isolated_rng():  # building initialises weights: the caller's random stream must not move
                self.build(state, network.entry)
        except Exception as e:  # a state dict of other shapes or keys, or meta the constructor refuses
            reason = " ".join(str(e).split())  # load_state_dict lists the mismatches on several lines
            raise CheckpointError(f"{where} does not load into the network its meta describes "
                                  f"({type(e).__name__}: {reason}).") from e

    def check_run(self, state: dict, name: str, source: str | os.PathLike, why: str, **expected: Any) -> dict:
        """Return ``state`` if its ``meta`` holds the ``expected`` values (``env="point_nav"``, ``proposal="diayn"``),
        else :class:`~umrl.validation.InvalidValue` naming argument ``name`` (its value ``source``), what the
        checkpoint holds and, in ``why``, who expects the rest: a checkpoint of another env or proposal is refused
        before any work (on another env it would fail in a matmul, or on another proposal run silently)."""
        found = {key: state["meta"].get(key) for key in expected}
        if found != expected:
            def run(values: Mapping[str, Any]) -> str:
                return f"a {self.what} run with " + ", ".join(f"{k}={v!r}" for k, v in values.items())

            raise InvalidValue(name, str(source), f"{run(expected)} ({why})", note=run(found))
        return state

    def load(self, path: str | os.PathLike) -> dict:
        """Load and check a checkpoint: a ``step_*.safetensors`` (or ``.pt``) file, a ``checkpoints/`` folder or a
        run's output_dir (the latest checkpoint); ``FileNotFoundError`` says what was looked for, ``CheckpointError`` names an
        unreadable file."""
        path = checkpoint_path(path)
        file = resolve_checkpoint(path if self.locate is None else self.locate(path))
        return self.check(read_checkpoint(file), file)

    def load_for_resume(self, checkpointer: Checkpointer, meta: Mapping[str, Any],
                        check_config: Callable[[Any], None] | None = None) -> tuple[Path, dict]:
        """``(path, state)`` of the newest readable checkpoint of ``checkpointer`` (an unreadable newer one is
        skipped with a warning naming it), checked, for a run whose networks are described by ``meta``.

        ``check_config(saved_config)`` runs first (recipes pass ``lambda saved: umrl.configs.check_resume(saved,
        cfg)``: a ``ConfigError`` listing the keys that differ beyond ``RESUME_ALLOW``); then ``ValueError`` if
        ``meta`` differs from the saved one (naming the file)."""
        path, state = checkpointer.load_latest_valid(check=self.check)
        if check_config is not None:
            check_config(state["config"])
        mismatched = {k: (state["meta"].get(k), v) for k, v in meta.items() if state["meta"].get(k) != v}
        if mismatched:
            raise ValueError(f"resume=true with a config that differs from {path}'s (saved, now): {mismatched}.")
        return path, state
