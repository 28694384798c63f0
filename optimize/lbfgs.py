"""Limited-memory BFGS driven one function-and-gradient evaluation at a time.

The gradient tuner's quasi-Newton method (:mod:`fojax.optimize.tuner`, ``method="lbfgs"``)
on a fixed sample of draws (a deterministic sample-average objective, as Nelder-Mead
gets): every tuner step evaluates the objective and its gradient at one trial point
and hands them to :func:`tell`, which either accepts the trial (Armijo's sufficient
decrease ``f_trial <= f + c1 alpha g.d``, finite value and gradient) and computes the
next direction by the two-loop recursion over the last ``memory`` pairs ``(s, y)``
(initial Hessian ``s.y / y.y``), or halves the step and tries again. Steps are capped
at ``max_step`` in every coordinate (a factor ``e^max_step`` on a log-mapped gain), so
a curvature estimate from a few pairs cannot throw the gains far outside the region
already seen; a direction that is not a descent direction, or ``max_backtracks``
failed trials in a row, reset the memory to steepest descent.

The whole state is a dict of float64 NumPy arrays and Python numbers
(:func:`state_to_json` / :func:`state_from_json` round-trip it exactly), so a
checkpointed run resumes bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

__all__ = ["LBFGS", "state_from_json", "state_to_json"]


@dataclasses.dataclass(frozen=True)
class LBFGS:
    """memory: pairs kept. max_step: largest change of any coordinate per step.
    c1: Armijo constant. shrink: step factor after a rejected trial. max_backtracks:
    rejected trials in a row before the memory is reset."""

    memory: int = 10
    max_step: float = 1.0
    c1: float = 1e-4
    shrink: float = 0.5
    max_backtracks: int = 8

    def start(self, x0) -> dict[str, Any]:
        """The state before the first evaluation (its trial point is ``x0``)."""
        x0 = np.asarray(x0, np.float64)
        return {
            "trial": x0.copy(),
            "x": None,
            "f": None,
            "g": None,
            "s": [],
            "y": [],
            "direction": None,
            "alpha": 0.0,
            "backtracks": 0,
            "accepted": 0,
        }

    def _direction(self, g: np.ndarray, s: list, y: list) -> np.ndarray:
        q = g.copy()
        rhos = [1.0 / float(np.dot(yi, si)) for si, yi in zip(s, y, strict=True)]
        alphas = []
        for si, yi, rho in zip(reversed(s), reversed(y), reversed(rhos), strict=True):
            a = rho * float(np.dot(si, q))
            alphas.append(a)
            q = q - a * yi
        if s:
            q = q * (float(np.dot(s[-1], y[-1])) / float(np.dot(y[-1], y[-1])))
        for si, yi, rho, a in zip(s, y, rhos, reversed(alphas), strict=True):
            b = rho * float(np.dot(yi, q))
            q = q + (a - b) * si
        return -q

    def _propose(self, state: dict) -> dict:
        """Set the direction and the first trial from the accepted point."""
        g = state["g"]
        direction = self._direction(g, state["s"], state["y"])
        if not np.all(np.isfinite(direction)) or float(np.dot(direction, g)) >= 0:
            state["s"], state["y"] = [], []
            direction = -g
        largest = float(np.max(np.abs(direction))) if direction.size else 0.0
        if state["s"]:
            alpha = 1.0 if largest <= self.max_step else self.max_step / largest
        else:  # steepest descent: a step of max_step in the largest coordinate
            alpha = self.max_step / largest if largest > 0 else 0.0
        state["direction"] = direction
        state["alpha"] = alpha
        state["backtracks"] = 0
        state["trial"] = state["x"] + alpha * direction
        return state

    def tell(self, state: dict, f: float, g) -> tuple[dict, bool]:
        """Consume the evaluation ``(f, g)`` at ``state["trial"]``; returns the new
        state (its ``trial`` is the next point to evaluate) and whether the trial was
        accepted."""
        g = np.asarray(g, np.float64)
        f = float(f)
        finite = math.isfinite(f) and bool(np.all(np.isfinite(g)))
        state = dict(state)
        if state["x"] is None:
            if not finite:
                raise FloatingPointError("the objective or its gradient is not finite at the start")
            state.update(x=state["trial"], f=f, g=g, accepted=1)
            return self._propose(state), True
        alpha, direction = state["alpha"], state["direction"]
        slope = float(np.dot(state["g"], direction))
        if finite and f <= state["f"] + self.c1 * alpha * slope:
            s = state["trial"] - state["x"]
            y = g - state["g"]
            sy = float(np.dot(s, y))
            pairs_s, pairs_y = list(state["s"]), list(state["y"])
            if sy > 1e-10 * float(np.linalg.norm(s)) * float(np.linalg.norm(y)):
                pairs_s, pairs_y = (pairs_s + [s])[-self.memory :], (pairs_y + [y])[-self.memory :]
            state.update(
                x=state["trial"], f=f, g=g, s=pairs_s, y=pairs_y, accepted=state["accepted"] + 1
            )
            return self._propose(state), True
        backtracks = state["backtracks"] + 1
        if backtracks > self.max_backtracks:
            state["s"], state["y"] = [], []
            state = self._propose(state)
            state["alpha"] *= self.shrink**backtracks
            state["trial"] = state["x"] + state["alpha"] * state["direction"]
            return state, False
        state["alpha"] = alpha * self.shrink
        state["backtracks"] = backtracks
        state["trial"] = state["x"] + state["alpha"] * direction
        return state, False


def state_to_json(state: dict) -> dict:
    """The state as JSON-ready lists (float64 values round-trip exactly)."""
    out = {}
    for key, value in state.items():
        if isinstance(value, np.ndarray):
            out[key] = {"array": value.tolist()}
        elif isinstance(value, list):
            out[key] = {"arrays": [v.tolist() for v in value]}
        else:
            out[key] = value
    return out


def state_from_json(document: dict) -> dict:
    """The inverse of :func:`state_to_json`."""
    out = {}
    for key, value in document.items():
        if isinstance(value, dict) and "array" in value:
            out[key] = np.asarray(value["array"], np.float64)
        elif isinstance(value, dict) and "arrays" in value:
            out[key] = [np.asarray(v, np.float64) for v in value["arrays"]]
        else:
            out[key] = value
    return out
