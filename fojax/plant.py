"""Quadrotor plant of the paper's Section III, eqs. (8)-(11).

State
-----
The plant state is a flat array of shape ``(12,)``::

    index  0  1  2  3    4      5    6   7   8   9     10      11
    value  x  y  z  phi  theta  psi  x'  y'  z'  phi'  theta'  psi'

position ``X_p = (x, y, z)`` in the earth frame (m, ``z`` up), Euler angles
``eta = (phi, theta, psi)`` (rad, roll/pitch/yaw, Z-Y-X sequence of eq. (9)), then
their time derivatives. The slices :data:`POSITION`, :data:`ATTITUDE`,
:data:`VELOCITY`, :data:`ATTITUDE_RATE` and :func:`split_state` name the parts.

Inputs
------
``inputs`` has shape ``(4,)``: ``(u_F, tau_x, tau_y, tau_z)``, total thrust (N) and
body torques (N m) of eq. (10).

Disturbances
------------
``disturbance_accel`` has shape ``(6,)``: ``(d_px, d_py, d_pz)`` in m/s^2, then
``(d_phi1, d_phi2, d_phi3)`` in rad/s^2. They are the accelerations ``d_p / m`` and
``d_eta / I`` of eq. (11): (53) and (56) give them in m/s^2 and rad/s^2, which is what
Assumption 3 bounds, so they are added as they are, never divided again by the mass
or the inertia.

Model
-----
(11a)-(11c) as printed mix up the rates; the standard model the paper cites is used,
with ``drag(w) = w |w|`` (the paper prints ``w^2``, which pushes the wrong way for
``w < 0``) and the coefficients under (11)::

    phi''   = a_phi1 theta' psi' - a_phi2 theta' Omega_r - a_phi3 drag(phi')
              + tau_x / I11 + d_phi1                                          (11a)
    theta'' = a_theta1 phi' psi' + a_theta2 phi' Omega_r - a_theta3 drag(theta')
              + tau_y / I22 + d_phi2                                          (11b)
    psi''   = a_psi1 phi' theta' - a_psi2 drag(psi') + tau_z / I33 + d_phi3   (11c)
    x''     = (c_psi s_theta c_phi + s_psi s_phi) u_F / m - (K_px / m) x' + d_px  (11d)
    y''     = (s_psi s_theta c_phi - c_psi s_phi) u_F / m - (K_py / m) y' + d_py  (11e)
    z''     = -g + c_theta c_phi u_F / m - (K_pz / m) z' + d_pz                 (11f)

``a_phi1 = (I22 - I33)/I11``, ``a_phi2 = J_r/I11``, ``a_phi3 = K_phi1/I11``,
``a_theta1 = (I33 - I11)/I22``, ``a_theta2 = J_r/I22``, ``a_theta3 = K_phi2/I22``,
``a_psi1 = (I11 - I22)/I33``, ``a_psi2 = K_phi3/I33``, and the rotor speed sum
``Omega_r = w1 - w2 + w3 - w4`` from the inverted mixer (10).

Everything is pure and works in the floating dtype of its arguments (float32 by
default, float64 when ``jax_enable_x64`` is on); ``jit``, ``vmap`` and ``grad`` apply.
"""

from __future__ import annotations

import functools
import math
import operator
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax._arrays import reverse_pass_boundary, unstack

Array = jax.Array

__all__ = [
    "ATTITUDE",
    "ATTITUDE_RATE",
    "POSITION",
    "STATE_SIZE",
    "VELOCITY",
    "PlantParams",
    "StateBlocks",
    "attitude_trig",
    "derivatives",
    "hover_inputs",
    "hover_state",
    "make_state",
    "allocate",
    "mixer",
    "nominal_params",
    "rk4_step",
    "rk4_step_parts",
    "rotor_speed_limit",
    "rotor_speed_sum",
    "rotor_speeds",
    "rotor_speeds_squared",
    "saturate_inputs",
    "signed_square",
    "speed_sum",
    "split_state",
    "state_blocks",
]

STATE_SIZE = 12
POSITION = slice(0, 3)
"""``(x, y, z)`` in the state vector."""
ATTITUDE = slice(3, 6)
"""``(phi, theta, psi)`` in the state vector."""
VELOCITY = slice(6, 9)
"""``(x', y', z')`` in the state vector."""
ATTITUDE_RATE = slice(9, 12)
"""``(phi', theta', psi')`` in the state vector."""

