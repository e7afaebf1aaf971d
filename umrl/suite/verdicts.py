"""The verdict rule: paired meta-test cells in, one of agrees / partly / disagrees / undecided out, per claim and env.

The rule (``docs/results/verdicts.md`` states it in the same words):

* **Evidence.** A claim is made of one or more *parts*; each part is a contrast between methods, read run by run.
  A run is one (pre-training seed, held-out task) pair, and every method of a seed meta-tests the same tasks, so
  the contrast is paired: for "A ahead of B" it is AUC(A) − AUC(B) over k = 0..K (the cells' whole horizon), for "A
  close behind B" it is A − (B + scratch) / 2 (A keeps at least half of B's lead over scratch), on the AUC or on the
  return at k = K. The part's numbers are the mean contrast over all runs of the seeds that hold every method it
  names, its 95 % percentile bootstrap interval (:func:`~umrl.metatest.stats.bootstrap_ci`: 2,000 resamples of the
  pooled runs, seed 0; the interval the results pages print as "paired"), each seed's own mean and on how many runs
  the contrast is above 0.
* **One part.** *agrees*: the interval lies above 0 and every pre-training seed's mean is above 0. *disagrees*: the
  interval lies below 0 and every seed's mean is below 0. *partly*: the interval excludes 0 but the seeds split (the
  pooled sign is not repeated on every seed). *undecided*: the interval holds 0.
* **A claim.** *agrees* when every part agrees; *partly* when at least one part agrees or is partly and not every
  part agrees; *disagrees* when no part agrees or is partly and at least one disagrees; *undecided* when every part
  is undecided. A claim counts only the parts whose methods have cells; the table names the ones without. A claim
  with parts lacking cells is at most *partly* (its other parts agreeing is not the claim agreeing), and a claim
  with no part that has cells on an env gets no verdict there (``no cells``).
* **Gates.** An env whose gate fails (:data:`GATES`: a condition without which the env tests no claim, decided on its
  results page) gets *not testable* for every claim, whatever its cells say.

With one pre-training seed the rule reads the same, but the interval then covers tasks only, not pre-training
variance: every verdict is printed with its seeds, and a one-seed verdict says less than a three-seed one.

Command (every table from the committed cells, no compute)::

    python -m umrl.suite.verdicts results/

Cells are the suite's per-cell CSV files as ``results/README.md`` keeps them,
``<root>/<env>/meta_test_ref/seed<s>/<method>[.<schedule>].csv``, each with its ``.json`` beside it (which names the
checkpoint whose saved config gives the pre-training budget).
"""
from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from umrl.configs.env_groups import env_defaults
from umrl.metatest.results import arm_label, read_rows, run_matrix
from umrl.metatest.stats import auc, bootstrap_ci

#: Every label the rule gives, in order of strength of agreement (``not testable`` from a gate).
VERDICTS = ("agrees", "partly", "disagrees", "undecided", "not testable")

#: Envs whose gate fails: env → why no claim is testable there, and the page that shows it. Their cells are not judged.
GATES = {
    "ant": (("the oracle ends nearer its goals than a policy that never moves only adapted, from 200 of 375 MAML "
             "iterations; the UML runs at that budget are not made"),
            "docs/results/reference_ant.md"),
}


@dataclass(frozen=True)
class Part:
    """One contrast of a claim: ``weights`` per method (arm label) on ``metric`` (``auc`` over k = 0..K or ``final``,
    the return at k = K), read per run; the part holds when the contrast is above 0."""

    text: str
    weights: Mapping[str, float]
    metric: str = "auc"


@dataclass(frozen=True)
class Claim:
    """A claim of the paper, as parts that must all hold."""

    text: str
    parts: tuple[Part, ...]


def ahead(a: str, b: str) -> Part:
    """"``a`` ahead of ``b``": AUC(a) − AUC(b) per run."""
    return Part(f"{a} ahead of {b}", {a: 1.0, b: -1.0})


