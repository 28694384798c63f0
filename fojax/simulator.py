"""Closed-loop rollout: plant + controller + scenario over a batch of draws, jit/grad-able.

Per step ``k`` (time ``t_k = k dt``): the reference and its exact derivatives at
``t_k`` (autodiff of the reference function), the controller's update from the
sampled state, then one RK4 step of the plant with the inputs, the disturbance and
the drag coefficients held over the step (zero-order hold). What the rollout records
beyond its snapshots (metrics, a tuning cost, the status flags) is folded in by
observers (:mod:`fojax.observers`).

**Batch last.** :func:`rollout` runs one draw or a batch of draws in one program: the
draw's arrays with the batch's axes last (:func:`fojax.scenarios.sample_draws`: the
state ``(12, draws)``, the errors ``(6, draws)``, the fractional memory ``(modes, 12,
draws)``). Every per-axis quantity is then one array whose rows are contiguous runs
over the draws, computed in vectorised passes, and the step is a few dozen arrays
rather than hundreds of per-draw scalars: fewer kernels, fewer residuals under
``grad`` and less to compile (docs/performance.md). The same code runs one draw
(batch shape ``()``); the controller's law and the observers are written for one
draw and run unchanged on the batch (:class:`fojax.controllers.ControlLaw`).

The time loop is a ``lax.scan`` over blocks of ``save_every`` steps (an inner scan);
one snapshot per block is kept, and each block is rematerialised under ``grad``
(``jax.checkpoint``), so reverse-mode memory grows with the number of blocks, not the
number of steps.

Loop layout (the arithmetic above, in another order): the controller's update for
step ``k + 1`` runs at the end of iteration ``k``, right after the plant step, and
its command and diagnostics travel in the loop carry (the first update runs before
the loop). The plant and the per-step bookkeeping then read the command from the
carry, where it is computed once (XLA's CPU backend otherwise recomputes an operand
inside every kernel reading it; see docs/performance.md). With the plant state the
carry holds the sines and cosines of its attitude, evaluated once per step
(:func:`fojax.plant.rk4_step_blocks`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from fojax import observers, plant, rotors, scenarios
from fojax._arrays import KEPT, unstack
from fojax.controllers.base import ControlInfo, Observation
from fojax.controllers.cascade import as_controller, broadcast_batch

Array = jax.Array

# Status bits, re-exported from :mod:`fojax.observers`.
NONFINITE = observers.NONFINITE
TILT_LIMIT = observers.TILT_LIMIT
ACTUATOR_LIMIT = observers.ACTUATOR_LIMIT
STATUS_NAMES = observers.STATUS_NAMES


def divisor_near(n: int, target: float) -> int:
    """The divisor of ``n`` nearest to ``target`` (the smaller one on a tie): a block
    length that splits ``n`` steps evenly (snapshots, checkpointed blocks)."""
    best = 1
    for d in range(1, int(math.isqrt(n)) + 1):
        if n % d == 0:
            for c in (d, n // d):
                if abs(c - target) < abs(best - target) or (
                    abs(c - target) == abs(best - target) and c < best
                ):
                    best = c
    return best


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """Static settings of a rollout.

    dt: step (s) of the plant integrator and the controller (default 1 ms).
    horizon: simulated time (s); ``round(horizon / dt)`` steps are taken.
    save_every: steps between saved snapshots (and checkpointed blocks).
    rotor_speed_limit: ``None`` (default): ideal actuators, the plant receives the
        command as it is; a number ``w_max`` (rad/s): rotor-limited actuators, each
        squared rotor speed of the command (the inverted mixer (10)) is clipped to
        ``[0, w_max^2]`` and the thrust and torques the plant receives are recomputed
        from the clipped speeds (:func:`fojax.plant.saturate_inputs`).
    """

    dt: float = 1e-3
    horizon: float = 80.0
    save_every: int = 100
    rotor_speed_limit: float | None = None

    def __post_init__(self) -> None:
        for label, value in (("dt", self.dt), ("horizon", self.horizon)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        if self.dt > self.horizon:
            raise ValueError(f"dt ({self.dt}) must not exceed the horizon ({self.horizon})")
        if not isinstance(self.save_every, int) or self.save_every < 1:
            raise ValueError(f"save_every must be a positive integer, got {self.save_every!r}")
        limit = self.rotor_speed_limit
        if limit is not None and not (
            isinstance(limit, int | float) and math.isfinite(limit) and limit > 0
        ):
            raise ValueError(f"rotor_speed_limit must be None or a number > 0, got {limit!r}")
        if self.steps % self.save_every:
            raise ValueError(
                f"save_every ({self.save_every}) must divide the number of steps ({self.steps}); "
                f"{divisor_near(self.steps, self.save_every)} does"
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
    """Result of one draw or of a batch.

    final_state: ``(12,)``. status: ``()`` int32 bit flags
    (:data:`fojax.observers.STATUS_NAMES`). outputs: what the rollout's observer
    finalized (``None`` without one). trajectory: :class:`Snapshot` with a leading
    ``(blocks,)`` axis. A batch adds its axes last to each.
    """

    final_state: Array
    status: Array
    outputs: Any
    trajectory: Snapshot


class LoopState(NamedTuple):
    """The time loop's carry, at the start of step ``k``.

    Shapes of one draw; a batch adds its axes last. state: the plant state ``x_k`` as
    its 12 entries. trig: the 6 entries of :func:`fojax.plant.attitude_trig` of ``x_k``.
    held: the draw's ``(noise, drag)``
    table rows in force at step ``k`` (each ``(6,)`` or ``None``). control: the
    controller's state after its update at ``t_k``. inputs, info: that update's command
    as its 4 entries and :class:`ControlInfo`. status: ``()`` the
    :class:`fojax.observers.Status` flags so far. observed: the observer's state.

    The state and the command are carried entry by entry: each entry is computed by its
    own arithmetic (an RK4 combination, eq. (13), a torque), and stacked into one array
    the stack would be their one reader, which XLA fuses into a single branchy,
    unvectorised concatenation kernel; carried apart, every entry is one vectorised
    kernel, and the arrays built from them where a step needs one (the controller's
    blocks of three, the observers' ``(12,)`` state) read stored values. Entry by entry,
    the plant's arithmetic also compiles alike in every program (one device or a
    partitioned mesh), so that a draw's numbers do not depend on the devices.
    """

    state: tuple
    trig: tuple
    held: tuple
    control: Any
    inputs: tuple
    info: ControlInfo
    status: Array
    observed: Any
    rotors: Any = None
    """With lagging rotors (the scenario's vehicle's ``rotor_time_constant``,
    :func:`fojax.rotors.lag_weights`): the four squared rotor speeds (rad^2/s^2) at
    ``t_k``; else ``None``."""


def _held_values(scenario: scenarios.Scenario, config: SimulationConfig):
    """``held(draw, k) -> (noise, drag)``: the rows of the draw's tables in force at step ``k``
    (:func:`fojax.scenarios.held_rows`; each ``None`` when the scenario has no such
    table).

    The draw's tables are laid out for ``config.dt`` (``sample_draw(..., dt=config.dt)``),
    so the row of step ``k`` is ``k // hold_steps`` with ``hold_steps`` known before
    tracing. The row then does not depend on the draw: over a batch each lookup is one
    contiguous slice ``(6, draws)`` of the ``(rows, 6, draws)`` table. The rollout reads
    each step's values once, at the end of the step before, and carries them.
    """
    noise_steps, _ = scenarios.hold_layout(scenario.horizon, scenario.noise_hold, config.dt)
    drag_steps, _ = scenarios.hold_layout(scenario.horizon, scenario.drag_hold, config.dt)

    def held(draw, k):
        noise = scenarios.held_row(draw.noise_accel, k, noise_steps) if scenario.has_noise else None
        drag = (
            scenarios.held_row(draw.drag_multipliers, k, drag_steps)
            if scenario.has_drag_variation
            else None
        )
        return noise, drag

    return held


def _per_draw(value: Array, ndim: int, batch: tuple[int, ...]) -> Array:
    """``value`` with ``ndim`` axes of one draw (time only, shared by a batch) repeated
    over the batch, its axes last; a value already per draw is kept."""
    value = jnp.asarray(value)
    if value.ndim == ndim + len(batch):
        return value
    value = value.reshape(value.shape + (1,) * len(batch))
    return jnp.broadcast_to(value, value.shape[:ndim] + batch)


def rollout(
    controller: Any,
    gains: Any,
    model: plant.PlantParams,
    scenario: scenarios.Scenario,
    draw: scenarios.Draw,
    config: SimulationConfig,
    observer: Any = None,
) -> Rollout:
    """Simulate one draw, or a batch of draws, of ``scenario`` under ``controller``.

    ``draw``: one :class:`fojax.scenarios.Draw` (:func:`fojax.scenarios.sample_draw`), or
    a batch with the batch's axes last (:func:`fojax.scenarios.sample_draws`: every
    leaf ``(..., draws)``); it must be sampled for ``config.dt`` (its tables are read by
    step index). ``controller``: a :class:`fojax.controllers.Cascade`
    (:func:`fojax.make_controller`), a bare :class:`fojax.controllers.ControlLaw` (run
    in a default cascade) or any object with the controller interface. ``gains``:
    shared by the batch (each field with its declared shape) or per draw (the batch's
    axes last). ``model`` is the nominal plant the controller uses; ``draw.params`` is
    the simulated plant. ``observer``, if given, is an
    :class:`fojax.observers.Observer` (or a :class:`fojax.observers.Chain` of them)
    folded over every step; its finalized outputs are ``Rollout.outputs``.

    Every per-draw array of the result has the batch's axes last (``final_state``
    ``(12, draws)``, ``trajectory.state`` ``(blocks, 12, draws)``);
    :func:`fojax.scenarios.batch_first` moves them first. Pure and traceable: ``grad``
    through ``outputs``. Gains are not checked here (they may be traced);
    :func:`fojax.study.run` checks them.
    """
    controller = as_controller(controller)
    batch = tuple(jnp.shape(draw.params.mass))
    params = controller.prepare(gains, model, batch)
    loop = _Loop(
        controller,
        scenario,
        config,
        observer,
        jnp.asarray(draw.params.mass).dtype,
        batch,
        _held_values(scenario, config),
        model,
    )
    loop0 = loop.first(params, draw)
    final, trajectory = lax.scan(loop.block_body(params, draw), loop0, jnp.arange(config.blocks))
    outputs = observer.finalize(final.observed) if observer is not None else None
    return Rollout(jnp.stack(final.state), final.status, outputs, trajectory)


def rollout_from_keys(
    controller: Any,
    gains: Any,
    model: plant.PlantParams,
    scenario: scenarios.Scenario,
    keys: Any,
    config: SimulationConfig,
    observer: Any = None,
    dtype: Any = None,
    member: Any = 0,
) -> Rollout:
    """:func:`rollout` of the draws ``keys`` ``(n, 2)`` name, each sampled for ``config.dt``
    in ``dtype`` (:func:`fojax.scenarios.sample_draws`; ``member``: a union's member), the
    batch's axes last. The Monte Carlo study, the tuner's cost and the requirements'
    evaluation all roll out this way. Pure."""
    draws = scenarios.sample_draws(scenario, keys, config.dt, dtype, member)
    return rollout(controller, gains, model, scenario, draws, config, observer)


_STATUS = observers.Status()


@dataclasses.dataclass(frozen=True)
class _Loop:
    """The time loop of one rollout, its static configuration settled in Python before
    tracing: the controller, the scenario, the settings, the observer (``None``: none),
    the draw's dtype and batch shape, ``held(draw, k)`` (:func:`_held_values`), and the
    controller's nominal plant (for the observers)."""

    controller: Any
    scenario: scenarios.Scenario
    config: SimulationConfig
    observer: Any
    dtype: Any
    batch: tuple[int, ...]
    held: Any
    model: plant.PlantParams

    def reference_at(self, draw, k):
        """The time, the reference with its two derivatives and the deterministic
        disturbance at step ``k`` (time only: shared by every draw; for a union
        scenario, each draw's member's, the batch last)."""
        t = k.astype(self.dtype) * self.config.dt
        derivatives, disturbance = scenarios.reference_and_disturbance(
            self.scenario, draw.member, t, draw.manoeuvre
        )
        return t, tuple(d.astype(self.dtype) for d in derivatives), disturbance.astype(self.dtype)

    def observe(self, draw, k, state):
        t, (ref, ref_vel, ref_acc), _ = self.reference_at(draw, k)
        return Observation(t, state, ref, ref_vel, ref_acc)

    def first(self, params, draw) -> LoopState:
        """The carry at step 0, with the first control update (later ones run at the end
        of the iteration before)."""
        state0 = scenarios.initial_states(self.scenario, draw, self.dtype, self.batch)
        obs0 = self.observe(draw, jnp.zeros((), jnp.int32), plant.state_blocks(state0))
        control0 = self.controller.init(params, obs0)
        control1, inputs0, info0 = self.controller.step(params, control0, obs0)
        observer = self.observer
        # lagging rotors start at the (squared) speeds of the first command
        speeds = (self.commanded_squares(draw.params, _entries(inputs0))
                  if self.lag is not None else None)  # fmt: skip
        return LoopState(
            state=_entries(state0),
            trig=plant.attitude_trig(*_entries(state0)[3:6]),
            held=self.held(draw, jnp.zeros((), jnp.int32)),
            control=control1,
            inputs=_entries(inputs0),
            info=info0,
            status=broadcast_batch(_STATUS.init(self.dtype), self.batch),
            observed=broadcast_batch(observer.init(self.dtype), self.batch)
            if observer is not None
            else None,
            rotors=speeds,
        )

    @property
    def lag(self) -> tuple[float, float] | None:
        """The rotors' :func:`fojax.rotors.lag_weights` over one step (``None``: the
        rotors turn at their commanded speeds)."""
        vehicle = self.scenario.vehicle
        constant = None if vehicle is None else vehicle.lag()
        return None if constant is None else rotors.lag_weights(constant, self.config.dt)

    def commanded_squares(self, params, inputs: tuple) -> tuple:
        """The four squared rotor speeds (rad^2/s^2) of the command ``inputs``: the
        inverted allocation, clipped to ``[0, w_max^2]`` for rotor-limited actuators (as
        they are for ideal ones)."""
        squared = plant.rotor_speeds_squared(params, jnp.stack(inputs))
        limit = self.config.rotor_speed_limit
        if limit is not None:
            squared = jnp.clip(squared, 0.0, limit * limit)
        return unstack(squared)

    def lagged(self, draw, loop: LoopState) -> tuple:
        """``(applied inputs, Omega_r, next squared rotor speeds)`` of lagging rotors over
        step ``k`` (:func:`fojax.rotors.lag_weights`): the step's mean squared speeds
        through the allocation, and their square roots' ``Omega_r``."""
        decay, mean = self.lag
        command = self.commanded_squares(draw.params, loop.inputs)
        gaps = tuple(w - c for w, c in zip(loop.rotors, command, strict=True))
        squared = tuple(c + mean * g for c, g in zip(command, gaps, strict=True))
        following = tuple(c + decay * g for c, g in zip(command, gaps, strict=True))
        applied = plant.allocate(draw.params, squared)
        return applied, plant.speed_sum(draw.params, plant.rotor_speeds(squared)), following

    def plant_step(self, draw, loop: LoopState, deterministic) -> tuple:
        """The plant's state entries after step ``k`` and the rotor speeds after it
        (``None`` unless they lag): one RK4 step with the held noise, drag and command
        (clipped to the rotor speed limit, if any; through lagging rotors, if they
        lag)."""
        noise, drag = loop.held
        k_p, k_phi = draw.params.drag_position, draw.params.drag_attitude
        if drag is not None:
            k_p, k_phi = k_p * drag[:3], k_phi * drag[3:]
        deterministic = observers.per_component(deterministic, loop.state[0][None])
        if noise is not None:
            deterministic = deterministic + noise.astype(self.dtype)
        applied, omega_r, following = loop.inputs, None, None
        if self.lag is not None:
            applied, omega_r, following = self.lagged(draw, loop)
        elif self.config.rotor_speed_limit is not None:
            applied = plant.saturate_inputs(draw.params, applied, self.config.rotor_speed_limit)
        state = plant.rk4_step_parts(
            draw.params,
            loop.state,
            applied,
            unstack(deterministic),
            self.config.dt,
            unstack(k_p),
            unstack(k_phi),
            loop.trig,
            omega_r,
        )
        return state, following

    def fold(self, draw, loop: LoopState, k, record: observers.StepRecord):
        """The status flags and the observer's state with step ``k``'s record folded in
        (a union's draw only up to its own scenario's horizon)."""
        status = _STATUS.update(loop.status, record)
        observer = self.observer
        observed = observer.update(loop.observed, record) if observer is not None else None
        if self.scenario.members:
            active = k < draw.steps
            status, observed = jax.tree.map(
                lambda new, old: jnp.where(active, new, old),
                (status, observed),
                (loop.status, loop.observed),
            )
        return status, observed

    def step(self, params, draw, loop: LoopState, k):
        t, (reference, _, _), deterministic = self.reference_at(draw, k)
        next_state, next_rotors = self.plant_step(draw, loop, deterministic)
        blocks = _blocks(loop.state)
        state = jnp.concatenate(blocks)
        record = observers.StepRecord(
            time=t,
            state=state,
            next_state=jnp.stack(next_state),
            reference=reference,
            inputs=jnp.stack(loop.inputs),
            info=loop.info,
            error=observers.tracking_error(blocks, reference, loop.info.attitude_reference),
            plant=draw.params,
            model=self.model,
        )
        status, observed = self.fold(draw, loop, k, record)
        # The control update of step k + 1, from the new state.
        control, next_inputs, next_info = self.controller.step(
            params, loop.control, self.observe(draw, k + 1, _blocks(next_state))
        )
        loop = LoopState(
            state=next_state,
            trig=plant.attitude_trig(*next_state[3:6]),
            held=self.held(draw, k + 1),
            control=control,
            inputs=_entries(next_inputs),
            info=next_info,
            status=status,
            observed=observed,
            rotors=next_rotors,
        )
        return loop, (reference, record.inputs, record.info)

    def block_body(self, params, draw):
        """The outer scan's body: ``save_every`` steps (an inner scan, each step
        checkpointed with :func:`_save_expensive`), then the block's :class:`Snapshot`;
        the block is rematerialised under ``grad``."""
        every, dt, batch = self.config.save_every, self.config.dt, self.batch

        def one_step(loop, k):
            return self.step(params, draw, loop, k)

        one_step = jax.checkpoint(one_step, policy=_save_expensive)

        @jax.checkpoint
        def block(loop: LoopState, block_index):
            ks = block_index * every + jnp.arange(every)
            loop, (refs, inputs, infos) = lax.scan(one_step, loop, ks)
            t_end = (block_index + 1).astype(self.dtype) * every * dt
            last = jax.tree.map(lambda x: x[-1], (refs, inputs, infos))
            snapshot = Snapshot(
                _per_draw(t_end, 0, batch),
                jnp.stack(loop.state),
                _per_draw(last[0], 1, batch),
                last[1],
                last[2],
                jnp.min(inputs, axis=0),
                jnp.max(inputs, axis=0),
            )
            return loop, snapshot

        return block


def _blocks(entries: tuple) -> plant.StateBlocks:
    """The state's blocks, stacked from its 12 carried entries."""
    return plant.StateBlocks(*(jnp.stack(entries[3 * i : 3 * i + 3]) for i in range(4)))


_EXPENSIVE = frozenset(
    {
        "exp", "exp2", "expm1", "log", "log1p", "pow", "sqrt", "rsqrt", "cbrt", "div",
        "tanh", "logistic", "sin", "cos", "tan", "atan", "atan2", "asin", "acos",
        "dot_general", "custom_vjp_call", "custom_vjp_call_jaxpr",
    }
)  # fmt: skip
"""Primitives whose outputs the reverse pass keeps (:func:`_save_expensive`)."""


def _save_expensive(primitive, *_, **params) -> bool:
    """The checkpoint policy of one step under ``grad``: keep the outputs of the
    operations XLA's CPU backend treats as expensive (transcendentals, divisions,
    products, the fractional memory's step) and the values marked by
    :func:`fojax._arrays.reverse_pass_boundary` (the RK4 stages), recompute everything
    else in the reverse pass, where XLA fuses the recomputation into the kernels that
    need it. Keeping every intermediate instead costs one memory write per value and
    step (measured slower, docs/performance.md)."""
    if primitive.name == "name":
        return params.get("name") == KEPT
    return primitive.name in _EXPENSIVE


def _entries(array: Array) -> tuple:
    """The entries of ``array`` along its leading axis (:func:`fojax._arrays.unstack`;
    XLA folds the pieces of a stack into its operands)."""
    return unstack(array)