# Nominal constants (Section V). The rotor inertia is not given: 2.8385e-5 kg m^2 is the
# value of the parameter set the paper's constants come from (its rho_b and rho_c are
# that set's thrust and drag factors scaled by 100).
_NOMINAL_MASS = 0.74  # kg
_NOMINAL_INERTIA = (0.4e-2, 0.4e-2, 0.84e-2)  # kg m^2
_NOMINAL_DRAG_POSITION = (1e-2, 1e-2, 1e-2)  # N s / m
_NOMINAL_DRAG_ATTITUDE = (1.2e-2, 1.2e-2, 1.2e-2)  # N s / rad (as printed)
_NOMINAL_THRUST_FACTOR = 3e-3  # N s^2
_NOMINAL_DRAG_FACTOR = 3.24e-2  # N m s^2
_NOMINAL_ARM_LENGTH = 0.21  # m
_NOMINAL_ROTOR_INERTIA = 2.8385e-5  # kg m^2
_GRAVITY = 9.81  # m / s^2


def _default_float(dtype=None):
    if dtype is None:
        return jnp.dtype(jnp.result_type(float))
    return jnp.dtype(dtype)


class PlantParams(NamedTuple):
    """Physical parameters of the quadrotor (all leaves are arrays).

    mass: ``()`` ``m`` in kg.
    inertia: ``(3,)`` ``(I11, I22, I33)`` in kg m^2 (diagonal inertia ``I``).
    drag_position: ``(3,)`` ``K_p = (K_px, K_py, K_pz)`` in N s/m.
    drag_attitude: ``(3,)`` ``K_phi = (K_phi1, K_phi2, K_phi3)``, multiplies
        ``drag(w) = w |w|``.
    thrust_factor: ``()`` ``rho_b`` in N s^2 (thrust per squared rotor speed).
    drag_factor: ``()`` ``rho_c`` in N m s^2 (yaw torque per squared rotor speed).
    arm_length: ``()`` ``d`` in m (the ``+`` of eq. (10)).
    rotor_inertia: ``()`` ``J_r`` in kg m^2.
    gravity: ``()`` ``g`` in m/s^2.
    layout: ``None``, the paper's ``+`` at ``arm_length`` (eq. (10) in closed form), or a
        :class:`fojax.rotors.Layout` (any four rotors; static, no leaves): the allocation
        that :func:`mixer`, :func:`rotor_speeds_squared`, :func:`saturate_inputs` and the
        gyroscopic ``Omega_r`` use.
    """

    mass: Array
    inertia: Array
    drag_position: Array
    drag_attitude: Array
    thrust_factor: Array
    drag_factor: Array
    arm_length: Array
    rotor_inertia: Array
    gravity: Array
    layout: Any = None


def nominal_params(dtype=None) -> PlantParams:
    """The paper's nominal constants (Section V).

    ``m = 0.74``, ``I = diag(0.4, 0.4, 0.84) 1e-2``, ``K_p = diag(1, 1, 1) 1e-2``,
    ``K_phi = diag(1.2, 1.2, 1.2) 1e-2``, ``rho_b = 3e-3``, ``rho_c = 3.24e-2``,
    ``d = 0.21``, ``J_r = 2.8385e-5``, ``g = 9.81`` (SI units).

    dtype: floating dtype of the leaves; default float32, or float64 with x64 enabled.
    """
    dtype = _default_float(dtype)

    def arr(value):
        return jnp.asarray(value, dtype=dtype)

    return PlantParams(
        mass=arr(_NOMINAL_MASS),
        inertia=arr(_NOMINAL_INERTIA),
        drag_position=arr(_NOMINAL_DRAG_POSITION),
        drag_attitude=arr(_NOMINAL_DRAG_ATTITUDE),
        thrust_factor=arr(_NOMINAL_THRUST_FACTOR),
        drag_factor=arr(_NOMINAL_DRAG_FACTOR),
        arm_length=arr(_NOMINAL_ARM_LENGTH),
        rotor_inertia=arr(_NOMINAL_ROTOR_INERTIA),
        gravity=arr(_GRAVITY),
    )


