"""``python -m umrl.checkpoints.convert OLD NEW``: rewrite a torch.save (pickle) checkpoint of older umrl versions
in the current format (:mod:`umrl.checkpoints.file`: data only, hash-checked).

It reads OLD with ``torch.load(weights_only=True)``, torch's restricted unpickler, allowing beyond tensors and
containers only numpy's array reconstruction (:data:`OLD_FORMAT_GLOBALS`, all that umrl's old checkpoints hold):
a file naming any other callable is refused before it runs. It is still an unpickler, so **convert only files you
trust** (your own runs, this repository's ``results/``). This command is the only place umrl reads a pickle; every
loader refuses the old format.

Absolute paths are machine-specific: an absolute ``output_dir`` in the config becomes NEW's run directory (relative
to the working directory when it lies inside it), ``--relocate FROM=TO`` rewrites other values that start with the
absolute path FROM (e.g. a MAML run's ``diayn_checkpoint``), and any absolute path left is an error listing them.
NEW may be a file (named ``*.safetensors``, or ``*.pt`` as umrl named checkpoints before) or a run directory
(written to ``NEW/checkpoints/step_<N>.safetensors``, ``N`` from OLD's name); the config is written beside it as
``config.yaml``.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from umrl.atomic_write import write_text_atomic
from umrl.checkpoints.file import write_checkpoint
from umrl.checkpoints.folder import LEGACY_SUFFIX, SUFFIX

OLD_FORMAT_GLOBALS = (np._core.multiarray._reconstruct, np.ndarray, np.dtype,
                      *(type(np.dtype(t)) for t in ("uint32", "uint64", "int64", "float32", "float64", "bool")))
"""The non-torch objects umrl's torch.save checkpoints hold (numpy arrays in RNG and replay states)."""

__all__ = ["OLD_FORMAT_GLOBALS", "UNSAFE_WARNING", "absolute_paths", "convert_checkpoint", "relocate_paths"]

UNSAFE_WARNING = ("umrl.checkpoints.convert unpickles {path}: a pickle can run arbitrary code while it loads. Convert "
                  "only checkpoints you trust (your own runs, this repository's results/).")


def relocate_paths(value: Any, relocate: Mapping[str, str]) -> Any:
    """``value`` with every string that starts with a key of ``relocate`` rewritten to start with its value."""
    if isinstance(value, Mapping):
        return {k: relocate_paths(v, relocate) for k, v in value.items()}
    if isinstance(value, list):
        return [relocate_paths(v, relocate) for v in value]
    if isinstance(value, str):
        for old, new in relocate.items():
            if value == old or value.startswith(old.rstrip("/") + "/"):
                return new + value[len(old.rstrip("/")):] if value != old else new
    return value


def absolute_paths(value: Any, prefix: str = "") -> dict[str, str]:
    """``{dotted key: value}`` for every string of ``value`` that is an absolute path."""
    if isinstance(value, Mapping):
        return {k: v for key, item in value.items() for k, v in absolute_paths(item, f"{prefix}{key}.").items()}
    if isinstance(value, list):
        return {k: v for i, item in enumerate(value) for k, v in absolute_paths(item, f"{prefix}{i}.").items()}
    return {prefix[:-1]: value} if isinstance(value, str) and os.path.isabs(value) else {}


def _run_dir(destination: Path) -> Path:
    """The run directory of a checkpoint file ``.../<run>/checkpoints/step_N.safetensors`` (else the file's
    folder)."""
    folder = destination.parent
    return folder.parent if folder.name == "checkpoints" else folder


def _portable(path: Path) -> str:
    path = path.absolute()
    cwd = Path.cwd().absolute()
    return str(path.relative_to(cwd)) if path.is_relative_to(cwd) else str(path)


def convert_checkpoint(source: str | os.PathLike, destination: str | os.PathLike,
                       relocate: Mapping[str, str] | None = None) -> Path:
    """Convert the trusted torch.save checkpoint ``source`` to ``destination`` (a file or a run directory, see the
    module docstring); warns (``UserWarning``) that it unpickles. Returns the written file.

    ``ValueError`` if the result would keep an absolute path (list of keys; pass ``relocate``)."""
    source = Path(source)
    if not source.is_file():
        raise FileNotFoundError(f"source: got {str(source)!r}; expected a checkpoint file (step_<N>.pt)")
    destination = Path(destination)
    if destination.suffix not in (SUFFIX, LEGACY_SUFFIX):
        destination = destination / "checkpoints" / (source.stem + SUFFIX)
    if destination.exists() and destination.resolve() == source.resolve():
        raise ValueError(f"destination: got {str(destination)!r}; expected a path other than the source")
    warnings.warn(UNSAFE_WARNING.format(path=source), UserWarning, stacklevel=2)
    with torch.serialization.safe_globals(list(OLD_FORMAT_GLOBALS)):
        state = torch.load(source, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "format" not in state:
        raise ValueError(f"source: got {source} holding a {type(state).__name__}; expected a umrl checkpoint dict "
                         "with a 'format' entry")
    config = state.get("config")
    if isinstance(config, Mapping):
        config = relocate_paths(dict(config), dict(relocate or {}))
        if os.path.isabs(str(config.get("output_dir", ""))):
            config["output_dir"] = _portable(_run_dir(destination))
        left = absolute_paths(config)
        if left:
            raise ValueError(f"{source}: its config keeps absolute paths {left}; map them with --relocate FROM=TO")
        state["config"] = config
    destination.parent.mkdir(parents=True, exist_ok=True)
    tmp = destination.with_name(destination.name + ".tmp")
    write_checkpoint(state, tmp)
    os.replace(tmp, destination)
    if isinstance(config, Mapping):
        write_text_atomic(destination.parent / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(config)))
    return destination


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m umrl.checkpoints.convert", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="a torch.save checkpoint you trust (it is unpickled)")
    parser.add_argument("destination", help="the new file (step_<N>.safetensors) or run directory")
    parser.add_argument("--relocate", action="append", default=[], metavar="FROM=TO",
                        help="rewrite config values starting with the absolute path FROM to start with TO")
    args = parser.parse_args(argv)
    relocate = {}
    for spec in args.relocate:
        old, sep, new = spec.partition("=")
        if not sep or not os.path.isabs(old):
            parser.error(f"--relocate: got {spec!r}; expected FROM=TO with FROM an absolute path")
        relocate[old] = new
    print(f"WARNING: {UNSAFE_WARNING.format(path=args.source)}", file=sys.stderr)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # printed above
        print(convert_checkpoint(args.source, args.destination, relocate))


if __name__ == "__main__":
    main()
