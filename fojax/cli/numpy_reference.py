"""The closed loop of scenarios 1-2 under AFONFTSMC in plain NumPy, vectorised over draws.

The reference for ``fojax bench``: the same plant (eq. (11) as read in
``docs/model.md``), RK4 at the same step, the AFONFTSMC with the sum-of-exponentials
fractional memory, and the same draws, written as a straightforward NumPy program
whose arrays carry the draws on their leading axis (``(n_draws, ...)``). Nothing here
is compiled; every line is one or a few NumPy calls over all draws at once.

What is reused from fojax, evaluated once to NumPy before the loop: the fractional
weights and the command filter's transition matrix (``AFONFTSMC.prepare``) and the
random tables of each draw (``fojax.scenarios.sample_draw``). The reference (54)-(55)
and the disturbances (53) are re-implemented in closed form, as functions of time
only, once per step for all draws.

:func:`prepare` converts the inputs once; :func:`simulate` is the timed loop.
``tests/test_performance.py`` checks that :func:`rollout` agrees with
``fojax.simulator.rollout`` in float64 on a short horizon.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from fojax import fractional, plant
from fojax.controllers import as_controller

__all__ = ["NumpyRollout", "disturbances_53", "prepare", "reference_54_55", "rollout", "simulate"]


_PLANT_FIELDS = tuple(f for f in plant.PlantParams._fields if f != "layout")


class NumpyRollout(NamedTuple):
    """Final state ``(n, 12)``, status bits ``(n,)`` and cost ``(n,)`` of every draw."""

    final_state: np.ndarray
    status: np.ndarray
    cost: np.ndarray


def reference_54_55(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. (54)-(55) and their exact first two derivatives at time ``t``, each ``(4,)``."""
    w = math.pi / 20.0
    c, s = math.cos(w * t), math.sin(w * t)
    position = np.array([0.5 * c, 0.5 * s, 2.0 - 2.0 * c, 0.5])
    velocity = np.array([-0.5 * w * s, 0.5 * w * c, 2.0 * w * s, 0.0])
    acceleration = np.array([-0.5 * w * w * c, -0.5 * w * w * s, 2.0 * w * w * c, 0.0])
    return position, velocity, acceleration


def disturbances_53(t: float) -> np.ndarray:
    """Eq. (53) as accelerations at time ``t``, ``(6,)``, with its closed windows."""
    d = np.array(
        [
            -(
                0.08 * math.sin(0.11 * t - 3.0403)
                + 0.04 * math.sin(0.5 * t - 13.5)
                + 0.008 * math.sin(1.6 * t - 15.0 * math.pi)
                + 0.006 * math.sin(0.3 * t - 8.6)
            ),
            0.05 * math.sin(0.4 * t) + 0.05 * math.cos(0.7 * t),
            0.05 * math.cos(0.7 * t) + 0.07 * math.sin(0.3),
            0.5 * math.cos(0.4 * t) + 1.0,
            0.5 * math.sin(0.5 * t) + 1.0,
            0.05 * math.sin(0.7 * t) + 0.1,
        ]
    )
    windows = np.array([10.0 <= t <= 30.0, 10.0 <= t <= 50.0] + [0.0 <= t <= 80.0] * 4, dtype=float)
    return d * windows


def _signed_power(value: np.ndarray, exponent: np.ndarray) -> np.ndarray:
    magnitude = np.abs(value)
    nonzero = magnitude > 0
    safe = np.where(nonzero, magnitude, 1.0)
    return np.where(nonzero, np.sign(value) * np.exp(exponent * np.log(safe)), 0.0)


_SWITCHING = {
    "sign": lambda surface, width: np.sign(surface),
    "sat": lambda surface, width: np.clip(surface / width, -1.0, 1.0),
    "tanh": lambda surface, width: np.tanh(surface / width),
}
"""The switching functions of the reaching law, of the surface and the boundary layer."""


