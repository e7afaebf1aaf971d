"""Benchmark figures: adaptation curves (return vs adaptation step) and the meta-training ablation.

Both take already-aggregated curves, ``{panel: {method: Curve}}``, so they can be checked without running anything;
:func:`umrl.metatest.results.curves_from_rows` builds them from the tidy results table. Figures are written as PNG
through :class:`matplotlib.figure.Figure`, without pyplot, so matplotlib's backend is left as the caller set it.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import matplotlib.ticker
import numpy as np
from matplotlib.figure import Figure

from umrl.figures import save_figure

#: One colour per method, stable across figures (methods outside this map get matplotlib's cycle).
METHOD_COLORS = {
    "uml_diayn": "tab:blue",
    "uml_random": "tab:orange",
    "oracle": "tab:green",
    "vime_init": "tab:purple",
    "diayn_init": "tab:brown",
    "scratch": "tab:gray",
    "uml_random_arena": "tab:red",  # the bounded-arena ablation of UML-random
}


@dataclass
class Curve:
    """A mean curve with a confidence band: ``x``, ``mean``, ``low``, ``high`` are 1-D arrays of equal length."""

    x: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray


def _panels(curves: Mapping[str, Mapping[str, Curve]], path: str | os.PathLike, *, xlabel: str, ylabel: str,
            title: str, marker: str | None, styles: Mapping[str, Mapping] | None) -> Path:
    if not curves:
        raise ValueError("nothing to plot: no curves were given.")
    fig = Figure(figsize=(5.0 * len(curves), 4.0))
    axes = fig.subplots(1, len(curves), squeeze=False)
    for ax, (panel, methods) in zip(axes[0], curves.items()):
        for method, curve in methods.items():
            style = dict((styles or {}).get(method) or {"color": METHOD_COLORS.get(method)})
            color = style.pop("color", None)
            ax.plot(curve.x, curve.mean, label=method, color=color, **{"marker": marker, **style})
            ax.fill_between(curve.x, curve.low, curve.high, color=color, alpha=0.2, linewidth=0)
        ax.set_title(panel)
        ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize="small")
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_adaptation_curves(curves: Mapping[str, Mapping[str, Curve]], path: str | os.PathLike, *,
                           styles: Mapping[str, Mapping] | None = None) -> Path:
    """Mean meta-test return vs adaptation step ``k``, one panel per env, 95 % bands; returns the PNG path.

    ``styles``: matplotlib line keywords per curve name (e.g. :func:`umrl.metatest.results.arm_styles`); default:
    the method's colour from :data:`METHOD_COLORS`, solid.
    """
    return _panels(curves, path, xlabel="adaptation step k", ylabel="mean return over tasks x seeds",
                   title="Meta-test adaptation", marker=None, styles=styles)


def plot_ablation(curves: Mapping[str, Mapping[str, Curve]], path: str | os.PathLike, *, metric: str,
                  styles: Mapping[str, Mapping] | None = None) -> Path:
    """Meta-test ``metric`` of checkpoints vs meta-training iteration, one panel per env; returns the PNG path."""
    return _panels(curves, path, xlabel="meta-training iteration", ylabel=metric,
                   title="Meta-training ablation", marker="o", styles=styles)