# ------------------------------------------------------------------------------- state


def rotor_speed_limit(thrust_to_weight: float = 2.0, params: PlantParams | None = None):
    """``w_max`` (rad/s) at which four rotors give ``thrust_to_weight`` times the weight of
    ``params`` (default :func:`nominal_params`: m = 0.74 kg, rho_b = 3e-3
    N s^2; anything with ``mass``, ``gravity`` and ``thrust_factor``, e.g. a
    :class:`fojax.vehicle.Vehicle`): ``w_max = sqrt(thrust_to_weight m g / (4 rho_b))``,
    34.78 rad/s at 2.

    Requirement files ask for rotor-limited actuators by this ratio (docs/model.md)."""
    if not (isinstance(thrust_to_weight, int | float) and thrust_to_weight > 0):
        raise ValueError(f"thrust_to_weight must be a number > 0, got {thrust_to_weight!r}")
    params = nominal_params() if params is None else params
    weight = float(params.mass) * float(params.gravity)
    return math.sqrt(thrust_to_weight * weight / (4.0 * float(params.thrust_factor)))


def make_state(position, attitude, velocity=None, attitude_rate=None, dtype=None) -> Array:
    """Assemble the ``(12,)`` state from its parts (each ``(3,)``; rates default to 0)."""
    dtype = _default_float(dtype)
    position = jnp.asarray(position, dtype=dtype)
    attitude = jnp.asarray(attitude, dtype=dtype)
    velocity = jnp.zeros(3, dtype) if velocity is None else jnp.asarray(velocity, dtype)
    attitude_rate = (
        jnp.zeros(3, dtype) if attitude_rate is None else jnp.asarray(attitude_rate, dtype)
    )
    return jnp.concatenate([position, attitude, velocity, attitude_rate])


def split_state(state: Array) -> tuple[Array, Array, Array, Array]:
    """Split a ``(..., 12)`` state into ``(position, attitude, velocity, attitude_rate)``.

    Each part has shape ``(..., 3)``: ``X_p``, ``eta = (phi, theta, psi)``, ``X_p'``,
    ``eta'``.
    """
    return (
        state[..., POSITION],
        state[..., ATTITUDE],
        state[..., VELOCITY],
        state[..., ATTITUDE_RATE],
    )


# ------------------------------------------------------------------------------- mixer


def mixer(params: PlantParams) -> Array:
    """The ``(4, 4)`` matrix ``M`` of eq. (10): ``(u_F, tau) = M (w1^2, w2^2, w3^2, w4^2)``.

    ::

        [[ rho_b,     rho_b,    rho_b,     rho_b   ],
         [ 0,        -rho_b d,  0,         rho_b d ],
         [-rho_b d,   0,        rho_b d,   0       ],
         [-rho_c,     rho_c,   -rho_c,     rho_c   ]]

    With a ``params.layout``, ``diag(rho_b, rho_b, rho_b, rho_c) G`` of
    :mod:`fojax.rotors`.
    """
    b = params.thrust_factor
    c = params.drag_factor
    if params.layout is not None:
        geometry = jnp.asarray(params.layout.geometry(), b.dtype)
        return jnp.stack([b, b, b, c])[:, None] * geometry
    bd = b * params.arm_length
    zero = jnp.zeros_like(bd)
    return jnp.stack(
        [
            jnp.stack([b, b, b, b]),
            jnp.stack([zero, -bd, zero, bd]),
            jnp.stack([-bd, zero, bd, zero]),
            jnp.stack([-c, c, -c, c]),
        ]
    )


def rotor_speeds_squared(params: PlantParams, inputs: Array) -> Array:
    """Squared rotor speeds ``w_i^2`` (``(4,)``, rad^2/s^2) that produce ``inputs``.

    Inverts eq. (10) in closed form; the result may be negative when ``inputs`` is
    not achievable (no clipping here).

    inputs: ``(4,)`` ``(u_F, tau_x, tau_y, tau_z)``.
    """
    return jnp.stack(_rotor_speeds_squared_parts(params, *_unstack(inputs, 4)))


