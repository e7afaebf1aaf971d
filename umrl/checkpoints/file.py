"""The checkpoint file: tensors stored as data, everything else as JSON, a content hash; reading it runs no code.

Why safetensors and not ``torch.load(weights_only=True)``: a safetensors file is an 8-byte length, a JSON header and
raw tensor bytes, parsed without executing anything the file names, whereas ``weights_only=True`` is still an
unpickler (restricted by an allow-list that has had bypasses in past torch releases) and would need numpy's and
tensordict's reconstruction functions allow-listed for the RNG states and replay buffers a resume restores.

A file is a safetensors file and is named as one: ``step_<N>.safetensors`` (umrl named the same files ``step_<N>.pt``
before, and still reads them). safetensors' own tools open it (``safe_open(path, "pt").metadata()`` shows the tree),
and ``torch.load`` recognises the suffix and hands back the bare tensors ``{"t0": ..., ...}`` (no pickle, no
``weights_only`` advice); :func:`read_checkpoint` gives the state. Its layout (:data:`FILE_FORMAT`):

- the safetensors tensors ``"t0"``, ``"t1"``, ... : every tensor and numpy array of the state, on the CPU;
- the safetensors metadata (strings): ``"format"`` = :data:`FILE_FORMAT`; ``"tree"``: the state as JSON, each
  tensor replaced by ``{"__tensor__": "t<i>"}`` (tags below); ``"sha256"``: :func:`content_hash` of the tree and
  every tensor's name, dtype, shape and bytes, checked on every read.

JSON tags (an object with one of these keys; every other object is a ``dict`` with string keys):
``__tensor__`` (a tensor), ``__ndarray__`` + ``dtype`` (a numpy array), ``__npscalar__`` + ``dtype`` (a numpy
scalar), ``__tuple__`` (a tuple), ``__dict__`` (a dict with non-string or reserved keys, as ``[key, value]`` pairs),
``__tensordict__`` + ``batch_size`` (a TensorDict), ``__size__`` (a ``torch.Size``), ``__dtype__`` (a torch dtype).
Anything else (an arbitrary object) is refused when saving: a checkpoint holds data only.

A file written by torch.save (umrl before :data:`FILE_FORMAT`) is refused with :class:`LegacyCheckpointError`:
unpickling it could run code. ``python -m umrl.checkpoints.convert OLD NEW`` converts a trusted one.

The hash is an integrity check, not a signature: whoever can write the file can recompute it. So :func:`read_checkpoint`
treats every file as untrusted input: only a regular file is opened (a FIFO, device or folder is refused before any
byte is read), tensors never exceed the file's bytes (safetensors checks every offset), numpy dtypes are numeric,
and any failure while parsing (a tree nested past the recursion limit, a TensorDict whose batch size does not fit
its tensors, a tag of the wrong type) is a :class:`CheckpointError` naming the file. What the state means (network
sizes, finite weights) is checked by :class:`umrl.checkpoints.CheckpointFormat`.
"""
from __future__ import annotations

import hashlib
import json
import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.torch
import torch
from tensordict import TensorDict, TensorDictBase

__all__ = ["FILE_FORMAT", "CheckpointError", "LegacyCheckpointError", "content_hash", "decode", "encode",
           "file_kind", "read_checkpoint", "write_checkpoint"]

FILE_FORMAT = "umrl.checkpoint.v2"
"""The container version (``v1``: the torch.save pickles before it); the recipes' own formats are inside the tree."""

_TAGS = ("__tensor__", "__ndarray__", "__npscalar__", "__tuple__", "__dict__", "__tensordict__", "__size__",
         "__dtype__")
