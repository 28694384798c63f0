"""fojax.statistics: t quantiles, one-sided and equivalence tests, Holm adjustment."""

import numpy as np
import pytest
from scipy import stats

from fojax import statistics


def test_t_quantile_is_exact():
    # The former hand-written table was off by 1.1e-4 at 11 degrees of freedom.
    for df in (1, 2, 5, 10, 11, 12, 30, 99, 5000):
        assert statistics.student_t_975(df) == pytest.approx(stats.t.ppf(0.975, df), rel=1e-12)
    assert statistics.student_t_975(11) == pytest.approx(2.200985160091639, rel=1e-12)
    with pytest.raises(ValueError):
        statistics.student_t_975(0)


def test_mean_ci_keeps_its_output():
    x = np.random.default_rng(1).normal(0.5, 1.0, 12)
    out = statistics.mean_ci(np.concatenate([x, [np.nan, -np.inf]]))
    assert set(out) == {"mean", "std", "ci95", "n", "n_nonfinite"}
    assert out["n"] == 12 and out["n_nonfinite"] == 2
    lo, hi = stats.t.interval(0.95, 11, loc=np.mean(x), scale=stats.sem(x))
    np.testing.assert_allclose(out["ci95"], [lo, hi], rtol=1e-12)
    assert statistics.mean_ci([np.nan])["mean"] is None
    assert statistics.mean_ci([2.0])["ci95"] is None


def test_one_sided_p_matches_scipy():
    x = np.random.default_rng(2).normal(0.3, 1.0, 25)
    for threshold in (0.0, 0.2, 0.6):
        for alternative in ("greater", "less"):
            want = stats.ttest_1samp(x, threshold, alternative=alternative).pvalue
            got = statistics.one_sided_p(x, threshold, alternative)
            assert got == pytest.approx(want, rel=1e-10)
    # Non-finite draws are left out.
    padded = np.concatenate([x, [np.nan, np.inf]])
    assert statistics.one_sided_p(padded) == pytest.approx(statistics.one_sided_p(x))


def test_degenerate_samples():
    assert statistics.one_sided_p([1.0]) == 1.0
    assert statistics.one_sided_p([np.nan, np.nan]) == 1.0
    # No spread: decided by the side of the threshold the common value lies on.
    assert statistics.one_sided_p([2.0] * 5, 1.0, "greater") == 0.0
    assert statistics.one_sided_p([2.0] * 5, 1.0, "less") == 1.0
    assert statistics.one_sided_p([1.0] * 5, 1.0, "greater") == 1.0
    assert statistics.equivalence_p([0.0] * 5, 0.1) == 0.0
    assert statistics.equivalence_p([0.0] * 5, 0.0) == 1.0
    with pytest.raises(ValueError):
        statistics.one_sided_p([1.0, 2.0], alternative="two-sided")


def test_equivalence_is_the_larger_one_sided_p():
    rng = np.random.default_rng(3)
    x = rng.normal(0.02, 0.05, 40)
    margin = 0.05
    lower = stats.ttest_1samp(x, -margin, alternative="greater").pvalue
    upper = stats.ttest_1samp(x, margin, alternative="less").pvalue
    assert statistics.equivalence_p(x, margin) == pytest.approx(max(lower, upper), rel=1e-10)
    # TOST at level alpha rejects exactly when the (1 - 2 alpha) interval lies in the margin.
    for shift in np.linspace(-0.06, 0.06, 13):
        y = x + shift
        lo, hi = stats.t.interval(0.90, y.size - 1, loc=np.mean(y), scale=stats.sem(y))
        inside = -margin < lo and hi < margin
        assert (statistics.equivalence_p(y, margin) < 0.05) == inside


def test_holm():
    p = [0.01, 0.04, 0.03, 0.005]
    # Sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1: 0.02, 0.03, 0.06, 0.04 -> monotone.
    np.testing.assert_allclose(statistics.holm(p), [0.03, 0.06, 0.06, 0.02])
    np.testing.assert_allclose(statistics.holm([0.5, 0.9]), [1.0, 1.0])
    np.testing.assert_allclose(statistics.holm([0.02]), [0.02])
    assert statistics.holm([]).size == 0
    with pytest.raises(ValueError):
        statistics.holm([0.1, np.nan])
    # Never below the raw p-values, never above Bonferroni.
    rng = np.random.default_rng(4)
    raw = rng.uniform(0, 0.2, 30)
    adjusted = statistics.holm(raw)
    assert np.all(adjusted >= raw) and np.all(adjusted <= np.minimum(raw * 30, 1.0) + 1e-15)