def _rotor_speeds_squared(params: dict, inputs):
    """``(n, 4)`` squared rotor speeds of the inverted mixer (10); ``inputs`` ``(n, 4)``,
    ``params`` the plant's (``"thrust_factor"``, ``"drag_factor"``, ``"arm_length"``)."""
    factors = {k: np.asarray(params[k])[..., None] for k in ("thrust_factor", "drag_factor")}
    bd = factors["thrust_factor"] * np.asarray(params["arm_length"])[..., None]
    common = inputs[:, :1] / (4.0 * factors["thrust_factor"])
    yaw = inputs[:, 3:] / (4.0 * factors["drag_factor"])
    tilt = inputs[:, [2, 1]] / (2.0 * bd)  # rotors 1, 2 subtract (tau_y, tau_x); 3, 4 add it
    yaw = np.concatenate([yaw, -yaw], axis=1)  # rotors 1, 3 subtract yaw; 2, 4 add it
    return np.concatenate([common - tilt - yaw, common + tilt - yaw], axis=1)


def _rotor_speed_sum(params: dict, inputs):
    speeds = np.sqrt(np.maximum(_rotor_speeds_squared(params, inputs), 0.0))
    return speeds[:, 0] - speeds[:, 1] + speeds[:, 2] - speeds[:, 3]


def _angular_drift(params: dict, rates, drag_attitude, omega_r):
    """The angular accelerations of eq. (11) without torque ``(n, 3)``: gyroscopic, rotor
    (rotor speed sum ``omega_r``) and quadratic drag terms. ``params``: a plant's, per
    draw (inertia ``(n, 3)``) or nominal (``(3,)``)."""
    inertia, j_r = params["inertia"], params["rotor_inertia"]
    i11, i22, i33 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    roll_rate, pitch_rate, yaw_rate = rates[:, 0], rates[:, 1], rates[:, 2]
    gyroscopic = np.stack(
        [
            (i22 - i33) / i11 * pitch_rate * yaw_rate - j_r / i11 * pitch_rate * omega_r,
            (i33 - i11) / i22 * roll_rate * yaw_rate + j_r / i22 * roll_rate * omega_r,
            (i11 - i22) / i33 * roll_rate * pitch_rate,
        ],
        axis=1,
    )
    return gyroscopic - drag_attitude / inertia * (rates * np.abs(rates))


def _derivatives(p, state, inputs, disturbance, drag_position, drag_attitude, omega_r):
    """Eq. (11) for all draws: ``(n, 12)``. ``p``: dict of per-draw plant arrays."""
    phi, theta, psi = state[:, 3], state[:, 4], state[:, 5]
    angular_accel = (
        _angular_drift(p, state[:, 9:12], drag_attitude, omega_r) + inputs[:, 1:] / p["inertia"]
    )
    c_phi, s_phi = np.cos(phi), np.sin(phi)
    c_theta, s_theta = np.cos(theta), np.sin(theta)
    c_psi, s_psi = np.cos(psi), np.sin(psi)
    specific_thrust = inputs[:, 0] / p["mass"]
    linear_accel = (
        np.stack(
            [
                c_psi * s_theta * c_phi + s_psi * s_phi,
                s_psi * s_theta * c_phi - c_psi * s_phi,
                c_theta * c_phi,
            ],
            axis=1,
        )
        * specific_thrust[:, None]
        - drag_position / p["mass"][:, None] * state[:, 6:9]
    )
    linear_accel[:, 2] -= p["gravity"]
    accel = np.concatenate([linear_accel, angular_accel], axis=1)
    return np.concatenate([state[:, 6:12], accel + disturbance], axis=1)