def _rotor_speeds_squared_parts(params: PlantParams, thrust, tau_x, tau_y, tau_z) -> tuple:
    """:func:`rotor_speeds_squared` from the four scalar inputs (four scalars)."""
    b = params.thrust_factor
    c = params.drag_factor
    if params.layout is not None:
        return _combine(params.layout.inverse(), (thrust / b, tau_x / b, tau_y / b, tau_z / c))
    bd = b * params.arm_length
    common = thrust / (4.0 * b)
    yaw = tau_z / (4.0 * c)
    roll = tau_x / (2.0 * bd)
    pitch = tau_y / (2.0 * bd)
    return (
        common - pitch - yaw,
        common - roll + yaw,
        common + pitch - yaw,
        common + roll + yaw,
    )


def saturate_inputs(params: PlantParams, inputs: tuple, speed_limit: float) -> tuple:
    """Rotor-limited actuators: ``inputs`` (four scalars ``(u_F, tau_x, tau_y, tau_z)``)
    as the rotors can produce them. Each squared rotor speed of the inverted mixer (10)
    is clipped to ``[0, speed_limit^2]`` (a rotor neither reverses nor exceeds its
    largest speed) and the thrust and torques are recomputed from the clipped speeds
    through the mixer. Returns four scalars."""
    squared = _rotor_speeds_squared_parts(params, *inputs)
    clipped = tuple(jnp.clip(w, 0.0, speed_limit * speed_limit) for w in squared)
    return allocate(params, clipped)


def allocate(params: PlantParams, squared: tuple) -> tuple:
    """The thrust and torques ``(u_F, tau_x, tau_y, tau_z)`` (four scalars) of the squared
    rotor speeds ``squared`` (four scalars): the mixer (10), or the ``params.layout``'s."""
    b, c = params.thrust_factor, params.drag_factor
    if params.layout is not None:
        scaled = _combine(params.layout.geometry(), squared)
        return (b * scaled[0], b * scaled[1], b * scaled[2], c * scaled[3])
    w1, w2, w3, w4 = squared
    bd = b * params.arm_length
    return (b * (w1 + w2 + w3 + w4), bd * (w4 - w2), bd * (w3 - w1), c * (w2 - w1 + w4 - w3))


def _combine(matrix, values: tuple) -> tuple:
    """``matrix @ values`` for a constant ``(4, 4)`` matrix (Python floats, zero entries
    skipped) and four scalars (any shape): four scalars."""
    out = []
    for row in matrix:
        terms = [float(m) * v for m, v in zip(row, values, strict=True) if float(m) != 0.0]
        out.append(functools.reduce(operator.add, terms))
    return tuple(out)


def _safe_sqrt_nonnegative(x: Array) -> Array:
    """``sqrt(max(x, 0))`` with a zero (not NaN/inf) gradient for ``x <= 0``."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def rotor_speed_sum(params: PlantParams, inputs: Array) -> Array:
    """``Omega_r = w1 - w2 + w3 - w4`` (rad/s, ``()``) of eq. (11).

    ``w_i = sqrt(max(w_i^2, 0))`` with ``w_i^2`` from :func:`rotor_speeds_squared`.
    Gradient-safe: the gradient is finite everywhere (zero where a rotor is clipped;
    at ``w_i^2 = 0`` the one-sided infinite derivative of the square root is replaced
    by zero).
    """
    return _rotor_speed_sum_parts(params, inputs[0], inputs[1], inputs[2], inputs[3])


def hover_inputs(params: PlantParams) -> Array:
    """Equilibrium inputs ``(m g, 0, 0, 0)`` (``(4,)``) for level hover."""
    thrust = params.mass * params.gravity
    zero = jnp.zeros_like(thrust)
    return jnp.stack([thrust, zero, zero, zero])


def hover_state(position=(0.0, 0.0, 0.0), yaw=0.0, dtype=None) -> Array:
    """A ``(12,)`` level hover state at ``position`` with heading ``yaw``, all rates zero."""
    dtype = _default_float(dtype)
    attitude = jnp.stack([jnp.zeros((), dtype), jnp.zeros((), dtype), jnp.asarray(yaw, dtype)])
    return make_state(position, attitude, dtype=dtype)


# ------------------------------------------------------------------------- dynamics
#
# The dynamics work on the state's four blocks of three, position, attitude, velocity
# and angular rate, each ``(3,)`` for one draw or ``(3, draws)`` for a batch (the
# batch's axes last: every row a contiguous run over the draws, computed in one
# vectorised pass). Per RK4 stage that is a handful of arrays, not one per entry: the
# number of kernels, and of values kept for the reverse pass, follows the number of
# arrays (docs/performance.md). Each acceleration ends with its division by the mass
# or the inertia: XLA keeps a division it would have to duplicate as a kernel of its
# own, so an RK4 stage's accelerations are computed once and read by the next stage.


def signed_square(w: Array) -> Array:
    """``drag(w) = w |w|``: the aerodynamic drag pushes against ``w`` (the paper prints
    ``w^2``); the same form in the plant and in the controllers' nominal model."""
    return w * jnp.abs(w)


