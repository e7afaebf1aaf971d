"""Meta-test results: tidy rows and CSV files, curves, the summary and ablation tables, the suite's ``summary.md``.

A row is one (method, env, seed, task, step) return and mean episode ``length`` (steps before the env ended the
episode, or the horizon), plus ``lr_schedule`` (``reference`` | ``constant`` | ``swept``: the step-size schedule the cell
adapted with; Adam's cells ``constant``) and any constant ``extra`` columns (the ablation's ``iteration``). Tables
and curves group rows by *arm*: the method, suffixed by its schedule when that is not the method's default
(:func:`arm_label`), so one table can hold both SGD schedules of a MAML initialisation.
"""
from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import warnings
from collections.abc import Collection, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from umrl.atomic_write import write_text_atomic
from umrl.metatest.method_table import default_lr_schedule
from umrl.metatest.plots import METHOD_COLORS, Curve
from umrl.metatest.stats import auc, bootstrap_ci, summarize
from umrl.validation import InvalidValue

#: Columns of the tidy results table (``extra`` columns follow them; files written before ``length`` lack it).
COLUMNS = ("method", "env", "seed", "task", "step", "return", "length", "lr_schedule")


def arm_label(method: str, lr_schedule: str | None = None) -> str:
    """The name a (method, schedule) pair has in tables, curves and legends: the method alone under its default
    schedule (:func:`~umrl.metatest.method_table.default_lr_schedule`: ``uml_diayn`` is the reference schedule, ``scratch``
    Adam's constant lr), else ``uml_diayn (constant)``."""
    if lr_schedule is None or lr_schedule == default_lr_schedule(method):
        return method
    return f"{method} ({lr_schedule})"


def _schedule(row: Mapping) -> str:
    return row.get("lr_schedule", "constant")  # files written before the column ran the constant schedule


def _label(row: Mapping) -> str:
    return arm_label(row["method"], _schedule(row))


def arm_styles(rows: Iterable[Mapping]) -> dict[str, dict]:
    """Line style per arm label: the method's colour, dashed for a schedule other than the method's default."""
    return {_label(r): {"color": METHOD_COLORS.get(r["method"]),
                        "linestyle": "-" if _schedule(r) == default_lr_schedule(r["method"]) else "--"} for r in rows}


def to_rows(returns: torch.Tensor | np.ndarray, lengths: torch.Tensor | np.ndarray, *, method: str, env: str,
            seed: int, lr_schedule: str | None = None, **extra) -> list[dict]:
    """Tidy rows (:data:`COLUMNS` plus ``extra`` columns) from returns and mean episode lengths, both ``[K + 1, T]``;
    ``lr_schedule`` None is the method's default schedule."""
    returns, lengths = np.asarray(returns), np.asarray(lengths)
    lr_schedule = default_lr_schedule(method) if lr_schedule is None else lr_schedule
    if lengths.shape != returns.shape:
        raise ValueError(f"lengths {lengths.shape} must match returns {returns.shape} ([K + 1, T]).")
    return [
        {"method": method, "env": env, "seed": int(seed), "task": int(t), "step": int(k),
         "return": float(returns[k, t]), "length": float(lengths[k, t]), "lr_schedule": lr_schedule, **extra}
        for k in range(returns.shape[0]) for t in range(returns.shape[1])
    ]


def write_rows(rows: Sequence[Mapping], path: str | os.PathLike) -> Path:
    """Write rows as CSV atomically (a killed write never leaves a partial file under ``path``).

    The columns are every key of any row, in the order first seen; a row without one (an older cell without
    ``length``) leaves it empty.
    """
    if not rows:
        raise ValueError(f"no rows to write to {path}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, csv_text(rows))
    return path


def csv_text(rows: Sequence[Mapping]) -> str:
    """The CSV :func:`write_rows` writes for ``rows`` (a header of every key of any row, in the order first seen)."""
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=list(dict.fromkeys(key for row in rows for key in row)))
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue()


