"""Summaries of a Monte Carlo run: status counts, metric tables, means with intervals."""

from __future__ import annotations

import numpy as np

from fojax import metrics, observers, statistics
from fojax.study._run import MonteCarloResult


def status_counts(status: np.ndarray) -> dict[str, int]:
    """Number of draws with each status flag set (a draw may have several)."""
    status = np.asarray(status)
    return {name: int(np.sum((status & bit) > 0)) for bit, name in observers.STATUS_NAMES.items()}


def metric_table(result: MonteCarloResult) -> dict[str, tuple[np.ndarray, str]]:
    """Scalar components of every metric: name -> (``(draws,)`` values, unit).

    Diverged draws (:data:`DIVERGED`) are set to NaN, so that no statistic uses them.
    """
    valid = result.valid
    table = {}
    for name, values in result.per_draw.items():
        values = np.asarray(values, dtype=np.float64)
        shape = values.shape[1:]
        names = metrics.component_names(name, shape)
        units = metrics.component_units(name, shape)
        flat = values.reshape(values.shape[0], -1)
        for j, (component, unit) in enumerate(zip(names, units, strict=True)):
            table[component] = (np.where(valid, flat[:, j], np.nan), unit)
    return table


def summarize(result: MonteCarloResult, extra: dict[str, np.ndarray] | None = None) -> dict:
    """JSON-ready summary of one controller's run.

    ``{"draws", "valid", "diverged", "status_counts", "metrics": {name: {"mean",
    "std", "ci95", "n", "n_nonfinite", "unit"}}}``; ``diverged`` counts the draws
    flagged non-finite or beyond the tilt limit, whose metrics are left out. ``inf``
    values (a surface never reached) are left out of the mean and counted in
    ``n_nonfinite``. ``extra`` adds per-draw series (name -> ``(draws,)``).
    """
    table = metric_table(result)
    out_metrics = {}
    for name, (values, unit) in table.items():
        out_metrics[name] = {**statistics.mean_ci(values), "unit": unit}
    for name, values in (extra or {}).items():
        values = np.where(result.valid, np.asarray(values, dtype=np.float64), np.nan)
        out_metrics[name] = {**statistics.mean_ci(values), "unit": "s"}
    valid = int(np.sum(result.valid))
    return {
        "draws": result.draws,
        "valid": valid,
        "diverged": result.draws - valid,
        "status_counts": status_counts(result.status),
        "metrics": out_metrics,
    }