def _unstack(vector: Array, size: int) -> tuple:
    return tuple(vector[i] for i in range(size))


def _rotor_speed_sum_parts(params: PlantParams, thrust, tau_x, tau_y, tau_z) -> Array:
    """:func:`rotor_speed_sum` from the four scalar inputs."""
    squared = _rotor_speeds_squared_parts(params, thrust, tau_x, tau_y, tau_z)
    return speed_sum(params, rotor_speeds(squared))


def rotor_speeds(squared: tuple) -> tuple:
    """``w_i = sqrt(max(w_i^2, 0))`` of four squared rotor speeds, gradient-safe (zero
    gradient where a rotor is clipped or at rest)."""
    return tuple(_safe_sqrt_nonnegative(w2) for w2 in squared)


def speed_sum(params: PlantParams, speeds: tuple) -> Array:
    """``Omega_r`` of the rotor speeds ``speeds`` (four scalars, rad/s): ``w1 - w2 + w3 -
    w4`` (eq. (11)), or ``sum_i s_i w_i`` with the ``params.layout``'s spins."""
    if params.layout is not None:
        terms = [v if s > 0 else -v for s, v in zip(params.layout.spins, speeds, strict=True)]
        return functools.reduce(operator.add, terms)
    return speeds[0] - speeds[1] + speeds[2] - speeds[3]


def attitude_trig(phi: Array, theta: Array, psi: Array) -> tuple:
    """``(cos phi, sin phi, cos theta, sin theta, cos psi, sin psi)`` of the Euler angles."""
    return (jnp.cos(phi), jnp.sin(phi), jnp.cos(theta), jnp.sin(theta), jnp.cos(psi), jnp.sin(psi))


# Taylor coefficients of (cos d - 1) / d^2 and sin(d) / d in powers of d^2, to d^14 and
# d^15: the next terms are below 1e-13 for |d| <= 1 and below float64 rounding for
# |d| <= 0.3.
_COS_M1_SERIES = tuple((-1) ** n / math.factorial(2 * n) for n in range(1, 8))
_SIN_SERIES = tuple((-1) ** n / math.factorial(2 * n + 1) for n in range(8))


def _horner(x: Array, coefficients: tuple) -> Array:
    result = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        result = c + x * result
    return result