def text_sha256(text: str) -> str:
    """The SHA-256 (hex) of ``text`` in UTF-8: what a cell's JSON records of its CSV (:func:`cell_finished`)."""
    return hashlib.sha256(text.encode()).hexdigest()


def read_rows(paths: Iterable[str | os.PathLike]) -> list[dict]:
    """Rows of one or more CSV files, with ``seed``/``task``/``step`` as int and ``return``/``length`` as float.

    Files written before the ``lr_schedule`` column existed read as ``constant``; before ``length``, rows have none.
    An empty file, a missing column, an unreadable number or a non-finite return raises ``ValueError`` naming the file.
    """
    rows = []
    for path in paths:
        rows += _read_file(Path(path))
    return rows


def _read_file(path: Path) -> list[dict]:
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            raise ValueError("no rows")
        for row in rows:
            row.update(seed=int(row["seed"]), task=int(row["task"]), step=int(row["step"]),
                       **{"return": float(row["return"])})
            if not math.isfinite(row["return"]):
                raise ValueError(f"return {row['return']} at seed {row['seed']}, task {row['task']}, step {row['step']}")
            if row.get("length"):
                row["length"] = float(row["length"])
            else:  # written before the column, or beside such rows (an empty field)
                row.pop("length", None)
            row.setdefault("lr_schedule", "constant")
    except (KeyError, TypeError, ValueError, csv.Error, UnicodeDecodeError) as e:
        what = f"no column {e}" if isinstance(e, KeyError) else f"{type(e).__name__}: {e}"
        raise ValueError(f"cannot read results file {path}: {what}") from None
    return rows


def cell_finished(path: str | os.PathLike, settings: Mapping) -> bool:
    """Whether the cell CSV ``path`` holds the finished result of a cell of ``settings`` (a plain mapping, as
    :meth:`umrl.metatest.CellSpec.settings` gives it).

    It does when ``path`` is a regular file (a symlink to one counts) that reads as a results file, and the ``.json``
    beside it is a JSON object recording these ``settings`` and the CSV's :func:`text_sha256` (``csv_sha256``). Any
    other file there (written with other settings, by an older umrl, cut short or edited, unreadable) is named in one
    ``UserWarning`` line, ``recomputing the cell <path>: <why>``, and removed with its ``.json`` (False: the cell runs
    again). A folder or another special file at either path raises :class:`~umrl.validation.InvalidValue` naming
    ``output``: it is not a result, and the cell could not write there.
    """
    path = Path(path)
    info_path = path.with_suffix(".json")
    for file in (path, info_path):
        if file.exists() and not file.is_file():
            kind = "a folder" if file.is_dir() else "a special file (FIFO, socket or device)"
            raise InvalidValue("output", str(path), "a path where the cell's CSV and the .json beside it are regular "
                               "files or absent", note=f"{file} is {kind}")
    if not path.exists():
        return False
    why = _stale_reason(path, info_path, settings)
    if why is None:
        return True
    warnings.warn(f"recomputing the cell {path}: {why}", UserWarning, stacklevel=2)
    path.unlink()
    info_path.unlink(missing_ok=True)
    return False


def _stale_reason(path: Path, info_path: Path, settings: Mapping) -> str | None:
    """Why the CSV ``path`` is no finished cell of ``settings`` (None when it is one)."""
    if not info_path.exists():
        return f"no {info_path.name} beside it"
    try:
        info = json.loads(info_path.read_text())
        if not isinstance(info, dict):
            return f"{info_path} does not hold a JSON object"
        if "settings" not in info or "csv_sha256" not in info:
            return f"{info_path} records no settings (written by an older umrl)"
        changed = _differences(info["settings"], json.loads(json.dumps(settings, default=str)))
        if changed:
            return "written with other settings (" + "; ".join(changed[:3]) + ("; ..." if len(changed) > 3 else "") + ")"
        with path.open(newline="") as f:  # the characters as written (the CSV's \r\n line ends kept)
            text = f.read()
        if text_sha256(text) != info["csv_sha256"]:
            return f"the CSV is not the one its {info_path.name} records (cut short or edited)"
        _read_file(path)  # a NaN return, say
    except (OSError, ValueError, UnicodeDecodeError) as e:  # _read_file's errors name the file
        return f"{info_path}: {e}" if isinstance(e, json.JSONDecodeError) else str(e)
    return None


