"""The controller interface of the closed-loop simulator.

A controller is a static configuration object (a frozen dataclass: step size,
fractional method, switching function; settled before tracing) with three pure
functions:

``prepare(gains, model) -> params``
    Everything derived from the gains and the controller's nominal model that stays
    fixed during a run (fractional weights, for instance), as a pytree. Called once
    per rollout, outside the time loop; differentiable in ``gains``.
``init(params, observation) -> state``
    The controller's internal state at ``t = 0`` (fractional memories, adaptive
    estimates, command filters), as a pytree of arrays.
``step(params, state, observation) -> (state, inputs, info)``
    One control update at the sample time; ``inputs`` is ``(4,)``
    ``(u_F, tau_x, tau_y, tau_z)``, held over the next plant step (zero-order hold);
    ``info`` is a :class:`ControlInfo`.

``gains`` is any pytree of arrays (what a tuner may change); ``model`` is the
:class:`fojax.plant.PlantParams` the controller believes in (the nominal plant).
User-written controllers implement the same three functions and plug into
:func:`fojax.simulator.rollout` unchanged.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


class Observation(NamedTuple):
    """What a controller sees at time ``t_k``.

    time: ``()`` s.
    state: ``(12,)`` plant state ``(x, y, z, phi, theta, psi, x', y', z', phi', theta', psi')``.
    reference: ``(4,)`` ``(x_r, y_r, z_r, psi_r)`` (m, rad).
    reference_velocity: ``(4,)`` its exact first time derivative.
    reference_acceleration: ``(4,)`` its exact second time derivative.
    """

    time: Array
    state: Array
    reference: Array
    reference_velocity: Array
    reference_acceleration: Array


class ControlInfo(NamedTuple):
    """Diagnostics returned with each control update (fixed shapes for every controller).

    surfaces: ``(6,)`` sliding variables ``(S_x, S_y, S_z, S_phi, S_theta, S_psi)``
        (controllers without surfaces return their error measure or zeros).
    attitude_reference: ``(3,)`` ``(phi_r, theta_r, psi_r)`` that the attitude loop
        tracks at this step (rad): the position loop's command of eq. (13) after the
        command filter, and the reference yaw. Attitude errors and metrics are taken
        against it.
    adaptive: ``(6, 3)`` adaptive estimates ``(b0, b1, b2)`` per axis (zeros when the
        controller does not adapt).
    """

    surfaces: Array
    attitude_reference: Array
    adaptive: Array


class Controller(Protocol):
    """What :func:`fojax.simulator.rollout` needs from a controller."""

    name: str

    def prepare(self, gains: Any, model: Any) -> Any: ...

    def init(self, params: Any, observation: Observation) -> Any: ...

    def step(
        self, params: Any, state: Any, observation: Observation
    ) -> tuple[Any, Array, ControlInfo]: ...


# ---------------------------------------------------------------- gain constraints


class Bounds(NamedTuple):
    """The feasible set of one gain field: ``low < value < high`` elementwise.

    ``include_low``: ``low <= value`` instead. ``symbol``: the name used in messages
    (for instance ``"p/q"``). Tuners map unconstrained parameters onto these sets.
    """

    low: float
    high: float = math.inf
    include_low: bool = False
    symbol: str | None = None

    def describe(self, name: str) -> str:
        symbol = self.symbol or name
        low_op = "<=" if self.include_low else "<"
        if math.isinf(self.high):
            return f"{symbol} must be {'>=' if self.include_low else '>'} {self.low:g}"
        return f"{symbol} must satisfy {self.low:g} {low_op} {symbol} < {self.high:g}"

    def contains(self, value: np.ndarray) -> np.ndarray:
        above = value >= self.low if self.include_low else value > self.low
        return above & (value < self.high)


def check_bounds(gains: Any, bounds: dict, shapes: dict, label: str) -> None:
    """Raise ``ValueError`` listing every field of ``gains`` that is non-finite, has the
    wrong shape or lies outside ``bounds`` (field -> :class:`Bounds`)."""
    problems = []
    for name in gains._fields:
        value = np.asarray(getattr(gains, name), dtype=float)
        if value.shape != shapes[name]:
            problems.append(f"{name} must have shape {shapes[name]}, got {value.shape}")
            continue
        if not np.all(np.isfinite(value)):
            problems.append(f"{name} must be finite, got {value.tolist()}")
            continue
        bound = bounds[name]
        if not np.all(bound.contains(value)):
            text = bound.describe(name)
            if bound.symbol:
                text = f"{name} {text}"
            problems.append(f"{text}, got {value.tolist()}")
    if problems:
        raise ValueError(f"invalid {label} gains:\n  " + "\n  ".join(problems))


# ------------------------------------------------------------------ shared helpers


def command_filter_update(frequency: float, damping: float, dt: float, dtype: Any):
    """Exact zero-order-hold update of the second-order attitude command filter.

    The filter ``x'' = w^2 (u - x) - 2 zeta w x'`` (``w = frequency``, ``zeta = damping``)
    on ``(x, x')`` with ``u`` held over a step of ``dt``: ``(x, x')_(k+1) = A (x, x')_k
    + b u_k``. Returns ``A`` ``(2, 2)`` and ``b`` ``(2,)`` from the matrix exponential of
    the augmented system.
    """
    w, zeta = frequency, damping
    augmented = jnp.asarray(
        [[0.0, 1.0, 0.0], [-w * w, -2.0 * zeta * w, w * w], [0.0, 0.0, 0.0]], dtype
    )
    exp = jax.scipy.linalg.expm(augmented * dt)
    return exp[:2, :2], exp[:2, 2]

SWITCHING_FUNCTIONS = ("sign", "sat", "tanh")


def switching(kind: str, surface: Array, width: Array) -> Array:
    """The switching function ``sgn(S)`` of the reaching laws.

    ``"sign"``: exact sign; ``"sat"``: ``clip(S / width, -1, 1)`` (boundary layer);
    ``"tanh"``: ``tanh(S / width)`` (smooth; for gradient-based tuning).
    """
    if kind == "sign":
        return jnp.sign(surface)
    if kind == "sat":
        return jnp.clip(surface / width, -1.0, 1.0)
    if kind == "tanh":
        return jnp.tanh(surface / width)
    raise ValueError(f"unknown switching function {kind!r}; choose one of {SWITCHING_FUNCTIONS}")


def signed_power(value: Array, exponent: Array) -> Array:
    """``sig^r(e) = |e|^r sign(e)`` (notes item 6), with finite gradients at ``e = 0``."""
    magnitude = jnp.abs(value)
    nonzero = magnitude > 0
    safe = jnp.where(nonzero, magnitude, 1.0)
    return jnp.where(nonzero, jnp.sign(value) * jnp.exp(exponent * jnp.log(safe)), 0.0)


def signed_square(rate: Array) -> Array:
    """Aerodynamic drag shape ``w |w|`` (notes item 1), the same in plant and controller."""
    return rate * jnp.abs(rate)


def attitude_drift_parts(model: Any, p: Array, q: Array, r: Array, rotor_speed_sum: Array):
    """:func:`attitude_drift` from the three rates ``(phi', theta', psi')`` as scalars.

    Returns the three accelerations as a tuple (each of the rates' shape).
    """
    i11, i22, i33 = model.inertia[0], model.inertia[1], model.inertia[2]
    k = model.drag_attitude
    j_r = model.rotor_inertia
    return (
        (i22 - i33) / i11 * q * r - j_r / i11 * q * rotor_speed_sum - k[0] / i11 * signed_square(p),
        (i33 - i11) / i22 * p * r + j_r / i22 * p * rotor_speed_sum - k[1] / i22 * signed_square(q),
        (i11 - i22) / i33 * p * q - k[2] / i33 * signed_square(r),
    )


def attitude_drift(model: Any, attitude_rate: Array, rotor_speed_sum: Array) -> Array:
    """The model's coupling and drag accelerations ``(3,)`` of eq. (11a)-(11c).

    ``{a_phi1 theta' psi' - a_phi2 theta' Omega_r - a_phi3 drag(phi'), ...}``: the
    bracket of eqs. (42)-(44) (notes items 1 and 10), without the torques.
    """
    p, q, r = attitude_rate[0], attitude_rate[1], attitude_rate[2]
    return jnp.stack(attitude_drift_parts(model, p, q, r, rotor_speed_sum))


def thrust_and_attitude_parts(
    model: Any, vx: Array, vy: Array, vz: Array, cos_yaw: Array, sin_yaw: Array
) -> tuple[Array, Array, Array]:
    """:func:`thrust_and_attitude` on scalars: ``v = (vx, vy, vz)`` and ``cos/sin(psi_r)``.

    Returns ``(u_F, phi_r, theta_r)``.
    """
    g = model.gravity
    lift = jnp.maximum(vz + g, 0.1 * g)
    theta_r = jnp.arctan((cos_yaw * vx + sin_yaw * vy) / lift)
    phi_r = jnp.arctan(jnp.cos(theta_r) * (sin_yaw * vx - cos_yaw * vy) / lift)
    thrust = model.mass * jnp.sqrt(vx * vx + vy * vy + lift * lift)
    return thrust, phi_r, theta_r


def thrust_and_attitude(model: Any, virtual: Array, yaw_reference: Array) -> tuple[Array, Array]:
    """Eq. (13): thrust ``u_F`` and ``(phi_r, theta_r)`` from the virtual control ``v``.

    ``v`` ``(3,)`` is the commanded acceleration without gravity (notes item 5). The
    vertical term ``v_z + g`` is kept above ``0.1 g`` so the quadrotor never asks to
    fly upside down (a documented guard; it is inactive in the paper's scenarios).
    """
    thrust, phi_r, theta_r = thrust_and_attitude_parts(
        model,
        virtual[0],
        virtual[1],
        virtual[2],
        jnp.cos(yaw_reference),
        jnp.sin(yaw_reference),
    )
    return thrust, jnp.stack([phi_r, theta_r])
