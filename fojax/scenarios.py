"""The paper's simulation scenarios (Section V) as data and pure functions of time.

A :class:`Scenario` is a static description (a frozen, hashable dataclass: pass it
to ``jit`` as a static argument or close over it). Everything random in a run is
drawn up front by :func:`sample_draw` into a :class:`Draw`, a NamedTuple of arrays
(``vmap`` over draws is the intended use), and read back at time ``t`` by
:func:`disturbance_at` and :func:`drag_at`, which index piecewise-constant tables:
no key is split inside the simulation loop.

Scenarios (every choice is listed in ``docs/model.md``):

1. Reference (54)-(55), deterministic disturbances (53), drag coefficients
   ``K_p``, ``K_phi`` varying randomly in time, horizon 80 s.
2. Scenario 1 plus Gaussian random disturbances.
3. Reference (57), disturbances (56), mass and inertia ``x (1 + U[0, 0.3])`` per
   draw, nominal drag, horizon 50 s.

Random processes (the paper's Figs. 3-4 are missing, these are our choices):

* drag: each of the six coefficients ``(K_px, K_py, K_pz, K_phi1, K_phi2, K_phi3)``
  is its nominal value times an independent ``U[1 - 0.2, 1 + 0.2]`` multiplier,
  held for 1 s (piecewise constant);
* Gaussian disturbance (scenario 2): independent zero-mean normal accelerations,
  standard deviation 0.1 m/s^2 per position axis and 0.1 rad/s^2 per attitude axis,
  held for 0.1 s, added to the deterministic disturbance.

Hold boundaries sit on the simulation step grid: a hold lasts
``round(hold / dt)`` steps and time ``t`` is mapped to step ``round(t / dt)``, so
float rounding of ``t = k dt`` never moves a boundary.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fojax import plant
from fojax._arrays import as_time as _as_time
from fojax.draws import (
    Draw,
    batch_first,
    batch_last,
    disturbance_at,
    drag_at,
    draw_keys,
    held_row,
    hold_layout,
    sample_draw,
    sample_draws,
)

Array = jax.Array

__all__ = [
    "Draw",
    "Scenario",
    "Shifted",
    "SCENARIO_IDS",
    "disturbance_at",
    "disturbances_53",
    "disturbances_56",
    "drag_at",
    "draw_keys",
    "get_scenario",
    "held_row",
    "hold_layout",
    "initial_state",
    "initial_states",
    "manoeuvre_scenario",
    "reference_54_55",
    "reference_57",
    "reference_57_smoothed",
    "reference_and_disturbance",
    "reference_with_derivatives",
    "sample_draw",
    "sample_draws",
    "batch_first",
    "batch_last",
    "union",
    "window",
]

SCENARIO_IDS = (1, 2, 3)


# --------------------------------------------------------------------------- references


def reference_54_55(t) -> Array:
    """Scenario 1-2 reference, eqs. (54)-(55), whose time variable is missing as printed.

    ``x_r = 0.5 cos(pi t / 20)``, ``y_r = 0.5 sin(pi t / 20)``,
    ``z_r = 2 - 2 cos(pi t / 20)`` (m), ``psi_r = 0.5`` rad.

    t: scalar time (s). Returns ``(4,)`` ``(x_r, y_r, z_r, psi_r)``.
    """
    t = _as_time(t)
    phase = jnp.pi * t / 20.0
    return jnp.stack(
        [
            0.5 * jnp.cos(phase),
            0.5 * jnp.sin(phase),
            2.0 - 2.0 * jnp.cos(phase),
            jnp.full_like(t, 0.5),
        ]
    )


def reference_57(t) -> Array:
    """Scenario 3 reference, eq. (57), as printed.

    ``x_r = 0`` for ``t <= 7``, ``10 (1 - cos(2 pi (t - 7) / 23))`` after;
    ``y_r = 0`` for ``t <= 7``, ``5 sin(4 pi (t - 7) / 23)`` after;
    ``z_r = 7 (1 - exp(-0.3 t))`` (m); ``psi_r = 0.5`` rad.

    Smoothness: ``x_r`` is C1 (its second derivative jumps from 0 to
    ``10 (2 pi / 23)^2`` at ``t = 7``), ``y_r`` is only C0 (its velocity jumps from 0
    to ``20 pi / 23`` m/s at ``t = 7``), and ``z_r'(0) = 2.1`` m/s. Derivatives from
    :func:`reference_with_derivatives` are the exact one-sided ones (left side at
    ``t = 7``). The paper's curve is kept; no smoothing is applied.

    t: scalar time (s). Returns ``(4,)`` ``(x_r, y_r, z_r, psi_r)``.
    """
    t = _as_time(t)
    after = t > 7.0
    shifted = jnp.where(after, t - 7.0, 0.0)
    x = jnp.where(after, 10.0 * (1.0 - jnp.cos(2.0 * jnp.pi * shifted / 23.0)), 0.0)
    y = jnp.where(after, 5.0 * jnp.sin(4.0 * jnp.pi * shifted / 23.0), 0.0)
    z = 7.0 * (1.0 - jnp.exp(-0.3 * t))
    return jnp.stack([x, y, z, jnp.full_like(t, 0.5)]).astype(t.dtype)


def reference_57_smoothed(t, ramp: float = 2.0) -> Array:
    """Scenario 3's reference (57) with its start at ``t = 7`` s smoothed.

    As printed, ``y_r`` starts at ``t = 7`` with a velocity jump of ``20 pi / 23`` m/s
    (and ``x_r`` with an acceleration jump). Here both horizontal terms are multiplied
    by the quintic blend ``b(s) = 10 s^3 - 15 s^4 + 6 s^5``, ``s = (t - 7) / ramp``
    clipped to ``[0, 1]`` (``ramp = 2`` s): ``b`` rises from 0 to 1 with zero first and
    second derivatives at both ends, so the reference is C2 and equals (57) from
    ``t = 7 + ramp``. ``z_r`` and ``psi_r`` are unchanged. For the sensitivity of the
    scenario-3 verdicts to the printed jump.
    """
    t = _as_time(t)
    s = jnp.clip((t - 7.0) / ramp, 0.0, 1.0)
    blend = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
    printed = reference_57(t)
    return jnp.stack([blend * printed[0], blend * printed[1], printed[2], printed[3]])


def reference_with_derivatives(
    reference_fn: Callable[[Array], Array], t
) -> tuple[Array, Array, Array]:
    """Reference and its first two time derivatives, by forward-mode autodiff.

    Exact derivatives of ``reference_fn`` itself (the paper's ``x_r'`` and ``x_r''``),
    never differences of samples.

    reference_fn: scalar ``t`` -> ``(4,)``. t: scalar time.
    Returns ``(position (4,), velocity (4,), acceleration (4,))``, each ordered
    ``(x, y, z, psi)``.
    """
    t = _as_time(t)
    one = jnp.ones_like(t)

    def value_and_rate(s):
        return jax.jvp(reference_fn, (s,), (one,))

    (position, velocity), (_, acceleration) = jax.jvp(value_and_rate, (t,), (one,))
    return position, velocity, acceleration


# ------------------------------------------------------------------------ disturbances


def _window(t: Array, start: float, stop: float) -> Array:
    return (t >= start) & (t <= stop)


def disturbances_53(t) -> Array:
    """Scenario 1-2 deterministic disturbances, eq. (53), as accelerations
    (m/s^2, rad/s^2: added to the plant's accelerations as they are).

    ``d_px = -(0.08 sin(0.11 t - 3.0403) + 0.04 sin(0.5 t - 13.5)
    + 0.008 sin(1.6 t - 15 pi) + 0.006 sin(0.3 t - 8.6))`` on ``[10, 30]``,
    ``d_py = 0.05 sin(0.4 t) + 0.05 cos(0.7 t)`` on ``[10, 50]``,
    ``d_pz = 0.05 cos(0.7 t) + 0.07 sin(0.3)`` (``sin(0.3)`` a constant, as printed),
    ``d_phi1 = 0.5 cos(0.4 t) + 1``, ``d_phi2 = 0.5 sin(0.5 t) + 1``,
    ``d_phi3 = 0.05 sin(0.7 t) + 0.1``, these four on ``[0, 80]``; zero outside the
    (closed) windows.

    t: scalar time (s). Returns ``(6,)``: m/s^2 (position) then rad/s^2 (attitude).
    """
    t = _as_time(t)
    zero = jnp.zeros_like(t)
    d_px = -(
        0.08 * jnp.sin(0.11 * t - 3.0403)
        + 0.04 * jnp.sin(0.5 * t - 13.5)
        + 0.008 * jnp.sin(1.6 * t - 15.0 * jnp.pi)
        + 0.006 * jnp.sin(0.3 * t - 8.6)
    )
    d_py = 0.05 * jnp.sin(0.4 * t) + 0.05 * jnp.cos(0.7 * t)
    d_pz = 0.05 * jnp.cos(0.7 * t) + 0.07 * math.sin(0.3)
    d_phi1 = 0.5 * jnp.cos(0.4 * t) + 1.0
    d_phi2 = 0.5 * jnp.sin(0.5 * t) + 1.0
    d_phi3 = 0.05 * jnp.sin(0.7 * t) + 0.1
    whole = _window(t, 0.0, 80.0)
    return jnp.stack(
        [
            jnp.where(_window(t, 10.0, 30.0), d_px, zero),
            jnp.where(_window(t, 10.0, 50.0), d_py, zero),
            jnp.where(whole, d_pz, zero),
            jnp.where(whole, d_phi1, zero),
            jnp.where(whole, d_phi2, zero),
            jnp.where(whole, d_phi3, zero),
        ]
    ).astype(t.dtype)


def disturbances_56(t) -> Array:
    """Scenario 3 deterministic disturbances, eq. (56), as accelerations, for all ``t``.

    ``d_px = 0.3 sin(2t) + 0.1 sin(3t)``, ``d_py = 0.2 cos(2t) + 0.2 sin(2t)``,
    ``d_pz = 0.5 cos(2t) + 0.7 sin(3t)`` (m/s^2); ``d_phi1 = 0.9 cos(0.4t) + 2.2 sin(2t)``,
    ``d_phi2 = 0.8 sin(t) + 1.4 cos(2t)``, ``d_phi3 = 1.3 sin(5t) + 1.5 cos(3t)`` (rad/s^2).

    t: scalar time (s). Returns ``(6,)``.
    """
    t = _as_time(t)
    return jnp.stack(
        [
            0.3 * jnp.sin(2.0 * t) + 0.1 * jnp.sin(3.0 * t),
            0.2 * jnp.cos(2.0 * t) + 0.2 * jnp.sin(2.0 * t),
            0.5 * jnp.cos(2.0 * t) + 0.7 * jnp.sin(3.0 * t),
            0.9 * jnp.cos(0.4 * t) + 2.2 * jnp.sin(2.0 * t),
            0.8 * jnp.sin(t) + 1.4 * jnp.cos(2.0 * t),
            1.3 * jnp.sin(5.0 * t) + 1.5 * jnp.cos(3.0 * t),
        ]
    )


# ---------------------------------------------------------------------------- scenarios


_INITIAL_POSITION = (0.05, 0.01, 0.0)
_INITIAL_ATTITUDE = (0.01, 0.01, 0.1)


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Static description of one of the paper's scenarios.

    scenario_id: 1, 2 or 3. name: short description.
    horizon: simulated time (s).
    reference: scalar ``t`` -> ``(4,)`` ``(x_r, y_r, z_r, psi_r)``.
    disturbance: scalar ``t`` -> ``(6,)`` deterministic disturbance accelerations.
    drag_variation: half-width ``a`` of the drag multipliers ``U[1 - a, 1 + a]``
        (0 keeps the nominal drag).
    drag_hold: hold time (s) of each drag multiplier.
    noise_std_position: standard deviation (m/s^2) of the Gaussian position
        disturbance, per axis (0: none).
    noise_std_attitude: standard deviation (rad/s^2) of the Gaussian attitude
        disturbance, per axis (0: none).
    noise_hold: hold time (s) of each Gaussian sample.
    mass_uncertainty: ``m = m_nominal (1 + U[0, mass_uncertainty])`` per draw.
    inertia_uncertainty: ``I_ii = I_ii_nominal (1 + U[0, inertia_uncertainty])``,
        independently per axis, per draw.
    initial_position, initial_attitude: ``(3,)`` tuples (m, rad).
    initial_velocity: ``(3,)`` tuple (m/s); the attitude rates start at 0.
    members: empty for a scenario; for the union of several (:func:`union`), the
        scenarios it holds. A union is one static structure (one compiled rollout):
        each draw says which member it belongs to (``Draw.member``), and its random
        tables, reference and disturbance follow that member.
    vehicle: the :class:`fojax.vehicle.Vehicle` flown (``None``: the paper's,
        :func:`fojax.plant.nominal_params`); :meth:`on` sets it. Disturbances and noise
        are accelerations and the uncertainties relative, so they carry over to any
        vehicle as they are (docs/model.md).
    """

    scenario_id: int
    name: str
    horizon: float
    reference: Callable[[Array], Array]
    disturbance: Callable[[Array], Array]
    drag_variation: float = 0.0
    drag_hold: float = 1.0
    noise_std_position: float = 0.0
    noise_std_attitude: float = 0.0
    noise_hold: float = 0.1
    mass_uncertainty: float = 0.0
    inertia_uncertainty: float = 0.0
    initial_position: tuple[float, float, float] = _INITIAL_POSITION
    initial_attitude: tuple[float, float, float] = _INITIAL_ATTITUDE
    initial_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    members: tuple = ()
    vehicle: Any = None
    manoeuvres: Any = None
    """``None``, or :class:`fojax.manoeuvres.Limits`: every draw flies a random manoeuvre
    of its own (``Draw.manoeuvre``, drawn from its key) in place of :attr:`reference`, and
    starts at rest, level, at the manoeuvre's start plus its offset with its yaw
    (:func:`manoeuvre_scenario`)."""

    def __post_init__(self) -> None:
        """``ValueError`` for a setting that would be ignored or misread: a negative
        standard deviation or uncertainty (the process would silently be off), a drag
        variation outside ``[0, 1)`` (multipliers must stay positive), a hold or horizon
        that is not a finite number > 0, an initial position or attitude that is not
        three numbers."""

        def number(name: str, value: Any) -> float:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"Scenario {name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"Scenario {name} must be finite, got {value!r}")
            return value

        for name in ("horizon", "drag_hold", "noise_hold"):
            if number(name, getattr(self, name)) <= 0:
                raise ValueError(f"Scenario {name} must be > 0 (s), got {getattr(self, name)!r}")
        for name in (
            "noise_std_position",
            "noise_std_attitude",
            "mass_uncertainty",
            "inertia_uncertainty",
        ):
            if number(name, getattr(self, name)) < 0:
                raise ValueError(
                    f"Scenario {name} must be >= 0 (0 turns it off), got {getattr(self, name)!r}"
                )
        if not 0 <= number("drag_variation", self.drag_variation) < 1:
            raise ValueError(
                "Scenario drag_variation must lie in [0, 1) (multipliers U[1 - a, 1 + a] stay "
                f"positive; 0 keeps the nominal drag), got {self.drag_variation!r}"
            )
        for name in ("initial_position", "initial_attitude", "initial_velocity"):
            value = getattr(self, name)
            if not isinstance(value, tuple | list) or len(value) != 3:
                raise ValueError(f"Scenario {name} must be three numbers, got {value!r}")
            for item in value:
                number(name, item)
        for name in ("reference", "disturbance"):
            if not callable(getattr(self, name)):
                raise ValueError(
                    f"Scenario {name} must be a function of time, got {getattr(self, name)!r}"
                )
        from fojax.manoeuvres import Limits
        from fojax.vehicle import Vehicle

        if self.manoeuvres is not None and not isinstance(self.manoeuvres, Limits):
            raise ValueError(
                f"Scenario manoeuvres must be fojax.manoeuvres.Limits or None, got "
                f"{self.manoeuvres!r}"
            )
        if self.vehicle is not None and not isinstance(self.vehicle, Vehicle):
            raise ValueError(
                f"Scenario vehicle must be a fojax.vehicle.Vehicle or None, got {self.vehicle!r}"
            )

    def on(self, vehicle) -> Scenario:
        """This scenario flown by ``vehicle`` (a :class:`fojax.vehicle.Vehicle`; ``None``:
        the paper's), a union's members with it."""
        members = tuple(dataclasses.replace(m, vehicle=vehicle) for m in self.members)
        return dataclasses.replace(self, vehicle=vehicle, members=members)

    def plant_params(self, dtype=None) -> plant.PlantParams:
        """The nominal plant of the scenario's vehicle (leaves of ``dtype``): the
        controllers' model, and the draws' plant before their uncertainty."""
        if self.vehicle is None:
            return plant.nominal_params(dtype)
        return self.vehicle.params(dtype)

    @property
    def has_noise(self) -> bool:
        return self.noise_std_position > 0 or self.noise_std_attitude > 0

    @property
    def has_drag_variation(self) -> bool:
        return self.drag_variation > 0

    def member_index(self, scenario: Scenario) -> int:
        """The index of ``scenario`` among the members of this union (0 for itself)."""
        if not self.members:
            if scenario != self:
                raise ValueError(f"{scenario.name!r} is not {self.name!r}")
            return 0
        try:
            return self.members.index(scenario)
        except ValueError:
            names = ", ".join(repr(m.name) for m in self.members)
            raise ValueError(f"{scenario.name!r} is not among this union's: {names}") from None


def union(*members: Scenario) -> Scenario:
    """One static scenario structure for several scenarios (one compiled rollout).

    The union's horizon is the longest member's, its tables have the longest layout;
    each draw is sampled for one member (``sample_draw(union, key, dt,
    member=i)``), so that its reference, deterministic disturbance, drag variation,
    noise and mass/inertia uncertainty are that member's, its unused tables hold
    multipliers of exactly 1 and noise of exactly 0, and the rollout stops recording
    it after the member's own horizon (``Draw.steps``). Draw ``i`` of a member is draw
    ``i`` of that scenario run alone: the same numbers in float64; in float32 within
    about 1e-5 of each signal's scale (up to 3e-4 relative on a value near zero), the
    two programs being fused and rounded apart (``tests/test_scenarios.py``).
    The members must share the hold times and the vehicle, and those that fly no
    manoeuvres the initial state; members that fly manoeuvres
    (:func:`manoeuvre_scenario`) must have as many segments.
    """
    if len(members) < 1 or not all(isinstance(m, Scenario) and not m.members for m in members):
        raise ValueError("union takes one or more scenarios (not unions)")
    first = members[0]
    for m in members[1:]:
        for name in ("drag_hold", "noise_hold", "vehicle"):
            if getattr(m, name) != getattr(first, name):
                raise ValueError(
                    f"the scenarios of a union must share {name}: {first.name!r} has "
                    f"{getattr(first, name)!r}, {m.name!r} has {getattr(m, name)!r}"
                )
    fixed = [m for m in members if m.manoeuvres is None]  # a manoeuvre sets its own start
    shapes = {m.manoeuvres.segments for m in members if m.manoeuvres is not None}
    if len(shapes) > 1:
        raise ValueError(f"the manoeuvres of a union's scenarios must have as many segments; "
                         f"got {sorted(shapes)}")  # fmt: skip
    return dataclasses.replace(
        fixed[0] if fixed else first,
        scenario_id=0,
        name=" | ".join(m.name for m in members),
        manoeuvres=next((m.manoeuvres for m in members if m.manoeuvres is not None), None),
        horizon=max(m.horizon for m in members),
        drag_variation=max(m.drag_variation for m in members),
        noise_std_position=max(m.noise_std_position for m in members),
        noise_std_attitude=max(m.noise_std_attitude for m in members),
        mass_uncertainty=max(m.mass_uncertainty for m in members),
        inertia_uncertainty=max(m.inertia_uncertainty for m in members),
        members=tuple(members),
    )


def _reference(scenario: Scenario, manoeuvre, t):
    """The reference with its two derivatives at ``t``: the scenario's function, or the
    draw's ``manoeuvre`` (:mod:`fojax.manoeuvres`; its batch's axes last) for a scenario
    that flies manoeuvres."""
    if scenario.manoeuvres is None:
        return reference_with_derivatives(scenario.reference, t)
    from fojax import manoeuvres

    return reference_with_derivatives(lambda s: manoeuvres.position(manoeuvre, s), t)


def reference_and_disturbance(scenario: Scenario, member: Array, t: Array, manoeuvre=None):
    """The reference with its two derivatives, and the deterministic disturbance, of
    ``member`` (a union's member index; ignored for a scenario) at time ``t``.

    Returns ``((position (4,), velocity (4,), acceleration (4,)), disturbance (6,))``.
    For a union every member's functions are evaluated (time only: shared by every
    draw) and each draw's member is selected: ``member`` of shape ``batch`` gives
    ``(4,) + batch`` and ``(6,) + batch`` (the batch's axes last). ``manoeuvre``: the
    draw's (``Draw.manoeuvre``) where the scenario, or a member, flies manoeuvres; its
    reference is then per draw (``(4,) + batch``).
    """
    if not scenario.members:
        return _reference(scenario, manoeuvre, t), scenario.disturbance(t)
    if any(m.manoeuvres is not None for m in scenario.members):
        return _select_per_draw(scenario, member, t, manoeuvre)
    values = [
        (reference_with_derivatives(m.reference, t), m.disturbance(t).astype(t.dtype))
        for m in scenario.members
    ]
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), *values)
    member = jnp.asarray(member)
    batch = tuple(range(member.ndim))
    # (members, k)[member] is member.shape + (k,): the batch's axes go last.
    return jax.tree.map(
        lambda leaf: jnp.moveaxis(leaf[member], batch, tuple(a - len(batch) for a in batch)),
        stacked,
    )