def prepare(controller, gains, model, draws, dtype=np.float64) -> dict:
    """Everything the loop needs, as NumPy arrays of ``dtype`` (done once, not timed).

    Same arguments as :func:`rollout`; returns a dict of named constants.
    """
    controller = as_controller(controller)
    law = controller.law
    if law.fractional_method != "soe":
        raise ValueError(
            "the NumPy reference implements the 'soe' fractional method only, got "
            f"{law.fractional_method!r}"
        )

    if model.layout is not None or draws.params.layout is not None:
        raise ValueError("the NumPy reference flies the paper's '+' rotors (eq. (10)) only")
    as_np = functools.partial(np.asarray, dtype=dtype)
    params = controller.prepare(gains, model)
    weights = params.law.surface_weights
    operator = law.memory.operator
    assert isinstance(operator, fractional.SumOfExponentials)
    return {
        "dtype": dtype,
        "dt": controller.dt,
        "switching": law.switching,
        "filter_frequency": controller.filter_frequency,
        "filter_damping": controller.filter_damping,
        "gains": {name: as_np(getattr(gains, name)) for name in gains._fields},
        "nominal": {name: as_np(getattr(model, name)) for name in _PLANT_FIELDS},
        "mode_weights": as_np(weights.mode_weights).T,  # (12, modes)
        "taps": as_np(weights.taps),  # (3, modes)
        "readout": as_np(np.stack([np.ones_like(weights.rates), -weights.rates])),  # (2, modes)
        "local": as_np(np.moveaxis(weights.local, -1, 0)),  # (12, 2, 3)
        "decay_m1": as_np(operator._tables["decay_m1"]),  # (modes,)
        "filter_transition": as_np(params.filter_transition),  # (2, 2)
        "filter_input": as_np(params.filter_input),  # (2,)
        "plant": {name: as_np(getattr(draws.params, name)) for name in _PLANT_FIELDS},
        "drag_table": as_np(draws.drag_multipliers),  # (n, rows, 6)
        "noise_table": as_np(draws.noise_accel),  # (n, rows, 6)
    }


def rollout(controller, gains, model, scenario, draws, config, dtype=np.float64) -> NumpyRollout:
    """Simulate every draw of ``draws`` (a batched :class:`fojax.scenarios.Draw`).

    Same arguments as ``jax.vmap(fojax.simulator.rollout)`` over the draws:
    ``controller`` a :class:`fojax.controllers.Cascade` of the AFONFTSMC with the ``"soe"`` method,
    ``gains`` its gains (shared), ``model`` the nominal plant, ``scenario`` scenario 1
    or 2, ``config`` a :class:`fojax.simulator.SimulationConfig` with the controller's
    ``dt``. ``dtype``: the floating type of every array in the loop.
    """
    return simulate(prepare(controller, gains, model, draws, dtype), scenario, config)


def simulate(prepared: dict, scenario, config) -> NumpyRollout:
    """The time loop of :func:`rollout`, from :func:`prepare`'s constants."""
    if scenario.scenario_id not in (1, 2):
        raise ValueError(
            f"the NumPy reference implements scenarios 1 and 2 only, got {scenario.scenario_id}"
        )
    if abs(config.dt - prepared["dt"]) > 1e-15:
        raise ValueError(
            f"config.dt ({config.dt}) must equal the controller's dt ({prepared['dt']})"
        )
    dtype, dt, g = prepared["dtype"], config.dt, prepared["gains"]
    n = prepared["plant"]["mass"].shape[0]

    state, modes, u_prev, u_prev2, adaptive, command_filter, last_inputs = _initial(
        prepared, scenario, n
    )
    status = np.zeros(n, np.int32)
    cost = np.zeros(n, dtype)

    for k in range(config.steps):
        ref, ref_vel, ref_acc = (np.asarray(a, dtype) for a in reference_54_55(k * dt))

        # ---- controller: errors of the six axes
        attitude_reference, error, error_rate = _errors(state, command_filter, ref, ref_vel, dtype)

        # ---- fractional memory: 12 channels, integral and its rate
        u = np.concatenate(
            [
                g["surface_c1"] * _signed_power(error, g["ratio"]),
                g["surface_c2"] * _signed_power(error, g["power"]),
            ],
            axis=1,
        )
        if k == 0:
            integral = rate = np.zeros((n, 12), dtype)
        else:
            integral, rate, modes = _memory_step(prepared, modes, (u, u_prev, u_prev2), k)
        u_prev2, u_prev = u_prev, u
        surface = error_rate + integral[:, :6] + integral[:, 6:]
        dsurface = rate[:, :6] + rate[:, 6:]

        # ---- reaching law and adaptive bound
        reaching, adaptive = _reaching_law(prepared, surface, error, error_rate, adaptive, dt)

        # ---- position loop, eq. (13)
        thrust, tilt_reference = _position_loop(
            prepared["nominal"], state, ref, ref_acc, dsurface, reaching
        )

        # ---- command filter and attitude loop
        terms = (ref_acc, dsurface, reaching)
        torque, command_filter = _attitude_loop(
            prepared, state, command_filter, tilt_reference, terms, last_inputs
        )
        inputs = last_inputs = np.concatenate([thrust[:, None], torque], axis=1)

        # ---- plant: RK4 with inputs, disturbance and drag held over the step
        next_state = _plant_step(prepared, scenario, state, inputs, k, dt)

        # ---- status and cost
        status |= _status_bits(prepared["plant"], next_state, inputs, surface)
        position_error = state[:, :3] - ref[:3]
        attitude_error = state[:, 3:6] - attitude_reference
        cost = cost + dt * (np.sum(position_error**2, axis=1) + np.sum(attitude_error**2, axis=1))
        state = next_state

    return NumpyRollout(state, status.astype(np.int32), cost)