def _derivative_parts(
    params: PlantParams, x: tuple, trig: tuple, inputs: tuple, omega_r, d: tuple, k_p, k_phi
) -> tuple:
    """Eq. (11) entry by entry: ``x`` the 12 state entries, ``trig`` the 6 of
    :func:`attitude_trig` (``cos phi, sin phi, cos theta, ...``), ``inputs`` 4, ``d`` 6,
    ``k_p``/``k_phi`` 3 each; ``omega_r`` the rotor speed sum of ``inputs``. Each entry
    is ``()`` or a batch's shape. Returns the 12 entries of the derivative.

    Written entry by entry, the arithmetic of each acceleration is one expression that
    XLA compiles alike in every program (one device or partitioned over several); the
    same arithmetic on ``(3, draws)`` blocks was fused, and so rounded, differently by a
    partitioned program. Each acceleration ends with its division by the mass or the
    inertia: XLA keeps such a division as a kernel of its own, so an RK4 stage's
    accelerations are computed once and read by the next stage.
    """
    vx, vy, vz = x[6], x[7], x[8]
    p, q, r = x[9], x[10], x[11]
    thrust, tau_x, tau_y, tau_z = inputs
    i11, i22, i33 = unstack(params.inertia)
    j_r = params.rotor_inertia
    m = params.mass

    # Eq. (11a)-(11c) multiplied through by the inertia, divided once at the end.
    roll_accel = (
        (i22 - i33) * q * r - j_r * q * omega_r - k_phi[0] * signed_square(p) + tau_x
    ) / i11 + d[3]
    pitch_accel = (
        (i33 - i11) * p * r + j_r * p * omega_r - k_phi[1] * signed_square(q) + tau_y
    ) / i22 + d[4]
    yaw_accel = ((i11 - i22) * p * q - k_phi[2] * signed_square(r) + tau_z) / i33 + d[5]

    # Eq. (11d)-(11f), forces divided by the mass at the end.
    c_phi, s_phi, c_theta, s_theta, c_psi, s_psi = trig
    s_theta_c_phi = s_theta * c_phi
    x_accel = ((c_psi * s_theta_c_phi + s_psi * s_phi) * thrust - k_p[0] * vx) / m + d[0]
    y_accel = ((s_psi * s_theta_c_phi - c_psi * s_phi) * thrust - k_p[1] * vy) / m + d[1]
    z_accel = (c_theta * c_phi * thrust - k_p[2] * vz) / m - params.gravity + d[2]
    return (vx, vy, vz, p, q, r, x_accel, y_accel, z_accel, roll_accel, pitch_accel, yaw_accel)


def _rotate(trig: tuple, increments: tuple) -> tuple:
    """:func:`attitude_trig` of the angles shifted by small ``increments`` (3 entries),
    from ``trig`` (the 6 entries ``(cos phi, sin phi, cos theta, ...)``).

    ``cos(a + d) = cos a + (cos a (cos d - 1) - sin a sin d)`` and likewise for ``sin``,
    with ``cos d - 1`` and ``sin d`` from their Taylor series (:data:`_SIN_SERIES`):
    float64-exact for ``|d| <= 0.3``, within ``1e-13`` for ``|d| <= 1`` (an angular rate
    of 1000 rad/s over a 1 ms step). Multiply-adds instead of the sine and cosine that
    XLA's CPU backend evaluates at ~2 ns each, and again in every kernel reading them.
    """
    out = []
    for i, d in enumerate(increments):
        c, s = trig[2 * i], trig[2 * i + 1]
        d2 = d * d
        cos_m1 = d2 * _horner(d2, _COS_M1_SERIES)
        sin_d = d * _horner(d2, _SIN_SERIES)
        out += [c + (c * cos_m1 - s * sin_d), s + (s * cos_m1 + c * sin_d)]
    return tuple(out)


def derivatives(
    params: PlantParams,
    state: Array,
    inputs: Array,
    disturbance_accel: Array,
    drag_position: Array | None = None,
    drag_attitude: Array | None = None,
) -> Array:
    """Time derivative ``(12,)`` of the state under eq. (11) (read as in the module docstring).

    params: :class:`PlantParams`.
    state: ``(12,)`` ``(x, y, z, phi, theta, psi, x', y', z', phi', theta', psi')``.
    inputs: ``(4,)`` ``(u_F, tau_x, tau_y, tau_z)``.
    disturbance_accel: ``(6,)`` ``(d_px, d_py, d_pz)`` m/s^2 and
        ``(d_phi1, d_phi2, d_phi3)`` rad/s^2, added directly (see the module docstring).
    drag_position: optional ``(3,)`` override of ``K_p`` (time-varying drag).
    drag_attitude: optional ``(3,)`` override of ``K_phi`` (time-varying drag).

    Returns ``(x', y', z', phi', theta', psi', x'', y'', z'', phi'', theta'', psi'')``.
    Every array may carry a batch's axes last (``state`` ``(12, draws)``).
    """
    k_p = params.drag_position if drag_position is None else drag_position
    k_phi = params.drag_attitude if drag_attitude is None else drag_attitude
    u = unstack(inputs)
    omega_r = _rotor_speed_sum_parts(params, *u)
    x = unstack(state)
    trig = attitude_trig(*x[3:6])
    parts = _derivative_parts(
        params, x, trig, u, omega_r, unstack(disturbance_accel), unstack(k_p), unstack(k_phi)
    )
    return jnp.stack([jnp.broadcast_to(v, x[0].shape).astype(state.dtype) for v in parts])


