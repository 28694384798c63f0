"""What a rollout records: observers folded over the time loop, chained.

An observer is a static object (a frozen dataclass, settled before tracing) with three
pure functions, in the style of optax's transformations:

``init(dtype) -> acc``
    Its running state, a pytree of arrays (fixed shapes).
``update(acc, record) -> acc``
    Fold in one step, a :class:`StepRecord`.
``finalize(acc) -> outputs``
    What it reports for the draw (a pytree of arrays).

:func:`fojax.simulator.rollout` calls them at every control step. ``init`` returns
the state of one draw; over a batch of draws the rollout broadcasts it, and every array
an observer sees and keeps, the batch's axes last (``record.error`` ``(6, draws)``, a
``(6,)`` sum ``(6, draws)``): write ``update`` with elementwise operations, indexing
along the leading axes and reductions over named leading axes (``jnp.sum(e[:3], 0)``,
never over all axes), and it runs unchanged on one draw and on a batch
(:func:`per_component` shapes a ``(k,)`` constant to broadcast along the components).
:class:`Chain` runs several under names
(``Chain(metrics=..., cost=...)``), :class:`Status` (the per-draw failure flags) runs
in every rollout. The per-draw metrics (:mod:`fojax.metrics`) and the tuning cost
(:mod:`optimize.cost`) are observers; :func:`tracking_error` is the one definition of
the tracking error they share.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from fojax import plant
from fojax._arrays import unstack
from fojax.controllers.base import ControlInfo

Array = jax.Array

__all__ = [
    "ACTUATOR_LIMIT",
    "NONFINITE",
    "STATUS_NAMES",
    "TILT_LIMIT",
    "Chain",
    "Observer",
    "Status",
    "StepRecord",
    "TrackingISE",
    "per_component",
    "tracking_error",
]

# Status flags per draw, as bits (:class:`Status`).
NONFINITE = 1  # a state, input or surface became NaN/inf
TILT_LIMIT = 2  # |roll| or |pitch| reached pi/2 (Assumption 1)
ACTUATOR_LIMIT = 4  # the command needed a negative squared rotor speed (mixer (10))
STATUS_NAMES = {NONFINITE: "nonfinite", TILT_LIMIT: "tilt_limit", ACTUATOR_LIMIT: "actuator_limit"}


class StepRecord(NamedTuple):
    """One control step ``k`` as the observers see it.

    time: ``()`` ``t_k``. state: ``(12,)`` ``x_k``. next_state: ``(12,)`` ``x_(k+1)``,
    after the plant step. reference: ``(4,)`` ``(x_r, y_r, z_r, psi_r)`` at ``t_k``.
    inputs: ``(4,)`` the command held over ``[t_k, t_(k+1))``. info: the controller's
    :class:`fojax.controllers.ControlInfo` of that command. error: ``(6,)``
    :func:`tracking_error`. plant: the simulated plant's
    :class:`fojax.plant.PlantParams` (the draw's). model: the controller's nominal plant
    (the vehicle's, without the draw's uncertainty).
    """

    time: Array
    state: Array
    next_state: Array
    reference: Array
    inputs: Array
    info: ControlInfo
    error: Array
    plant: plant.PlantParams
    model: plant.PlantParams


def per_component(values: Any, like: Array) -> Array:
    """``values`` ``(k,)`` (one per component) shaped to broadcast against ``like``, an
    array ``(k,) + batch`` of one draw or of a batch (the batch's axes last): ``(k, 1)``
    against ``(k, draws)``."""
    values = jnp.asarray(values)
    return values.reshape(values.shape + (1,) * (jnp.ndim(like) - values.ndim))


def tracking_error(state: Array, reference: Array, attitude_reference: Array) -> Array:
    """``(6,)`` tracking errors ``e = actual - reference`` over ``(x, y, z, phi, theta,
    psi)``: the position against the reference trajectory, the attitude against the
    attitude reference the attitude loop tracks (``ControlInfo.attitude_reference``:
    the position loop's command after the command filter; ``psi`` against the
    reference yaw). ``state``: the ``(12,)`` state or its blocks
    (:class:`fojax.plant.StateBlocks`). Over a batch: ``state`` ``(12, draws)``,
    ``reference`` ``(4,)`` or ``(4, draws)``, the result ``(6, draws)``.
    """
    state = plant.state_blocks(state)
    position = state.position - per_component(reference[:3], state.position)
    attitude = state.attitude - attitude_reference.astype(state.attitude.dtype)
    return jnp.concatenate([position, attitude])


class Observer(Protocol):
    def init(self, dtype: Any) -> Any: ...

    def update(self, acc: Any, record: StepRecord) -> Any: ...

    def finalize(self, acc: Any) -> Any: ...


@dataclasses.dataclass(frozen=True)
class Status:
    """Per-draw failure flags (bits of :data:`STATUS_NAMES`), or-ed over the run.

    ``NONFINITE``: the state after a step, the command or a surface is NaN or inf;
    ``TILT_LIMIT``: ``|phi|`` or ``|theta|`` reached ``pi/2`` after a step (Assumption 1);
    ``ACTUATOR_LIMIT``: the command needed a negative squared rotor speed of the
    simulated plant's mixer (10).
    """

    def init(self, dtype: Any) -> Array:
        return jnp.zeros((), jnp.int32)

    def update(self, acc: Array, record: StepRecord) -> Array:
        state, inputs = record.next_state, record.inputs
        finite = (
            jnp.all(jnp.isfinite(state), 0)
            & jnp.all(jnp.isfinite(inputs), 0)
            & jnp.all(jnp.isfinite(record.info.surfaces), 0)
        )
        tilt = jnp.any(jnp.abs(state[3:5]) >= jnp.pi / 2, 0)
        actuator = jnp.any(plant.rotor_speeds_squared(record.plant, inputs) < 0, 0)
        flags = (
            jnp.where(finite, 0, NONFINITE)
            | jnp.where(tilt, TILT_LIMIT, 0)
            | jnp.where(actuator, ACTUATOR_LIMIT, 0)
        )
        return acc | flags.astype(jnp.int32)

    def finalize(self, acc: Array) -> Array:
        return acc


@dataclasses.dataclass(frozen=True)
class TrackingISE:
    """``()`` the integral of the squared tracking errors (position and attitude),
    ``sum_k dt |e(t_k)|^2``: a plain differentiable cost."""

    dt: float

    def init(self, dtype: Any) -> Array:
        return jnp.zeros((), dtype)

    def update(self, acc: Array, record: StepRecord) -> Array:
        position, attitude = unstack(record.error, (3, 3))
        return acc + self.dt * (jnp.sum(position**2, 0) + jnp.sum(attitude**2, 0))

    def finalize(self, acc: Array) -> Array:
        return acc


class Chain:
    """Several observers under names; ``init``/``update``/``finalize`` act on dicts.

    ``Chain(metrics=MetricsObserver(...), cost=CostObserver(...))``: the outputs are
    ``{"metrics": ..., "cost": ...}``. Hashable and comparable by its observers, like
    the frozen dataclasses it holds.
    """

    def __init__(self, **observers: Any):
        for name, observer in observers.items():
            missing = [f for f in ("init", "update", "finalize") if not hasattr(observer, f)]
            if missing:
                raise TypeError(f"observer {name!r} has no {', '.join(missing)}")
        self.observers = tuple(observers.items())

    def __hash__(self) -> int:
        return hash(self.observers)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Chain) and self.observers == other.observers

    def init(self, dtype: Any) -> dict:
        return {name: o.init(dtype) for name, o in self.observers}

    def update(self, acc: dict, record: StepRecord) -> dict:
        return {name: o.update(acc[name], record) for name, o in self.observers}

    def finalize(self, acc: dict) -> dict:
        return {name: o.finalize(acc[name]) for name, o in self.observers}
