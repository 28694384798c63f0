"""Gradient strategies: any optax transformation, and limited-memory BFGS.

:class:`Optax` takes one step of an ``optax.GradientTransformation`` per request, on a
fresh tuning sample every step (``sample="fresh"``) or on the fixed sample, with the
tuning law's width annealed geometrically from ``anneal[0]`` to ``anneal[1]`` over
``steps``. :func:`adam` is fojax's setting: ``clip_by_global_norm`` then Adam with a
cosine-decayed step.

:class:`LBFGS` is quasi-Newton on the fixed sample (a deterministic sample-average
objective) at one width: every request evaluates the loss and its gradient at one
trial point, accepted on Armijo's sufficient decrease ``f_trial <= f + c1 alpha g.d``
(finite value and gradient), after which the next direction comes from the two-loop
recursion over the last ``memory`` pairs ``(s, y)`` (initial Hessian ``s.y / y.y``);
a rejected trial halves the step. Steps are capped at ``max_step`` in every
coordinate (a factor ``e^max_step`` on a log-mapped gain), so a curvature estimate
from a few pairs cannot throw the gains far outside the region already seen; the first
step, and any after a direction that does not descend or ``max_backtracks`` rejections
in a row, is steepest descent (the memory reset).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fojax.optimize import checks
from fojax.optimize.requests import Request

__all__ = ["LBFGS", "Optax", "adam"]


def _scalar(value, dtype=np.float64) -> np.ndarray:
    return np.asarray(value, dtype)


@dataclasses.dataclass(frozen=True)
class Optax:
    """One step of ``transformation`` per request (module docstring). description:
    JSON-ready settings of the transformation (its fingerprint)."""

    transformation: Any
    steps: int
    description: tuple = ()
    sample: str = "fresh"
    anneal: tuple[float, float] = (1.0, 1.0)
    name: str = "optax"

    def __post_init__(self) -> None:
        checks.choice("sample", self.sample, ("fresh", "fixed"))
        for width in self.anneal:
            checks.number("an anneal width", width)

    def width(self, step: int) -> float:
        first, last = self.anneal
        fraction = min(step, self.steps - 1) / max(self.steps - 1, 1)
        return float(first * (last / first) ** fraction)

    def init(self, x0) -> dict:
        x = jnp.asarray(x0, jnp.result_type(float))
        opt = jax.tree.map(np.asarray, self.transformation.init(x))
        return {"x": np.asarray(x), "opt": opt, "step": _scalar(0, np.int64)}

    def ask(self, state) -> Request:
        step = int(state["step"])
        sample = step if self.sample == "fresh" else 0
        return Request(state["x"][None].astype(np.float64), True, sample, self.width(step))

    def tell(self, state, request, evaluation) -> dict:
        gradient = jnp.asarray(evaluation.gradient, np.asarray(state["x"]).dtype)
        x, opt = _compiled(self.transformation)(gradient, state["opt"], state["x"])
        return {"x": np.asarray(x), "opt": jax.tree.map(np.asarray, opt), "step": state["step"] + 1}

    def answer(self, state) -> np.ndarray:
        return np.asarray(state["x"], np.float64)

    def restart(self, state) -> dict:
        """A fresh optimiser (and schedule) at the current point."""
        return self.init(state["x"])

    def settings(self) -> dict:
        return {"name": self.name, "steps": self.steps, "sample": self.sample,
                "anneal": list(self.anneal), **dict(self.description)}  # fmt: skip

    def row(self, state) -> dict:
        """The step length of the last step: a cosine decay's (:func:`adam`), if any."""
        description = dict(self.description)
        if "learning_rate" not in description:
            return {"step_length": None}
        rate, final = description["learning_rate"], description.get("final_learning_rate", 1.0)
        last = max(self.steps - 1, 1)
        fraction = min(max(int(state["step"]) - 1, 0), last) / last
        return {
            "step_length": rate * ((1 - final) * 0.5 * (1 + math.cos(math.pi * fraction)) + final)
        }

    def needs(self) -> tuple:
        return (("gradient", self.anneal[1]),)


@functools.lru_cache(maxsize=8)
def _compiled(transformation):
    """One optax step ``(gradient, opt, x) -> (x, opt)``, compiled once per transformation."""

    def step(gradient, opt, x):
        updates, opt = transformation.update(gradient, opt, x)
        return optax.apply_updates(x, updates), opt

    return jax.jit(step)


def adam(
    steps: int,
    learning_rate: float = 0.05,
    final_learning_rate: float = 0.1,
    clip_norm: float = 1.0,
    anneal: tuple[float, float] = (4.0, 1.0),
    sample: str = "fresh",
) -> Optax:
    """``clip_by_global_norm(clip_norm)`` then Adam with a cosine-decayed step from
    ``learning_rate`` to ``final_learning_rate`` times it over ``steps``."""
    checks.number("learning_rate", learning_rate)
    checks.number("clip_norm", clip_norm)
    checks.number("final_learning_rate", final_learning_rate, allow_low=True, high=1)
    checks.integer("steps", steps)
    schedule = optax.cosine_decay_schedule(
        learning_rate, max(steps - 1, 1), alpha=final_learning_rate
    )
    transformation = optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(schedule))
    description = (("learning_rate", learning_rate), ("final_learning_rate", final_learning_rate),
                   ("clip_norm", clip_norm))  # fmt: skip
    return Optax(transformation, steps, description, sample, tuple(anneal), "adam")


