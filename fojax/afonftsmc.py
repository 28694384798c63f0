"""The paper's adaptive fractional-order nonsingular fast terminal sliding mode control.

Position loop eqs. (12)-(28), attitude loop eqs. (37)-(47) of Labbadi & Cherkaoui,
read as in ``docs/model.md``. Axes are ordered ``(x, y, z, phi, theta, psi)``; every
gain is a ``(6,)`` array (one value per axis) so gains can be batched, sampled and
differentiated.

Sliding surface per axis (16)-(18), (37)-(39), with ``e1`` the tracking error and
``e2`` its rate:

    S = e2 + D^(gamma1 - 1)[c1 sig^(p/q)(e1)] + I^gamma2[c2 sig^phi(e1)]

``D^(gamma1 - 1)`` is a fractional integral of order ``1 - gamma1`` (notes item 7).
The time derivative of each fractional term is read from the same fractional memory
(``D^gamma1 f = d/dt D^(gamma1 - 1) f``, and ``d/dt I^gamma2 g``), so the equivalent
control cancels exactly the derivative of ``S`` as defined. Reaching law (24), (42)-(44)
with the adaptive bound ``b0 + b1|e1| + b2|e2| + mu`` and laws (25)-(27), (45)-(47)
``b_dot = eta * (|S|, |e1||S|, |e2||S|)`` (notes item 8), integrated by forward Euler
at the control step.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax import fractional, plant
from fojax.controller import (
    SWITCHING_FUNCTIONS,
    Bounds,
    ControlInfo,
    Observation,
    attitude_drift_parts,
    check_bounds,
    command_filter_update,
    signed_power,
    switching,
    thrust_and_attitude_parts,
)

Array = jax.Array


class AFONFTSMCGains(NamedTuple):
    """Gains of the AFONFTSMC, each ``(6,)`` over ``(x, y, z, phi, theta, psi)``.

    surface_c1: ``c_i1`` (> 0), weight of the ``p/q`` term of the surface.
    surface_c2: ``c_i2`` (> 0), weight of the ``phi`` term.
    reaching_h1: ``hbar_i1`` (> 0), switching gain.
    reaching_h2: ``hbar_i2`` (> 0), proportional reaching gain.
    power: ``phi_i`` (> 0), exponent of the ``I^gamma2`` term.
    ratio: ``p_i / q_i``, with ``1 < p/q < 2`` (nonsingular).
    gamma1: ``gamma_i1`` in ``(0, 1)``.
    gamma2: ``gamma_i2`` in ``(0, 1)``.
    adaptation: ``(6, 3)`` rates ``(eta_i0, eta_i1, eta_i2)`` (>= 0).
    mu: ``mu`` (> 0), the small constant of the reaching law.
    boundary_layer: width of ``sat``/``tanh`` switching (> 0; unused by ``sign``).
    """

    surface_c1: Array
    surface_c2: Array
    reaching_h1: Array
    reaching_h2: Array
    power: Array
    ratio: Array
    gamma1: Array
    gamma2: Array
    adaptation: Array
    mu: Array
    boundary_layer: Array


def paper_gains(dtype: Any = None) -> AFONFTSMCGains:
    """The gains of Section V (notes item 16), ``mu = 1e-3``.

    Boundary layer (``sat``/``tanh`` only): 0.05 for position, 0.2 for attitude. In a
    boundary layer the switching term is a gain ``h1 / width`` on ``S``; the discrete
    loop at ``dt`` stays free of a period-2 limit cycle while ``h1 dt / width < 2``,
    which the paper's attitude ``h1 = 156.4`` breaks below a width of 0.078 at 1 ms.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype

    def axes(position_xy, position_z, attitude):
        return jnp.asarray([position_xy, position_xy, position_z] + [attitude] * 3, dtype)

    return AFONFTSMCGains(
        surface_c1=axes(0.1797, 4.4265, 35.5118),
        surface_c2=axes(0.1769, 3.7049, 3.9926),
        reaching_h1=axes(2.6044, 16.1251, 156.4373),
        reaching_h2=axes(0.2204, 0.8876, 5.8670),
        power=jnp.full((6,), 3.0, dtype),
        ratio=jnp.full((6,), 11.0 / 10.0, dtype),
        gamma1=jnp.full((6,), 0.99, dtype),
        gamma2=jnp.full((6,), 0.01, dtype),
        adaptation=jnp.full((6, 3), 0.01, dtype),
        mu=jnp.full((6,), 1e-3, dtype),
        boundary_layer=axes(0.05, 0.05, 0.2),
    )


