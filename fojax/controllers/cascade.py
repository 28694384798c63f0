"""The cascade every controller shares: position loop, eq. (13), command filter,
attitude loop, around a control law (:class:`fojax.controllers.ControlLaw`).

Per axis ``i`` of ``(x, y, z, phi, theta, psi)`` the nominal model is the double
integrator ``e1'' = a_i + d_i`` once its terms are cancelled (``e1 = q_i - q_i^r``,
``e2 = q_i' - q_i^r'``, ``a_i`` the law's commanded error acceleration, ``d_i`` the
unknown disturbance, eq. (11) with Assumption 3):

* position, eqs. (11d)-(11f), (23) and (13): the virtual control (the commanded
  acceleration without gravity) is ``v = x_r'' + (K_p / m) x' + a`` with the nominal
  model's drag (the drag term of (23)); eq. (13) turns ``v`` into the thrust ``u_F``
  and the attitude commands ``(phi_r, theta_r)``;
* ``phi_r, theta_r`` pass through a second-order command filter
  ``r_f'' = w^2 (r - r_f) - 2 zeta w r_f'`` (``w = filter_frequency``, ``zeta =
  filter_damping``), discretised exactly (zero-order hold) and started at the initial
  attitude at rest: the attitude loop needs the first two derivatives of its
  reference, which eq. (13) does not provide. ``(r_f, r_f', r_f'')`` are the attitude
  references and their derivatives; ``psi_r`` comes from the reference;
* attitude, eqs. (11a)-(11c) and (42)-(44): ``tau = I (eta_r'' - F(eta') + a)`` with
  ``F`` the nominal coupling and drag accelerations, the gyroscopic ``Omega_r`` from the
  previous command through the inverted mixer (10).

The attitude loop tracks the filter's output at the start of the step, so the errors
of all six axes are known before the law runs, and the law sees them at once, as
``(6,)`` arrays.

Layout: one draw's arrays, or a batch's with its axes last (``state`` ``(12, draws)``,
errors ``(6, draws)``, the command filter ``(2, 2, draws)``). With the batch last every
per-axis quantity is one array whose rows are contiguous runs over the draws, which
XLA's CPU backend computes in vectorised passes; a rollout under ``vmap`` (batch first)
would make them ``(draws, 6)`` arrays with a minor axis of six, which it does not
vectorise (docs/performance.md).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax import plant
from fojax._arrays import unstack
from fojax.controllers.base import (
    ControlInfo,
    ControlLaw,
    Observation,
    check_positive,
)

Array = jax.Array

__all__ = [
    "Cascade",
    "broadcast_batch",
    "CascadeParams",
    "CascadeState",
    "as_controller",
    "attitude_drift",
    "command_filter_update",
    "thrust_and_attitude",
]


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


def attitude_drift(model: Any, p: Array, q: Array, r: Array, rotor_speed_sum: Array):
    """The nominal model's coupling and drag accelerations of eq. (11a)-(11c), from the
    three rates ``(phi', theta', psi')`` as scalars: the bracket of eqs. (42)-(44)
    without the torques, ``{a_phi1 theta' psi' - a_phi2 theta' Omega_r - a_phi3
    drag(phi'), ...}`` with the drag ``w |w|`` of :func:`fojax.plant.signed_square`.

    Returns the three accelerations as a tuple (each of the rates' shape).
    """
    i11, i22, i33 = model.inertia[0], model.inertia[1], model.inertia[2]
    k = model.drag_attitude
    j_r = model.rotor_inertia
    square = plant.signed_square
    return (
        (i22 - i33) / i11 * q * r - j_r / i11 * q * rotor_speed_sum - k[0] / i11 * square(p),
        (i33 - i11) / i22 * p * r + j_r / i22 * p * rotor_speed_sum - k[1] / i22 * square(q),
        (i11 - i22) / i33 * p * q - k[2] / i33 * square(r),
    )


def thrust_and_attitude(
    model: Any,
    vx: Array,
    vy: Array,
    vz: Array,
    cos_yaw: Array,
    sin_yaw: Array,
    thrust_floor: float = 0.1,
) -> tuple[Array, Array, Array]:
    """Eq. (13) on scalars: thrust ``u_F`` and ``(phi_r, theta_r)`` from the virtual
    control ``v = (vx, vy, vz)`` (the commanded acceleration without gravity) and the
    reference yaw's cosine and sine.

    The vertical term ``v_z + g`` is kept above ``thrust_floor g`` so that the
    quadrotor never asks to fly upside down. The guard is active whenever the
    commanded vertical acceleration is below ``-(1 - thrust_floor) g``: rarely under
    smooth switching, but under the paper's ``sgn`` the z loop's switching gain
    (``hbar_z1 = 16.1 > g``) drives it in about two thirds of the steps.
    """
    g = model.gravity
    lift = jnp.maximum(vz + g, thrust_floor * g)
    theta_r = jnp.arctan((cos_yaw * vx + sin_yaw * vy) / lift)
    phi_r = jnp.arctan(jnp.cos(theta_r) * (sin_yaw * vx - cos_yaw * vy) / lift)
    thrust = model.mass * jnp.sqrt(vx * vx + vy * vy + lift * lift)
    return thrust, phi_r, theta_r


class CascadeParams(NamedTuple):
    """Per-run constants: the nominal model, the law's parameters, the command filter.

    law: what the law's ``prepare`` returned (its gains and precomputed weights).
    filter_transition: ``(2, 2)``, filter_input: ``(2,)``: the exact zero-order-hold
    update of the command filter ``(value, rate)``.
    """

    model: plant.PlantParams
    law: Any
    filter_transition: Array
    filter_input: Array


class CascadeState(NamedTuple):
    """Controller memory.

    law: the law's state (fractional memories, adaptive estimates) or ``()``.
    command_filter: ``(2, 2)`` rows ``(phi, theta)``, columns ``(value, rate)``.
    last_inputs: the previous command (for the gyroscopic term), its four entries
        ``(u_F, tau_x, tau_y, tau_z)`` (each ``()``, or the batch's shape). Kept apart:
        stacked, the stack would be the one reader of the command's arithmetic, which
        XLA fuses into one unvectorised concatenation kernel.
    """

    law: Any
    command_filter: Array
    last_inputs: Array


@dataclasses.dataclass(frozen=True)
class Cascade:
    """Position loop -> eq. (13) -> command filter -> attitude loop, around ``law``.

    Args:
        law: the :class:`fojax.controllers.ControlLaw` (it carries ``dt`` and
            ``horizon``).
        filter_frequency: natural frequency (rad/s) of the attitude command filter.
        filter_damping: its damping ratio.
        thrust_floor: eq. (13)'s guard, ``v_z + g >= thrust_floor g`` (a fraction of
            ``g`` in ``(0, 1]``).
    """

    law: ControlLaw
    filter_frequency: float = 50.0
    filter_damping: float = 1.0
    thrust_floor: float = 0.1

    def __post_init__(self) -> None:
        if not isinstance(self.law, ControlLaw):
            raise TypeError(
                f"Cascade needs a ControlLaw, got {type(self.law).__name__}: build one with "
                "fojax.make_controller(name, ...) or pass e.g. fojax.controllers.AFONFTSMC()"
            )
        check_positive(self, "filter_frequency", "filter_damping", "thrust_floor")
        if self.thrust_floor > 1:
            raise ValueError(f"thrust_floor must lie in (0, 1], got {self.thrust_floor!r}")

    # -- what follows from the law ---------------------------------------------------------
    @property
    def name(self) -> str:
        return self.law.name

    @property
    def dt(self) -> float:
        return self.law.dt

    @property
    def horizon(self) -> float:
        return self.law.horizon

    @property
    def GAINS(self):  # noqa: N802 (the law's class constant)
        return self.law.GAINS

    def default_gains(self, dtype: Any = None) -> Any:
        return self.law.default_gains(dtype)

    def check_gains(self, gains: Any) -> None:
        self.law.check_gains(gains)

    # -- the controller interface (fojax.controllers.base) -------------------------------
    def prepare(
        self, gains: Any, model: plant.PlantParams, batch_shape: tuple[int, ...] = ()
    ) -> CascadeParams:
        """Per-run constants; ``gains`` shared by the batch or given per draw
        (:meth:`fojax.controllers.GainSpec.broadcast`)."""
        dtype = jnp.asarray(jax.tree.leaves(gains)[0]).dtype
        gains = self.law.GAINS.broadcast(gains, batch_shape)
        transition, gain = command_filter_update(
            self.filter_frequency, self.filter_damping, self.dt, dtype
        )
        return CascadeParams(model, self.law.prepare(gains, dtype), transition, gain)

    def init(self, params: CascadeParams, observation: Observation) -> CascadeState:
        """The state at ``t = 0``: the law's state of one draw broadcast over the batch
        (``observation.state`` ``(12,) + batch`` or its blocks)."""
        state = plant.state_blocks(observation.state)
        dtype = state.position.dtype
        batch = state.position.shape[1:]
        attitude = state.attitude[0:2]
        return CascadeState(
            law=broadcast_batch(self.law.init(params.law, dtype), batch, floating_only=True),
            command_filter=jnp.stack([attitude, jnp.zeros_like(attitude)], axis=1),
            last_inputs=tuple(
                broadcast_batch(plant.hover_inputs(params.model).astype(dtype), batch)
            ),
        )

    def step(
        self, params: CascadeParams, state: CascadeState, observation: Observation
    ) -> tuple[CascadeState, Array, ControlInfo]:
        model = params.model
        x = [v for block in plant.state_blocks(observation.state) for v in unstack(block)]
        ref, ref_vel, ref_acc = (
            observation.reference,
            observation.reference_velocity,
            observation.reference_acceleration,
        )
        yaw_reference = ref[3]

        # Errors of both loops, eqs. (14)-(15), (40)-(41), (6,) + batch: the attitude
        # loop tracks the command filter's output, known at the start of the step.
        filt = state.command_filter  # (2, 2) + batch: rows (phi, theta), (value, rate)
        reference = (ref[0], ref[1], ref[2], filt[0, 0], filt[1, 0], yaw_reference)
        reference_rate = (ref_vel[0], ref_vel[1], ref_vel[2], filt[0, 1], filt[1, 1], ref_vel[3])
        error = jnp.stack([x[i] - reference[i] for i in range(6)])
        error_rate = jnp.stack([x[6 + i] - reference_rate[i] for i in range(6)])
        law_state, out = self.law.step(params.law, state.law, error, error_rate)
        accel = _axes(out.acceleration)

        # Position loop, eqs. (23) and (13).
        virtual = [
            model.drag_position[i] / model.mass * x[6 + i] + ref_acc[i] + accel[i] for i in range(3)
        ]
        thrust, phi_r, theta_r = thrust_and_attitude(
            model, *virtual, jnp.cos(yaw_reference), jnp.sin(yaw_reference), self.thrust_floor
        )

        # Command filter: phi_r, theta_r and their two derivatives. Row by row: a stack
        # of (phi_r, theta_r) would be the one reader of eq. (13)'s arithmetic, which XLA
        # then fuses into a branchy, unvectorised concatenation kernel.
        w, zeta = self.filter_frequency, self.filter_damping
        transition, gain = params.filter_transition, params.filter_input
        filtered_accel, command_filter = [], []
        for i, tilt in enumerate((phi_r, theta_r)):
            value, rate = filt[i, 0], filt[i, 1]
            filtered_accel.append(w * w * (tilt - value) - 2.0 * zeta * w * rate)
            command_filter.append(
                jnp.stack(
                    [
                        value * transition[j, 0] + rate * transition[j, 1] + tilt * gain[j]
                        for j in range(2)
                    ]
                )
            )
        command_filter = jnp.stack(command_filter)

        # Attitude loop, eqs. (42)-(44).
        omega_r = plant.rotor_speed_sum(model, state.last_inputs)
        drift = attitude_drift(model, x[9], x[10], x[11], omega_r)
        attitude_reference_accel = (filtered_accel[0], filtered_accel[1], ref_acc[3])
        torque = [
            model.inertia[i] * (-drift[i] + attitude_reference_accel[i] + accel[3 + i])
            for i in range(3)
        ]

        inputs = (thrust, *torque)
        surfaces = _axes(out.surface)
        if out.adaptive is None:
            adaptive = jnp.zeros((6, 3) + surfaces.shape[1:], surfaces.dtype)
        else:
            adaptive = jnp.broadcast_to(out.adaptive, (6, 3) + surfaces.shape[1:])
        new_state = CascadeState(law_state, command_filter, inputs)
        info = ControlInfo(
            surfaces=surfaces,
            attitude_reference=jnp.stack(
                jnp.broadcast_arrays(filt[0, 0], filt[1, 0], yaw_reference)
            ),
            adaptive=adaptive,
        )
        return new_state, jnp.stack(inputs), info


def _axes(values: Any) -> Array:
    """A law's per-axis output as one ``(6,) + batch`` array (a tuple of six stacked)."""
    if isinstance(values, tuple | list):
        return jnp.stack(jnp.broadcast_arrays(*values))
    return jnp.asarray(values)


def broadcast_batch(
    tree: Any, batch_shape: tuple[int, ...], floating_only: bool = False
) -> Any:
    """Every leaf of ``tree`` (one draw's arrays) repeated over a batch of shape
    ``batch_shape``, the batch's axes last (``(6, 3)`` -> ``(6, 3, draws)``).

    ``floating_only``: integer and boolean leaves stay as they are, shared by the batch
    (a law's step counters: every draw of a batch starts and steps together; a flag
    that is the same for every draw keeps a scalar predicate that XLA vectorises around).
    """
    batch_shape = tuple(batch_shape)
    if not batch_shape:
        return tree

    def repeat(leaf):
        if floating_only and not jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            return leaf
        shape = jnp.shape(leaf)
        expanded = jnp.reshape(leaf, shape + (1,) * len(batch_shape))
        return jnp.broadcast_to(expanded, shape + batch_shape)

    return jax.tree.map(repeat, tree)


def as_controller(controller: Any) -> Any:
    """``controller`` as something :func:`fojax.simulator.rollout` can run: a
    :class:`Cascade` as it is, a :class:`ControlLaw` inside a default :class:`Cascade`,
    any other object with ``prepare``/``init``/``step``/``name`` as it is.

    ``TypeError`` with what to pass instead otherwise (a controller's name, say).
    """
    if isinstance(controller, ControlLaw):
        return Cascade(controller)
    if isinstance(controller, str):
        raise TypeError(
            f"expected a controller object, got the string {controller!r}: build it with "
            f"fojax.make_controller({controller!r}, dt=..., horizon=...)"
        )
    missing = [a for a in ("name", "prepare", "init", "step") if not hasattr(controller, a)]
    if missing:
        raise TypeError(
            f"expected a controller (fojax.make_controller(...)), got "
            f"{type(controller).__name__}, which has no {', '.join(missing)}"
        )
    return controller
