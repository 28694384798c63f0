"""Closed-loop rollout: plant + controller + scenario, one draw, jit/vmap/grad-able.

Per step ``k`` (time ``t_k = k dt``): the reference and its exact derivatives at
``t_k`` (autodiff of the reference function), the controller's update from the
sampled state, then one RK4 step of the plant with the inputs, the disturbance and
the drag coefficients held over the step (zero-order hold).

The time loop is a ``lax.scan`` over blocks of ``save_every`` steps (an inner scan);
one snapshot per block is kept, and each block is rematerialised under ``grad``
(``jax.checkpoint``), so reverse-mode memory grows with the number of blocks, not the
number of steps.

Loop layout (the arithmetic above, in another order): the controller's update for
step ``k + 1`` runs at the end of iteration ``k``, right after the plant step, and
its command and diagnostics travel in the loop carry (the first update runs before
the loop). The plant and the per-step bookkeeping then read the command from the
carry, where it is computed once; when both ran in the same iteration, XLA's CPU
backend recomputed the whole control law inside each of the ~20 kernels that read
the command (every RK4 stage, the rotor speeds, the status flags; see
docs/performance.md). The plant state is carried as its 12 entries (one contiguous
array per entry under ``vmap``), stacked only where a ``(12,)`` array is needed, and
with it the sines and cosines of its attitude, evaluated once per step
(:func:`fojax.plant.rk4_step_parts`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from fojax import plant, scenarios
from fojax.controller import ControlInfo, Observation

Array = jax.Array

# Status flags per draw, as bits of ``Rollout.status``.
NONFINITE = 1  # a state, input or surface became NaN/inf
TILT_LIMIT = 2  # |roll| or |pitch| reached pi/2 (Assumption 1)
ACTUATOR_LIMIT = 4  # the command needed a negative squared rotor speed (mixer (10))
STATUS_NAMES = {NONFINITE: "nonfinite", TILT_LIMIT: "tilt_limit", ACTUATOR_LIMIT: "actuator_limit"}


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """Static settings of a rollout.

    dt: step (s) of the plant integrator and the controller (default 1 ms).
    horizon: simulated time (s); ``round(horizon / dt)`` steps are taken.
    save_every: steps between saved snapshots (and checkpointed blocks).
    """

    dt: float = 1e-3
    horizon: float = 80.0
    save_every: int = 100

    def __post_init__(self) -> None:
        for label, value in (("dt", self.dt), ("horizon", self.horizon)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        if self.dt > self.horizon:
            raise ValueError(f"dt ({self.dt}) must not exceed the horizon ({self.horizon})")
        if not isinstance(self.save_every, int) or self.save_every < 1:
            raise ValueError(f"save_every must be a positive integer, got {self.save_every!r}")
        if self.steps % self.save_every:
            raise ValueError(
                f"save_every ({self.save_every}) must divide the number of steps ({self.steps})"
            )

    @property
    def steps(self) -> int:
        return int(round(self.horizon / self.dt))

    @property
    def blocks(self) -> int:
        return self.steps // self.save_every


class Snapshot(NamedTuple):
    """Saved every ``save_every`` steps (after the step).

    inputs_low, inputs_high: ``(4,)`` the smallest and largest command held over the
    block's ``save_every`` steps (the full-rate envelope, so that a command switching
    at every step shows as the band it fills, not as aliased samples).
    """

    time: Array  # ()
    state: Array  # (12,)
    reference: Array  # (4,)
    inputs: Array  # (4,)
    info: ControlInfo
    inputs_low: Array  # (4,)
    inputs_high: Array  # (4,)


class Rollout(NamedTuple):
    """Result of one draw.

    final_state: ``(12,)``. status: ``()`` int32 bit flags (:data:`STATUS_NAMES`).
    cost: ``()`` integral of squared position and attitude errors (for gradients).
    extra: whatever the per-step accumulator returned (metrics), or ``None``.
    trajectory: :class:`Snapshot` with a leading ``(blocks,)`` axis.
    """

    final_state: Array
    status: Array
    cost: Array
    extra: Any
    trajectory: Snapshot


def _status(state: Array, inputs: Array, info: ControlInfo, params: plant.PlantParams) -> Array:
    finite = (
        jnp.all(jnp.isfinite(state))
        & jnp.all(jnp.isfinite(inputs))
        & jnp.all(jnp.isfinite(info.surfaces))
    )
    tilt = jnp.any(jnp.abs(state[3:5]) >= jnp.pi / 2)
    actuator = jnp.any(plant.rotor_speeds_squared(params, inputs) < 0)
    return (
        jnp.where(finite, 0, NONFINITE)
        | jnp.where(tilt, TILT_LIMIT, 0)
        | jnp.where(actuator, ACTUATOR_LIMIT, 0)
    ).astype(jnp.int32)


def _hold_row(k: Array, horizon: float, hold: float, dt: float, n_rows: int) -> Array:
    """Row of a hold table at step ``k``, from the static layout of ``sample_draw``."""
    hold_steps, _ = scenarios._hold_layout(horizon, hold, dt)
    return jnp.clip(k // hold_steps, 0, n_rows - 1)


def _held_values(scenario: scenarios.Scenario, draw: scenarios.Draw, config: SimulationConfig):
    """``held(k) -> (noise, drag)``: the rows of the draw's tables in force at step ``k``
    (time ``t = k dt``): ``noise`` ``(6,)`` the Gaussian part of
    :func:`fojax.scenarios.disturbance_at`, ``drag`` ``(6,)`` the multipliers of
    :func:`fojax.scenarios.drag_at` (each ``None`` when the scenario has no such table).

    The draw's tables are laid out for ``config.dt`` (``sample_draw(..., dt=config.dt)``),
    so the row of step ``k`` is ``k // hold_steps`` with ``hold_steps`` known before
    tracing (the same row as ``round(t / dt) // hold_steps``). The row then does not
    depend on the draw, and under ``vmap`` each lookup is one slice of the batched
    table instead of a gather per draw. The rollout reads each step's values once, at
    the end of the step before, and carries them: a row of a ``(draws, rows, 6)`` table
    is a strided read that XLA otherwise repeated inside every kernel using it.
    """
    dt = config.dt

    def row_of(table, k, hold):
        row = _hold_row(k, scenario.horizon, hold, dt, table.shape[0])
        return lax.dynamic_index_in_dim(table, row, keepdims=False)

    def held(k):
        noise = row_of(draw.noise_accel, k, scenario.noise_hold) if scenario.has_noise else None
        drag = (
            row_of(draw.drag_multipliers, k, scenario.drag_hold)
            if scenario.has_drag_variation
            else None
        )
        return noise, drag

    return held


def rollout(
    controller: Any,
    gains: Any,
    model: plant.PlantParams,
    scenario: scenarios.Scenario,
    draw: scenarios.Draw,
    config: SimulationConfig,
    accumulator: Any = None,
) -> Rollout:
    """Simulate one draw of ``scenario`` under ``controller`` with ``gains``.

    ``model`` is the nominal plant the controller uses; ``draw.params`` is the
    simulated plant; ``draw`` must be sampled for ``config.dt`` (its tables are read by
    step index). ``accumulator``, if given, is a pair ``(init, update)`` with
    ``init() -> acc`` and ``update(acc, t, state, reference, inputs, info) -> acc``,
    evaluated every step (online metrics). Pure; ``vmap`` over ``draw`` (and
    ``gains``) for Monte Carlo, ``grad`` through ``cost`` or ``extra``.
    """
    dt = config.dt
    dtype = jnp.asarray(draw.params.mass).dtype
    params = controller.prepare(gains, model)
    state0 = scenarios.initial_state(scenario, dtype)

    def reference_at(k):
        """The reference and its two derivatives at step ``k`` (time only: shared by
        every draw under ``vmap``)."""
        t = k.astype(dtype) * dt
        derivatives = scenarios.reference_with_derivatives(scenario.reference, t)
        return t, tuple(d.astype(dtype) for d in derivatives)

    def observe(k, state):
        t, (ref, ref_vel, ref_acc) = reference_at(k)
        return Observation(t, state, ref, ref_vel, ref_acc)

    obs0 = observe(jnp.zeros((), jnp.int32), state0)
    control0 = controller.init(params, obs0)
    # The first control update; later ones run at the end of the iteration before.
    control1, inputs0, info0 = controller.step(params, control0, obs0)
    acc0 = accumulator[0]() if accumulator is not None else None
    held_at = _held_values(scenario, draw, config)

    def one_step(carry, k):
        # state: x_k (12 scalars); inputs, info: the update at t_k; control: the
        # controller state after it.
        state, trig, held, control, inputs, info, status, cost, acc = carry
        t, (reference, _, _) = reference_at(k)
        noise, drag = held
        k_p, k_phi = draw.params.drag_position, draw.params.drag_attitude
        drag_position = tuple(k_p[i] if drag is None else k_p[i] * drag[i] for i in range(3))
        drag_attitude = tuple(
            k_phi[i] if drag is None else k_phi[i] * drag[3 + i] for i in range(3)
        )
        deterministic = scenario.disturbance(t).astype(dtype)  # time only
        disturbance = tuple(
            deterministic[i] if noise is None else deterministic[i] + noise[i].astype(dtype)
            for i in range(6)
        )
        next_state = plant.rk4_step_parts(
            draw.params,
            state,
            tuple(inputs[i] for i in range(4)),
            disturbance,
            dt,
            drag_position,
            drag_attitude,
            tuple(trig[i] for i in range(6)),
        )
        next_trig = jnp.stack(plant.attitude_trig(*next_state[3:6]))
        state_array = jnp.stack(state)
        status = status | _status(jnp.stack(next_state), inputs, info, draw.params)
        position_error = state_array[:3] - reference[:3]
        attitude_error = state_array[3:6] - info.attitude_reference
        cost = cost + dt * (jnp.sum(position_error**2) + jnp.sum(attitude_error**2))
        if accumulator is not None:
            acc = accumulator[1](acc, t, state_array, reference, inputs, info)
        # The control update of step k + 1, from the new state.
        control, next_inputs, next_info = controller.step(
            params, control, observe(k + 1, jnp.stack(next_state))
        )
        carry = (
            next_state,
            next_trig,
            held_at(k + 1),
            control,
            next_inputs,
            next_info,
            status,
            cost,
            acc,
        )
        return carry, (reference, inputs, info)

    @jax.checkpoint
    def block(carry, block_index):
        ks = block_index * config.save_every + jnp.arange(config.save_every)
        carry, (refs, inputs, infos) = lax.scan(one_step, carry, ks)
        t_end = (block_index + 1).astype(dtype) * config.save_every * dt
        last = jax.tree.map(lambda x: x[-1], (refs, inputs, infos))
        snapshot = Snapshot(
            t_end,
            jnp.stack(carry[0]),
            last[0],
            last[1],
            last[2],
            jnp.min(inputs, axis=0),
            jnp.max(inputs, axis=0),
        )
        return carry, snapshot

    state0_parts = tuple(state0[i] for i in range(12))
    carry0 = (
        state0_parts,
        jnp.stack(plant.attitude_trig(*state0_parts[3:6])),
        held_at(jnp.zeros((), jnp.int32)),
        control1,
        inputs0,
        info0,
        jnp.zeros((), jnp.int32),
        jnp.zeros((), dtype),
        acc0,
    )
    (final, _, _, _, _, _, status, cost, acc), trajectory = lax.scan(
        block, carry0, jnp.arange(config.blocks)
    )
    return Rollout(jnp.stack(final), status, cost, acc, trajectory)