_HEADER_LIMIT = 100 * 2**20  # safetensors' own limit on the JSON header
_NUMPY_KINDS = "biufc"  # bool, integers, floats, complex: what an array in a checkpoint may hold


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read or used (truncated, corrupted, empty, of another format, special,
    malformed, or holding what umrl never writes); the message starts ``cannot read checkpoint <path> (<what>): ``."""


class LegacyCheckpointError(CheckpointError):
    """A torch.save (pickle) checkpoint: refused, since unpickling can run code; convert a trusted one."""


def encode(state: Any) -> tuple[Any, dict[str, torch.Tensor]]:
    """``(tree, tensors)``: ``state`` as a JSON-able tree and the tensors it refers to (CPU, contiguous copies).

    ``TypeError`` names the path of the first value that is not data (see the module's tags)."""
    tensors: dict[str, torch.Tensor] = {}

    def add(tensor: torch.Tensor) -> str:
        name = f"t{len(tensors)}"
        tensors[name] = tensor.detach().to("cpu", copy=True).contiguous()
        return name

    def walk(value: Any, path: str) -> Any:
        if value is None or isinstance(value, (bool, int, float, str)):
            return value
        if isinstance(value, torch.Tensor):
            return {"__tensor__": add(value)}
        if isinstance(value, np.ndarray):
            return {"__ndarray__": add(torch.from_numpy(np.ascontiguousarray(value))), "dtype": value.dtype.str}
        if isinstance(value, np.generic):
            return {"__npscalar__": value.item(), "dtype": value.dtype.str}
        if isinstance(value, torch.dtype):
            return {"__dtype__": str(value).removeprefix("torch.")}
        if isinstance(value, TensorDictBase):
            return {"__tensordict__": {k: walk(v, f"{path}.{k}") for k, v in value.items()},
                    "batch_size": list(value.batch_size)}
        if isinstance(value, torch.Size):
            return {"__size__": list(value)}
        if isinstance(value, tuple):
            return {"__tuple__": [walk(v, f"{path}[{i}]") for i, v in enumerate(value)]}
        if isinstance(value, list):
            return [walk(v, f"{path}[{i}]") for i, v in enumerate(value)]
        if isinstance(value, Mapping):
            if all(isinstance(k, str) and k not in _TAGS for k in value):
                return {k: walk(v, f"{path}.{k}") for k, v in value.items()}
            return {"__dict__": [[walk(k, f"{path} key"), walk(v, f"{path}[{k!r}]")] for k, v in value.items()]}
        raise TypeError(f"checkpoint entry {path or '<root>'} is a {type(value).__module__}.{type(value).__qualname__}; "
                        "a checkpoint holds tensors, arrays, numbers, strings and containers of them only.")

    return walk(state, ""), tensors


def decode(tree: Any, tensors: Mapping[str, torch.Tensor]) -> Any:
    """The state :func:`encode` took apart; ``ValueError`` on an unknown tag or a missing tensor."""
    if isinstance(tree, list):
        return [decode(v, tensors) for v in tree]
    if not isinstance(tree, dict):
        return tree
    tag = next((key for key in _TAGS if key in tree), None)
    if tag is None:
        return {k: decode(v, tensors) for k, v in tree.items()}
    value = tree[tag]
    if tag in ("__tensor__", "__ndarray__"):
        if not isinstance(value, str) or value not in tensors:
            raise ValueError(f"the tree names a tensor {value!r} the file does not hold")
        return tensors[value] if tag == "__tensor__" else tensors[value].numpy().astype(_numeric_dtype(tree["dtype"]))
    if tag == "__npscalar__":
        return _numeric_dtype(tree["dtype"]).type(value)
    if tag == "__dtype__":
        dtype = getattr(torch, str(value), None)
        if not isinstance(dtype, torch.dtype):
            raise ValueError(f"unknown torch dtype {value!r}")
        return dtype
    if tag == "__tuple__":
        return tuple(decode(v, tensors) for v in value)
    if tag == "__size__":
        return torch.Size([_dimension(v) for v in value])
    if tag == "__dict__":
        return {decode(k, tensors): decode(v, tensors) for k, v in value}
    return TensorDict({k: decode(v, tensors) for k, v in value.items()}, batch_size=[_dimension(v) for v in tree["batch_size"]])


def _numeric_dtype(name: Any) -> np.dtype:
    """The numpy dtype ``name`` if it is a number or bool; ``ValueError`` otherwise (an object or a string dtype
    could make an array of arbitrary size out of a few bytes)."""
    dtype = np.dtype(str(name))
    if dtype.kind not in _NUMPY_KINDS:
        raise ValueError(f"numpy dtype {name!r} is not numeric")
    return dtype


def _dimension(value: Any) -> int:
    """``value`` if it is a whole number a tensor dimension can be (0 to 2⁶³ − 1); ``ValueError`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**63:
        raise ValueError(f"size entry {value!r} is not a tensor dimension")
    return value


def content_hash(tree_json: str, tensors: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 of the format, the JSON tree and every tensor's name, dtype, shape and bytes (in name order)."""
    digest = hashlib.sha256(f"{FILE_FORMAT}\0{tree_json}".encode())
    for name in sorted(tensors):
        tensor = tensors[name].contiguous()
        digest.update(f"\0{name}\0{tensor.dtype}\0{list(tensor.shape)}\0".encode())
        if tensor.numel():
            digest.update(tensor.reshape(-1).view(torch.uint8).numpy())
    return digest.hexdigest()


def write_checkpoint(state: Any, path: str | os.PathLike) -> None:
    """Write ``state`` to ``path`` in :data:`FILE_FORMAT` (not atomically: the checkpointer writes a ``.tmp``).

    A failed write (a full disk, a file-size limit) removes what it wrote and raises ``OSError`` naming ``path``."""
    tree, tensors = encode(state)
    tree_json = json.dumps(tree, allow_nan=True, separators=(",", ":"))
    metadata = {"format": FILE_FORMAT, "tree": tree_json, "sha256": content_hash(tree_json, tensors)}
    try:
        safetensors.torch.save_file(tensors, str(path), metadata=metadata)
    except (OSError, safetensors.SafetensorError) as e:  # safetensors reports a failed write as its own error
        Path(path).unlink(missing_ok=True)  # half a file only takes the space the next attempt needs
        reason = e.strerror if isinstance(e, OSError) else str(e)
        raise OSError(f"cannot write checkpoint {path}: {reason}; free space (or raise the file-size limit) and "
                      "resume: the previous checkpoint is intact.") from e


def _is_pickle(head: bytes) -> bool:
    """torch.save's zip archive (``PK``) or its older raw pickle (protocol opcode ``0x80``)."""
    return head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"


def file_kind(mode: int) -> str:
    """What kind of file ``mode`` (an ``os.stat`` mode) is, in words."""
    kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
             (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def _read_regular_file(path: Path) -> bytes:
    """The bytes of ``path`` (a symlink is followed) if it is a regular file; :class:`CheckpointError` before
    reading anything else (a FIFO would block, ``/dev/zero`` never ends) or when it cannot be opened;
    ``FileNotFoundError`` if it does not exist."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO opens at once instead of waiting for a writer
    except FileNotFoundError:
        raise
    except OSError as e:
        raise CheckpointError(f"cannot read checkpoint {path} (not opened): {e.strerror}.") from e
    try:
        mode = os.fstat(fd).st_mode  # of what was opened: no window between a check and the open
        if not stat.S_ISREG(mode):
            raise CheckpointError(f"cannot read checkpoint {path} ({file_kind(mode)}): not a regular file; "
                                  "give a step_<N>.safetensors (or .pt) file or a run folder.")
        with os.fdopen(os.dup(fd), "rb") as file:
            return file.read()
    except OSError as e:
        raise CheckpointError(f"cannot read checkpoint {path} (not read): {e.strerror}.") from e
    finally:
        os.close(fd)


def read_checkpoint(path: str | os.PathLike) -> dict:
    """The state :func:`write_checkpoint` wrote to ``path``, its hash checked; tensors on the CPU.

    Raises :class:`CheckpointError` naming ``path`` for anything but a readable regular file in
    :data:`FILE_FORMAT` with a matching hash, whose tree decodes (truncated, corrupted, empty, foreign, special,
    unreadable or malformed files alike), :class:`LegacyCheckpointError` for a torch.save pickle;
    ``FileNotFoundError`` if there is no file."""
    path = Path(path)
    data = _read_regular_file(path)

    def fail(reason: str, error: type[CheckpointError] = CheckpointError) -> CheckpointError:
        return error(f"cannot read checkpoint {path} ({len(data)} bytes): {reason}")

    size = int.from_bytes(data[:8], "little") if len(data) >= 8 else -1
    if not (0 < size <= min(_HEADER_LIMIT, len(data) - 8) and data[8:9] == b"{"):
        if _is_pickle(data[:4]):
            raise fail("it is a torch.save pickle (umrl.checkpoint.v1), which is not loaded because unpickling can "
                       "run code; convert a copy you trust with `python -m umrl.checkpoints.convert OLD NEW`.",
                       LegacyCheckpointError)
        raise fail("not a umrl checkpoint (no safetensors header: empty, truncated or another kind of file); "
                   "delete it to resume from the previous checkpoint.")
    try:
        metadata = json.loads(data[8:8 + size])["__metadata__"]
        if metadata.get("format") != FILE_FORMAT:
            raise ValueError(f"container format {metadata.get('format')!r}, expected {FILE_FORMAT!r}")
        tensors = safetensors.torch.load(data)
        tree_json = metadata["tree"]
        if content_hash(tree_json, tensors) != metadata["sha256"]:
            raise ValueError("content hash mismatch: the file was modified or corrupted after it was written")
        return decode(json.loads(tree_json), tensors)
    except Exception as e:  # the file is untrusted input: whatever fails while parsing it is the file's fault
        raise fail(f"{type(e).__name__}: {e}; delete it to resume from the previous checkpoint.") from e