GAINS_BOUNDS = {
    "surface_c1": Bounds(0.0),
    "surface_c2": Bounds(0.0),
    "reaching_h1": Bounds(0.0),
    "reaching_h2": Bounds(0.0),
    "power": Bounds(0.0),
    "ratio": Bounds(1.0, 2.0, symbol="p/q"),
    "gamma1": Bounds(0.0, 1.0),
    "gamma2": Bounds(0.0, 1.0),
    "adaptation": Bounds(0.0, include_low=True),
    "mu": Bounds(0.0),
    "boundary_layer": Bounds(0.0),
}
"""The paper's constraints on each gain (Section IV): positive gains, ``1 < p/q < 2``,
``0 < gamma < 1``, non-negative adaptation rates."""

GAINS_SHAPES = {name: ((6, 3) if name == "adaptation" else (6,)) for name in GAINS_BOUNDS}


def check_gains(gains: AFONFTSMCGains) -> None:
    """Raise ``ValueError`` naming every entry that breaks the paper's constraints."""
    check_bounds(gains, GAINS_BOUNDS, GAINS_SHAPES, "AFONFTSMC")


class AFONFTSMCParams(NamedTuple):
    """Per-run constants: gains, the nominal model and precomputed weights."""

    gains: AFONFTSMCGains
    model: plant.PlantParams
    surface_weights: Any  # fractional weights of the 12-channel surface memory
    filter_transition: Array  # (2, 2) command filter, exact zero-order-hold update
    filter_input: Array  # (2,)


class AFONFTSMCState(NamedTuple):
    """Controller memory.

    surface_memory: the fractional memory of the 12 surface signals, channels
        ``c1 sig^(p/q)(e1)`` for ``(x, y, z, phi, theta, psi)`` then
        ``c2 sig^phi(e1)`` for the same axes (:class:`fojax.fractional.IntegralWithRate`:
        each channel gives its fractional integral and that integral's time derivative).
    adaptive: ``(6, 3)`` estimates ``(b0, b1, b2)`` per axis before the previous
        step's update; the update (25)-(27)/(45)-(47) is applied at the start of the
        next step from the three quantities below, so it reads stored values only.
    previous_surface, previous_error, previous_error_rate: ``(6,)`` ``S``, ``e1``,
        ``e2`` of the previous step (zeros before the first).
    command_filter: ``(2, 2)`` rows ``(phi, theta)``, columns ``(value, rate)``.
    last_inputs: ``(4,)`` the previous command (for the gyroscopic term).
    """

    surface_memory: Any
    adaptive: Array
    previous_surface: Array
    previous_error: Array
    previous_error_rate: Array
    command_filter: Array
    last_inputs: Array