def _differences(recorded: Any, wanted: Any, key: str = "") -> list[str]:
    """``<key>: <recorded>, now <wanted>`` for each leaf where two JSON trees differ (dotted keys)."""
    if isinstance(recorded, dict) and isinstance(wanted, dict):
        return [line for k in dict.fromkeys([*recorded, *wanted])
                for line in _differences(recorded.get(k), wanted.get(k), f"{key}.{k}" if key else k)]
    return [] if recorded == wanted else [f"{key}: {recorded!r}, now {wanted!r}"]


def run_matrix(rows: Iterable[Mapping], *, env: str, method: str, value: str = "return") -> np.ndarray:
    """``[runs, K + 1]`` returns (or another ``value`` column) of one (env, arm): one row per (seed, task), sorted;
    ``method`` is an arm label. A run missing steps or holding a non-finite value raises ``ValueError`` naming it."""
    table: dict[tuple[int, int], dict[int, float]] = {}
    for row in rows:
        if row["env"] == env and _label(row) == method:
            table.setdefault((row["seed"], row["task"]), {})[row["step"]] = row[value]
    if not table:
        raise ValueError(f"no results for method {method!r} on env {env!r}.")
    steps = sorted(next(iter(table.values())))
    for (seed, task), values in sorted(table.items()):
        if sorted(values) != steps:
            raise ValueError(f"{method!r} on {env!r}: seed {seed}, task {task} has steps {sorted(values)}, others "
                             f"{steps} (a partial results file?)")
        bad = {k: v for k, v in values.items() if not np.isfinite(v)}
        if bad:
            raise ValueError(f"{method!r} on {env!r}: seed {seed}, task {task} has non-finite {value} {bad}")
    return np.array([[table[run][k] for k in steps] for run in sorted(table)])


def _ordered_arms(rows: Sequence[Mapping], env: str, methods: Sequence[str] | None) -> list[str]:
    """Arms present for ``env``: in the order of ``methods`` (each method's default schedule first), others sorted."""
    order = {m: i for i, m in enumerate(methods or [])}
    present = {(r["method"], _schedule(r)) for r in rows if r["env"] == env}
    ranked = sorted(present, key=lambda a: (order.get(a[0], len(order)), a[0], a[1] != default_lr_schedule(a[0]), a[1]))
    return [arm_label(*arm) for arm in ranked]


def mean_curve(matrix: np.ndarray, *, confidence: float = 0.95) -> Curve:
    """Mean over runs of a ``[runs, K + 1]`` matrix (:func:`run_matrix`) per step, with a bootstrap CI band."""
    bands = np.array([bootstrap_ci(matrix[:, k], confidence=confidence) for k in range(matrix.shape[1])])
    return Curve(np.arange(matrix.shape[1]), matrix.mean(0), bands[:, 0], bands[:, 1])


def curves_from_rows(rows: Sequence[Mapping], *, methods: Sequence[str] | None = None,
                     confidence: float = 0.95) -> dict[str, dict[str, Curve]]:
    """``{env: {arm label: Curve}}``: mean return per step over (seed, task) runs with bootstrap CI bands.

    Methods come in the order of ``methods`` (others after them, sorted).
    """
    curves: dict[str, dict[str, Curve]] = {}
    for env in sorted({r["env"] for r in rows}):
        for label in _ordered_arms(rows, env, methods):
            curves.setdefault(env, {})[label] = mean_curve(run_matrix(rows, env=env, method=label),
                                                           confidence=confidence)
    return curves


