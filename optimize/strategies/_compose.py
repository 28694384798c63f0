"""Strategies built from strategies: a chain, and the augmented Lagrangian.

:class:`Chain` runs ``first`` for ``switch`` requests, then starts ``second`` from
``first``'s answer: a population search that hands its best to a gradient polish.

:class:`AugmentedLagrangian` tunes to requirements with any inner strategy. Draw ``i``
of a sample of ``n`` has a target ``f_i`` and normalised violations ``v_ij`` (``<= 0``
where it meets requirement ``j``). With ``F = mean_i f_i / f_0`` (over the valid draws;
``f_0`` the start's mean) and one constraint ``c_j <= 0`` per requirement, the loss the
inner strategy minimises is the augmented Lagrangian of the inequality constraints
(Nocedal & Wright, Sec. 17.4, the Rockafellar form)::

    L(x; lam, rho) = F + sum_j (max(0, lam_j + rho c_j)^2 - lam_j^2) / (2 rho)

for ``inner_steps`` requests, then (after measuring ``c`` at the inner answer on the
fixed sample, evaluation law) ``lam_j <- max(0, lam_j + rho c_j)`` and ``rho <- growth
rho`` (capped at ``penalty_max``) when the largest violation did not fall below a
quarter of the previous one; the inner strategy is restarted (:meth:`restart`) on the
new loss. Two choices of ``c_j``:

* ``formulation="mean"``: ``c_j = mean_i max(v_ij + m, 0)`` (``m`` the margin): zero
  exactly when every draw meets requirement ``j`` with margin ``m`` (an exact penalty:
  a finite multiplier makes the minimiser feasible; a squared hinge needs ``lam -> inf``
  and was measured to stop short of the constraint);
* ``formulation="chance"``: ``c_j = mean_i sigmoid((v_ij + m) / T) - alpha``, a smooth
  share of draws violating ``j``, at most ``alpha``.

A diverged draw (non-finite outputs, status ``nonfinite`` or ``tilt_limit``) counts as a
full violation (its ``c_j`` term is 1) and adds nothing to ``F`` or the gradient.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fojax.optimize import checks
from fojax.optimize.losses import FORMULATIONS, AlmLoss
from fojax.optimize.requests import Request

__all__ = ["AugmentedLagrangian", "Chain"]


@dataclasses.dataclass(frozen=True)
class Chain:
    """``first`` for ``switch`` requests, then ``second`` from ``first``'s answer."""

    first: Any
    second: Any
    switch: int
    name: str = "chain"

    def __post_init__(self) -> None:
        checks.integer("switch", self.switch)

    def _active(self, state, key: str = "phase"):
        """``(name, strategy, its state)`` of the phase (``key="told"``: of the last
        request)."""
        name = ("first", "second")[int(state[key])]
        return name, getattr(self, name), state[name]

    def init(self, x0) -> dict:
        zero = np.asarray(0)
        return dict(phase=zero, count=zero, told=zero, first=self.first.init(x0),
                    second=self.second.init(x0))  # fmt: skip

    def ask(self, state) -> Request:
        _, strategy, inner = self._active(state)
        return strategy.ask(inner)

    def tell(self, state, request, evaluation) -> dict:
        state = dict(state)
        state["told"] = np.asarray(state["phase"])
        if int(state["phase"]) == 1:
            state["second"] = self.second.tell(state["second"], request, evaluation)
            return state
        state["first"] = self.first.tell(state["first"], request, evaluation)
        state["count"] = state["count"] + 1
        if int(state["count"]) >= self.switch:
            state["phase"] = np.asarray(1)
            state["second"] = self.second.init(self.first.answer(state["first"]))
        return state

    def answer(self, state) -> np.ndarray:
        _, strategy, inner = self._active(state)
        return strategy.answer(inner)

    def restart(self, state) -> dict:
        name, strategy, inner = self._active(state)
        return {**state, name: strategy.restart(inner)}

    def settings(self) -> dict:
        first, second = self.first.settings(), self.second.settings()
        return {"name": self.name, "switch": self.switch, "first": first, "second": second}

    def row(self, state) -> dict:
        """The row of the strategy that took the last request."""
        _, strategy, inner = self._active(state, "told")
        return {"phase": strategy.name, **strategy.row(inner)}

    def needs(self) -> tuple:
        return tuple(dict.fromkeys(self.first.needs() + self.second.needs()))


_SCALE, _INNER, _MEASURE = range(3)


