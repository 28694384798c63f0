"""What is random in a run of a scenario (:mod:`fojax.scenarios`), drawn up front.

:func:`sample_draw` draws everything random of one run into a :class:`Draw`, a
NamedTuple of arrays (``vmap`` over draws is the intended use), from the key
:func:`draw_keys` gives draw ``i``; :func:`disturbance_at` and :func:`drag_at` read it
back at time ``t`` from piecewise-constant tables (:func:`held_row`), so no key is split
inside the simulation loop. Every name is also :mod:`fojax.scenarios`'.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fojax import plant
from fojax._arrays import as_time as _as_time

Array = jax.Array

Scenario = Any
"""A :class:`fojax.scenarios.Scenario` (that module builds on this one and re-exports
its functions, so this one does not import it)."""


class Draw(NamedTuple):
    """Everything random in one run, sampled up front (all leaves are arrays).

    params: :class:`fojax.plant.PlantParams` of the simulated plant (mass and inertia
        perturbed in scenario 3; the controller keeps the nominal values).
    drag_multipliers: ``(n_drag_holds, 6)`` multipliers of
        ``(K_px, K_py, K_pz, K_phi1, K_phi2, K_phi3)``, one row per drag hold.
    noise_accel: ``(n_noise_holds, 6)`` Gaussian disturbance accelerations
        (m/s^2, rad/s^2), one row per noise hold.
    time_step: ``()`` the step ``dt`` the tables were laid out for.
    drag_hold_steps, noise_hold_steps: ``()`` int32, steps per hold.
    member: ``()`` int32, the member of a union scenario the draw belongs to (0 for a
        scenario). steps: ``()`` int32, that scenario's own number of steps (its
        horizon / dt): a rollout records the draw up to there.
    manoeuvre: ``None``, or the :class:`fojax.manoeuvres.Manoeuvre` the draw flies
        where its scenario (or a union's member) flies manoeuvres, drawn from a key of
        its own (the other processes draw as without it).
    """

    params: plant.PlantParams
    drag_multipliers: Array
    noise_accel: Array
    time_step: Array
    drag_hold_steps: Array
    noise_hold_steps: Array
    member: Array
    steps: Array
    manoeuvre: Any = None


def draw_keys(seed: int, indices: Iterable[int] | Array) -> Array:
    """Per-draw keys ``fold_in(PRNGKey(seed), i)`` for each ``i`` in ``indices``.

    Draw ``i`` depends only on ``(seed, i)``, never on how many draws are made.
    Indices must lie in ``[0, 2**32)`` (a ``ValueError`` otherwise: they are 32-bit).
    Returns ``(len(indices), 2)`` uint32 raw keys.
    """
    base = jax.random.PRNGKey(seed)
    if not hasattr(indices, "shape"):
        indices = np.asarray(list(indices))
    if not isinstance(indices, jax.core.Tracer) and np.size(indices):
        host = np.asarray(indices)
        low, high = host.min(), host.max()
        if low < 0 or high >= 2**32:
            raise ValueError(
                f"draw indices must lie in [0, 2**32) (they are folded in as 32-bit "
                f"integers; others would repeat draws), got {low if low < 0 else high}"
            )
    indices = jnp.asarray(indices).astype(jnp.uint32)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(indices)


_VEHICLE_TAG = 0x5E41
"""Folded into a draw's key for its vehicle file's uncertainty (:meth:`Vehicle.perturb`)."""
_MANOEUVRE_TAG = 0x3A4E
"""Folded into a draw's key for its manoeuvre (:func:`fojax.manoeuvres.sample`)."""


def _manoeuvre(scenario: Scenario, key: Array, member: Any, dtype):
    """The draw's manoeuvre (``None`` where no member flies one): each member that flies
    manoeuvres draws one from the same key, the draw's member's is kept."""
    from fojax import manoeuvres

    flying = [m for m in (scenario.members or (scenario,)) if m.manoeuvres is not None]
    if not flying:
        return None
    key = jax.random.fold_in(key, _MANOEUVRE_TAG)
    drawn = [manoeuvres.sample(key, m.manoeuvres, m.horizon, dtype) for m in flying]
    if len(drawn) == 1:
        return drawn[0]
    index = [i for i, m in enumerate(scenario.members) if m.manoeuvres is not None]
    which = jnp.clip(jnp.searchsorted(jnp.asarray(index), member), 0, len(index) - 1)
    return jax.tree.map(lambda *leaves: jnp.stack(leaves)[which], *drawn)


def hold_layout(horizon: float, hold: float, dt: float) -> tuple[int, int]:
    """``(steps per hold, number of holds)`` covering steps ``0 ... ceil(horizon/dt)``."""
    hold_steps = max(1, round(hold / dt))
    n_steps = math.ceil(horizon / dt - 1e-9)
    return hold_steps, n_steps // hold_steps + 1


def _member_values(scenario: Scenario, member: Any, dtype) -> dict[str, Any]:
    """The random processes' parameters of ``member``: Python numbers for a scenario,
    rows of small tables selected by the (traced) ``member`` for a union."""
    names = ("mass_uncertainty", "inertia_uncertainty", "drag_variation")
    if not scenario.members:
        values = {name: getattr(scenario, name) for name in names}
        values["noise_std"] = [scenario.noise_std_position] * 3 + [scenario.noise_std_attitude] * 3
        return values
    members = scenario.members
    values = {
        name: jnp.asarray([getattr(m, name) for m in members], dtype)[member] for name in names
    }
    # 1 - a and 1 + a in Python (float64), as a scenario run alone computes them.
    values["drag_low"] = jnp.asarray([1.0 - m.drag_variation for m in members], dtype)[member]
    values["drag_high"] = jnp.asarray([1.0 + m.drag_variation for m in members], dtype)[member]
    values["noise_std"] = jnp.asarray(
        [[m.noise_std_position] * 3 + [m.noise_std_attitude] * 3 for m in members], dtype
    )[member]
    return values


def _check_member(scenario: Scenario, member: Any) -> None:
    """``ValueError`` for a concrete ``member`` that :func:`sample_draw` would not use
    as asked: other than 0 for a plain scenario, outside ``[0, len(members))`` for a
    union (JAX would clamp it to a valid index). A traced index is not checked."""
    if isinstance(member, jax.core.Tracer):
        return
    try:
        index = int(member) if jnp.ndim(member) == 0 else None
    except (TypeError, ValueError):
        index = None
    if index is None or isinstance(member, bool) or index != member:
        raise ValueError(f"member must be an integer index, got {member!r}")
    if not scenario.members:
        if index != 0:
            raise ValueError(
                f"member={index} given for {scenario.name!r}, which is not a union of "
                "scenarios (fojax.scenarios.union): its draws have member 0"
            )
    elif not 0 <= index < len(scenario.members):
        raise ValueError(
            f"member must be 0 to {len(scenario.members) - 1} for this union of "
            f"{len(scenario.members)} scenarios, got {index}"
        )


def sample_draw(scenario: Scenario, key: Array, dt: float, dtype=None, member: Any = 0) -> Draw:
    """Sample one :class:`Draw` of ``scenario`` from ``key`` for a step ``dt`` (s).

    ``key`` should come from :func:`draw_keys`. ``dt`` must be a Python number (it
    fixes the table shapes). Tables of disabled processes have a single row
    (multipliers 1, noise 0). For a union (:func:`union`), ``member`` (an index, may
    be traced) picks the member whose processes are sampled; a concrete one must lie
    in ``[0, len(members))``, and for a plain scenario be 0 (``ValueError``
    otherwise). Pure and ``vmap``-able over ``key`` (and ``member``).
    """
    dt = float(dt)
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    _check_member(scenario, member)
    float_dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    key_params, key_drag, key_noise = jax.random.split(key, 3)
    key_mass, key_inertia = jax.random.split(key_params)
    values = _member_values(scenario, member, float_dtype)
    if scenario.members:
        member_steps = jnp.asarray(
            [math.ceil(m.horizon / dt - 1e-9) for m in scenario.members], jnp.int32
        )[member]
    else:
        member_steps = math.ceil(scenario.horizon / dt - 1e-9)

    nominal = scenario.plant_params(float_dtype)
    mass_factor = 1.0 + jax.random.uniform(
        key_mass, (), float_dtype, 0.0, values["mass_uncertainty"]
    )
    inertia_factor = 1.0 + jax.random.uniform(
        key_inertia, (3,), float_dtype, 0.0, values["inertia_uncertainty"]
    )
    params = nominal._replace(
        mass=nominal.mass * mass_factor, inertia=nominal.inertia * inertia_factor
    )
    if scenario.vehicle is not None and scenario.vehicle.uncertainty:
        # a key of its own: the scenario's processes draw as without it
        params = scenario.vehicle.perturb(params, jax.random.fold_in(key, _VEHICLE_TAG))

    drag_hold_steps, n_drag = hold_layout(scenario.horizon, scenario.drag_hold, dt)
    if scenario.has_drag_variation:
        if scenario.members:
            low, high = values["drag_low"], values["drag_high"]
        else:
            low, high = 1.0 - values["drag_variation"], 1.0 + values["drag_variation"]
        drag_multipliers = jax.random.uniform(key_drag, (n_drag, 6), float_dtype, low, high)
    else:
        drag_multipliers = jnp.ones((1, 6), float_dtype)

    noise_hold_steps, n_noise = hold_layout(scenario.horizon, scenario.noise_hold, dt)
    if scenario.has_noise:
        std = jnp.asarray(values["noise_std"], float_dtype)
        noise_accel = std * jax.random.normal(key_noise, (n_noise, 6), float_dtype)
    else:
        noise_accel = jnp.zeros((1, 6), float_dtype)

    return Draw(
        params=params,
        drag_multipliers=drag_multipliers,
        noise_accel=noise_accel,
        time_step=jnp.asarray(dt, float_dtype),
        drag_hold_steps=jnp.asarray(drag_hold_steps, jnp.int32),
        noise_hold_steps=jnp.asarray(noise_hold_steps, jnp.int32),
        member=jnp.asarray(member, jnp.int32),
        steps=jnp.asarray(member_steps, jnp.int32),
        manoeuvre=_manoeuvre(scenario, key, member, float_dtype),
    )


def sample_draws(scenario: Scenario, keys: Array, dt: float, dtype=None, member: Any = 0) -> Draw:
    """:func:`sample_draw` for every key of ``keys`` ``(draws, 2)``, as one :class:`Draw`
    with the batch's axis last (``params.mass`` ``(draws,)``, ``noise_accel`` ``(rows,
    6, draws)``): what :func:`fojax.simulator.rollout` runs over a batch. ``member``: one
    union member for every draw, or ``(draws,)``. Draw ``i`` is the same as
    ``sample_draw(scenario, keys[i], ...)`` (one ``vmap``).
    """
    keys = jnp.asarray(keys)
    member = jnp.broadcast_to(jnp.asarray(member, jnp.int32), keys.shape[:1])
    draws = jax.vmap(lambda key, m: sample_draw(scenario, key, dt, dtype, m))(keys, member)
    return batch_last(draws)


def batch_last(tree: Any) -> Any:
    """Every leaf's leading (draw) axis moved last: a batch laid out by ``vmap``
    (``(draws, ...)``) as a rollout over the batch takes it (``(..., draws)``)."""
    return jax.tree.map(lambda leaf: jnp.moveaxis(leaf, 0, -1), tree)


def batch_first(tree: Any) -> Any:
    """The inverse of :func:`batch_last`: every leaf's last (draw) axis moved first."""
    return jax.tree.map(lambda leaf: jnp.moveaxis(leaf, -1, 0), tree)


def held_row(table: Array, step: Array, hold_steps) -> Array:
    """The row of a hold table (``(rows, 6)``) in force at step ``step``: row
    ``step // hold_steps``, past the end the last. The one lookup of the draw's tables,
    by the rollout (``hold_steps`` known before tracing) and by :func:`disturbance_at`
    and :func:`drag_at` (from the draw)."""
    row = jnp.clip(step // hold_steps, 0, table.shape[0] - 1)
    return jax.lax.dynamic_index_in_dim(table, row, keepdims=False)


def _step_of(t: Array, draw: Draw) -> Array:
    return jnp.round(t / draw.time_step).astype(jnp.int32)


def disturbance_at(scenario: Scenario, draw: Draw, t) -> Array:
    """Total disturbance acceleration ``(6,)`` at time ``t``: deterministic + Gaussian.

    Traceable in ``t``; the Gaussian part is the row of ``draw.noise_accel`` of the
    hold containing step ``round(t / dt)`` (zero when the scenario has no noise; times
    past the table reuse its last row).
    """
    t = _as_time(t)
    deterministic = scenario.disturbance(t)
    if not scenario.has_noise:
        return deterministic
    noise = held_row(draw.noise_accel, _step_of(t, draw), draw.noise_hold_steps)
    return deterministic + noise.astype(deterministic.dtype)


def drag_at(scenario: Scenario, draw: Draw, t) -> tuple[Array, Array]:
    """Drag coefficients ``(K_p (3,), K_phi (3,))`` in force at time ``t``.

    The draw's (nominal) drag times the multipliers of the hold containing step
    ``round(t / dt)``; the nominal drag when the scenario has no drag variation.
    """
    if not scenario.has_drag_variation:
        return draw.params.drag_position, draw.params.drag_attitude
    t = _as_time(t)
    multipliers = held_row(draw.drag_multipliers, _step_of(t, draw), draw.drag_hold_steps)
    return (
        draw.params.drag_position * multipliers[:3],
        draw.params.drag_attitude * multipliers[3:],
    )