def _select_per_draw(scenario: Scenario, member: Array, t: Array, manoeuvre):
    """:func:`reference_and_disturbance` of a union with a member that flies manoeuvres:
    each member's values broadcast to the batch, each draw's member's taken."""
    member = jnp.asarray(member)
    values = [
        (_reference(m, manoeuvre, t), m.disturbance(t).astype(t.dtype))
        for m in scenario.members
    ]

    def per_draw(leaf):  # (k,) shared by the draws, or (k,) + batch: (k,) + batch
        leaf = jnp.asarray(leaf)
        if leaf.ndim == 1:
            leaf = leaf.reshape(leaf.shape + (1,) * member.ndim)
        return jnp.broadcast_to(leaf, leaf.shape[:1] + member.shape)

    stacked = jax.tree.map(lambda *leaves: jnp.stack([per_draw(x) for x in leaves]), *values)
    return jax.tree.map(
        lambda leaf: jnp.take_along_axis(leaf, member[None, None], axis=0)[0], stacked
    )


def manoeuvre_scenario(limits, base: Scenario | None = None, horizon: float = 30.0,
                       name: str | None = None) -> Scenario:  # fmt: skip
    """A scenario whose every draw flies a random manoeuvre within ``limits``
    (:class:`fojax.manoeuvres.Limits`) under ``base``'s random processes and
    deterministic disturbances (default scenario 2's), over ``horizon`` s."""
    base = _SCENARIOS[2] if base is None else base
    return dataclasses.replace(
        base,
        scenario_id=0,
        name=name or f"random manoeuvres under scenario {base.scenario_id}'s disturbances",
        horizon=float(horizon),
        manoeuvres=limits,
    )


