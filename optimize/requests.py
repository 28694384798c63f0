"""What a strategy asks and what it is told: :class:`Request` (points, gradient or
not, which sample, which law, which loss), :class:`Evaluation` (the loss per point, the
gradient, the per-draw :class:`Outputs`, what it cost)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from fojax.optimize import cost as cost_lib

__all__ = ["Evaluation", "Outputs", "Request"]


class Outputs(NamedTuple):
    """Per-draw outputs, on the host (float64), leading axes ``(..., n)``.

    values: ``(..., n, 1 + R)``: the target ``f`` and the ``R`` violations (non-finite
    where a draw diverged). terms: ``(..., n, 4)`` ``(P, A, E, C)``. status:
    ``(..., n)`` int32 flags. metrics: requirement metric name -> ``(..., n)`` (with a
    requirement set), else ``None``.
    """

    values: np.ndarray
    terms: np.ndarray
    status: np.ndarray
    metrics: dict | None = None

    @property
    def valid(self) -> np.ndarray:
        """``(..., n)`` bool: finite outputs and no divergence flag."""
        finite = np.all(np.isfinite(self.values), -1)
        return finite & ((self.status & cost_lib.DIVERGED) == 0)


class Request(NamedTuple):
    """What a strategy asks to have evaluated.

    points: ``(P, d)`` float64 parameter vectors (:meth:`Objective.vector` order).
    gradient: the loss's gradient at the single point (``P = 1``). sample: the tuning
    sample's index (0: the fixed sample). width: the tuning law's width scale; ``None``:
    the evaluation law. loss: what turns outputs into numbers (``None``: the objective's
    :class:`MeanLoss`). draws: the sample's size (``None``: the spec's).
    """

    points: np.ndarray
    gradient: bool = False
    sample: int = 0
    width: float | None = None
    loss: Any = None
    draws: int | None = None
    dt: float | None = None


class Evaluation(NamedTuple):
    """values: ``(P,)`` the loss per point. gradient: ``(d,)`` or ``None``. outputs:
    :class:`Outputs` ``(P, n, ...)``. bad_gradients: draws (not diverged) whose gradient
    was not finite, left out. draw_steps: draws x steps simulated. work: what it cost, in
    lane-steps of whole calls (:meth:`Objective.work`; ``None``: ``draw_steps``)."""

    values: np.ndarray
    gradient: np.ndarray | None
    outputs: Outputs
    bad_gradients: int
    draw_steps: int
    work: int | None = None
