"""Yield: the share of Monte Carlo draws that meet every requirement, with its exact
(Clopper-Pearson) 95 % interval, the failures per requirement and the one that fails
most often. Plain NumPy and ``scipy.stats`` on the host."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np
from scipy import stats as _stats

from fojax.requirements._spec import RequirementSet

__all__ = ["YieldResult", "clopper_pearson", "evaluate", "pass_matrix"]


def clopper_pearson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval of a binomial proportion.

    ``lower = Beta(a/2; k, n - k + 1)`` quantile (0 when ``k = 0``), ``upper = Beta(1 - a/2;
    k + 1, n - k)`` quantile (1 when ``k = n``), ``a = 1 - confidence``; at ``k = 0`` the
    upper end is ``1 - (a/2)^(1/n)``, at ``k = n`` the lower end ``(a/2)^(1/n)``.
    """
    k, n = int(successes), int(trials)
    if n < 1 or not 0 <= k <= n:
        raise ValueError(f"need 0 <= successes <= trials and trials >= 1, got {k} of {n}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    alpha = 1.0 - confidence
    lower = 0.0 if k == 0 else float(_stats.beta.ppf(alpha / 2, k, n - k + 1))
    upper = 1.0 if k == n else float(_stats.beta.ppf(1 - alpha / 2, k + 1, n - k))
    return lower, upper


def pass_matrix(requirements: RequirementSet, metrics: Mapping[str, np.ndarray]) -> np.ndarray:
    """``(requirements, draws)`` bool: draw ``i`` meets requirement ``j``.

    ``metrics``: metric name -> ``(draws,)`` per-draw values in the metric's canonical
    unit (:func:`fojax.requirements.draw_metrics`). A non-finite value (a diverged draw)
    meets no requirement.
    """
    missing = [m for m in requirements.metrics if m not in metrics]
    if missing:
        raise KeyError(
            f"per-draw metrics missing for {', '.join(missing)} (have {', '.join(metrics)})"
        )
    rows = []
    for r in requirements:
        values = np.asarray(metrics[r.metric], np.float64)
        if values.ndim != 1:
            raise ValueError(f"metric {r.metric!r}: expected (draws,), got shape {values.shape}")
        bound = r.canonical_value
        with np.errstate(invalid="ignore"):
            ok = values <= bound if r.bound == "upper" else values >= bound
        rows.append(ok & np.isfinite(values))
    return np.stack(rows)


@dataclasses.dataclass(frozen=True)
class YieldResult:
    """Yield of one set of draws.

    names: the requirements, in the set's order. draws: number of draws. passed:
    draws meeting every requirement. yield_: ``passed / draws``. interval: the
    Clopper-Pearson interval at ``confidence``. failures: draws failing each
    requirement (same order as ``names``). most_failed: the requirement failed by the
    most draws (the first on a tie; ``None`` when no draw fails any). matrix: the
    ``(requirements, draws)`` pass matrix.
    """

    names: tuple[str, ...]
    draws: int
    passed: int
    interval: tuple[float, float]
    failures: tuple[int, ...]
    confidence: float
    matrix: np.ndarray = dataclasses.field(repr=False, compare=False)

    @property
    def yield_(self) -> float:
        return self.passed / self.draws

    @property
    def most_failed(self) -> str | None:
        if not any(self.failures):
            return None
        return self.names[int(np.argmax(self.failures))]

    def to_dict(self) -> dict:
        """JSON-ready summary (for summary.json)."""
        return {
            "draws": self.draws,
            "passed": self.passed,
            "yield": self.yield_,
            "interval": list(self.interval),
            "confidence": self.confidence,
            "interval_method": "clopper-pearson",
            "failures": dict(zip(self.names, self.failures, strict=True)),
            "most_failed": self.most_failed,
        }

    def describe(self) -> str:
        low, high = self.interval
        text = (
            f"yield {self.yield_:.1%} ({self.passed}/{self.draws}, "
            f"{self.confidence:.0%} interval {low:.1%} - {high:.1%})"
        )
        if self.most_failed is not None:
            worst = max(self.failures)
            text += f"; most failed: {self.most_failed} ({worst} draw{'' if worst == 1 else 's'})"
        return text


def evaluate(
    requirements: RequirementSet,
    metrics: Mapping[str, np.ndarray],
    confidence: float = 0.95,
    valid: np.ndarray | None = None,
) -> YieldResult:
    """The yield of per-draw ``metrics`` (name -> ``(draws,)``, canonical units) against
    ``requirements``. ``valid``: optional ``(draws,)`` bool; a draw that is not valid (it
    diverged) fails every requirement."""
    matrix = pass_matrix(requirements, metrics)
    if valid is not None:
        matrix = matrix & np.asarray(valid, bool)[None, :]
    draws = int(matrix.shape[1])
    if draws < 1:
        raise ValueError("no draws to evaluate")
    passed = int(np.sum(np.all(matrix, axis=0)))
    failures = tuple(int(x) for x in np.sum(~matrix, axis=1))
    if not math.isfinite(confidence):
        raise ValueError(f"confidence must be finite, got {confidence!r}")
    return YieldResult(
        requirements.names,
        draws,
        passed,
        clopper_pearson(passed, draws, confidence),
        failures,
        confidence,
        matrix,
    )