def _memory_step(prepared: dict, modes, samples, k: int):
    """The fractional memory's 12 channels at step ``k >= 1``: ``(integral, rate,
    modes)`` from the inputs ``samples = (u, u_prev, u_prev2)``, each ``(n, 12)``."""
    u, u_prev, u_prev2 = samples
    samples = (u, u_prev, u_prev2 if k > 1 else 2.0 * u_prev - u)  # each (n, 12)
    history = modes @ prepared["readout"].T  # (n, 12, 2)
    local, taps = prepared["local"], prepared["taps"]
    outputs = history + sum(local[:, :, i] * samples[i][:, :, None] for i in range(3))
    increment = prepared["mode_weights"] * sum(taps[i] * samples[i][:, :, None] for i in range(3))
    modes = modes + (prepared["decay_m1"] * modes + increment)
    return outputs[..., 0], outputs[..., 1], modes


def _reaching_law(prepared: dict, surface, error, error_rate, adaptive, dt: float):
    """The reaching law with its adaptive bound, and the bound's next estimates."""
    g = prepared["gains"]
    sw = _SWITCHING[prepared["switching"]](surface, g["boundary_layer"])
    a0, a1, a2 = np.moveaxis(adaptive, 2, 0)
    bound = a0 + a1 * np.abs(error) + a2 * np.abs(error_rate)
    reaching = -g["reaching_h1"] * sw - g["reaching_h2"] * surface - (bound + g["mu"]) * sw
    regressor = np.stack([np.ones_like(error), np.abs(error), np.abs(error_rate)], axis=2)
    adaptive = adaptive + dt * g["adaptation"] * regressor * np.abs(surface)[:, :, None]
    return reaching, adaptive


def _position_loop(nominal: dict, state, ref, ref_acc, dsurface, reaching):
    """Eq. (13): the thrust ``(n,)`` and the tilt reference ``(n, 2)`` (roll, pitch)."""
    virtual = (
        nominal["drag_position"] / nominal["mass"] * state[:, 6:9]
        + ref_acc[:3]
        - dsurface[:, :3]
        + reaching[:, :3]
    )
    gravity = nominal["gravity"]
    lift = np.maximum(virtual[:, 2] + gravity, 0.1 * gravity)
    c_psi, s_psi = math.cos(ref[3]), math.sin(ref[3])
    vx, vy = virtual[:, 0], virtual[:, 1]
    theta_r = np.arctan((c_psi * vx + s_psi * vy) / lift)
    phi_r = np.arctan(np.cos(theta_r) * (s_psi * vx - c_psi * vy) / lift)
    thrust = nominal["mass"] * np.sqrt(vx * vx + vy * vy + lift * lift)
    return thrust, np.stack([phi_r, theta_r], axis=1)