def close_behind(a: str, b: str, metric: str = "auc", baseline: str = "scratch") -> Part:
    """"``a`` close behind ``b``": ``a`` keeps at least half of ``b``'s lead over ``baseline``, i.e.
    a − (b + baseline) / 2 per run."""
    where = "over k = 0..K" if metric == "auc" else "at k = K"
    return Part(f"{a} close behind {b} {where} (above the midpoint of {b} and {baseline})",
                {a: 1.0, b: -0.5, baseline: -0.5}, metric)


#: The paper's claims, each as the parts the rule tests.
CLAIMS = (
    Claim("UML-DIAYN learns faster than scratch", (ahead("uml_diayn", "scratch"),)),
    Claim("UML-random learns faster than scratch", (ahead("uml_random", "scratch"),)),
    Claim("UML beats VIME-init and DIAYN-init", (
        ahead("uml_diayn", "vime_init"), ahead("uml_diayn", "diayn_init"),
        ahead("uml_random", "vime_init"), ahead("uml_random", "diayn_init"))),
    Claim("the oracle learns fastest, UML-DIAYN close behind, similar by k = K", (
        ahead("oracle", "uml_diayn"), close_behind("uml_diayn", "oracle"),
        close_behind("uml_diayn", "oracle", metric="final"))),
)


@dataclass(frozen=True)
class Evidence:
    """The numbers one part rests on: pooled mean contrast [95 % CI], each seed's mean, runs above 0, and the label."""

    part: Part
    mean: float
    low: float
    high: float
    seed_means: dict[int, float]
    ahead: int
    runs: int
    verdict: str
    scale: float | None = None  # |scratch's mean| on the part's metric and seeds, for the figure's relative axis

    def short(self) -> str:
        """``+237.9 [182.9, 292.3]``: the number a table cell shows."""
        return f"{self.mean:+.1f} [{self.low:.1f}, {self.high:.1f}]"


@dataclass(frozen=True)
class ClaimVerdict:
    """A claim's verdict on one env: the label, the evidence of each part with cells, the parts without."""

    claim: Claim
    env: str
    verdict: str
    evidence: tuple[Evidence, ...] = ()
    missing: tuple[str, ...] = ()
    reason: str = ""

    @property
    def deciding(self) -> Evidence | None:
        """The part the label rests on: the first with the claim's label, else the first that does not agree."""
        for e in self.evidence:
            if e.verdict == self.verdict:
                return e
        return next((e for e in self.evidence if e.verdict != "agrees"), None)


def part_verdict(low: float, high: float, seed_means: Sequence[float]) -> str:
    """The rule for one part, from its pooled interval ``[low, high]`` and each pre-training seed's mean contrast."""
    if not seed_means:
        raise ValueError("part_verdict needs at least one seed's mean.")
    if low > high:
        raise ValueError(f"interval low {low} is above high {high}.")
    if low > 0 and all(m > 0 for m in seed_means):
        return "agrees"
    if high < 0 and all(m < 0 for m in seed_means):
        return "disagrees"
    if low > 0 or high < 0:
        return "partly"
    return "undecided"


def claim_verdict(part_verdicts: Sequence[str]) -> str:
    """The rule for a claim, from the verdicts of its parts (each one of agrees / partly / disagrees / undecided)."""
    unknown = set(part_verdicts) - set(VERDICTS[:4])
    if not part_verdicts or unknown:
        raise ValueError(f"part verdicts: got {list(part_verdicts)}; expected one or more of {VERDICTS[:4]}.")
    if all(v == "agrees" for v in part_verdicts):
        return "agrees"
    if any(v in ("agrees", "partly") for v in part_verdicts):
        return "partly"
    return "disagrees" if "disagrees" in part_verdicts else "undecided"


def contrast(per_seed: Mapping[str, Mapping[int, np.ndarray]], part: Part) -> dict[int, np.ndarray]:
    """``{seed: [tasks] contrast}`` of ``part`` over the seeds where every method it names has a cell.

    ``per_seed``: ``{arm label: {seed: [tasks, K + 1] returns}}`` (:func:`~umrl.metatest.results.run_matrix` per
    seed). Empty when some method has no cell on any shared seed; tasks or horizons that differ raise ``ValueError``.
    """
    seeds = sorted(set.intersection(*(set(per_seed.get(arm, {})) for arm in part.weights)))
    values = {}
    for seed in seeds:
        matrices = {arm: per_seed[arm][seed] for arm in part.weights}
        shapes = {m.shape for m in matrices.values()}
        if len(shapes) > 1:
            raise ValueError(f"{part.text}, seed {seed}: the methods' [tasks, K + 1] differ ({shapes}); paired "
                             "cells must meta-test the same tasks at the same horizon.")
        values[seed] = sum(w * _read(part, matrices[arm]) for arm, w in part.weights.items())
    return values