class StateBlocks(NamedTuple):
    """The state's four blocks, each ``(3,)`` (a batch's axes last): position
    ``(x, y, z)``, attitude ``(phi, theta, psi)``, their rates."""

    position: Array
    attitude: Array
    velocity: Array
    rate: Array


def state_blocks(state: Array | StateBlocks) -> StateBlocks:
    """The :class:`StateBlocks` of a ``(12,) + batch`` state (blocks as they are)."""
    if isinstance(state, StateBlocks):
        return state
    return StateBlocks(state[0:3], state[3:6], state[6:9], state[9:12])


def rk4_step_parts(
    params: PlantParams,
    state: tuple,
    inputs: tuple,
    disturbance: tuple,
    dt,
    drag_position: tuple,
    drag_attitude: tuple,
    trig: tuple,
    omega_r: Array | None = None,
) -> tuple:
    """One classical Runge-Kutta step of eq. (11), entry by entry: ``state`` the 12
    entries, ``inputs`` 4, ``disturbance`` 6, the drag coefficients 3 each, held over
    the step, ``trig`` the 6 entries of :func:`attitude_trig` of the attitude (``cos
    phi, sin phi, cos theta, ...``); each entry ``()`` or a batch's shape. ``omega_r``:
    the gyroscopic rotor speed held over the step (default: that of ``inputs``, rotors
    at their commanded speeds). Returns the 12 entries of the next state.

    The closed-loop simulator carries the state and the trig of its attitude entry by
    entry (see :func:`_derivative_parts`), the trig computed once per step; the stages'
    trig follows from it by :func:`_rotate` (the attitude moves by at most ``dt`` times
    the rates in a stage), so a step evaluates no sine or cosine itself. Each stage's
    state, trig and derivative is a boundary of the reverse pass
    (:func:`fojax._arrays.reverse_pass_boundary`).
    """
    dtype = state[0].dtype
    if omega_r is None:  # the inputs are held over the step
        omega_r = _rotor_speed_sum_parts(params, *inputs)
    dt = jnp.asarray(dt, dtype=dtype)

    def f(x, x_trig):
        return _derivative_parts(
            params, x, x_trig, inputs, omega_r, disturbance, drag_position, drag_attitude
        )

    def stage(h, k):
        """The derivative at the state ``x + h k``."""
        x = reverse_pass_boundary(tuple(xi + h * ki for xi, ki in zip(state, k, strict=True)))
        x_trig = reverse_pass_boundary(_rotate(trig, tuple(h * ki for ki in k[3:6])))
        return reverse_pass_boundary(f(x, x_trig))

    k1 = reverse_pass_boundary(f(state, trig))
    k2 = stage(0.5 * dt, k1)
    k3 = stage(0.5 * dt, k2)
    k4 = stage(dt, k3)
    return tuple(
        (xi + dt / 6.0 * (a + 2.0 * b + 2.0 * c + e)).astype(dtype)
        for xi, a, b, c, e in zip(state, k1, k2, k3, k4, strict=True)
    )


def rk4_step(
    params: PlantParams,
    state: Array,
    inputs: Array,
    disturbance_accel: Array,
    dt,
    drag_position: Array | None = None,
    drag_attitude: Array | None = None,
) -> Array:
    """One classical Runge-Kutta step of :func:`derivatives` (``(12,)`` -> ``(12,)``).

    ``inputs``, ``disturbance_accel`` and the drag overrides are held constant over the
    step (zero-order hold), so the step is fourth-order accurate in ``dt`` for smooth
    dynamics. Pure: ``jit``, ``vmap`` and ``grad`` apply; every array may carry a
    batch's axes last.
    """
    k_p = params.drag_position if drag_position is None else drag_position
    k_phi = params.drag_attitude if drag_attitude is None else drag_attitude
    x = unstack(state)
    parts = rk4_step_parts(
        params,
        x,
        unstack(inputs),
        unstack(disturbance_accel),
        dt,
        unstack(k_p),
        unstack(k_phi),
        attitude_trig(*x[3:6]),
    )
    return jnp.stack(parts)
