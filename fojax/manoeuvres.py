"""Random smooth manoeuvres: a flight envelope drawn from a key, as arrays.

A manoeuvre (:class:`Manoeuvre`) is ``S`` consecutive *minimum-jerk point-to-point
segments* in ``(x, y, z, yaw)``: segment ``j`` goes from waypoint ``P_j`` to
``P_(j+1)`` (each ``(4,)``) over ``[t_j, t_(j+1)]``, ``T_j = t_(j+1) - t_j``, as::

    position(t) = P_j + (P_(j+1) - P_j) s(u),   u = (t - t_j) / T_j in [0, 1],
    s(u) = 10 u^3 - 15 u^4 + 6 u^5.

``s`` has zero first and second derivatives at ``u = 0`` and ``u = 1``, so every segment
starts and ends at rest and the manoeuvre is C2 (position, velocity and acceleration
continuous: the two derivatives the laws use); every waypoint is a momentary hover.
The jerk is not continuous (it steps by up to ``60 |D| / T^3`` at a waypoint; the
cascade's command filter smooths the attitude commands it drives). All four axes share
``s``, so a segment is a straight line in 4-D. Before ``t = 0`` the manoeuvre is at
``P_0``; after the last segment it holds the last waypoint. A *hover* segment has
``P_(j+1) = P_j``: the vehicle holds a waypoint for ``T_j``.

Peaks of one segment over a distance ``D`` (:func:`peaks`): speed ``15/8 D/T`` (at
``u = 1/2``), acceleration ``10/sqrt(3) D/T^2`` (at ``u = 1/2 -+ sqrt(3)/6``), the
same factors for the yaw rate and yaw acceleration over the yaw change. A move's
duration is the shortest meeting every limit of :class:`Limits`::

    T_j >= 15/8 |dp| / speed,          T_j >= sqrt(10/sqrt(3) |dp| / acceleration),
    T_j >= 15/8 |dyaw| / yaw_rate,     T_j >= sqrt(10/sqrt(3) |dyaw| / yaw_acceleration),
    T_j >= min_duration,

(``|dp|`` the Euclidean length of the position part), then stretched by a random factor
``U[1, max_stretch]``: a slower move stays within every limit. A hover lasts
``U[hover_duration]``. With a ``horizon``, :func:`sample` then stretches all durations
by one factor ``max(1, horizon / total)``, so that the manoeuvre never ends before the
horizon (a slower manoeuvre again stays within the limits); choose ``segments`` so that
this factor is about 1 for a typical draw (a longer manoeuvre is cut by the run's end,
which is harmless).

*Choice of the yaw acceleration limit*: besides the yaw rate,
:class:`Limits` bounds the yaw acceleration, which is what the rotors' yaw torque
limits (a rate limit alone lets a small yaw change over a short move ask for an
acceleration up to ``3.08 yaw_rate / min_duration``).

Random draws (:func:`sample`): every quantity has its own key, ``fold_in(key, i)`` with a
fixed ``i`` per quantity (:data:`STREAMS`), so that adding a quantity later leaves the
others' draws as they are:

* waypoint candidates ``Q_0..Q_S``: ``x, y ~ U[-half_extent, half_extent]``, ``z ~
  U[z_range]``, ``yaw ~ U[yaw_range]`` (no wrapping: a move turns through the plain
  difference, less than the range's width);
* segment ``j`` is a hover with probability ``hover_probability``, independently;
  ``P_0 = Q_0`` and ``P_(j+1) = P_j`` for a hover, else ``Q_(j+1)``;
* the hovers' durations, the moves' stretch factors;
* ``offset`` ``(3,) ~ U[-initial_offset, initial_offset]``: where the vehicle starts,
  relative to ``P_0``'s position (:func:`initial_position`), so that it does not start
  on the reference.

Evaluation (:func:`position`) is a sum over all segments, ``P_0 + sum_j (P_(j+1) -
P_j) s(clip(u_j, 0, 1))``: a segment not yet begun adds 0, one done adds its whole
increment. No lookup, no gather, no branch on traced values; each term is C2 in ``t``
(``s'`` and ``s''`` vanish where the clip bends), so forward-mode derivatives are
exact and finite everywhere, at the boundaries and after the end included; every
``T_j`` is at least ``min_duration`` (or the shortest hover) > 0, so nothing divides by
zero. It costs ``S`` quintics per evaluation. It reads the leaves along their leading
axes only, so it takes one draw (``starts`` ``(S + 1,)``, ``waypoints`` ``(S + 1, 4)``)
or a batch's with its axes last (``(S + 1, *batch)``, ``(S + 1, 4, *batch)``: the
rollout's layout) as they are, giving ``(4,)`` or ``(4, *batch)``; the same as
``jax.vmap(position, in_axes=(-1, None), out_axes=-1)``. A batch with its axes first
(what ``vmap`` over :func:`sample` returns) must be read under ``vmap`` (or moved to the
batch-last layout first): :func:`position`, :func:`initial_position` and :func:`peaks`
would misread it (not always with an error).

Limits from a vehicle (:meth:`Limits.from_vehicle`), each scaled by ``fraction``
(default 0.5: the reference leaves the other half to the controller):

* acceleration: the reference's acceleration ``a`` (any direction) asks the thrust for
  ``a + g e_z``, tilted from vertical by at most ``asin(|a| / g)`` and of magnitude at
  most ``g + |a|``. So ``|a| <= g sin(theta_max)`` keeps the tilt within the vehicle's
  ``max_tilt()`` and ``|a| <= g (TW - 1)`` the thrust within its thrust-to-weight
  ``TW`` (where its rotors are limited), whatever the move's direction: the level-
  flight bounds ``g tan(theta_max)`` and ``g sqrt(TW^2 - 1)`` would not hold for a
  climbing or descending move. ``acceleration = fraction g min(sin(theta_max), TW - 1)``.
* yaw acceleration: the largest yaw torque ``tau_z`` (:class:`fojax.rotors.Authority`,
  the other rotors at zero speed) over ``I_zz``, times the share of it left while the
  rotors hold the weight, ``min(1, 2 min(1 - 1/TW, 1/TW))`` (four rotors hovering at
  equal speeds: two speed up and two slow down by as much, the thrust unchanged; 0.89
  for the Crazyflie, 0.77 for the Iris). Ideal rotors: :data:`IDEAL_YAW_ACCELERATION`.
* speed and yaw rate are not set by the vehicle (its drag-limited top speed is tens of
  m/s; its yaw rate is limited only through the yaw acceleration): :data:`DEFAULT_SPEED`
  and :data:`DEFAULT_YAW_RATE`, not scaled by ``fraction``.

Every field of :class:`Limits` can be given to :meth:`Limits.from_vehicle` to override
what it derives or defaults.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax._arrays import as_time

Array = jax.Array

__all__ = [
    "DEFAULT_SPEED",
    "DEFAULT_YAW_RATE",
    "IDEAL_YAW_ACCELERATION",
    "PEAK_ACCELERATION",
    "PEAK_SPEED",
    "STREAMS",
    "Limits",
    "Manoeuvre",
    "initial_position",
    "peaks",
    "position",
    "sample",
]

PEAK_SPEED = 15.0 / 8.0
"""``max s'(u) = s'(1/2)``: a segment's peak speed is ``PEAK_SPEED D / T``."""
PEAK_ACCELERATION = 10.0 / math.sqrt(3.0)
"""``max |s''(u)|`` (at ``u = 1/2 -+ sqrt(3)/6``): peak acceleration ``PEAK_ACCELERATION
D / T^2``."""
DEFAULT_SPEED = 1.0
"""Peak speed (m/s) :meth:`Limits.from_vehicle` sets (a choice, not the vehicle's)."""
DEFAULT_YAW_RATE = 1.0
"""Peak yaw rate (rad/s) :meth:`Limits.from_vehicle` sets (a choice, not the vehicle's)."""
IDEAL_YAW_ACCELERATION = 2.0
"""Peak yaw acceleration (rad/s^2) :meth:`Limits.from_vehicle` sets for a vehicle with
ideal (unlimited) rotors: :data:`DEFAULT_YAW_RATE` reached from rest in 0.5 s."""
STREAMS = {"waypoints": 0, "hover": 1, "hover_duration": 2, "stretch": 3, "offset": 4}
"""The ``fold_in`` index of each drawn quantity's key (module docstring)."""