def _read(part: Part, matrix: np.ndarray) -> np.ndarray:
    """``[tasks]`` values of the part's metric: AUC over k = 0..K, or the return at k = K."""
    return auc(matrix) if part.metric == "auc" else matrix[:, -1]


def evidence(part: Part, values: Mapping[int, np.ndarray], scale: float | None = None) -> Evidence:
    """Apply the one-part rule to ``{seed: [tasks] contrast}``: pooled mean and bootstrap CI, per-seed means."""
    pooled = np.concatenate([np.asarray(values[s], dtype=np.float64) for s in sorted(values)])
    low, high = bootstrap_ci(pooled)
    seed_means = {s: float(np.mean(values[s])) for s in sorted(values)}
    return Evidence(part, float(pooled.mean()), low, high, seed_means, int((pooled > 0).sum()), pooled.size,
                    part_verdict(low, high, list(seed_means.values())), scale)


def judge(claim: Claim, env: str, per_seed: Mapping[str, Mapping[int, np.ndarray]]) -> ClaimVerdict:
    """The claim's verdict on ``env`` from ``{arm: {seed: [tasks, K + 1]}}``; ``no cells`` where no part has cells."""
    if env in GATES:
        return ClaimVerdict(claim, env, "not testable", reason=GATES[env][0])
    found, missing = [], []
    for part in claim.parts:
        values = contrast(per_seed, part)
        if values:
            scratch = [_read(part, per_seed["scratch"][s]) for s in values if s in per_seed.get("scratch", {})]
            scale = float(abs(np.concatenate(scratch).mean())) if scratch else None
            found.append(evidence(part, values, scale))
        else:
            missing.append(part.text)
    if not found:
        return ClaimVerdict(claim, env, "no cells", missing=tuple(missing), reason="no committed cells")
    verdict = claim_verdict([e.verdict for e in found])
    if missing and verdict == "agrees":
        verdict = "partly"
    return ClaimVerdict(claim, env, verdict, tuple(found), tuple(missing))


@dataclass
class EnvCells:
    """The committed cells of one env: ``{arm: {seed: [tasks, K + 1]}}`` and the pre-training budgets they name."""

    per_seed: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    budgets: dict[str, set[str]] = field(default_factory=dict)


def find_cells(root: str | Path) -> list[Path]:
    """Cell CSV files under ``root`` (``<env>/meta_test_ref/seed<s>/<method>[.<schedule>].csv``), sorted."""
    return sorted(Path(root).glob("*/meta_test_ref/seed*/*.csv"))


def _budget(cell_csv: Path, root: Path, env: str) -> tuple[str, str] | None:
    """``("MAML", "100 / 100")`` or ``("DIAYN", "50000 / 50000")`` from the config of the checkpoint the cell's json
    names (relative to the cell's folder, or an absolute path whose ``results/…`` tail is read under ``root``'s
    parent), against the env's reference budget; None when the cell trains nothing or the checkpoint is not kept."""
    info = cell_csv.with_suffix(".json")
    checkpoint = json.loads(info.read_text()).get("checkpoint") if info.exists() else None
    if not checkpoint:
        return None
    if not Path(checkpoint).is_absolute():  # relative to the cell's folder
        run = info.parent / checkpoint
    elif "results/" in checkpoint:  # an absolute path of the machine that ran it: the same run under this root
        run = root.parent / checkpoint[checkpoint.index("results/"):]
    else:
        run = Path(checkpoint)
    config = run / "checkpoints" / "config.yaml"
    if not config.is_file():
        return None
    cfg = yaml.safe_load(config.read_text())
    if "proposal" in cfg:
        return "MAML", f"{cfg['iterations']} / {env_defaults('maml', env)['iterations']}"
    if "collector" in cfg:
        return "DIAYN", f"{cfg['collector']['total_frames']} / {env_defaults('diayn', env)['collector']['total_frames']}"
    return None


