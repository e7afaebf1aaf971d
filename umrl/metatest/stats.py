"""Statistics for meta-test results: area under the adaptation curve, interquartile mean, bootstrap CIs.

Everything here takes NumPy arrays (or sequences) and returns floats / arrays; nothing depends on torch.

* :func:`auc` — trapezoidal area under a return curve recorded at adaptation steps ``k = 0…K``.
* :func:`iqm` — interquartile mean: the mean of the middle 50 % of the values (the ``trim_mean(x, 0.25)`` of
  Agarwal et al., "Deep RL at the edge of the statistical precipice", 2021), robust to a few outlier runs.
* :func:`bootstrap_ci` — percentile bootstrap confidence interval of any statistic.
* :func:`summarize` — the summary row the benchmark table prints (mean, IQM and their CIs).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np


def auc(returns: Sequence[float] | np.ndarray, steps: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Area under return curves by the trapezoidal rule.

    Args:
        returns: ``[..., S]`` returns at ``S`` adaptation steps (the last axis is the step axis).
        steps: ``[S]`` step values, increasing; default ``0, 1, …, S-1``.

    Returns:
        ``[...]`` areas (a 0-d array for one curve). With unit spacing and ``S = K + 1`` points the area of a constant
        curve ``r`` is ``K · r``.
    """
    returns = np.asarray(returns, dtype=np.float64)
    if returns.ndim == 0 or returns.shape[-1] < 2:
        raise ValueError(f"auc needs at least two points on the last axis, got shape {returns.shape}.")
    x = np.arange(returns.shape[-1], dtype=np.float64) if steps is None else np.asarray(steps, dtype=np.float64)
    if x.shape != (returns.shape[-1],) or np.any(np.diff(x) <= 0):
        raise ValueError(f"steps must be {returns.shape[-1]} increasing values, got {x.tolist()}.")
    widths = np.diff(x)
    return ((returns[..., 1:] + returns[..., :-1]) * 0.5 * widths).sum(-1)


def iqm(values: Sequence[float] | np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean along ``axis``: drop ``floor(n / 4)`` values at each end of the sorted data, average the rest."""
    values = np.sort(np.asarray(values, dtype=np.float64), axis=axis)
    n = values.shape[axis]
    if n == 0:
        raise ValueError("iqm of an empty array is undefined.")
    cut = n // 4
    return np.take(values, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def bootstrap_ci(
    values: Sequence[float] | np.ndarray,
    statistic: Callable[..., np.ndarray] = np.mean,
    *,
    confidence: float = 0.95,
    num_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of ``statistic`` over the 1-D sample ``values``.

    ``statistic`` must accept an ``axis`` keyword (``np.mean``, :func:`iqm`, ...): all resamples are evaluated in one
    vectorised call on a ``[num_resamples, n]`` array. Returns ``(low, high)``; a sample of one value gives a
    zero-width interval.
    """
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.size == 0:
        raise ValueError("bootstrap_ci needs at least one value.")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}.")
    rng = np.random.default_rng(seed)
    resamples = values[rng.integers(0, values.size, size=(num_resamples, values.size))]
    stats = statistic(resamples, axis=-1)
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(stats, [alpha, 1.0 - alpha])
    return float(low), float(high)


def summarize(values: Sequence[float] | np.ndarray, *, confidence: float = 0.95, num_resamples: int = 2000,
              seed: int = 0) -> dict[str, float]:
    """``mean``, ``mean_low``/``mean_high``, ``iqm``, ``iqm_low``/``iqm_high`` (bootstrap CIs) and ``n`` of a sample."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    mean_ci = bootstrap_ci(values, np.mean, confidence=confidence, num_resamples=num_resamples, seed=seed)
    iqm_ci = bootstrap_ci(values, iqm, confidence=confidence, num_resamples=num_resamples, seed=seed)
    return {
        "n": float(values.size),
        "mean": float(values.mean()),
        "mean_low": mean_ci[0],
        "mean_high": mean_ci[1],
        "iqm": float(iqm(values)),
        "iqm_low": iqm_ci[0],
        "iqm_high": iqm_ci[1],
    }
