"""The cascade shared by the compared controllers (FL, BSMC, FOBSMC, ANFTSMC).

Every compared controller uses the same plant-model reading as the AFONFTSMC
(``docs/model.md``), so that the comparison is between control laws, not between
models. Per axis ``i`` of ``(x, y, z, phi, theta, psi)`` the nominal model is the
double integrator

    e1'' = a_i + d_i,    e1 = q_i - q_i^r,  e2 = q_i' - q_i^r'

once the model terms are cancelled, where ``a_i`` is the commanded *error*
acceleration that each control law chooses (its ``law`` function), and ``d_i`` the
unknown disturbance (eq. (11) with the disturbances of Assumption 3):

* position, eq. (11d)-(11f) with (13): the virtual control (commanded acceleration
  without gravity, notes item 5) is ``v = x_r'' + b x' + a`` with ``b = K_p / m`` of
  the nominal model (the drag term of (23)); eq. (13) turns ``v`` into ``u_F`` and
  ``(phi_r, theta_r)`` (:func:`fojax.controller.thrust_and_attitude`);
* attitude, eq. (11a)-(11c) (notes items 1, 10): ``tau = I (eta_r'' - F(eta') + a)``
  with ``F`` the coupling and drag terms (:func:`fojax.controller.attitude_drift`),
  the gyroscopic ``Omega_r`` from the previous command through the inverted mixer;
* ``phi_r, theta_r`` pass through the same second-order command filter as the
  AFONFTSMC's (notes item 11): ``r_f'' = w^2 (r - r_f) - 2 zeta w r_f'``, discretised
  exactly, started at the initial attitude at rest; ``(r_f, r_f', r_f'')`` are the
  attitude references and their derivatives. ``psi_r`` comes from the reference.

:class:`Cascade` implements ``prepare``/``init``/``step`` of
:mod:`fojax.controller` around a per-controller ``law``; a subclass supplies
``_init_law`` and ``_law``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax import plant
from fojax.controller import (
    SWITCHING_FUNCTIONS,
    ControlInfo,
    Observation,
    attitude_drift,
    command_filter_update,
    signed_power,
    thrust_and_attitude,
)

Array = jax.Array

POSITION_AXES = slice(0, 3)
ATTITUDE_AXES = slice(3, 6)


def abs_power(value: Array, exponent: Array) -> Array:
    """``|e|^r`` with a zero value and a finite gradient at ``e = 0`` (any ``r > 0``)."""
    return signed_power(jnp.abs(value), exponent)


class CascadeParams(NamedTuple):
    """Per-run constants: the gains, the nominal model, law constants, command filter.

    law: whatever the law precomputes from the gains (fractional weights), or ``()``.
    filter_transition: ``(2, 2)``, filter_input: ``(2,)``: the exact zero-order-hold
    update of the command filter ``(value, rate)``.
    """

    gains: Any
    model: plant.PlantParams
    law: Any
    filter_transition: Array
    filter_input: Array


class CascadeState(NamedTuple):
    """Controller memory.

    law: the law's own state (fractional memories, adaptive estimates) or ``()``.
    command_filter: ``(2, 2)`` rows ``(phi, theta)``, columns ``(value, rate)``.
    last_inputs: ``(4,)`` the previous command (for the gyroscopic term).
    """

    law: Any
    command_filter: Array
    last_inputs: Array


class LawOutput(NamedTuple):
    """What a control law returns for one loop (3 axes).

    acceleration: ``(3,)`` commanded error acceleration ``a`` (m/s^2 or rad/s^2).
    surface: ``(3,)`` the law's sliding variable (or error measure).
    adaptive: ``(3, 3)`` adaptive estimates per axis before this update (zeros when
        the law does not adapt).
    """

    acceleration: Array
    surface: Array
    adaptive: Array


def check_config(controller: Any) -> None:
    """Validate the shared configuration fields before anything is traced."""
    for label in ("dt", "horizon", "filter_frequency", "filter_damping"):
        value = getattr(controller, label)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
    kind = getattr(controller, "switching", None)
    if kind is not None and kind not in SWITCHING_FUNCTIONS:
        raise ValueError(
            f"unknown switching function {kind!r}; choose one of {SWITCHING_FUNCTIONS}"
        )


@dataclasses.dataclass(frozen=True)
class Cascade:
    """Position loop -> eq. (13) -> command filter -> attitude loop, around ``_law``.

    Args:
        dt: control step (s).
        horizon: run length (s) (sizes fractional memories where a law has them).
        filter_frequency: natural frequency (rad/s) of the attitude command filter.
        filter_damping: its damping ratio.
    """

    dt: float = 1e-3
    horizon: float = 80.0
    filter_frequency: float = 50.0
    filter_damping: float = 1.0

    def __post_init__(self) -> None:
        check_config(self)

    # -- what a subclass provides ------------------------------------------------------
    def _prepare_law(self, gains: Any, dtype: Any) -> Any:
        return ()

    def _init_law(self, params: CascadeParams, dtype: Any) -> Any:
        """The law state ``(position part, attitude part)`` at ``t = 0``."""
        return ((), ())

    def _law(
        self, params: CascadeParams, axes: slice, law_state: Any, e1: Array, e2: Array
    ) -> tuple[Any, LawOutput]:
        """``(new law state for these axes, LawOutput)`` for the 3 axes ``axes``."""
        raise NotImplementedError

    def _split_law_state(self, law_state: Any) -> tuple[Any, Any]:
        """``(position part, attitude part)`` of the law state."""
        return law_state

    def _join_law_state(self, position: Any, attitude: Any) -> Any:
        return (position, attitude)

    # -- the protocol of fojax.controller ------------------------------------------------
    def prepare(self, gains: Any, model: plant.PlantParams) -> CascadeParams:
        dtype = jnp.asarray(jax.tree.leaves(gains)[0]).dtype
        transition, gain = command_filter_update(
            self.filter_frequency, self.filter_damping, self.dt, dtype
        )
        return CascadeParams(
            gains=gains,
            model=model,
            law=self._prepare_law(gains, dtype),
            filter_transition=transition,
            filter_input=gain,
        )

    def init(self, params: CascadeParams, observation: Observation) -> CascadeState:
        dtype = observation.state.dtype
        attitude = observation.state[3:5]
        return CascadeState(
            law=self._init_law(params, dtype),
            command_filter=jnp.stack([attitude, jnp.zeros_like(attitude)], axis=1),
            last_inputs=plant.hover_inputs(params.model).astype(dtype),
        )

    def step(
        self, params: CascadeParams, state: CascadeState, observation: Observation
    ) -> tuple[CascadeState, Array, ControlInfo]:
        model = params.model
        x = observation.state
        position, attitude = x[0:3], x[3:6]
        velocity, attitude_rate = x[6:9], x[9:12]
        position_state, attitude_state = self._split_law_state(state.law)

        # Position loop: v = x_r'' + b x' + a (the model's drag cancelled, as in (23)).
        position_error = position - observation.reference[:3]
        velocity_error = velocity - observation.reference_velocity[:3]
        position_state, position_law = self._law(
            params, POSITION_AXES, position_state, position_error, velocity_error
        )
        virtual = (
            model.drag_position / model.mass * velocity
            + observation.reference_acceleration[:3]
            + position_law.acceleration
        )
        yaw_reference = observation.reference[3]
        thrust, tilt_reference = thrust_and_attitude(model, virtual, yaw_reference)

        # Command filter (notes item 11), as in the AFONFTSMC.
        filt = state.command_filter
        w, zeta = self.filter_frequency, self.filter_damping
        filtered_accel = w * w * (tilt_reference - filt[:, 0]) - 2.0 * zeta * w * filt[:, 1]
        attitude_reference = jnp.concatenate([filt[:, 0], yaw_reference[None]])
        attitude_reference_rate = jnp.concatenate([filt[:, 1], observation.reference_velocity[3:4]])
        attitude_reference_accel = jnp.concatenate(
            [filtered_accel, observation.reference_acceleration[3:4]]
        )
        command_filter = (
            filt @ params.filter_transition.T + tilt_reference[:, None] * params.filter_input
        )

        # Attitude loop: tau = I (eta_r'' - F(eta') + a).
        attitude_error = attitude - attitude_reference
        rate_error = attitude_rate - attitude_reference_rate
        attitude_state, attitude_law = self._law(
            params, ATTITUDE_AXES, attitude_state, attitude_error, rate_error
        )
        omega_r = plant.rotor_speed_sum(model, state.last_inputs)
        drift = attitude_drift(model, attitude_rate, omega_r)
        torque = model.inertia * (-drift + attitude_reference_accel + attitude_law.acceleration)

        inputs = jnp.concatenate([thrust[None], torque])
        new_state = CascadeState(
            law=self._join_law_state(position_state, attitude_state),
            command_filter=command_filter,
            last_inputs=inputs,
        )
        info = ControlInfo(
            surfaces=jnp.concatenate([position_law.surface, attitude_law.surface]),
            attitude_reference=attitude_reference,
            adaptive=jnp.concatenate([position_law.adaptive, attitude_law.adaptive]),
        )
        return new_state, inputs, info


def axes_gains(position_xy: float, position_z: float, attitude: float, dtype: Any) -> Array:
    """``(6,)`` per-axis gains: the same value for x and y, z, and all attitude axes."""
    return jnp.asarray([position_xy, position_xy, position_z] + [attitude] * 3, dtype)


def default_dtype(dtype: Any) -> Any:
    return jnp.result_type(float) if dtype is None else dtype
