"""IQM, bootstrap CI and AUC on inputs whose answers are known by hand."""
import numpy as np
import pytest

from umrl.metatest.stats import auc, bootstrap_ci, iqm, summarize


def test_auc_trapezoid_known_values():
    assert auc([1.0, 1.0, 1.0]) == pytest.approx(2.0)  # constant r over K=2 unit steps -> K * r
    assert auc([0.0, 2.0, 4.0]) == pytest.approx(4.0)  # a line: (0+2)/2 + (2+4)/2
    assert auc([0.0, 2.0], steps=[0.0, 3.0]) == pytest.approx(3.0)
    np.testing.assert_allclose(auc(np.array([[1.0, 1.0], [0.0, 1.0]])), [1.0, 0.5])


def test_auc_rejects_bad_steps():
    with pytest.raises(ValueError, match="increasing"):
        auc([1.0, 2.0], steps=[1.0, 1.0])
    with pytest.raises(ValueError, match="two points"):
        auc([1.0])


def test_iqm_drops_quartiles():
    # 8 values: sorted -100, 1..6, 100; drop 2 at each end -> mean(2, 3, 4, 5) = 3.5, whatever the outliers are.
    assert iqm([100.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, -100.0]) == pytest.approx(3.5)
    assert iqm([7.0]) == pytest.approx(7.0)
    np.testing.assert_allclose(iqm(np.array([[1.0, 2.0, 3.0, 4.0], [0.0, 0.0, 10.0, 10.0]]), axis=-1), [2.5, 5.0])


def test_bootstrap_ci_brackets_the_mean_and_shrinks_with_n():
    rng = np.random.default_rng(0)
    small = rng.normal(1.0, 1.0, size=20)
    large = rng.normal(1.0, 1.0, size=2000)
    lo_s, hi_s = bootstrap_ci(small)
    lo_l, hi_l = bootstrap_ci(large)
    assert lo_s < small.mean() < hi_s
    assert lo_l < 1.0 < hi_l
    assert (hi_l - lo_l) < (hi_s - lo_s) / 5  # width ~ 1/sqrt(n): 10x more precise with 100x the data
    # For a normal sample, the 95 % bootstrap CI of the mean is close to mean +- 1.96 * sd / sqrt(n).
    half = 1.96 * large.std(ddof=1) / np.sqrt(large.size)
    assert (hi_l - lo_l) / 2 == pytest.approx(half, rel=0.1)
    assert bootstrap_ci([3.0]) == (3.0, 3.0)


def test_summarize_keys_and_order():
    s = summarize([1.0, 2.0, 3.0, 4.0])
    assert s["mean"] == pytest.approx(2.5) and s["iqm"] == pytest.approx(2.5) and s["n"] == 4
    assert s["mean_low"] <= s["mean"] <= s["mean_high"]
    assert s["iqm_low"] <= s["iqm"] <= s["iqm_high"]
