"""Losses: how a request's per-draw outputs become one number per point, and the
cotangents of that number by each draw's outputs (what the per-draw reverse pass of
:class:`fojax.optimize.Objective` weights): :class:`MeanLoss` (the weighted sum) and
:class:`AlmLoss` (the requirements' augmented Lagrangian)."""

from __future__ import annotations

import dataclasses

import numpy as np

from fojax.optimize import cost as cost_lib
from fojax.optimize.requests import Outputs

__all__ = ["FORMULATIONS", "AlmLoss", "MeanLoss"]

FORMULATIONS = ("mean", "chance")


@dataclasses.dataclass(frozen=True)
class MeanLoss:
    """The weighted-sum objective: mean (or CVaR, :class:`~fojax.optimize.cost.CostConfig`)
    of ``J`` over the draws, a diverged draw costing ``divergence_cost``; its gradient is
    the same weights on the per-draw gradients of ``J`` (no forward pass first)."""

    config: cost_lib.CostConfig

    def weights(self, outputs: Outputs) -> tuple[np.ndarray, np.ndarray]:
        """``(loss (...,), weights (..., n))`` of outputs ``(..., n)``."""
        cost = np.where(outputs.valid, outputs.values[..., 0], self.config.divergence_cost)
        n = cost.shape[-1]
        if self.config.objective == "mean":
            weights = np.full(cost.shape, 1.0 / n)
        else:  # the k largest, ties broken by index
            k = self.config.tail_count(n)
            order = np.argsort(-cost, axis=-1, kind="stable")[..., :k]
            weights = np.zeros(cost.shape)
            np.put_along_axis(weights, order, 1.0 / k, axis=-1)
        return np.sum(weights * cost, -1), weights

    def values(self, outputs: Outputs) -> np.ndarray:
        return self.weights(outputs)[0]

    def cotangents(self, outputs: Outputs) -> np.ndarray:
        """``(n, 1)``: every draw's ``J`` with weight 1 (the weights come after)."""
        return np.ones(outputs.values.shape[:-1] + (1,))


@dataclasses.dataclass(frozen=True)
class AlmLoss:
    """The augmented Lagrangian (:class:`fojax.optimize.strategies.AugmentedLagrangian`,
    whose docstring has the formulation) at multipliers ``lam`` ``(R,)``, penalty ``rho``
    and scale ``f_0``, as a loss of the objective's outputs."""

    lam: np.ndarray
    rho: float
    scale: float
    formulation: str = "mean"
    margin: float = 0.05
    temperature: float = 0.1
    allowed_share: float = 0.0

    def parts(self, outputs: Outputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(F (...,), c (..., R), per-draw constraint terms (..., n, R))``."""
        valid = outputs.valid
        f = np.where(valid, outputs.values[..., 0], 0.0)
        F = np.sum(f, -1) / np.maximum(np.sum(valid, -1), 1) / self.scale
        shifted = np.where(valid[..., None], outputs.values[..., 1:], 0.0) + self.margin
        if self.formulation == "mean":
            per_draw = np.maximum(shifted, 0.0)
        else:
            per_draw = 1.0 / (1.0 + np.exp(-shifted / self.temperature))
        per_draw = np.where(valid[..., None], per_draw, 1.0)
        share = self.allowed_share if self.formulation == "chance" else 0.0
        return F, np.mean(per_draw, -2) - share, per_draw

    def values(self, outputs: Outputs) -> np.ndarray:
        """``L`` per point; a point with diverged draws ranks after every point of the
        request without one, by its count of them (a diverged draw's violation is
        capped in ``c``, where a real violation is not: ranked by ``L`` alone, a
        candidate that diverges everywhere would beat one that violates by much)."""
        F, c, _ = self.parts(outputs)
        shifted = np.maximum(0.0, self.lam + self.rho * c)
        loss = F + np.sum(shifted**2 - self.lam**2, -1) / (2.0 * self.rho)
        diverged = np.sum(~np.asarray(outputs.valid), -1)
        if not np.any(diverged):
            return loss
        finite = loss[(diverged == 0) & np.isfinite(loss)]
        worst = np.max(finite) if finite.size else np.max(loss[np.isfinite(loss)], initial=0.0)
        return np.where(diverged > 0, worst + diverged * (1.0 + abs(worst)), loss)

    def cotangents(self, outputs: Outputs) -> np.ndarray:
        """``(n, 1 + R)``: the derivatives of ``L`` by each draw's outputs (0 for a draw
        that is not valid)."""
        valid = outputs.valid
        n = valid.shape[-1]
        _, c, per_draw = self.parts(outputs)
        dL_dc = np.maximum(0.0, self.lam + self.rho * c)
        shifted = outputs.values[..., 1:] + self.margin
        if self.formulation == "mean":
            slope = (shifted > 0).astype(np.float64)
        else:
            slope = per_draw * (1 - per_draw) / self.temperature
        cot = np.empty(outputs.values.shape)
        cot[..., 0] = valid / max(int(np.sum(valid)), 1) / self.scale
        cot[..., 1:] = valid[..., None] * slope * dL_dc / n
        return np.where(np.isfinite(cot), cot, 0.0)