def _number(owner: str, name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{owner} {name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{owner} {name} must be finite, got {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class Limits:
    """What a manoeuvre may ask, and the space it flies in: static configuration (a
    frozen, hashable dataclass; pass it to ``jit`` as a static argument).

    speed: peak speed, m/s (> 0), of the position ``(x, y, z)``.
    acceleration: peak acceleration, m/s^2 (> 0), of the position (the vector's norm).
    yaw_rate: peak yaw rate, rad/s (> 0).
    yaw_acceleration: peak yaw acceleration, rad/s^2 (> 0).
    half_extent: waypoints' ``x, y`` lie in ``[-half_extent, half_extent]``, m (>= 0).
    z_range: ``(z_min, z_max)``, m: the waypoints' heights (``z_min <= z_max``).
    yaw_range: ``(yaw_min, yaw_max)``, rad: the waypoints' yaw (``yaw_min <= yaw_max``).
    segments: the number ``S`` of segments (an integer >= 1; static: the arrays' shapes).
    hover_probability: the probability that a segment is a hover, in ``[0, 1]``.
    hover_duration: ``(shortest, longest)`` hover, s (``0 < shortest <= longest``).
    initial_offset: half-width, m (>= 0), of the vehicle's start around ``P_0``, per axis.
    min_duration: the shortest move, s (> 0): keeps ``T_j`` away from 0.
    max_stretch: a move's duration is its shortest times ``U[1, max_stretch]`` (>= 1).

    The defaults fly a 4 m x 4 m x 2 m box; with ``Limits.from_vehicle(Vehicle.paper())``
    (the speed limit binds for most moves) a move lasts about 5.5 s on average and a hover
    2 s, so the six segments last about 28 s (18 s to 38 s for 90 % of the draws, without
    a horizon).
    """

    speed: float
    acceleration: float
    yaw_rate: float
    yaw_acceleration: float
    half_extent: float = 2.0
    z_range: tuple[float, float] = (0.5, 2.5)
    yaw_range: tuple[float, float] = (-math.pi / 2, math.pi / 2)
    segments: int = 6
    hover_probability: float = 0.25
    hover_duration: tuple[float, float] = (1.0, 3.0)
    initial_offset: float = 0.1
    min_duration: float = 1.0
    max_stretch: float = 1.5

    def __post_init__(self) -> None:
        """``ValueError`` naming the field and what to change, for a value that is not a
        finite number, out of its range, or a range whose ends are reversed."""
        owner = "Limits"
        for name, unit in (("speed", "m/s"), ("acceleration", "m/s^2"), ("yaw_rate", "rad/s"),
                           ("yaw_acceleration", "rad/s^2"), ("min_duration", "s")):  # fmt: skip
            if _number(owner, name, getattr(self, name)) <= 0:
                raise ValueError(f"{owner} {name} must be > 0 ({unit}), got "
                                 f"{getattr(self, name)!r}")  # fmt: skip
        for name in ("half_extent", "initial_offset"):
            if _number(owner, name, getattr(self, name)) < 0:
                raise ValueError(f"{owner} {name} must be >= 0 (m; 0 keeps it at the centre), "
                                 f"got {getattr(self, name)!r}")  # fmt: skip
        for name in ("z_range", "yaw_range", "hover_duration"):
            value = getattr(self, name)
            if not isinstance(value, tuple | list) or len(value) != 2:
                raise ValueError(f"{owner} {name} must be two numbers (low, high), got {value!r}")
            low, high = (_number(owner, name, v) for v in value)
            if low > high:
                raise ValueError(f"{owner} {name} must be (low, high) with low <= high, got "
                                 f"{value!r}: swap them")  # fmt: skip
            object.__setattr__(self, name, (low, high))  # a list becomes a (hashable) tuple
        if self.hover_duration[0] <= 0:
            raise ValueError(f"{owner} hover_duration must be > 0 s at its shortest, got "
                             f"{self.hover_duration!r}")  # fmt: skip
        segments = self.segments
        if isinstance(segments, bool) or not isinstance(segments, int) or segments < 1:
            raise ValueError(f"{owner} segments must be an integer >= 1, got {segments!r}")
        if not 0 <= _number(owner, "hover_probability", self.hover_probability) <= 1:
            raise ValueError(f"{owner} hover_probability must lie in [0, 1], got "
                             f"{self.hover_probability!r}")  # fmt: skip
        if _number(owner, "max_stretch", self.max_stretch) < 1:
            raise ValueError(f"{owner} max_stretch must be >= 1 (1: every move as fast as the "
                             f"limits allow), got {self.max_stretch!r}")  # fmt: skip

    @classmethod
    def from_vehicle(cls, vehicle, speed_limit: float | None = ..., fraction: float = 0.5,
                     **overrides) -> Limits:  # fmt: skip
        """Limits a ``vehicle`` can fly with margin (module docstring): ``acceleration =
        fraction g min(sin(theta_max), TW - 1)`` and ``yaw_acceleration = fraction tau_z
        min(1, 2 min(1 - 1/TW, 1/TW)) / I_zz`` (:data:`IDEAL_YAW_ACCELERATION` for
        ideal rotors), speed and yaw rate :data:`DEFAULT_SPEED`, :data:`DEFAULT_YAW_RATE`.

        vehicle: has ``gravity``, ``inertia`` ``(3,)``, ``max_tilt()`` (rad) and
            ``authority(speed_limit)`` (:class:`fojax.vehicle.Vehicle`).
        speed_limit: the rotors' speed limit, rad/s, as ``vehicle.authority`` takes it
            (default the vehicle's own; ``None``: unlimited rotors).
        fraction: in ``(0, 1]``; the share of the vehicle's authority the reference may
            ask (1: all of it, leaving the controller nothing to correct with).
        overrides: any field of :class:`Limits` (the geometry, or a derived limit).
        """
        if not 0 < _number("Limits.from_vehicle", "fraction", fraction) <= 1:
            raise ValueError(f"Limits.from_vehicle fraction must lie in (0, 1], got {fraction!r}")
        authority = vehicle.authority(speed_limit)
        gravity, tilt = float(vehicle.gravity), float(vehicle.max_tilt())
        ratio = authority.thrust_to_weight
        if ratio is not None and ratio <= 1:
            raise ValueError(
                f"Limits.from_vehicle: the vehicle's rotors give {ratio:.3g} times its weight "
                "at this speed limit, not enough to hover; raise the speed limit"
            )
        bound = math.sin(tilt) if ratio is None else min(math.sin(tilt), ratio - 1.0)
        acceleration = fraction * gravity * bound
        if authority.max_torque is None:
            yaw_acceleration = IDEAL_YAW_ACCELERATION
        else:
            share = 1.0 if ratio is None else min(1.0, 2.0 * min(1.0 - 1.0 / ratio, 1.0 / ratio))
            yaw_acceleration = fraction * authority.max_torque[2] * share / vehicle.inertia[2]
        values = dict(speed=DEFAULT_SPEED, acceleration=acceleration, yaw_rate=DEFAULT_YAW_RATE,
                      yaw_acceleration=yaw_acceleration)  # fmt: skip
        unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"Limits.from_vehicle: unknown field(s) {', '.join(unknown)}")
        return cls(**{**values, **overrides})


class Manoeuvre(NamedTuple):
    """One draw's manoeuvre (arrays; a batch's has its axes last, or first under
    ``vmap``: :func:`position` takes the leading-axes layout as it is).

    starts: ``(S + 1,)`` s, the segments' start times, ``starts[0] = 0``; ``starts[S]``
        the end of the last segment (the last waypoint is held after it).
    waypoints: ``(S + 1, 4)`` ``(x, y, z, yaw)`` (m, rad); a hover segment ``j`` has
        ``waypoints[j + 1] == waypoints[j]``.
    offset: ``(3,)`` m, the vehicle's start relative to ``waypoints[0, :3]``.
    """

    starts: Array
    waypoints: Array
    offset: Array


def _shape(u):
    """``s(u) = 10 u^3 - 15 u^4 + 6 u^5`` (Horner: exactly 1 at ``u = 1``)."""
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def _durations(starts: Array) -> Array:
    return starts[1:] - starts[:-1]


def _distances(waypoints: Array) -> tuple[Array, Array]:
    """``(|dp|, |dyaw|)`` per segment, ``(S, *batch)`` each."""
    step = waypoints[1:] - waypoints[:-1]
    return jnp.sqrt(jnp.sum(step[:, :3] ** 2, axis=1)), jnp.abs(step[:, 3])


def sample(key, limits: Limits, horizon: float | None = None, dtype=None) -> Manoeuvre:
    """A random :class:`Manoeuvre` within ``limits`` (module docstring), drawn from
    ``key``. Pure; ``jit`` (``limits`` static) and ``vmap`` over ``key``.

    horizon: s, or ``None``. Given, every duration is stretched by ``max(1, horizon /
        total)``, so the manoeuvre lasts at least the horizon.
    dtype: of the arrays (default float64 with x64 enabled, else float32).
    """
    dtype = jnp.dtype(jnp.result_type(float) if dtype is None else dtype)
    count = limits.segments

    def stream(name):
        return jax.random.fold_in(key, STREAMS[name])

    low = jnp.asarray([-limits.half_extent, -limits.half_extent, limits.z_range[0],
                       limits.yaw_range[0]], dtype)  # fmt: skip
    high = jnp.asarray([limits.half_extent, limits.half_extent, limits.z_range[1],
                        limits.yaw_range[1]], dtype)  # fmt: skip
    candidates = jax.random.uniform(stream("waypoints"), (count + 1, 4), dtype, low, high)
    hover = jax.random.uniform(stream("hover"), (count,), dtype) < limits.hover_probability
    # P_(j+1) is the candidate of the last move up to segment j (P_0 = Q_0).
    moved = jnp.where(hover, 0, jnp.arange(1, count + 1))
    index = jnp.concatenate([jnp.zeros((1,), moved.dtype), jax.lax.cummax(moved)])
    waypoints = candidates[index]

    distance, turn = _distances(waypoints)
    shortest = jnp.max(
        jnp.stack([
            PEAK_SPEED * distance / limits.speed,
            jnp.sqrt(PEAK_ACCELERATION * distance / limits.acceleration),
            PEAK_SPEED * turn / limits.yaw_rate,
            jnp.sqrt(PEAK_ACCELERATION * turn / limits.yaw_acceleration),
            jnp.full_like(distance, limits.min_duration),
        ]),
        axis=0,
    )  # fmt: skip
    stretch = jax.random.uniform(stream("stretch"), (count,), dtype, 1.0, limits.max_stretch)
    held = jax.random.uniform(stream("hover_duration"), (count,), dtype,
                              limits.hover_duration[0], limits.hover_duration[1])  # fmt: skip
    durations = jnp.where(hover, held, shortest * stretch)
    if horizon is not None:
        durations = durations * jnp.maximum(1.0, jnp.asarray(horizon, dtype) / jnp.sum(durations))
    starts = jnp.concatenate([jnp.zeros((1,), dtype), jnp.cumsum(durations)])
    offset = jax.random.uniform(stream("offset"), (3,), dtype, -limits.initial_offset,
                                limits.initial_offset)  # fmt: skip
    return Manoeuvre(starts, waypoints, offset)


def position(manoeuvre: Manoeuvre, t) -> Array:
    """``(x, y, z, yaw)`` of ``manoeuvre`` at the scalar time ``t`` (s): ``(4,)``, or
    ``(4, *batch)`` for a manoeuvre whose leaves carry a batch's axes last.

    Twice differentiable in ``t`` by forward mode, finite everywhere (module
    docstring): ``fojax.scenarios.reference_with_derivatives(lambda s: position(m, s),
    t)`` gives the position, velocity and acceleration.
    """
    t = as_time(t)
    starts = manoeuvre.starts
    waypoints = manoeuvre.waypoints
    u = jnp.clip((t - starts[:-1]) / _durations(starts), 0.0, 1.0)  # (S, *batch)
    step = waypoints[1:] - waypoints[:-1]  # (S, 4, *batch)
    return waypoints[0] + jnp.sum(step * _shape(u)[:, None], axis=0)


def initial_position(manoeuvre: Manoeuvre) -> Array:
    """``(3,)`` (or ``(3, *batch)``) m: where the vehicle starts, ``P_0``'s position
    plus the offset (the reference starts at ``P_0``, yaw ``waypoints[0, 3]``)."""
    return manoeuvre.waypoints[0, :3] + manoeuvre.offset


def peaks(manoeuvre: Manoeuvre) -> dict[str, Array]:
    """Each segment's analytic peaks, ``(S,)`` (or ``(S, *batch)``) arrays: ``speed``
    (m/s) and ``acceleration`` (m/s^2) of the position, ``yaw_rate`` (rad/s) and
    ``yaw_acceleration`` (rad/s^2): ``15/8 D/T`` and ``10/sqrt(3) D/T^2`` over the
    segment's distance ``D`` and duration ``T``. Take ``max(axis=0)`` for the
    manoeuvre's."""
    durations = _durations(manoeuvre.starts)
    distance, turn = _distances(manoeuvre.waypoints)
    return {
        "speed": PEAK_SPEED * distance / durations,
        "acceleration": PEAK_ACCELERATION * distance / durations**2,
        "yaw_rate": PEAK_SPEED * turn / durations,
        "yaw_acceleration": PEAK_ACCELERATION * turn / durations**2,
    }
