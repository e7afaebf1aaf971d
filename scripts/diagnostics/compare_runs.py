"""Compare meta-test curves across suite runs: one arm from each of several ``results.csv`` files, side by side.

    python scripts/diagnostics/compare_runs.py --env point_nav --horizons 20 100 \\
        --run "UML-random, 20 it=uml_random (reference)@outputs/suite/long_seeds/results.csv" \\
        --run "UML-random, 500 it=uml_random (reference)@outputs/suite/it500/results.csv" \\
        --run "scratch (Adam)=scratch@outputs/suite/it500/results.csv" --out docs/budgets.png

Each ``--run`` is ``LABEL=ARM@PATH``: the arm label as the suite's tables print it (``uml_diayn``,
``uml_random (reference)``), read from ``PATH`` (a ``results.csv`` or the suite output folder holding one). This is
how runs that differ in what the suite's cache keys on (MAML budgets, resumed copies of pre-training runs) are put
in one table and one figure. A ``PATH`` with glob characters reads every file it matches as one run, so per-seed
copies of cells pool without merging them first
(``"UML-DIAYN=uml_diayn@results/point_nav/meta_test_ref/seed*/uml_diayn.csv"``).

Prints, per run, the IQM return at ``--steps`` and the AUC IQM [95 % bootstrap CI] over k = 0..K for each horizon K
the run reaches (``—`` where it stops earlier), then the AUC of each seed's mean curve over tasks (with independent
pre-training per seed: one number per pre-training run), and draws one panel per horizon: mean return with a 95 %
band; runs of the same method are shades of its colour, lighter first.

With ``--paired``, every later run is also compared with the first task by task (runs of one seed meta-test the same
held-out tasks): the mean per-task AUC difference (later − first) [95 % bootstrap CI over seeds × tasks] and on how
many tasks the later run is ahead.
"""
from __future__ import annotations

import argparse
import glob
from pathlib import Path

import numpy as np
from matplotlib.colors import to_rgb

from umrl.metatest import (
    METHOD_COLORS,
    arm_label,
    auc,
    bootstrap_ci,
    iqm,
    mean_curve,
    plot_adaptation_curves,
    read_rows,
    run_matrix,
    summarize,
)


def parse_run(spec: str) -> tuple[str, str, list[Path]]:
    """``LABEL=ARM@PATH`` → ``(label, arm, results.csv paths)``; a glob ``PATH`` gives every match; a clear error for
    anything else."""
    label, sep, rest = spec.partition("=")
    arm, at, path = rest.rpartition("@")
    if not (sep and at and label and arm and path):
        raise SystemExit(f"--run: got {spec!r}; expected LABEL=ARM@PATH, e.g. "
                         "'UML-DIAYN=uml_diayn (reference)@outputs/suite/quick/results.csv'.")
    if glob.has_magic(path):
        csvs = sorted(Path(match) for match in glob.glob(path))
        if not csvs or not all(csv.is_file() for csv in csvs):
            raise SystemExit(f"--run {label!r}: {path!r} matches no file (or a folder); a glob must match csv files.")
        return label, arm, csvs
    csv = Path(path) / "results.csv" if Path(path).is_dir() else Path(path)
    if not csv.is_file():
        raise SystemExit(f"--run {label!r}: {path!r} is neither a results.csv nor a folder holding one.")
    return label, arm, [csv]


def load_seeds(csvs: list[Path], *, env: str, arm: str) -> dict[int, np.ndarray]:
    """``{seed: [tasks, K + 1] returns}`` of one arm over ``csvs``; names the arms they have when ``arm`` is not one."""
    all_rows = read_rows(csvs)
    rows = [r for r in all_rows if r["env"] == env and arm_label(r["method"], r["lr_schedule"]) == arm]
    if not rows:
        arms = sorted({(r["env"], arm_label(r["method"], r["lr_schedule"])) for r in all_rows})
        available = ", ".join(f"{a!r} on {e}" for e, a in arms)
        raise SystemExit(f"{', '.join(map(str, csvs))}: no arm {arm!r} on env {env!r}; it has {available}.")
    seeds = sorted({r["seed"] for r in rows})
    return {seed: run_matrix([r for r in rows if r["seed"] == seed], env=env, method=arm) for seed in seeds}


def run_styles(labels_arms: list[tuple[str, str]]) -> dict[str, dict]:
    """Line colour per run label: its method's colour, runs of one method shaded from light to full in given order."""
    by_method: dict[str, list[str]] = {}
    for label, arm in labels_arms:
        by_method.setdefault(arm.split(" ")[0], []).append(label)
    styles = {}
    for method, labels in by_method.items():
        base = np.array(to_rgb(METHOD_COLORS.get(method, "tab:olive")))
        for i, label in enumerate(labels):
            strength = 1.0 if len(labels) == 1 else 0.35 + 0.65 * i / (len(labels) - 1)
            styles[label] = {"color": tuple(1.0 - strength * (1.0 - base))}
    return styles