def initial_states(scenario: Scenario, draw, dtype, batch: tuple[int, ...]) -> Array:
    """The ``(12,) + batch`` initial states of a draw or a batch (batch last): the
    scenario's (:func:`initial_state`; for a union, each draw's member's), or, where the
    draw flies a manoeuvre, at rest and level at its start plus its offset, with its
    starting yaw."""
    fixed = _fixed_states(scenario, draw, dtype, batch)
    if scenario.manoeuvres is None:
        return fixed
    from fojax import manoeuvres

    m = draw.manoeuvre
    position = manoeuvres.initial_position(m).astype(dtype)
    zero = jnp.zeros_like(position[0])
    flown = jnp.concatenate([position, jnp.stack([zero, zero, m.waypoints[0, 3].astype(dtype)]),
                             jnp.zeros((6,) + position.shape[1:], dtype)])  # fmt: skip
    if not scenario.members:
        return flown
    own = jnp.asarray([m.manoeuvres is not None for m in scenario.members])[draw.member]
    return jnp.where(own, flown, fixed)


def _fixed_states(scenario: Scenario, draw, dtype, batch: tuple[int, ...]) -> Array:
    """``(12,) + batch``: the scenario's initial state, or each draw's member's where a
    union's members start apart (e.g. a :func:`window`)."""
    starts = [m for m in scenario.members if m.manoeuvres is None]
    if len({_start(m) for m in starts}) <= 1:
        fixed = initial_state(scenario, dtype)
        return jnp.broadcast_to(fixed.reshape((12,) + (1,) * len(batch)), (12,) + batch)
    rows = jnp.stack([initial_state(m, dtype) for m in scenario.members])  # (members, 12)
    picked = rows[jnp.asarray(draw.member)]  # batch + (12,)
    return jnp.broadcast_to(jnp.moveaxis(picked, -1, 0), (12,) + batch)


