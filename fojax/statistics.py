"""Summary statistics and tests of Monte Carlo metrics.

Plain NumPy and ``scipy.stats`` on the host, after the simulation.

* :func:`mean_ci`: mean and 95 % Student-t interval ``mean +- t_(0.975, n-1) s/sqrt(n)``
  over the finite values; :func:`paired_difference`: the same on per-draw differences
  (the same draw under two controllers, common random numbers).
* :func:`one_sided_p`: p-value of the one-sample t-test of ``mean > threshold`` (or
  ``< threshold``) against the null hypothesis that it is not.
* :func:`equivalence_p`: two one-sided tests (TOST) of ``-margin < mean < margin``.
* :func:`holm`: Holm-Bonferroni adjustment of a family of p-values.

Quantiles and tail probabilities come from ``scipy.stats.t`` (exact to double
precision). Only finite values enter; a test with fewer than two finite values cannot
reject (p = 1). A sample without spread (every value equal) gives p = 0 when its value
lies strictly on the tested side and p = 1 otherwise.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats as _stats

__all__ = [
    "equivalence_p",
    "holm",
    "mean_ci",
    "one_sided_p",
    "paired_difference",
    "student_t_975",
    "t_quantile",
]


def t_quantile(probability: float, df: int) -> float:
    """The ``probability`` quantile of Student's t with ``df`` (>= 1) degrees of freedom."""
    if df < 1:
        raise ValueError(f"df must be >= 1, got {df}")
    return float(_stats.t.ppf(probability, df))


def student_t_975(df: int) -> float:
    """The 97.5 % quantile of Student's t with ``df`` degrees of freedom (``df >= 1``)."""
    return t_quantile(0.975, df)


def _finite(values) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64).ravel()
    return values[np.isfinite(values)]


def mean_ci(values) -> dict:
    """Mean, standard deviation and 95 % interval of the finite entries of ``values``.

    Returns ``{"mean", "std", "ci95": [low, high], "n", "n_nonfinite"}``; with fewer
    than two finite values ``std`` and ``ci95`` are ``None`` (and ``mean`` too with none).
    """
    values = np.asarray(values, dtype=np.float64).ravel()
    finite = values[np.isfinite(values)]
    n = int(finite.size)
    out = {"n": n, "n_nonfinite": int(values.size - n)}
    if n == 0:
        return {**out, "mean": None, "std": None, "ci95": None}
    mean = float(np.mean(finite))
    if n < 2:
        return {**out, "mean": mean, "std": None, "ci95": None}
    std = float(np.std(finite, ddof=1))
    half = student_t_975(n - 1) * std / math.sqrt(n)
    return {**out, "mean": mean, "std": std, "ci95": [mean - half, mean + half]}


def _paired(values, baseline) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    baseline = np.asarray(baseline, dtype=np.float64)
    if values.shape != baseline.shape:
        raise ValueError(f"shapes differ: {values.shape} vs {baseline.shape}")
    both = np.isfinite(values) & np.isfinite(baseline)
    difference = np.full(values.shape, np.nan)
    np.subtract(values, baseline, out=difference, where=both)
    return difference


def paired_difference(values, baseline) -> dict:
    """:func:`mean_ci` of ``values - baseline`` over draws where both are finite."""
    return mean_ci(_paired(values, baseline))


def one_sided_p(values, threshold: float = 0.0, alternative: str = "greater") -> float:
    """p-value of the one-sample t-test of ``mean > threshold`` (``alternative="greater"``)
    or ``mean < threshold`` (``"less"``), over the finite entries of ``values``.

    The null hypothesis is the complement (``mean <= threshold``, resp. ``>=``); a small
    p-value supports the alternative. Fewer than two finite values: 1.
    """
    if alternative not in ("greater", "less"):
        raise ValueError(f"alternative must be 'greater' or 'less', got {alternative!r}")
    finite = _finite(values)
    n = finite.size
    if n < 2:
        return 1.0
    mean = float(np.mean(finite))
    std = float(np.std(finite, ddof=1))
    sign = 1.0 if alternative == "greater" else -1.0
    if std == 0.0:
        return 0.0 if sign * (mean - threshold) > 0 else 1.0
    t = sign * (mean - threshold) / (std / math.sqrt(n))
    return float(_stats.t.sf(t, n - 1))


def equivalence_p(values, margin: float) -> float:
    """Two one-sided tests (TOST) of ``-margin < mean < margin``: the larger of the two
    one-sided p-values. The null hypothesis is ``|mean| >= margin``; ``margin`` >= 0
    (0 cannot be rejected)."""
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0, got {margin!r}")
    if margin == 0:
        return 1.0
    return max(
        one_sided_p(values, -margin, "greater"),
        one_sided_p(values, margin, "less"),
    )


def holm(p_values) -> np.ndarray:
    """Holm-Bonferroni adjusted p-values of a family, in the input order.

    The ``k``-th smallest of ``m`` p-values is multiplied by ``m - k + 1``, made
    non-decreasing in that order and capped at 1; rejecting each hypothesis whose
    adjusted p-value is below ``alpha`` keeps the family-wise error rate at ``alpha``
    under any dependence between the tests.
    """
    p = np.asarray(p_values, dtype=np.float64).ravel()
    if np.any(np.isnan(p)) or np.any((p < 0) | (p > 1)):
        raise ValueError("p-values must lie in [0, 1]")
    m = p.size
    if m == 0:
        return p.copy()
    order = np.argsort(p, kind="stable")
    scaled = p[order] * (m - np.arange(m))
    adjusted = np.minimum(np.maximum.accumulate(scaled), 1.0)
    out = np.empty(m)
    out[order] = adjusted
    return out