@dataclasses.dataclass(frozen=True)
class AugmentedLagrangian:
    """Requirements as constraints around ``inner`` (module docstring). requirements:
    ``R``. outer_steps: multiplier updates. inner_steps: inner requests per outer step.
    penalty, penalty_growth, penalty_max: ``rho`` at the start, its growth, its cap.
    formulation, margin, temperature, allowed_share: ``c_j`` (:class:`AlmLoss`)."""

    inner: Any
    requirements: int
    outer_steps: int = 6
    inner_steps: int = 10
    penalty: float = 10.0
    penalty_growth: float = 2.0
    penalty_max: float = 1e3
    formulation: str = "mean"
    margin: float = 0.05
    temperature: float = 0.1
    allowed_share: float = 0.0
    name: str = "augmented-lagrangian"

    def __post_init__(self) -> None:
        checks.choice("formulation", self.formulation, FORMULATIONS)
        for label in ("outer_steps", "inner_steps", "requirements"):
            checks.integer(label, getattr(self, label))
        for label in ("penalty", "penalty_max", "temperature"):
            checks.number(label, getattr(self, label))
        checks.number("penalty_growth", self.penalty_growth, 1, allow_low=True)
        checks.number("margin", self.margin, allow_low=True)
        if not 0 <= self.allowed_share < 1:
            raise ValueError(f"allowed_share must be in [0, 1), got {self.allowed_share!r}")
        if self.formulation == "chance" and self.allowed_share == 0:
            raise ValueError(
                "the chance surrogate needs allowed_share > 0 (its sigmoid is > 0 on every "
                "draw, so a zero share can never be met); e.g. allowed_share=0.05, or use "
                "formulation='mean' to require every draw"
            )

    @property
    def requests(self) -> int:
        """Requests of a whole run: the scale, then per outer step the inner requests and
        one measurement."""
        return 1 + self.outer_steps * (self.inner_steps + 1)

    def loss(self, state) -> AlmLoss:
        shape = (self.formulation, self.margin, self.temperature, self.allowed_share)
        return AlmLoss(np.asarray(state["lam"]), float(state["rho"]), float(state["scale"]), *shape)

    def init(self, x0) -> dict:
        R, zero = self.requirements, np.asarray(0)
        return dict(
            inner=self.inner.init(x0), lam=np.zeros(R), rho=np.asarray(float(self.penalty)),
            scale=np.asarray(1.0), phase=np.asarray(_SCALE), outer=zero, count=zero,
            previous=np.asarray(np.inf), c=np.zeros(R), F=np.asarray(0.0),
        )  # fmt: skip

    def ask(self, state) -> Request:
        phase = int(state["phase"])
        if phase == _INNER:
            return self.inner.ask(state["inner"])._replace(loss=self.loss(state))
        x = self.inner.answer(state["inner"])
        return Request(x[None], False, 0, None, self.loss(state))

    def tell(self, state, request, evaluation) -> dict:
        state, phase = dict(state), int(state["phase"])
        if phase == _INNER:
            state["inner"] = self.inner.tell(state["inner"], request, evaluation)
            state["count"] = state["count"] + 1
            if int(state["count"]) >= self.inner_steps:
                state.update(phase=np.asarray(_MEASURE), count=np.asarray(0))
            return state
        F, c, _ = self.loss(state).parts(evaluation.outputs)
        if phase == _SCALE:
            f0 = float(F[0])  # the scale is 1 here: F is the start's mean target
            state.update(scale=np.asarray(f0 if f0 > 1e-12 else 1.0), phase=np.asarray(_INNER))
            return state
        c = np.asarray(c[0], np.float64)
        rho = float(state["rho"])
        worst = float(np.max(np.maximum(c, 0.0)))
        if worst > 0.25 * float(state["previous"]):
            rho = min(rho * self.penalty_growth, self.penalty_max)
        state.update(
            lam=np.maximum(0.0, state["lam"] + float(state["rho"]) * c), rho=np.asarray(rho)
        )
        state.update(previous=np.asarray(worst), c=c, F=np.asarray(float(F[0])))
        state.update(outer=state["outer"] + 1, phase=np.asarray(_INNER))
        state["inner"] = self.inner.restart(state["inner"])
        return state

    def answer(self, state) -> np.ndarray:
        return self.inner.answer(state["inner"])

    def restart(self, state) -> dict:
        return {**state, "inner": self.inner.restart(state["inner"])}

    def settings(self) -> dict:
        leave_out = ("inner", "outer_steps")  # the budget's (a run may go on for longer)
        out = {k: v for k, v in dataclasses.asdict(self).items() if k not in leave_out}
        return {**out, "inner": self.inner.settings()}

    def row(self, state) -> dict:
        return {
            "outer_step": int(state["outer"]),
            "penalty": float(state["rho"]),
            "multipliers": np.asarray(state["lam"]).tolist(),
            "constraints": np.asarray(state["c"]).tolist(),
            **self.inner.row(state["inner"]),
        }

    def needs(self) -> tuple:
        return tuple(dict.fromkeys((("forward", None),) + self.inner.needs()))
