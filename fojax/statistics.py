"""Summary statistics of Monte Carlo metrics: means with 95 % confidence intervals.

Plain NumPy on the host, after the simulation. Intervals are Student-t intervals
``mean +- t_(0.975, n-1) s / sqrt(n)`` over the finite values; paired differences
(the same draw under two controllers, common random numbers) use the same interval on
the per-draw differences.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["mean_ci", "paired_difference", "student_t_975"]

# t_(0.975, df) for df = 1 ... 10; beyond, the Cornish-Fisher expansion below is
# accurate to better than 1e-4.
_T975 = (12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060, 2.2622, 2.2281)
_Z975 = 1.959963984540054


def student_t_975(df: int) -> float:
    """The 97.5 % quantile of Student's t with ``df`` degrees of freedom (``df >= 1``)."""
    if df < 1:
        raise ValueError(f"df must be >= 1, got {df}")
    if df <= len(_T975):
        return _T975[df - 1]
    z = _Z975
    return (
        z
        + (z**3 + z) / (4 * df)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * df**3)
    )


def mean_ci(values) -> dict:
    """Mean, standard deviation and 95 % interval of the finite entries of ``values``.

    Returns ``{"mean", "std", "ci95": [low, high], "n", "n_nonfinite"}``; with fewer
    than two finite values the interval is ``[mean, mean]`` widened to ``None``.
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


def paired_difference(values, baseline) -> dict:
    """:func:`mean_ci` of ``values - baseline`` over draws where both are finite."""
    values = np.asarray(values, dtype=np.float64)
    baseline = np.asarray(baseline, dtype=np.float64)
    if values.shape != baseline.shape:
        raise ValueError(f"shapes differ: {values.shape} vs {baseline.shape}")
    both = np.isfinite(values) & np.isfinite(baseline)
    difference = np.full(values.shape, np.nan)
    np.subtract(values, baseline, out=difference, where=both)
    return mean_ci(difference)