def load_cells(root: str | Path) -> dict[str, EnvCells]:
    """``{env: EnvCells}`` of every cell under ``root``; a root without cells raises ``ValueError``."""
    root = Path(root).resolve()
    paths = find_cells(root)
    if not paths:
        raise ValueError(f"no meta-test cells under {root}; expected <env>/meta_test_ref/seed<s>/<method>.csv.")
    envs: dict[str, EnvCells] = {}
    for path in paths:
        rows = read_rows([path])
        for env, arm, seed in sorted({(r["env"], _arm(r), r["seed"]) for r in rows}):
            cells = envs.setdefault(env, EnvCells())
            cells.per_seed.setdefault(arm, {})[seed] = run_matrix(rows, env=env, method=arm)
            budget = _budget(path, root, env) if env not in GATES else None
            if budget:
                cells.budgets.setdefault(budget[0], set()).add(budget[1])
    return envs


def _arm(row: Mapping) -> str:
    return arm_label(row["method"], row["lr_schedule"])


def budget_note(budgets: Mapping[str, set[str]]) -> str:
    """``MAML 100 / 100 it., DIAYN 50000 / 50000 env steps``: each budget the cells name, against the reference's."""
    units = {"MAML": "it.", "DIAYN": "env steps"}
    return ", ".join(f"{kind} {' or '.join(sorted(values))} {units[kind]}" for kind, values in sorted(budgets.items(),
                     key=lambda kv: kv[0] != "MAML"))


def verdict_table(root: str | Path, claims: Sequence[Claim] = CLAIMS) -> tuple[str, list[ClaimVerdict]]:
    """Markdown of every claim's verdict per env (the envs with cells, and every gated env), then each part's numbers.

    Returns ``(markdown, verdicts)``."""
    cells = load_cells(root)
    envs = sorted(set(cells) | set(GATES))
    verdicts = [judge(claim, env, cells.get(env, EnvCells()).per_seed) for claim in claims for env in envs]
    lines = ["| claim | " + " | ".join(envs) + " |", "|---|" + "---|" * len(envs)]
    for claim in claims:
        row = [v for v in verdicts if v.claim is claim]
        lines.append(f"| {claim.text} | " + " | ".join(_cell(v) for v in row) + " |")
    lines += ["", "| env | seeds | pre-training budget (cells / reference) |", "|---|---|---|"]
    for env in envs:
        if env in GATES:
            lines.append(f"| {env} | — | gate: {GATES[env][0]} ({GATES[env][1]}) |")
            continue
        seeds = sorted({s for arm in cells[env].per_seed.values() for s in arm})
        lines.append(f"| {env} | {', '.join(map(str, seeds))} | {budget_note(cells[env].budgets) or 'unknown'} |")
    lines += ["", "| env | claim part | verdict | mean [95 % CI] | per seed | runs above 0 |", "|---|---|---|---|---|---|"]
    for v in sorted(verdicts, key=lambda v: v.env):
        for e in v.evidence:
            per_seed = " / ".join(f"{s}: {m:+.1f}" for s, m in e.seed_means.items())
            lines.append(f"| {v.env} | {e.part.text} | {e.verdict} | {e.short()} | {per_seed} | {e.ahead} of {e.runs} |")
        lines += [f"| {v.env} | {text} | no cells | | | |" for text in v.missing]
    return "\n".join(lines) + "\n", verdicts


#: Marker colour of each part verdict in :func:`plot_verdicts`.
VERDICT_COLORS = {"agrees": "tab:green", "partly": "tab:olive", "disagrees": "tab:red", "undecided": "tab:gray"}


