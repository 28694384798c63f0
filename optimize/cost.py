"""The tuning cost: per-draw tracking, effort and chattering terms through
:func:`fojax.simulator.rollout`, and the mean or CVaR over a minibatch of draws.

Per draw (rectangle sums at the control instants ``t_k = k dt``, as
:mod:`fojax.metrics`; errors ``e = actual - reference``, roll and pitch against the
attitude reference the attitude loop tracks, ``ControlInfo.attitude_reference``):

* tracking, ``error="ise"``: ``P = int |e_pos|^2 dt`` (m^2 s), ``A = int |e_att|^2 dt``
  (rad^2 s); ``error="itae"``: ``P = int t sum_i |e_pos,i| dt``, ``A`` likewise;
* effort ``E = int |a|^2 dt`` and chattering ``C = sum_k |a_k - a_(k-1)|_1`` (total
  variation) of the commanded accelerations ``a = ((u_F - m g) / m, tau_x / I_11,
  tau_y / I_22, tau_z / I_33)`` of the controller's nominal model (m/s^2, rad/s^2:
  the four inputs on comparable scales, zero at hover);
* ``J = w_pos P + w_att A + w_effort E + w_chattering C``.

A draw that diverges (status ``nonfinite`` or ``tilt_limit``, or a non-finite ``J``)
costs ``divergence_cost`` and contributes no gradient. Over a sample of ``n`` draws,
``objective="mean"`` is the mean of ``J``, ``objective="cvar"`` the mean of the
``ceil(cvar_fraction n)`` largest (the conditional value at risk of the worst tail):
:class:`fojax.optimize.MeanLoss`. :func:`make_batch_cost` and :func:`per_draw_gradients`
compute ``J`` and its per-draw gradients by the gains directly (the references the tests
check the objective against).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fojax import observers, plant, scenarios, simulator
from fojax._arrays import unstack
from fojax.optimize import checks

Array = jax.Array

__all__ = [
    "DIVERGED", "ERRORS", "OBJECTIVES", "CostConfig", "CostObserver", "CostTerms",
    "TorqueVariation", "case_scales", "make_batch_cost", "per_draw_gradients",
]  # fmt: skip

ERRORS = ("ise", "itae")
OBJECTIVES = ("mean", "cvar")
DIVERGED = observers.NONFINITE | observers.TILT_LIMIT


@dataclasses.dataclass(frozen=True)
class CostConfig:
    """Static settings of the tuning cost (see the module docstring).

    error: ``"ise"`` or ``"itae"``. position_weight, attitude_weight, effort_weight,
    chattering_weight: ``w_pos, w_att, w_effort, w_chattering`` (>= 0, not all 0).
    objective: ``"mean"`` or ``"cvar"``. cvar_fraction: the worst fraction of draws
    CVaR averages, in ``(0, 1]`` (with ``objective="cvar"`` only; the mean does not
    use it). divergence_cost: the cost of a diverged draw (> 0).
    """

    error: str = "ise"
    position_weight: float = 1.0
    attitude_weight: float = 1.0
    effort_weight: float = 1e-5
    chattering_weight: float = 1e-5
    objective: str = "mean"
    cvar_fraction: float = 0.25
    divergence_cost: float = 1e3

    def __post_init__(self) -> None:
        if self.error not in ERRORS:
            raise ValueError(f"unknown error measure {self.error!r}; choose one of {ERRORS}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"unknown objective {self.objective!r}; choose one of {OBJECTIVES}")
        for term in ("position", "attitude", "effort", "chattering"):
            checks.number(f"{term}_weight", getattr(self, f"{term}_weight"), allow_low=True)
        if not any(w > 0 for w in self.weights):
            raise ValueError("at least one cost weight must be > 0")
        if not (isinstance(self.cvar_fraction, int | float) and 0 < self.cvar_fraction <= 1):
            raise ValueError(f"cvar_fraction must be in (0, 1], got {self.cvar_fraction!r}")
        checks.number("divergence_cost", self.divergence_cost)

    @property
    def weights(self) -> tuple[float, float, float, float]:
        return (self.position_weight, self.attitude_weight, self.effort_weight,
                self.chattering_weight)  # fmt: skip

    def tail_count(self, draws: int) -> int:
        """Draws averaged by the CVaR objective out of ``draws``."""
        return max(1, math.ceil(self.cvar_fraction * draws - 1e-9))


class CostTerms(NamedTuple):
    """Running sums of one draw (the state of :class:`CostObserver`).

    position, attitude: ``()`` tracking terms ``P``, ``A``. effort: ``()`` ``E``.
    chattering: ``()`` ``C``. previous: ``(4,)`` the last commanded accelerations.
    started: ``()`` bool, a previous command exists.
    """

    position: Array
    attitude: Array
    effort: Array
    chattering: Array
    previous: Array
    started: Array


@dataclasses.dataclass(frozen=True)
class CostObserver:
    """The cost's running sums as an observer of the rollout (:mod:`fojax.observers`).

    config: :class:`CostConfig`. dt: the step. Accelerations are scaled by the
    controller's nominal plant (the record's ``model``: the vehicle's).
    """

    config: CostConfig
    dt: float

    def init(self, dtype) -> CostTerms:
        zero = jnp.zeros((), dtype)
        return CostTerms(zero, zero, zero, zero, jnp.zeros(4, dtype), jnp.zeros((), bool))

    def update(self, acc: CostTerms, record) -> CostTerms:
        dtype = record.state.dtype
        model = record.model
        inputs = record.inputs
        scale = observers.per_component(
            jnp.concatenate([model.mass[None], model.inertia]).astype(dtype), inputs
        )
        hover = observers.per_component(plant.hover_inputs(model).astype(dtype), inputs)
        position_error, attitude_error = unstack(record.error, (3, 3))
        if self.config.error == "itae":
            position = record.time * jnp.sum(jnp.abs(position_error), 0)
            attitude = record.time * jnp.sum(jnp.abs(attitude_error), 0)
        else:
            position = jnp.sum(position_error**2, 0)
            attitude = jnp.sum(attitude_error**2, 0)
        accel = (inputs - hover) / scale
        jump = jnp.where(acc.started, jnp.sum(jnp.abs(accel - acc.previous), 0), 0.0)
        dt = self.dt
        return CostTerms(
            position=acc.position + dt * position,
            attitude=acc.attitude + dt * attitude,
            effort=acc.effort + dt * jnp.sum(accel**2, 0),
            chattering=acc.chattering + jump,
            previous=accel,
            started=jnp.ones_like(acc.started),
        )

    def finalize(self, acc: CostTerms) -> Array:
        """``(4,)`` the terms ``(P, A, E, C)``."""
        return jnp.stack([acc.position, acc.attitude, acc.effort, acc.chattering])


@dataclasses.dataclass(frozen=True)
class TorqueVariation:
    """The total variation of the three torque commands over a run (N m), ``sum_k
    |tau_k - tau_(k-1)|_1``, as an observer (:mod:`fojax.observers`): what the
    requirement metric ``torque_chattering`` measures per second, which a flight
    envelope's chattering bound holds each case to (:attr:`ProblemSpec.case_chattering`)."""

    def init(self, dtype):
        return (jnp.zeros((), dtype), jnp.zeros(3, dtype), jnp.zeros((), bool))

    def update(self, acc, record):
        total, previous, started = acc
        torques = record.inputs[1:]
        jump = jnp.where(started, jnp.sum(jnp.abs(torques - previous), 0), 0.0)
        return total + jump, torques, jnp.ones_like(started)

    def finalize(self, acc):
        return acc[0]