@dataclasses.dataclass(frozen=True)
class AFONFTSMC:
    """The paper's controller (see the module docstring).

    Args:
        dt: control and plant step (s).
        horizon: run length (s), sizes the fractional memory.
        fractional_method: ``"soe"`` (accurate default) or ``"oustaloup"`` (the
            paper's CRONE filters, Remark 4) or ``"gl"``.
        fractional_options: extra options of the fractional operator, as a tuple of
            ``(name, value)`` pairs.
        switching: ``"sign"`` (the paper), ``"sat"`` or ``"tanh"``.
        filter_frequency: natural frequency (rad/s) of the second-order command filter
            that supplies ``phi_r, theta_r`` and their derivatives (notes item 11).
        filter_damping: its damping ratio.
    """

    dt: float = 1e-3
    horizon: float = 80.0
    fractional_method: str = "soe"
    fractional_options: tuple = ()
    switching: str = "sign"
    filter_frequency: float = 50.0
    filter_damping: float = 1.0

    name = "afonftsmc"
    gains_type = AFONFTSMCGains
    gains_bounds = GAINS_BOUNDS

    def __post_init__(self) -> None:
        if self.switching not in SWITCHING_FUNCTIONS:
            raise ValueError(
                f"unknown switching function {self.switching!r}; choose one of "
                f"{SWITCHING_FUNCTIONS}"
            )
        for label, value in (
            ("dt", self.dt),
            ("horizon", self.horizon),
            ("filter_frequency", self.filter_frequency),
            ("filter_damping", self.filter_damping),
        ):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        # Validates the method and its options before anything is traced.
        self.operator  # noqa: B018

    # -- gains ----------------------------------------------------------------------
    @staticmethod
    def default_gains(dtype: Any = None) -> AFONFTSMCGains:
        """The paper's gains (:func:`paper_gains`)."""
        return paper_gains(dtype)

    @staticmethod
    def check_gains(gains: AFONFTSMCGains) -> None:
        """Raise ``ValueError`` if ``gains`` break the paper's constraints."""
        check_gains(gains)

    @staticmethod
    def reaching_time_bound(gains: AFONFTSMCGains, initial_surface: Array) -> Array:
        """Finite-time bound of eq. (34) on reaching ``S = 0``, per axis ``(..., 6)``.

        Lemma 1 with ``V = S^2 / 2``, ``lambda_1 = sqrt(2) (hbar_1 + mu)``,
        ``lambda_2 = 2 hbar_2`` and ``V' <= -lambda_1 V^(1/2) - lambda_2 V``, (33), gives
        ``t_r <= (2 / lambda_2) ln((lambda_2 V0^(1/2) + lambda_1) / lambda_1)``
        ``= (1 / hbar_2) ln(1 + hbar_2 |S(0)| / (hbar_1 + mu))``. (34) as printed swaps
        ``lambda_1`` and ``lambda_2``; this is the form Lemma 1 gives. The adaptive
        estimation errors of the paper's ``V(t_0)`` are taken as zero (their true
        bounds are unknown), and the bound assumes the adaptive term dominates the
        disturbance, so it is a reference value, not a guarantee for every draw.
        """
        h1 = jnp.asarray(gains.reaching_h1) + jnp.asarray(gains.mu)
        h2 = jnp.asarray(gains.reaching_h2)
        return jnp.log1p(h2 * jnp.abs(initial_surface) / h1) / h2

    @property
    def operator(self):
        return fractional.make_operator(
            self.fractional_method, self.dt, self.horizon, **dict(self.fractional_options)
        )

    @property
    def _memory(self) -> fractional.IntegralWithRate:
        return fractional.IntegralWithRate(self.operator)

    def prepare(self, gains: AFONFTSMCGains, model: plant.PlantParams) -> AFONFTSMCParams:
        dtype = jnp.asarray(gains.surface_c1).dtype
        # Channels 0-5, the p/q terms: integral of order 1 - gamma1 (the S term) and its
        # time derivative, the derivative of order gamma1. Channels 6-11, the phi terms:
        # integral of order gamma2 and its time derivative, the derivative of order
        # 1 - gamma2. All twelve share one memory (one array of modes).
        integral_orders = jnp.concatenate([1.0 - gains.gamma1, gains.gamma2])
        surface_weights = self._memory.coefficients(integral_orders, dtype)
        transition, gain = command_filter_update(
            self.filter_frequency, self.filter_damping, self.dt, dtype
        )
        return AFONFTSMCParams(
            gains=gains,
            model=model,
            surface_weights=surface_weights,
            filter_transition=transition,
            filter_input=gain,
        )

    def init(self, params: AFONFTSMCParams, observation: Observation) -> AFONFTSMCState:
        dtype = observation.state.dtype
        attitude = observation.state[3:5]
        return AFONFTSMCState(
            surface_memory=self._memory.init((12,), dtype),
            adaptive=jnp.zeros((6, 3), dtype),
            previous_surface=jnp.zeros((6,), dtype),
            previous_error=jnp.zeros((6,), dtype),
            previous_error_rate=jnp.zeros((6,), dtype),
            command_filter=jnp.stack([attitude, jnp.zeros_like(attitude)], axis=1),
            last_inputs=plant.hover_inputs(params.model).astype(dtype),
        )

    # The step works on scalars, one per axis (tuples of six), and stacks only what it
    # returns or stores: under ``vmap`` each scalar is one contiguous ``(draws,)`` array,
    # which XLA's CPU backend computes in one vectorised loop, where a small stacked
    # vector became a branchy loop recomputing its shared operands per element
    # (docs/performance.md, "Where the time goes").

    def _surface(self, params, memory, error, error_rate):
        """Surfaces (16)-(18)/(37)-(39) of the six axes and the fractional part of dS/dt.

        error, error_rate: six scalars each, ``e1``, ``e2`` over
        ``(x, y, z, phi, theta, psi)``. Returns the memory and six scalars each of ``S``
        and of the fractional terms of ``dS/dt``.
        """
        g = params.gains
        p_terms = [g.surface_c1[i] * signed_power(e, g.ratio[i]) for i, e in enumerate(error)]
        phi_terms = [g.surface_c2[i] * signed_power(e, g.power[i]) for i, e in enumerate(error)]
        signals = jnp.stack(p_terms + phi_terms)
        memory, (integral, rate) = self._memory.step(params.surface_weights, memory, signals)
        surface = tuple(error_rate[i] + integral[i] + integral[6 + i] for i in range(6))
        dsurface = tuple(rate[i] + rate[6 + i] for i in range(6))
        return memory, surface, dsurface

    def _adapt(self, params, state):
        """The adaptive update (25)-(27)/(45)-(47) owed by the previous step (Euler)."""
        magnitude = jnp.abs(state.previous_surface)
        regressor = jnp.stack(
            [
                jnp.ones_like(magnitude),
                jnp.abs(state.previous_error),
                jnp.abs(state.previous_error_rate),
            ],
            axis=1,
        )
        return state.adaptive + self.dt * params.gains.adaptation * regressor * magnitude[:, None]

    def _reaching(self, params, adaptive, surface, error, error_rate):
        """Reaching law (24)/(42)-(44) with the adaptive bound, six scalars."""
        g = params.gains
        out = []
        for i in range(6):
            sw = switching(self.switching, surface[i], g.boundary_layer[i])
            bound = (
                adaptive[i, 0]
                + adaptive[i, 1] * jnp.abs(error[i])
                + adaptive[i, 2] * jnp.abs(error_rate[i])
            )
            out.append(
                -g.reaching_h1[i] * sw - g.reaching_h2[i] * surface[i] - (bound + g.mu[i]) * sw
            )
        return tuple(out)

    def step(
        self, params: AFONFTSMCParams, state: AFONFTSMCState, observation: Observation
    ) -> tuple[AFONFTSMCState, Array, ControlInfo]:
        model = params.model
        x = observation.state
        ref, ref_vel, ref_acc = (
            observation.reference,
            observation.reference_velocity,
            observation.reference_acceleration,
        )
        yaw_reference = ref[3]

        # Errors of both loops, eqs. (14)-(15), (40)-(41). The attitude loop tracks the
        # command filter's output (notes item 11), known at the start of the step.
        filt = state.command_filter
        reference = (ref[0], ref[1], ref[2], filt[0, 0], filt[1, 0], yaw_reference)
        reference_rate = (ref_vel[0], ref_vel[1], ref_vel[2], filt[0, 1], filt[1, 1], ref_vel[3])
        error = tuple(x[i] - reference[i] for i in range(6))
        error_rate = tuple(x[6 + i] - reference_rate[i] for i in range(6))

        # Surfaces and reaching laws of the six axes.
        memory, surface, dsurface = self._surface(params, state.surface_memory, error, error_rate)
        adaptive = self._adapt(params, state)
        reaching = self._reaching(params, adaptive, surface, error, error_rate)

        # Position loop, eqs. (23)-(28), (12)-(13).
        virtual = [
            model.drag_position[i] / model.mass * x[6 + i] + ref_acc[i] - dsurface[i] + reaching[i]
            for i in range(3)
        ]
        thrust, phi_r, theta_r = thrust_and_attitude_parts(
            model, *virtual, jnp.cos(yaw_reference), jnp.sin(yaw_reference)
        )

        # Command filter (notes item 11): phi_r, theta_r and two derivatives.
        w, zeta = self.filter_frequency, self.filter_damping
        tilt_reference = (phi_r, theta_r)
        filtered_accel = [
            w * w * (tilt_reference[i] - filt[i, 0]) - 2.0 * zeta * w * filt[i, 1] for i in range(2)
        ]
        transition, gain = params.filter_transition, params.filter_input
        command_filter = jnp.stack(
            [
                jnp.stack(
                    [
                        filt[i, 0] * transition[j, 0]
                        + filt[i, 1] * transition[j, 1]
                        + tilt_reference[i] * gain[j]
                        for j in range(2)
                    ]
                )
                for i in range(2)
            ]
        )

        # Attitude loop, eqs. (42)-(44).
        last = state.last_inputs
        omega_r = plant.rotor_speed_sum(model, last)
        drift = attitude_drift_parts(model, x[9], x[10], x[11], omega_r)
        attitude_reference_accel = (filtered_accel[0], filtered_accel[1], ref_acc[3])
        torque = [
            model.inertia[i]
            * (-drift[i] + attitude_reference_accel[i] - dsurface[3 + i] + reaching[3 + i])
            for i in range(3)
        ]

        inputs = jnp.stack([thrust, *torque])
        surfaces = jnp.stack(surface)
        new_state = AFONFTSMCState(
            surface_memory=memory,
            adaptive=adaptive,
            previous_surface=surfaces,
            previous_error=jnp.stack(error),
            previous_error_rate=jnp.stack(error_rate),
            command_filter=command_filter,
            last_inputs=inputs,
        )
        info = ControlInfo(
            surfaces=surfaces,
            attitude_reference=jnp.stack([filt[0, 0], filt[1, 0], yaw_reference]),
            adaptive=adaptive,
        )
        return new_state, inputs, info