def paired_table(per_seed: dict[str, dict[int, np.ndarray]], horizons: list[int]) -> list[str]:
    """Markdown rows: each later run against the first, per-task AUC difference over the seeds both runs hold."""
    (first, base), *others = per_seed.items()
    header = ["run", f"against {first}: tasks"] + [f"AUC k<={h} difference [95% CI], ahead" for h in horizons]
    lines = ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, seeds in others:
        shared = sorted(set(seeds) & set(base))
        if not shared or any(seeds[s].shape[0] != base[s].shape[0] for s in shared):
            raise SystemExit(f"--paired: {label!r} and {first!r} share no seed with the same tasks "
                             f"(seeds {sorted(seeds)} and {sorted(base)}).")
        cells = [label, str(sum(base[s].shape[0] for s in shared))]
        for h in horizons:
            if min(min(seeds[s].shape[1], base[s].shape[1]) for s in shared) <= h:
                cells.append("—")
                continue
            diff = np.concatenate([auc(seeds[s][:, :h + 1]) - auc(base[s][:, :h + 1]) for s in shared])
            low, high = bootstrap_ci(diff)
            cells.append(f"{diff.mean():.1f} [{low:.1f}, {high:.1f}], {int((diff > 0).sum())}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", required=True, help="LABEL=ARM@PATH (repeat)")
    parser.add_argument("--env", default="point_nav")
    parser.add_argument("--horizons", type=int, nargs="+", default=[20, 100], help="K of each AUC column and panel")
    parser.add_argument("--steps", type=int, nargs="*", default=[0, 1], help="k of the return columns")
    parser.add_argument("--out", default=None, help="PNG of the curves (default: no figure)")
    parser.add_argument("--paired", action="store_true", help="also compare each later run with the first, per task")
    args = parser.parse_args()
    for name, least in (("horizons", 1), ("steps", 0)):
        if min(getattr(args, name), default=least) < least:
            raise SystemExit(f"--{name}: got {getattr(args, name)}; expected integers >= {least}.")
    runs = [parse_run(spec) for spec in args.run]
    if len({label for label, _, _ in runs}) < len(runs):
        raise SystemExit(f"--run: labels must differ, got {[label for label, _, _ in runs]}.")
    per_seed = {label: load_seeds(csvs, env=args.env, arm=arm) for label, arm, csvs in runs}
    matrices = {label: np.concatenate(list(seeds.values())) for label, seeds in per_seed.items()}

    header = ["run", "arm", "runs"] + [f"k={k} IQM" for k in args.steps]
    header += [f"AUC k<={h} IQM [95% CI]" for h in args.horizons]
    lines = [f"{args.env}: IQM over seeds x tasks", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, arm, _ in runs:
        matrix = matrices[label]
        last = matrix.shape[1] - 1
        cells = [label, arm, str(matrix.shape[0])]
        cells += [f"{iqm(matrix[:, k]):.1f}" if k <= last else "—" for k in args.steps]
        for horizon in args.horizons:
            if horizon > last:
                cells.append("—")
                continue
            s = summarize(auc(matrix[:, :horizon + 1]))
            cells.append(f"{s['iqm']:.1f} [{s['iqm_low']:.1f}, {s['iqm_high']:.1f}]")
        lines.append("| " + " | ".join(cells) + " |")
    header = ["run", "seeds"] + [f"AUC k<={h} of each seed's mean curve" for h in args.horizons]
    lines += ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, seeds in per_seed.items():
        cells = [label, " / ".join(map(str, seeds))]
        cells += [" / ".join(f"{auc(m[:, :h + 1].mean(0)):.1f}" for m in seeds.values())
                  if matrices[label].shape[1] > h else "—" for h in args.horizons]
        lines.append("| " + " | ".join(cells) + " |")
    if args.paired:
        lines += paired_table(per_seed, args.horizons)
    print("\n".join(lines))

    if args.out:
        panels = {f"{args.env}, k = 0..{h}": {label: mean_curve(m[:, :h + 1]) for label, m in matrices.items()
                                              if m.shape[1] > h} for h in args.horizons}
        panels = {panel: curves for panel, curves in panels.items() if curves}
        styles = run_styles([(label, arm) for label, arm, _ in runs])
        print(f"figure: {plot_adaptation_curves(panels, args.out, styles=styles)}")


if __name__ == "__main__":
    main()