def make_batch_cost(
    controller: Any,
    scenario: scenarios.Scenario,
    sim_config: simulator.SimulationConfig,
    cost_config: CostConfig,
    dtype: Any = None,
):
    """``cost(gains, keys) -> (J (n,), terms (n, 4), status (n,))`` of the draws ``keys``
    ``(n, 2)`` in one batch-last rollout; ``gains`` shared by the draws or one copy per draw
    (the draws' axis last). ``controller`` is built for ``sim_config.horizon``. ``J`` is
    the raw weighted sum (non-finite when a draw diverged). Pure."""
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    model = scenario.plant_params(dtype)
    observer = CostObserver(cost_config, sim_config.dt)
    weights = jnp.asarray(cost_config.weights, dtype)

    def cost(gains, keys):
        result = simulator.rollout_from_keys(
            controller, gains, model, scenario, keys, sim_config, observer, dtype
        )
        terms = result.outputs  # (4, n)
        return jnp.sum(weights[:, None] * terms, 0), terms.T, result.status

    return cost


def per_draw_gradients(batch_cost, gains: Any, keys: Array):
    """``(J (n,), terms (n, 4), status (n,), gradients)``: the cost of every draw and its
    gradient by ``gains`` (each field ``(n,) + shape``): one batch-last rollout with one
    copy of the gains per draw, differentiated once (each draw's cost depends on its own
    copy only, so a diverged draw does not touch the others' gradients)."""
    n = keys.shape[0]
    copies = jax.tree.map(lambda g: jnp.broadcast_to(g[..., None], g.shape + (n,)), gains)

    def total(copies):
        j, terms, status = batch_cost(copies, keys)
        return jnp.sum(j), (j, terms, status)

    gradients, (j, terms, status) = jax.grad(total, has_aux=True)(copies)
    return j, terms, status, jax.tree.map(lambda g: jnp.moveaxis(g, -1, 0), gradients)


def case_scales(costs: np.ndarray, status: np.ndarray, members: np.ndarray,
                cases: int) -> tuple[float, ...]:  # fmt: skip
    """Per case, the divisor of :attr:`ProblemSpec.case_scales` from a reference's costs
    ``J`` ``(n,)`` on draws of the cases ``members`` ``(n,)``: the median of the case's
    draws that did not diverge. A case where every draw diverged takes the median of the
    other cases' scales."""
    costs = np.asarray(costs, np.float64)
    kept = ((np.asarray(status) & DIVERGED) == 0) & np.isfinite(costs)
    rows = []
    for c in range(cases):
        mine = (np.asarray(members) == c) & kept
        rows.append(float(np.median(costs[mine])) if np.any(mine) else None)
    known = [r for r in rows if r is not None and r > 0]
    if not known:
        raise ValueError("every reference draw diverged: no scale for any case")
    fallback = float(np.median(known))
    return tuple(fallback if r is None or r <= 0 else r for r in rows)