def _start(scenario: Scenario) -> tuple:
    return (scenario.initial_position, scenario.initial_attitude, scenario.initial_velocity)


@dataclasses.dataclass(frozen=True)
class Shifted:
    """``function(t + start)``: a scenario's reference or disturbance from ``start`` (s)
    on (:func:`window`); equal when its function and start are."""

    function: Callable[[Array], Array]
    start: float

    def __call__(self, t):
        return self.function(t + self.start)


def window(scenario: Scenario, start: float, name: str | None = None) -> Scenario:
    """``scenario`` from ``start`` (s) to its end: its reference and deterministic
    disturbance shifted by ``start``, its horizon ``horizon - start``, starting on the
    reference (position, velocity and yaw at ``start``), level, with zero attitude
    rates; its random processes and uncertainties as they are (stationary). A case of
    steady flight under the scenario's later disturbances, without its initial
    transient."""
    if scenario.members or scenario.manoeuvres is not None:
        raise ValueError("window takes one of the paper's scenarios (not a union, not "
                         "manoeuvres)")  # fmt: skip
    if isinstance(start, bool) or not isinstance(start, int | float) or not (
        0 < start < scenario.horizon
    ):
        raise ValueError(f"a window's start must lie in (0, {scenario.horizon:g}) s (the "
                         f"scenario's horizon), got {start!r}")  # fmt: skip
    position, velocity, _ = (
        np.asarray(v, np.float64)
        for v in reference_with_derivatives(scenario.reference, jnp.asarray(float(start)))
    )
    return dataclasses.replace(
        scenario,
        name=name or f"{scenario.name}, from {start:g} s",
        horizon=scenario.horizon - start,
        reference=Shifted(scenario.reference, float(start)),
        disturbance=Shifted(scenario.disturbance, float(start)),
        initial_position=tuple(float(v) for v in position[:3]),
        initial_attitude=(0.0, 0.0, float(position[3])),
        initial_velocity=tuple(float(v) for v in velocity[:3]),
    )


