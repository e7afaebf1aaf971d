"""Read offline wandb runs (``offline-run-*/run-*.wandb``) for tests: the records wandb-core wrote, parsed with
wandb's own protobuf classes.

A ``.wandb`` file is a 7-byte header (``:W&B``, magic, version) then LevelDB-log style chunks in 32 KiB blocks:
4-byte checksum, 2-byte little-endian length, 1-byte type (full, first, middle, last), payload; a block's tail
shorter than a chunk header is zero padding."""
from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from wandb.proto.wandb_internal_pb2 import Record

_BLOCK, _HEADER, _CHUNK = 32 * 1024, 7, 7
_FULL, _LAST = 1, 4


def records(path: str | Path) -> list[Record]:
    data = Path(path).read_bytes()
    if len(data) < _HEADER:  # created, header not flushed yet
        return []
    if data[:4] != b":W&B":
        raise ValueError(f"{path}: not a .wandb file (header {data[:4]!r})")
    out, parts, pos = [], [], _HEADER
    while pos + _CHUNK <= len(data):
        left = _BLOCK - pos % _BLOCK
        if left < _CHUNK:
            pos += left
            continue
        length, kind = int.from_bytes(data[pos + 4:pos + 6], "little"), data[pos + 6]
        if pos + _CHUNK + length > len(data):  # the writer has not flushed the rest yet
            break
        if kind == 0:  # zero padding to the end of the block
            pos += left
            continue
        parts.append(data[pos + _CHUNK:pos + _CHUNK + length])
        pos += _CHUNK + length
        if kind in (_FULL, _LAST):
            out.append(Record.FromString(b"".join(parts)))
            parts = []
    return out


@dataclass
class OfflineRun:
    """What one offline run holds: its name, group and job type, config keys and values (JSON text), each logged
    metric's values, the files of its logged tables and images (``{key: path under files/}``), and whether it was
    finished (its exit record is written)."""

    path: Path
    name: str = ""
    group: str = ""
    job_type: str = ""
    finished: bool = False
    config: dict[str, str] = field(default_factory=dict)
    metrics: dict[str, list[str]] = field(default_factory=dict)
    tables: dict[str, str] = field(default_factory=dict)
    images: dict[str, str] = field(default_factory=dict)

    @property
    def num_values(self) -> int:
        return sum(len(v) for v in self.metrics.values())

    def table(self, key: str) -> dict:
        """The table logged under ``key``: ``{"columns": [...], "data": [[...], ...]}`` (wandb's table file)."""
        return json.loads((self.path / "files" / self.tables[key]).read_text())


def read_run(run_dir: str | Path, wait_s: float = 30.0) -> OfflineRun:
    """The :class:`OfflineRun` of an ``offline-run-*`` directory.

    ``run.finish()`` returns before wandb-core has written the run's file (the service creates and closes it
    asynchronously), so this waits up to ``wait_s`` seconds for the file and its exit record; a run still without
    one is returned unfinished."""
    deadline = time.monotonic() + wait_s
    while True:
        files = list(Path(run_dir).glob("run-*.wandb"))
        run = _parse_run(Path(run_dir), records(files[0]) if files else [])
        if run.finished or time.monotonic() > deadline:
            return run
        time.sleep(0.05)


def _parse_run(run_dir: Path, items: list[Record]) -> OfflineRun:
    run = OfflineRun(run_dir)
    for record in items:
        kind = record.WhichOneof("record_type")
        if kind == "run":
            run.name, run.group, run.job_type = record.run.display_name, record.run.run_group, record.run.job_type
            run.config.update({item.key: item.value_json for item in record.run.config.update})
        elif kind == "config":
            run.config.update({item.key: item.value_json for item in record.config.update})
        elif kind == "exit":
            run.finished = True
        elif kind == "history":
            media: dict[str, dict[str, str]] = {}  # a table or image: nested items {key: {_type, path, ...}}
            for item in record.history.item:
                if not item.key and len(item.nested_key) > 1:
                    media.setdefault("/".join(item.nested_key[:-1]), {})[item.nested_key[-1]] = item.value_json
                    continue
                key = item.key or "/".join(item.nested_key)
                if not key.startswith("_"):
                    run.metrics.setdefault(key, []).append(item.value_json)
            for key, fields in media.items():
                kind = json.loads(fields.get("_type", "null"))
                if kind in ("table-file", "image-file"):
                    (run.tables if kind == "table-file" else run.images)[key] = json.loads(fields["path"])
    return run


def offline_runs(directory: str | Path) -> list[OfflineRun]:
    """Every offline run under ``directory`` (searched recursively), oldest first."""
    return [read_run(p) for p in sorted(Path(directory).rglob("offline-run-*")) if p.is_dir()]


def sync_dry_run(folder: str | Path) -> set[str]:
    """The run ids ``wandb sync --dry-run``, run in ``folder``, would upload (what a user publishing an output tree
    gets: wandb looks in ``folder/wandb``)."""
    wandb_cli = Path(sys.executable).with_name("wandb")
    out = subprocess.run([str(wandb_cli), "sync", "--dry-run"], cwd=folder, capture_output=True, text=True, timeout=120,
                         check=True)
    return set(re.findall(r"run-([a-z0-9]+)\.wandb", out.stdout + out.stderr))


def run_id(run: OfflineRun) -> str:
    """The id in an ``offline-run-<date>_<time>-<id>`` folder name."""
    return run.path.name.rsplit("-", 1)[1]
