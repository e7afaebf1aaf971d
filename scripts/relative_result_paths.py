"""Rewrites the absolute ``"checkpoint"`` paths that older meta-test cell files (``*.json`` beside a cell's csv)
recorded into the relative form umrl writes now (:func:`umrl.metatest.provenance.relative_path`: relative to the
cell file's folder), changing nothing else in any file.

    python scripts/relative_result_paths.py results              # rewrite every cell file under results/
    python scripts/relative_result_paths.py results --check      # list what would change, write nothing
    python scripts/relative_result_paths.py old_results --root /home/me/umrl   # written on another machine

``--root`` is where the repository was on the machine that wrote the files (default: this repository); a recorded
path below it is taken to be that path in this repository. A recorded absolute path outside ``--root`` is an error
naming the file, not a guess. Only the ``"checkpoint"`` string is replaced in the file's text; the rewritten file
is parsed back and must equal the original in every other field.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path, PurePosixPath

from umrl.atomic_write import write_text_atomic
from umrl.metatest.provenance import relative_path

REPO = Path(__file__).resolve().parents[1]
FIELD = "checkpoint"


def rewritten(path: Path, root: PurePosixPath) -> str | None:
    """The text of cell file ``path`` with its absolute ``"checkpoint"`` made relative, or ``None`` if it has none."""
    text = path.read_text()
    cell = json.loads(text)
    recorded = cell.get(FIELD) if isinstance(cell, dict) else None
    if not isinstance(recorded, str) or not os.path.isabs(recorded):
        return None
    if not PurePosixPath(recorded).is_relative_to(root):
        raise SystemExit(f"{path}: {FIELD} {recorded!r} is outside --root {root}; give the root it was written under.")
    here = REPO / PurePosixPath(recorded).relative_to(root)
    field = f'"{FIELD}": {json.dumps(recorded)}'
    if text.count(field) != 1:
        raise SystemExit(f"{path}: expected one {field!r} in the text, found {text.count(field)}.")
    new_text = text.replace(field, f'"{FIELD}": {json.dumps(relative_path(here, path))}')
    if json.loads(new_text) != {**cell, FIELD: relative_path(here, path)}:
        raise SystemExit(f"{path}: the rewrite would change more than {FIELD}; nothing written.")
    return new_text


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="folders searched for *.json cell files")
    parser.add_argument("--root", type=PurePosixPath, default=PurePosixPath(REPO),
                        help="the repository's absolute path on the machine that wrote the files (default: this one)")
    parser.add_argument("--check", action="store_true", help="list the files that would change; write nothing")
    args = parser.parse_args(argv)
    changes = {path: text for folder in args.folders for path in sorted(folder.rglob("*.json"))
               if (text := rewritten(path, args.root)) is not None}  # every file checked before any is written
    for path, text in changes.items():
        if not args.check:
            write_text_atomic(path, text)
        print(f"{'would rewrite' if args.check else 'rewrote'} {path}: {json.loads(text)[FIELD]}")
    print(f"{len(changes)} file(s) {'to rewrite' if args.check else 'rewritten'}.")


if __name__ == "__main__":
    main()