_SCENARIO_1 = Scenario(
    scenario_id=1,
    name="drag uncertainty + disturbances (53), reference (54)-(55)",
    horizon=80.0,
    reference=reference_54_55,
    disturbance=disturbances_53,
    drag_variation=0.2,
)
_SCENARIOS = {
    1: _SCENARIO_1,
    2: dataclasses.replace(
        _SCENARIO_1,
        scenario_id=2,
        name="scenario 1 + Gaussian random disturbances",
        noise_std_position=0.1,
        noise_std_attitude=0.1,
    ),
    3: Scenario(
        scenario_id=3,
        name="30% mass/inertia uncertainty + disturbances (56), reference (57)",
        horizon=50.0,
        reference=reference_57,
        disturbance=disturbances_56,
        mass_uncertainty=0.3,
        inertia_uncertainty=0.3,
    ),
}


def get_scenario(scenario_id: int) -> Scenario:
    """The :class:`Scenario` numbered ``scenario_id`` (1, 2 or 3; an integer, or its
    text). Anything else, ``2.7`` or ``True`` included, is a ``ValueError``."""
    number = None
    if isinstance(scenario_id, int) and not isinstance(scenario_id, bool):
        number = scenario_id
    elif isinstance(scenario_id, float) and scenario_id.is_integer():
        number = int(scenario_id)
    elif isinstance(scenario_id, str) and scenario_id.strip().isdigit():
        number = int(scenario_id)
    elif hasattr(scenario_id, "dtype") and getattr(scenario_id, "ndim", None) == 0:
        if jnp.issubdtype(scenario_id.dtype, jnp.integer):  # a NumPy or JAX integer
            number = int(scenario_id)
    if number not in _SCENARIOS:
        raise ValueError(f"unknown scenario id {scenario_id!r}; expected one of {SCENARIO_IDS}")
    return _SCENARIOS[number]


def initial_state(scenario: Scenario, dtype=None) -> Array:
    """The ``(12,)`` initial plant state: position, attitude, zero rates (Section V); a
    scenario that flies manoeuvres starts each draw elsewhere (:func:`initial_states`)."""
    return plant.make_state(scenario.initial_position, scenario.initial_attitude,
                            scenario.initial_velocity, dtype=dtype)  # fmt: skip