def _attitude_loop(prepared: dict, state, command_filter, tilt_reference, terms, last_inputs):
    """The command filter's step and the attitude loop's torques ``(n, 3)``: returns
    ``(torque, next command_filter)``; ``terms``: ``(ref_acc, dsurface, reaching)``."""
    ref_acc, dsurface, reaching = terms
    nominal, dtype, n = prepared["nominal"], prepared["dtype"], state.shape[0]
    w, zeta = prepared["filter_frequency"], prepared["filter_damping"]
    filtered_accel = (
        w * w * (tilt_reference - command_filter[:, :, 0])
        - 2.0 * zeta * w * command_filter[:, :, 1]
    )
    attitude_reference_accel = np.concatenate(
        [filtered_accel, np.full((n, 1), ref_acc[3], dtype)], axis=1
    )
    command_filter = (
        command_filter @ prepared["filter_transition"].T
        + tilt_reference[:, :, None] * prepared["filter_input"]
    )
    omega_r_model = _rotor_speed_sum(nominal, last_inputs)  # from the previous step's inputs
    drift = _angular_drift(nominal, state[:, 9:12], nominal["drag_attitude"], omega_r_model)
    torque = nominal["inertia"] * (
        -drift + attitude_reference_accel - dsurface[:, 3:] + reaching[:, 3:]
    )
    return torque, command_filter


def _status_bits(plant_params: dict, next_state, inputs, surface):
    """The step's status bits ``(n,)``: 1 nonfinite, 2 tilt limit, 4 actuator limit."""
    finite = np.all(np.isfinite(np.concatenate([next_state, inputs, surface], axis=1)), axis=1)
    tilt = np.any(np.abs(next_state[:, 3:5]) >= math.pi / 2, axis=1)
    actuator = np.any(_rotor_speeds_squared(plant_params, inputs) < 0, axis=1)
    return np.where(finite, 0, 1) | np.where(tilt, 2, 0) | np.where(actuator, 4, 0)


def _errors(state, command_filter, ref, ref_vel, dtype):
    """The attitude reference ``(n, 3)`` and the six axes' errors and error rates."""
    n = state.shape[0]
    reference, reference_rate = (
        np.concatenate(
            [np.broadcast_to(r[:3], (n, 3)), command_filter[:, :, i], np.full((n, 1), r[3], dtype)],
            axis=1,
        )
        for i, r in enumerate((ref, ref_vel))
    )
    return reference[:, 3:], state[:, :6] - reference, state[:, 6:12] - reference_rate


def _plant_step(prepared: dict, scenario, state, inputs, k: int, dt: float):
    """The plant's RK4 step ``k`` of :func:`_derivatives`, with the inputs, the
    disturbance and the drag held over the step."""
    plant_params = prepared["plant"]

    def held_row(table, hold: float):  # the table's row of step k, each held ``hold`` s
        return table[:, min(k // max(1, round(hold / dt)), table.shape[1] - 1)]

    disturbance = np.asarray(disturbances_53(k * dt), prepared["dtype"]) + held_row(
        prepared["noise_table"], scenario.noise_hold
    )
    multipliers = held_row(prepared["drag_table"], scenario.drag_hold)
    drag_position = plant_params["drag_position"] * multipliers[:, :3]
    drag_attitude = plant_params["drag_attitude"] * multipliers[:, 3:]
    omega_r = _rotor_speed_sum(plant_params, inputs)
    held = (inputs, disturbance, drag_position, drag_attitude, omega_r)
    k1 = _derivatives(plant_params, state, *held)
    k2 = _derivatives(plant_params, state + 0.5 * dt * k1, *held)
    k3 = _derivatives(plant_params, state + 0.5 * dt * k2, *held)
    k4 = _derivatives(plant_params, state + dt * k3, *held)
    return state + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def _initial(prepared: dict, scenario, n: int):
    """The loop's state at ``t = 0``: plant state, memory modes, the last two memory
    inputs, adaptive estimates, command filter, last inputs (hover thrust)."""
    dtype, nominal = prepared["dtype"], prepared["nominal"]
    state = np.zeros((n, 12), dtype)
    state[:, :6] = np.concatenate([scenario.initial_position, scenario.initial_attitude])
    modes = np.zeros((n, 12, prepared["decay_m1"].shape[0]), dtype)
    command_filter = np.stack([state[:, 3:5], np.zeros((n, 2), dtype)], axis=2)
    last_inputs = np.zeros((n, 4), dtype)
    last_inputs[:, 0] = nominal["mass"] * nominal["gravity"]
    u_prev, u_prev2, adaptive = (np.zeros(shape, dtype) for shape in ((n, 12), (n, 12), (n, 6, 3)))
    return state, modes, u_prev, u_prev2, adaptive, command_filter, last_inputs