@dataclasses.dataclass(frozen=True)
class LBFGS:
    """memory: pairs kept. max_step: largest change of any coordinate per step. width:
    the tuning law's width scale. c1: Armijo's constant. shrink: step factor after a
    rejected trial. max_backtracks: rejections in a row before the memory is reset."""

    memory: int = 10
    max_step: float = 1.0
    width: float = 1.0
    c1: float = 1e-4
    shrink: float = 0.5
    max_backtracks: int = 8
    name: str = "lbfgs"

    def __post_init__(self) -> None:
        checks.integer("memory", self.memory)
        checks.number("max_step", self.max_step)
        if self.width is not None:  # None: the evaluation law
            checks.number("width", self.width)

    def init(self, x0) -> dict:
        x0 = np.asarray(x0, np.float64)
        d, m = x0.size, self.memory
        zero, none, no = _scalar(0.0), _scalar(0, np.int64), _scalar(False, bool)
        return dict(
            trial=x0.copy(), x=x0.copy(), f=zero, g=np.zeros(d), s=np.zeros((m, d)),
            y=np.zeros((m, d)), pairs=none, direction=np.zeros(d), alpha=zero, backtracks=none,
            accepted=none, started=no, moved=no,
        )  # fmt: skip

    def ask(self, state) -> Request:
        return Request(state["trial"][None], True, 0, self.width)

    def answer(self, state) -> np.ndarray:
        return state["x"].copy()

    def restart(self, state) -> dict:
        return {**self.init(state["x"]), "accepted": state["accepted"]}

    def settings(self) -> dict:
        return {"name": self.name, **dataclasses.asdict(self)}

    def row(self, state) -> dict:
        return {"step_length": float(state["alpha"]), "accepted": int(state["moved"])}

    def needs(self) -> tuple:
        return (("gradient", self.width),)

    def _direction(self, state) -> np.ndarray:
        g, k = state["g"], int(state["pairs"])
        s, y = list(state["s"][:k]), list(state["y"][:k])
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
            q = q + (a - rho * float(np.dot(yi, q))) * si
        return -q

    def _propose(self, state: dict) -> dict:
        """The direction and the first trial from the accepted point."""
        g = state["g"]
        direction = self._direction(state)
        if not np.all(np.isfinite(direction)) or float(np.dot(direction, g)) >= 0:
            state["pairs"] = _scalar(0, np.int64)
            direction = -g
        largest = float(np.max(np.abs(direction))) if direction.size else 0.0
        if int(state["pairs"]):
            alpha = 1.0 if largest <= self.max_step else self.max_step / largest
        else:  # steepest descent: a step of max_step in the largest coordinate
            alpha = self.max_step / largest if largest > 0 else 0.0
        state.update(direction=direction, alpha=_scalar(alpha), backtracks=_scalar(0, np.int64))
        state["trial"] = state["x"] + alpha * direction
        return state

    def tell(self, state, request, evaluation) -> dict:
        f, g = float(evaluation.values[0]), np.asarray(evaluation.gradient, np.float64)
        finite = math.isfinite(f) and bool(np.all(np.isfinite(g)))
        state = dict(state)
        if not bool(state["started"]):
            if not finite:
                raise FloatingPointError("the loss or its gradient is not finite at the start")
            state.update(x=state["trial"], f=_scalar(f), g=g, started=_scalar(True, bool))
            state.update(accepted=state["accepted"] + 1, moved=_scalar(True, bool))
            return self._propose(state)
        alpha, direction = float(state["alpha"]), state["direction"]
        slope = float(np.dot(state["g"], direction))
        if finite and f <= float(state["f"]) + self.c1 * alpha * slope:
            s, y = state["trial"] - state["x"], g - state["g"]
            if float(np.dot(s, y)) > 1e-10 * float(np.linalg.norm(s)) * float(np.linalg.norm(y)):
                k = int(state["pairs"])
                pairs_s, pairs_y = state["s"].copy(), state["y"].copy()
                if k == self.memory:
                    pairs_s, pairs_y, k = np.roll(pairs_s, -1, 0), np.roll(pairs_y, -1, 0), k - 1
                pairs_s[k], pairs_y[k] = s, y
                state.update(s=pairs_s, y=pairs_y, pairs=_scalar(k + 1, np.int64))
            state.update(x=state["trial"], f=_scalar(f), g=g, moved=_scalar(True, bool))
            state["accepted"] = state["accepted"] + 1
            return self._propose(state)
        backtracks = int(state["backtracks"]) + 1
        state["moved"] = _scalar(False, bool)
        if backtracks > self.max_backtracks:
            state["pairs"] = _scalar(0, np.int64)
            state = self._propose(state)
            state["alpha"] = _scalar(float(state["alpha"]) * self.shrink**backtracks)
        else:
            state.update(
                alpha=_scalar(alpha * self.shrink), backtracks=_scalar(backtracks, np.int64)
            )
        state["trial"] = state["x"] + float(state["alpha"]) * state["direction"]
        return state