def summary_table(rows: Sequence[Mapping], *, steps: Sequence[int] = (0, 1, 5), methods: Sequence[str] | None = None,
                  confidence: float = 0.95) -> tuple[str, list[dict]]:
    """Markdown table and records: return at ``k ∈ steps ∪ {K}`` (steps above K left out) and AUC per (env, arm).

    Every cell is the IQM over (seed, task) runs with its bootstrap CI; the AUC is also given as a mean with CI.
    Where the env ends episodes early (the rows' ``length`` varies), a last column gives the mean episode length at
    k = 0 and k = K: there a return sums fewer steps for a policy whose episodes end sooner.
    Returns ``(markdown, records)``; each record holds ``env``, ``method`` (the arm label), ``metric`` (``return_k<k>``,
    ``auc``, ``length_k<k>``) and :func:`~umrl.metatest.stats.summarize`'s keys.
    """
    records = []
    lines = []
    for env in sorted({r["env"] for r in rows}):
        order = _ordered_arms(rows, env, methods)
        num_steps = run_matrix(rows, env=env, method=order[0]).shape[1] - 1
        ks = sorted({k for k in steps if k <= num_steps} | {num_steps})
        env_rows = [r for r in rows if r["env"] == env]
        show_lengths = all("length" in r for r in env_rows) and len({r["length"] for r in env_rows}) > 1
        header = ["method"] + [f"k={k} IQM [95% CI]" for k in ks] + ["AUC IQM [95% CI]", "AUC mean [95% CI]", "runs"]
        header += [f"episode length k=0 / k={num_steps} (mean)"] if show_lengths else []
        lines += [f"### {env}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for method in order:
            matrix = run_matrix(rows, env=env, method=method)
            cells = []
            for k in ks:
                s = summarize(matrix[:, k], confidence=confidence)
                records.append({"env": env, "method": method, "metric": f"return_k{k}", **s})
                cells.append(f"{s['iqm']:.2f} [{s['iqm_low']:.2f}, {s['iqm_high']:.2f}]")
            s = summarize(auc(matrix), confidence=confidence)
            records.append({"env": env, "method": method, "metric": "auc", **s})
            cells.append(f"{s['iqm']:.1f} [{s['iqm_low']:.1f}, {s['iqm_high']:.1f}]")
            cells.append(f"{s['mean']:.1f} [{s['mean_low']:.1f}, {s['mean_high']:.1f}]")
            cells.append(str(matrix.shape[0]))
            if show_lengths:
                length = run_matrix(rows, env=env, method=method, value="length")
                ends = [summarize(length[:, k], confidence=confidence) for k in (0, num_steps)]
                records += [{"env": env, "method": method, "metric": f"length_k{k}", **e}
                            for k, e in zip((0, num_steps), ends)]
                cells.append(f"{ends[0]['mean']:.1f} / {ends[1]['mean']:.1f}")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines), records


def baseline_arms(rows: Iterable[Mapping]) -> set[str]:
    """Arm labels of ablation rows without an ``iteration`` (methods meta-tested once, not along meta-training)."""
    return {_label(r) for r in rows if r.get("iteration") is None}


def ablation_curves(rows: Sequence[Mapping], *, metric: str) -> dict[str, dict[str, Curve]]:
    """``{env: {arm label: Curve over meta-training iterations}}`` of the per-run ``metric`` (``auc`` | ``final``).

    Rows of meta-trained checkpoints carry an ``iteration`` column (the meta-training iteration of the checkpoint).
    An arm whose rows have none (a baseline such as scratch, meta-tested once) is a flat curve over the env's first
    and last iteration, the level the checkpoints are read against.
    """
    if metric not in ("auc", "final"):
        raise ValueError(f"metric must be 'auc' or 'final', got {metric!r}.")

    def stats(arm_rows: Sequence[Mapping], env: str, label: str) -> tuple[float, float, float]:
        matrix = run_matrix(arm_rows, env=env, method=label)
        values = auc(matrix) if metric == "auc" else matrix[:, -1]
        return (values.mean(), *bootstrap_ci(values))

    curves: dict[str, dict[str, Curve]] = {}
    baselines = []
    for env, label in sorted({(r["env"], _label(r)) for r in rows}):
        arm_rows = [r for r in rows if r["env"] == env and _label(r) == label]
        if label in baseline_arms(arm_rows):
            baselines.append((env, label, stats(arm_rows, env, label)))
            continue
        iterations = sorted({int(r["iteration"]) for r in arm_rows})
        mean, low, high = (list(x) for x in zip(*(
            stats([r for r in arm_rows if int(r["iteration"]) == it], env, label) for it in iterations)))
        curves.setdefault(env, {})[label] = Curve(iterations, mean, low, high)
    for env, label, (mean, low, high) in baselines:
        xs = sorted({x for c in curves.get(env, {}).values() for x in c.x}) or [0]
        span = [xs[0], xs[-1]]
        curves.setdefault(env, {})[label] = Curve(span, [mean] * 2, [low] * 2, [high] * 2)
    return curves


