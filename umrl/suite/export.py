"""Export a suite's finished cells of one env into the layout ``results/`` keeps and
:mod:`umrl.suite.verdicts` reads: the cache keys leave the names, each ``.json``'s checkpoint is re-pointed
relative to its copy (:func:`~umrl.metatest.provenance.relative_path`), so the copies read as the suite's own did.

=================================================================== ==================================================
suite ``output_dir``                                                ``dst`` (e.g. ``results/<env>``)
=================================================================== ==================================================
``cells/<env>/<method>/seed<s>[.<schedule>]-<key>.{csv,json}``      ``meta_test_ref/seed<s>/<method>[.<schedule>].*``
``ablation/<env>/<method>/seed<s>/iter<N>-<key>.{csv,json}``        ``along_meta_training/seed<s>/<method>/iter<N>.*``
``ablation/<env>/<baseline>/seed<s>-<key>.{csv,json}``              ``along_meta_training/seed<s>/<baseline>.*``
=================================================================== ==================================================

Command::

    python -m umrl.suite.export outputs/suite/ref3_half_cheetah half_cheetah results/half_cheetah --methods uml_diayn

``--parts ablation`` exports only the ablation's cells (a suite run for them alone keeps its main cells cheap, at
``protocol.num_steps=1``, and those must not overwrite the real ones). Only finished cells (a ``.json`` beside the
CSV) are exported; two cells with one name and different keys (a folder holding runs of two configs or code
versions) are refused, naming both, before anything is copied.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
from collections.abc import Iterable
from pathlib import Path

from umrl.atomic_write import write_text_atomic
from umrl.metatest.cache import KEY_LENGTH
from umrl.metatest.provenance import relative_path, resolve_recorded_path

__all__ = ["PARTS", "export_cells", "exported_name"]

#: The parts of a suite folder :func:`export_cells` can copy: the main cells and the meta-training ablation's.
PARTS = {"cells": "meta_test_ref", "ablation": "along_meta_training"}

_KEYED = re.compile(rf"(?P<name>.+)-[0-9a-f]{{{KEY_LENGTH}}}")  # <name>-<config_key>


def exported_name(cell_csv: Path, suite_dir: Path, env: str) -> Path | None:
    """Where ``cell_csv`` goes under the export folder (:data:`__doc__`'s table), or None for a file of no cell.

    >>> exported_name(Path("s/cells/pn/oracle/seed2.constant-0a1b2c3d4e5f.csv"), Path("s"), "pn").as_posix()
    'meta_test_ref/seed2/oracle.constant.csv'
    >>> exported_name(Path("s/ablation/pn/oracle/seed0/iter20-0a1b2c3d4e5f.csv"), Path("s"), "pn").as_posix()
    'along_meta_training/seed0/oracle/iter20.csv'
    """
    parts = cell_csv.relative_to(suite_dir).parts
    keyed = _KEYED.fullmatch(cell_csv.stem)
    if keyed is None or len(parts) < 4 or parts[1] != env:
        return None
    name = keyed["name"]
    if parts[0] == "cells" and len(parts) == 4:
        seed, _, schedule = name.partition(".")
        return Path(PARTS["cells"], seed, parts[2] + (f".{schedule}" if schedule else "") + ".csv")
    if parts[0] == "ablation" and len(parts) == 5:
        return Path(PARTS["ablation"], parts[3], parts[2], f"{name}.csv")
    if parts[0] == "ablation" and len(parts) == 4:
        return Path(PARTS["ablation"], name, f"{parts[2]}.csv")
    return None


def export_cells(suite_dir: str | Path, env: str, dst: str | Path, methods: Iterable[str] | None = None,
                 parts: Iterable[str] = tuple(PARTS)) -> list[Path]:
    """Copy the finished cells of ``env`` (of ``methods`` only, if given; of the :data:`PARTS` named in ``parts``)
    from the suite folder ``suite_dir`` to ``dst``; returns the CSV files written. Raises ``ValueError`` naming both
    files when two cells map to one name, or naming a part that is not one of :data:`PARTS`."""
    suite_dir, dst, parts = Path(suite_dir), Path(dst), list(parts)
    unknown = [part for part in parts if part not in PARTS]
    if unknown or not parts:
        raise ValueError(f"parts: got {parts}; expected one or more of {sorted(PARTS)}")
    wanted = None if methods is None else set(methods)
    plan: dict[Path, Path] = {}
    for csv in sorted(path for part in parts for path in suite_dir.glob(f"{part}/{env}/**/*.csv")):
        target = exported_name(csv, suite_dir, env)
        method = csv.relative_to(suite_dir).parts[2]
        if target is None or not csv.with_suffix(".json").is_file() or (wanted is not None and method not in wanted):
            continue
        if target in plan:
            raise ValueError(f"export: {plan[target]} and {csv} are both {dst / target}; keep one (other "
                             "settings or code versions wrote the other) or export the suite folder of one config")
        plan[target] = csv
    written = []
    for target, csv in plan.items():
        out = dst / target
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(csv, out)
        info = json.loads(csv.with_suffix(".json").read_text())
        if info.get("checkpoint"):
            info["checkpoint"] = relative_path(resolve_recorded_path(info["checkpoint"], csv), out)
        write_text_atomic(out.with_suffix(".json"), json.dumps(info, indent=1) + "\n")
        written.append(out)
    return written


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m umrl.suite.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("suite_dir", help="a suite's output_dir")
    parser.add_argument("env", help="the env whose cells to export")
    parser.add_argument("dst", help="the export folder, e.g. results/<env>")
    parser.add_argument("--methods", nargs="+", help="only these methods' cells (default: every method)")
    parser.add_argument("--parts", nargs="+", choices=sorted(PARTS), default=list(PARTS),
                        help="cells (-> meta_test_ref), ablation (-> along_meta_training); default: both")
    args = parser.parse_args(argv)
    written = export_cells(args.suite_dir, args.env, args.dst, args.methods, args.parts)
    for path in written:
        print(path)
    print(f"{len(written)} cells exported to {args.dst}")


if __name__ == "__main__":
    main()