def plot_verdicts(verdicts: Sequence[ClaimVerdict], path: str | Path) -> Path:
    """Each part's paired mean and 95 % interval as a share of scratch's mean (|AUC| or |return at k = K|), one row
    per part and one panel per env, coloured by the part's verdict; returns the PNG path."""
    from matplotlib.figure import Figure

    from umrl.figures import save_figure

    panels: dict[str, list[tuple[int, Evidence]]] = {}
    for v in verdicts:
        panels.setdefault(v.env, []).extend((id(v.claim), e) for e in v.evidence if e.scale)
    panels = {env: rows[::-1] for env, rows in sorted(panels.items()) if rows}  # the first claim on top
    if not panels:
        raise ValueError("nothing to plot: no part has cells and a scratch baseline.")
    height = max(len(rows) for rows in panels.values())
    fig = Figure(figsize=(6.5 * len(panels), 1.2 + 0.42 * height))
    for ax, (env, rows) in zip(fig.subplots(1, len(panels), squeeze=False)[0], panels.items()):
        for y, (claim, e) in enumerate(rows):
            mean, low, high = (100.0 * x / e.scale for x in (e.mean, e.low, e.high))
            ax.errorbar(mean, y, xerr=[[mean - low], [high - mean]], fmt="o", capsize=3,
                        color=VERDICT_COLORS[e.verdict], label=e.verdict)
            if y and rows[y - 1][0] != claim:
                ax.axhline(y - 0.5, color="gray", linewidth=0.6, linestyle=":")
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_ylim(-0.6, len(rows) - 0.4)
        ax.set_yticks(range(len(rows)), [_label(e) for _, e in rows], fontsize="small")
        seeds = sorted({s for _, e in rows for s in e.seed_means})
        ax.set_title(f"{env}, pre-training seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}")
        ax.set_xlabel("paired difference, % of scratch's |mean| [95 % CI]")
        ax.grid(axis="x", alpha=0.3)
        labels = dict(zip(*ax.get_legend_handles_labels()[::-1]))
        ax.legend([labels[k] for k in VERDICT_COLORS if k in labels], [k for k in VERDICT_COLORS if k in labels],
                  fontsize="small", loc="best")
    return save_figure(fig, path)


def _label(e: Evidence) -> str:
    """A part's short name for the figure: ``uml_diayn > scratch``, ``uml_diayn ≥ ½(oracle + scratch), k = K``."""
    names = [arm for arm, w in e.part.weights.items() if w > 0] + [arm for arm, w in e.part.weights.items() if w < 0]
    if len(names) == 2:
        return f"{names[0]} > {names[1]}"
    where = "AUC" if e.part.metric == "auc" else "k = K"
    return f"{names[0]} > ½({names[1]} + {names[2]}), {where}"


def _cell(v: ClaimVerdict) -> str:
    if v.verdict == "not testable":
        return f"{v.verdict} (gate)"
    if not v.evidence:
        return v.verdict
    e = v.deciding or v.evidence[0]
    seeds = f"seed{'s' if len(e.seed_means) > 1 else ''} {'/'.join(map(str, e.seed_means))}"
    text = f"**{v.verdict}**: {e.part.text} {e.short()}, {seeds}"
    return text + (f"; no cells for {len(v.missing)} of {len(v.claim.parts)} parts" if v.missing else "")


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="The paper's claims judged by the verdict rule on committed cells.")
    parser.add_argument("root", nargs="?", default="results", help="folder holding <env>/meta_test_ref/seed<s>/")
    parser.add_argument("--figure", default=None, help="also draw every part's interval into this PNG")
    args = parser.parse_args(argv)
    try:
        markdown, verdicts = verdict_table(args.root)
        figure = plot_verdicts(verdicts, args.figure) if args.figure else None
    except ValueError as e:
        raise SystemExit(f"verdicts: {e}") from None
    print(markdown, end="")
    if figure:
        print(f"\nfigure: {figure}")


if __name__ == "__main__":
    main()

__all__ = [
    "CLAIMS",
    "GATES",
    "VERDICTS",
    "Claim",
    "ClaimVerdict",
    "Evidence",
    "Part",
    "ahead",
    "claim_verdict",
    "close_behind",
    "contrast",
    "evidence",
    "judge",
    "load_cells",
    "part_verdict",
    "plot_verdicts",
    "verdict_table",
]
