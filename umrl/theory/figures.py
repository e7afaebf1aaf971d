"""Figures of the tabular analysis, drawn on :class:`matplotlib.figure.Figure` without pyplot (matplotlib's backend is
left as the caller set it; matplotlib is imported on first use, not on import)."""
from __future__ import annotations

import math
from pathlib import Path

import torch

from umrl.theory.cmp import DeterministicCMP, reachable_at
from umrl.theory.evaluation import Evaluation
from umrl.validation import InvalidValue


def plot_grid_marginals(cmp: DeterministicCMP, rows: list[Evaluation], path: str | Path) -> Path:
    """One panel per row: its exploration marginal ``[S]`` drawn on the grid (``cmp.shape``), unreachable cells hatched,
    titled with the worst-case regret."""
    from matplotlib.figure import Figure

    if cmp.shape is None:
        raise InvalidValue("cmp", cmp.name, "a grid (a CMP with a shape)")
    columns = min(4, len(rows))
    lines = math.ceil(len(rows) / columns)
    fig = Figure(figsize=(3 * columns, 3 * lines))
    axes = fig.subplots(lines, columns, squeeze=False)
    unreachable = (~reachable_at(cmp)).reshape(cmp.shape).numpy()
    top = max(float(row.marginal.max()) for row in rows)
    for ax, row in zip(axes.flat, rows):
        image = ax.imshow(row.marginal.reshape(cmp.shape).numpy(), cmap="viridis", vmin=0, vmax=top)
        ax.contourf(unreachable, levels=[0.5, 1.5], hatches=["//"], colors="none")
        start = divmod(cmp.start, cmp.shape[1])
        ax.plot(start[1], start[0], marker="*", color="red", markersize=10)
        ax.set_title(f"{row.proposal}\nworst-case regret {row.worst_case:.4g}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.flat[len(rows):]:
        ax.axis("off")
    fig.colorbar(image, ax=axes, shrink=0.6, label="terminal marginal rho(s_T)")
    fig.suptitle(f"{cmp.name}, T={cmp.horizon}: where the learner meta-trained on each proposal explores (Eq. 4; "
                 "red star: start; hatched: unreachable at T)", fontsize=9)
    return _save(fig, path)


def plot_regret_against_latents(cmp: DeterministicCMP, latents: list[int], curves: dict[str, list[float]],
                                path: str | Path) -> Path:
    """The ``"... worst-case"`` curves of :func:`~umrl.theory.evaluation.regret_against_latents` (learners meta-trained
    on each proposal) against ``|Z|`` (infinite values drawn as crosses at the top), and the MI the ascent reached
    against its maximum."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import ScalarFormatter

    reachable = int(reachable_at(cmp).sum())
    fig = Figure(figsize=(10, 4))
    left, right = fig.subplots(1, 2)
    regrets = {key: torch.tensor(values) for key, values in curves.items() if key.endswith("worst-case")}
    finite = [float(v) for values in regrets.values() for v in values if v.isfinite()]
    ceiling = 1.5 * max(finite + [reachable])
    for key, values in regrets.items():
        line, = left.plot(latents, torch.where(values.isinf(), torch.nan, values), "o-", label=key, markersize=4)
        infinite = values.isinf()
        left.plot(torch.tensor(latents)[infinite], torch.full((int(infinite.sum()),), ceiling), "x",
                  color=line.get_color(), markersize=9)
    left.axhline(reachable, color="k", linestyle=":", label="|S_T| (Lemma 1 minimum)")
    left.axvline(reachable, color="grey", linewidth=0.5)
    left.set_yscale("log")
    left.yaxis.set_major_formatter(ScalarFormatter())
    left.set_xlabel("|Z| (latents)")
    left.set_ylabel("worst-case regret of the Eq. 4 learner\n(episodes); x on top = infinite")
    left.legend(fontsize=7)
    right.plot(latents, curves["MI reached"], "o-", label="I(s_T; z) reached by ascent")
    right.plot(latents, curves["MI maximum"], "k.", label="max over conditionals (even split)")
    right.axhline(math.log(reachable), color="k", linestyle=":", label="log |S_T|")
    right.set_xlabel("|Z| (latents)")
    right.set_ylabel("nats")
    right.legend(fontsize=7)
    fig.suptitle(f"{cmp.name}, T={cmp.horizon}, |S_T|={reachable}")
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    """Write ``fig`` as a small PNG at ``path`` (parent folders created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    return path