def ablation_table(curves: Mapping[str, Mapping[str, Curve]], baselines: Collection[str] = ()) -> str:
    """Markdown of :func:`ablation_curves`' output: one line per (env, arm, iteration) with mean and 95 % CI; an arm
    in ``baselines`` (not meta-trained) gets one line, its iteration shown as "—"."""
    lines = ["# Meta-training ablation", "", "| env | method | iteration | AUC mean [95% CI] |", "|---|---|---|---|"]
    for env, methods in curves.items():
        for method, c in methods.items():
            points = list(zip(c.x, c.mean, c.low, c.high))
            if method in baselines:
                points = [("—", *points[0][1:])]
            lines += [f"| {env} | {method} | {it} | {m:.1f} [{lo:.1f}, {hi:.1f}] |" for it, m, lo, hi in points]
    return "\n".join(lines) + "\n"


def pretraining_note(seeds: Sequence[int], pretrain_seeds: Sequence[int]) -> str:
    """One sentence saying which pre-training run stands behind each meta-test seed (and what that leaves out)."""
    pairs = ", ".join(f"{s}→{p}" for s, p in zip(seeds, pretrain_seeds))
    if len(set(pretrain_seeds)) == len(pretrain_seeds):
        return (f"Pre-training: independent per meta-test seed (meta-test seed → pre-training seed: {pairs}); "
                "the intervals include pre-training variance.")
    return (f"Pre-training: **shared** (meta-test seed → pre-training seed: {pairs}); the intervals leave out "
            "pre-training variance.")


def suite_summary(table: str, *, profile: str, pretraining: str, lr_lines: Sequence[str], time_lines: Sequence[str],
                  settings_yaml: str, provenance: Mapping[str, str], ablation: str | None = None) -> str:
    """The suite's ``summary.md``: title, protocol line, pre-training note, the table (:func:`summary_table`),
    learning rates, wall times, provenance (:func:`~umrl.metatest.provenance.provenance`), settings and the ablation table."""
    markdown = (f"# Benchmark suite `{profile}`\n\nMeta-test return (IQM over tasks x seeds, 95% bootstrap "
                f"CI); AUC = trapezoidal area under the return curve over k = 0..K.\n\n{pretraining}\n\n{table}\n"
                "## Meta-test learning rates\n\n" + "\n".join(lr_lines) + "\n\n## Wall time\n\n"
                + "\n".join(time_lines) + "\n\n## Provenance\n\n" + "\n".join(f"- {k}: {v}" for k, v in provenance.items())
                + f"\n\n## Settings\n\n```yaml\n{settings_yaml}```\n")
    if ablation:
        markdown += "\n" + ablation.replace("# Meta", "## Meta")
    return markdown


__all__ = [
    "COLUMNS",
    "ablation_curves",
    "ablation_table",
    "arm_label",
    "arm_styles",
    "baseline_arms",
    "cell_finished",
    "csv_text",
    "curves_from_rows",
    "mean_curve",
    "pretraining_note",
    "read_rows",
    "run_matrix",
    "suite_summary",
    "summary_table",
    "text_sha256",
    "to_rows",
    "write_rows",
]
