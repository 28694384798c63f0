"""Per-draw performance metrics, accumulated online inside the rollout's time loop.

:class:`Metrics` is an observer (:mod:`fojax.observers`): nothing of the full-rate
trajectory is stored; a small pytree (:class:`MetricsState`) folds in every control
step and becomes the metrics of one draw at the end. Over a batch of draws every leaf
gains the batch's axes last (:mod:`fojax.observers`).

Errors are :func:`fojax.observers.tracking_error` (``e = actual - reference``; the
attitude against the attitude reference the attitude loop tracks), sampled at the
control instants ``t_k = k dt``, ``k = 0 ... steps - 1``; integrals are rectangle sums
``sum_k f(t_k) dt`` over the horizon ``T = steps dt``. Axes are ordered ``(x, y, z, phi,
theta, psi)``, inputs ``(u_F, tau_x, tau_y, tau_z)``.

Metrics (name: shape, unit):

``position_rmse``: ``()`` m, ``sqrt(1/T int |e_p|^2 dt)`` (Euclidean norm over x, y, z).
``attitude_rmse``: ``()`` rad, the same over ``(phi, theta, psi)``.
``rmse``: ``(6,)`` per axis. ``iae``: ``(6,)`` ``int |e| dt``. ``itae``: ``(6,)``
``int t |e| dt``. ``max_error``: ``(6,)`` ``max |e|``.
``settling_time``: ``(6,)`` s, the first time after which ``|e|`` stays within the
band (``position_band`` m, ``attitude_band`` rad) to the end of the run; ``T`` when the
error is outside the band at the last sample.
``overshoot``: ``(6,)`` the largest excursion past the reference, measured against the
direction of the first error larger than ``overshoot_threshold`` (an error that
starts negative overshoots when it turns positive, and vice versa).
``control_effort``: ``(4,)`` RMS of each input (N, N m).
``chattering``: ``(4,)`` total variation ``sum_k |u_k - u_(k-1)|`` of each input.
``actuator_saturation``: ``()`` fraction of the run during which the command needs a
negative squared rotor speed (the inverted mixer, eq. (10)).
``reaching_time``: ``(6,)`` s, the first time after which ``|S| <= reaching_band`` holds
to the end of the run, for the sliding variables ``S`` of ``ControlInfo.surfaces``
(the sliding mode is reached and kept); ``inf`` when ``|S|`` is outside the band at
the last sample, 0 when it never leaves it.
``initial_surface``: ``(6,)`` ``S(t_0)``, for the finite-time bound of eq. (34).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from fojax import observers, plant

Array = jax.Array

__all__ = [
    "AXES",
    "INPUTS",
    "METRIC_UNITS",
    "Metrics",
    "MetricsConfig",
    "MetricsState",
    "component_names",
    "component_units",
]

AXES = ("x", "y", "z", "phi", "theta", "psi")
INPUTS = ("thrust", "tau_x", "tau_y", "tau_z")

# Unit of each metric, per component group (position axes, attitude axes, inputs).
METRIC_UNITS = {
    "position_rmse": "m",
    "attitude_rmse": "rad",
    "rmse": ("m", "rad"),
    "iae": ("m s", "rad s"),
    "itae": ("m s^2", "rad s^2"),
    "max_error": ("m", "rad"),
    "settling_time": ("s", "s"),
    "overshoot": ("m", "rad"),
    "control_effort": ("N", "N m"),
    "chattering": ("N", "N m"),
    "actuator_saturation": "1",
    "reaching_time": ("s", "s"),
    "initial_surface": ("m/s", "rad/s"),
}


@dataclasses.dataclass(frozen=True)
class MetricsConfig:
    """Static settings of the metrics.

    dt: control step (s). steps: number of control steps (horizon ``steps dt``).
    position_band: settling band of the position errors (m).
    attitude_band: settling band of the attitude errors (rad).
    overshoot_threshold: an error must exceed this (m or rad) to fix the direction
        that later counts as overshoot.
    reaching_band: ``|S|`` below this counts as having reached the sliding surface:
        one number for every axis, or a tuple of six, one per axis ``(x, y, z, phi,
        theta, psi)`` (for instance proportional to each axis' switching gain times
        ``dt``, the band that switching at a fixed step leaves).
    """

    dt: float
    steps: int
    position_band: float = 0.05
    attitude_band: float = 0.05
    overshoot_threshold: float = 1e-3
    reaching_band: float | tuple[float, ...] = 0.01

    def __post_init__(self) -> None:
        for label in ("dt", "position_band", "attitude_band", "overshoot_threshold"):
            value = getattr(self, label)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        band = self.reaching_band
        if isinstance(band, list | tuple):
            values = tuple(band)
            if len(values) != 6:
                raise ValueError(
                    f"reaching_band must be one number or six (one per axis), got {len(values)}"
                )
            object.__setattr__(self, "reaching_band", tuple(float(v) for v in values))
        else:
            values = (band,)
        for value in values:
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"reaching_band must be finite and > 0, got {band!r}")
        if not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"steps must be a positive integer, got {self.steps!r}")

    @property
    def horizon(self) -> float:
        return self.steps * self.dt

    def bands(self, dtype) -> Array:
        """``(6,)`` settling bands per axis."""
        return jnp.asarray([self.position_band] * 3 + [self.attitude_band] * 3, dtype)

    def reaching_bands(self, dtype) -> Array:
        """``(6,)`` reaching bands per axis (``()`` when one band serves every axis)."""
        return jnp.asarray(self.reaching_band, dtype)


class MetricsState(NamedTuple):
    """Running sums of one draw (all leaves arrays; shapes without the draw axis)."""

    count: Array  # () int32, samples seen
    squared_error: Array  # (6,) sum e^2 dt
    absolute_error: Array  # (6,) sum |e| dt
    time_weighted_error: Array  # (6,) sum t |e| dt
    max_error: Array  # (6,)
    last_outside: Array  # (6,) last sample time with |e| > band (-1: never)
    direction: Array  # (6,) sign of the first error above the threshold (0: none yet)
    overshoot: Array  # (6,)
    squared_input: Array  # (4,) sum u^2 dt
    variation: Array  # (4,) sum |u_k - u_(k-1)|
    previous_input: Array  # (4,)
    saturated_time: Array  # () time with an infeasible command
    surface_last_outside: Array  # (6,) last sample time with |S| > band (-1: never)
    initial_surface: Array  # (6,)


def _init(dtype=None) -> MetricsState:
    """Empty running sums."""
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    zeros6 = jnp.zeros(6, dtype)
    zeros4 = jnp.zeros(4, dtype)
    return MetricsState(
        count=jnp.zeros((), jnp.int32),
        squared_error=zeros6,
        absolute_error=zeros6,
        time_weighted_error=zeros6,
        max_error=zeros6,
        last_outside=jnp.full(6, -1.0, dtype),
        direction=zeros6,
        overshoot=zeros6,
        squared_input=zeros4,
        variation=zeros4,
        previous_input=zeros4,
        saturated_time=jnp.zeros((), dtype),
        surface_last_outside=jnp.full(6, -1.0, dtype),
        initial_surface=zeros6,
    )


def _update(
    config: MetricsConfig,
    acc: MetricsState,
    t: Array,
    error: Array,
    inputs: Array,
    surfaces: Array,
    mixer_params: plant.PlantParams,
) -> MetricsState:
    """Fold the sample at time ``t`` into the running sums.

    error: ``(6,)`` tracking errors ``(x, y, z, phi, theta, psi)``.
    inputs: ``(4,)`` the command held over ``[t, t + dt)``.
    surfaces: ``(6,)`` sliding variables.
    mixer_params: the plant parameters whose mixer (10) decides feasibility.
    """
    dt = config.dt
    dtype = acc.squared_error.dtype
    error = error.astype(dtype)
    inputs = inputs.astype(dtype)
    surfaces = surfaces.astype(dtype)
    t = jnp.asarray(t, dtype)
    first = acc.count == 0
    magnitude = jnp.abs(error)

    outside = magnitude > observers.per_component(config.bands(dtype), magnitude)
    last_outside = jnp.where(outside, t, acc.last_outside)

    undecided = (acc.direction == 0) & (magnitude > config.overshoot_threshold)
    direction = jnp.where(undecided, jnp.sign(error), acc.direction)
    overshoot = jnp.maximum(acc.overshoot, jnp.maximum(-direction * error, 0.0))

    variation = acc.variation + jnp.where(first, 0.0, jnp.abs(inputs - acc.previous_input))
    infeasible = jnp.any(plant.rotor_speeds_squared(mixer_params, inputs) < 0, 0)
    surface_outside = jnp.abs(surfaces) > observers.per_component(
        config.reaching_bands(dtype), surfaces
    )
    surface_last_outside = jnp.where(surface_outside, t, acc.surface_last_outside)

    return MetricsState(
        count=acc.count + 1,
        squared_error=acc.squared_error + dt * error * error,
        absolute_error=acc.absolute_error + dt * magnitude,
        time_weighted_error=acc.time_weighted_error + dt * t * magnitude,
        max_error=jnp.maximum(acc.max_error, magnitude),
        last_outside=last_outside,
        direction=direction,
        overshoot=overshoot,
        squared_input=acc.squared_input + dt * inputs * inputs,
        variation=variation,
        previous_input=inputs,
        saturated_time=acc.saturated_time + jnp.where(infeasible, dt, 0.0),
        surface_last_outside=surface_last_outside,
        initial_surface=jnp.where(first, surfaces, acc.initial_surface),
    )


def _finalize(config: MetricsConfig, acc: MetricsState) -> dict[str, Array]:
    """The metrics of one draw (see the module docstring), as a dict of arrays.

    The horizon ``T`` is the recorded samples times ``dt``: ``config.horizon``, or a
    union scenario's member's own horizon when the rollout stopped recording earlier.
    """
    dt = config.dt
    horizon = acc.count.astype(acc.max_error.dtype) * dt
    # Settled from the sample after the last one outside the band; never outside: 0.
    settling = jnp.where(acc.last_outside < 0, 0.0, jnp.minimum(acc.last_outside + dt, horizon))
    last_sample = horizon - dt
    reaching = jnp.where(
        acc.surface_last_outside < 0,
        0.0,
        jnp.where(
            acc.surface_last_outside >= last_sample - 0.5 * dt,
            jnp.inf,
            acc.surface_last_outside + dt,
        ),
    )
    # Times 1 / T rather than divided by T (a draw's, broadcast): XLA rewrites such a
    # division into that product in some programs and not in others, and a draw's
    # numbers must not depend on the program it ran in (the devices, the batch).
    per_second = 1.0 / horizon
    return {
        "position_rmse": jnp.sqrt(jnp.sum(acc.squared_error[:3], 0) * per_second),
        "attitude_rmse": jnp.sqrt(jnp.sum(acc.squared_error[3:], 0) * per_second),
        "rmse": jnp.sqrt(acc.squared_error * per_second),
        "iae": acc.absolute_error,
        "itae": acc.time_weighted_error,
        "max_error": acc.max_error,
        "settling_time": settling.astype(acc.max_error.dtype),
        "overshoot": acc.overshoot,
        "control_effort": jnp.sqrt(acc.squared_input * per_second),
        "chattering": acc.variation,
        "actuator_saturation": acc.saturated_time * per_second,
        "reaching_time": reaching.astype(acc.max_error.dtype),
        "initial_surface": acc.initial_surface,
    }


@dataclasses.dataclass(frozen=True)
class Metrics:
    """The metrics as an observer of the rollout (:mod:`fojax.observers`).

    config: :class:`MetricsConfig`. Feasibility of a command (``actuator_saturation``)
    is judged by the mixer (10) of the controller's nominal plant.
    """

    config: MetricsConfig

    def init(self, dtype) -> MetricsState:
        return _init(dtype)

    def update(self, acc: MetricsState, record) -> MetricsState:
        mixer = record.model
        return _update(
            self.config, acc, record.time, record.error, record.inputs, record.info.surfaces, mixer
        )

    def finalize(self, acc: MetricsState) -> dict[str, Array]:
        return _finalize(self.config, acc)


def component_names(name: str, value_shape: tuple[int, ...]) -> list[str]:
    """Names of the scalar components of metric ``name`` with per-draw shape ``value_shape``.

    ``()`` -> ``[name]``; ``(6,)`` -> ``name_x ... name_psi``; ``(4,)`` -> ``name_thrust``
    ... ``name_tau_z``.
    """
    if value_shape == ():
        return [name]
    if value_shape == (6,):
        return [f"{name}_{axis}" for axis in AXES]
    if value_shape == (4,):
        return [f"{name}_{channel}" for channel in INPUTS]
    raise ValueError(f"metric {name!r} has unsupported shape {value_shape}")


def component_units(name: str, value_shape: tuple[int, ...]) -> list[str]:
    """Units of the components listed by :func:`component_names`."""
    unit = METRIC_UNITS.get(name, "")
    if value_shape == ():
        return [unit if isinstance(unit, str) else unit[0]]
    if isinstance(unit, str):
        return [unit] * value_shape[0]
    if value_shape == (6,):
        return [unit[0]] * 3 + [unit[1]] * 3
    return [unit[0]] + [unit[1]] * 3
