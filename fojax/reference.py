"""References from timed waypoints (:class:`Waypoints`), smooth enough for every law.

A reference file is TOML: an optional ``description`` and a ``[reference]`` table of
equally long lists, each with its unit::

    description = "a climb and a square"

    [reference]
    time = { value = [0, 10, 20, 30, 40], unit = "s" }
    x = { value = [0.05, 1, 1, 0, 0], unit = "m" }
    y = { value = [0.01, 0, 1, 1, 0], unit = "m" }
    z = { value = [0, 2, 2, 2, 2], unit = "m" }
    yaw = { value = [0.1, 0.1, 0.1, 0.1, 0.1], unit = "rad" }

Or a named built-in reference (:data:`BUILTINS`), the table holding only its name::

    [reference]
    builtin = "paper-54-55"

The reference through waypoints (:meth:`Waypoints.reference`) is, per axis, the quintic
interpolating spline (degree 5, four continuous derivatives), by default at rest at
both ends (zero velocity and acceleration at the first and last waypoint; ``ends =
"not-a-knot"`` lets the ends follow the waypoints instead), and holds the last waypoint
after it. The laws use the reference and its first two derivatives (exact,
by forward-mode autodiff: :func:`fojax.scenarios.reference_with_derivatives`).
:meth:`Waypoints.peaks` (:meth:`Builtin.peaks`) reports its peak speed, acceleration, and
the tilt and thrust its acceleration asks for; :func:`problems_for` compares them with
what a vehicle can fly. :func:`load` checks the file and raises one
:class:`ReferenceError` listing every problem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from fojax import _files

__all__ = [
    "AXES", "BUILTINS", "Builtin", "ReferenceError", "SplineReference", "Waypoints", "load",
    "parse", "problems_for",
]  # fmt: skip


class ReferenceError(ValueError):
    """A reference file or table that cannot be used; the message lists every problem."""


AXES = {
    "time": {"s": 1.0},
    "x": {"m": 1.0, "cm": 1e-2},
    "y": {"m": 1.0, "cm": 1e-2},
    "z": {"m": 1.0, "cm": 1e-2},
    "yaw": {"rad": 1.0, "deg": math.pi / 180.0},
}
"""The lists of a reference file and their units (the first one SI)."""

DEGREE = 5
"""The splines' degree: four continuous derivatives."""
ENDS = ("rest", "not-a-knot")
"""The end conditions of a reference file's ``ends`` (:attr:`Waypoints.ends`)."""
BUILTINS = {
    "paper-54-55": ("reference_54_55", "the paper's (54)-(55): scenarios 1 and 2"),
    "paper-57": ("reference_57", "the paper's (57) as printed: scenario 3"),
    "paper-57-smoothed": ("reference_57_smoothed", "(57) with its start at 7 s smoothed"),
}
"""Named references of a file's ``builtin``: the :mod:`fojax.scenarios` function and
what it is."""


def _peaks(derivatives, start: float, end: float, samples_per_second: int,
           breaks=None) -> dict:  # fmt: skip
    """Peak speed, acceleration, implied tilt and thrust over ``[start, end]`` of
    ``derivatives(t, order) -> (len(t), 4)``, sampled ``samples_per_second`` and, with
    ``breaks`` (a piecewise polynomial's), 64 times in every piece however short."""
    t = np.linspace(start, end, max(2, int(samples_per_second * (end - start)) + 1))
    if breaks is not None:
        b = np.asarray(breaks, np.float64)
        t = np.union1d(t, (b[:-1, None] + np.diff(b)[:, None] * np.linspace(0, 1, 65)).ravel())
    velocity = derivatives(t, 1)[:, :3]
    acceleration = derivatives(t, 2)[:, :3]
    vertical = acceleration[:, 2] + 9.81
    horizontal = np.hypot(acceleration[:, 0], acceleration[:, 1])
    return {
        "speed": float(np.max(np.linalg.norm(velocity, axis=1))),
        "acceleration": float(np.max(np.linalg.norm(acceleration, axis=1))),
        "tilt": float(np.max(np.arctan2(horizontal, vertical))),
        "thrust": float(np.max(np.hypot(horizontal, vertical)) / 9.81),
    }


def problems_for(peaks: dict, vehicle, speed_limit: float | None = ...) -> list[str]:
    """Why a reference of ``peaks`` (:meth:`Waypoints.peaks`) is beyond what ``vehicle``
    (a :class:`fojax.vehicle.Vehicle`; ``None``: the paper's) can fly, with its rotors
    limited to ``speed_limit`` rad/s (default the vehicle's own; ``None``: unlimited):
    a peak thrust (``|a + g e_z|`` over ``g``, the weights it asks for) at or above the
    vehicle's thrust-to-weight, or a tilt past its ``tilt_limit``. Empty when it can."""
    from fojax.vehicle import Vehicle

    vehicle = Vehicle.paper() if vehicle is None else vehicle
    out = []
    ratio = vehicle.authority(speed_limit).thrust_to_weight
    if ratio is not None and peaks["thrust"] >= ratio:
        out.append(
            f"its peak acceleration ({peaks['acceleration']:.3g} m/s^2) asks for "
            f"{peaks['thrust']:.3g} times the weight in thrust, and the vehicle's rotors give "
            f"{ratio:.3g} times it"
        )
    limit = vehicle.max_tilt()
    if peaks["tilt"] > limit:
        where = "its tilt_limit" if vehicle.tilt_limit is not None else "the default limit"
        out.append(
            f"its acceleration asks for a tilt of {math.degrees(peaks['tilt']):.1f} deg, past "
            f"the vehicle's {math.degrees(limit):.0f} deg ({where})"
        )
    return out


@dataclasses.dataclass(frozen=True)
class Builtin:
    """A named reference of :mod:`fojax.scenarios` (:data:`BUILTINS`), defined at every
    time (``end`` is ``None``)."""

    name: str
    description: str = ""
    end = None

    def reference(self):
        """The scenarios' function ``t -> (4,)``."""
        from fojax import scenarios

        return getattr(scenarios, BUILTINS[self.name][0])

    def fingerprint(self) -> str:
        return self.name

    def peaks(self, until: float, samples_per_second: int = 100) -> dict:
        """As :meth:`Waypoints.peaks`, over ``[0, until]`` (one-sided derivatives where
        the reference has a kink)."""
        import jax

        from fojax import scenarios

        function = self.reference()
        each = jax.jit(jax.vmap(lambda t: scenarios.reference_with_derivatives(function, t)))

        def derivatives(t, order):
            return np.asarray(each(np.asarray(t))[order], np.float64)

        return _peaks(derivatives, 0.0, float(until), samples_per_second)

    def to_dict(self) -> dict:
        return {"description": self.description, "builtin": self.name}


@dataclasses.dataclass(frozen=True)
class Waypoints:
    """Timed waypoints in SI units: ``times`` ``(n,)`` s, strictly increasing from 0;
    ``positions`` ``(n, 3)`` m; ``yaw`` ``(n,)`` rad (tuples, so that it hashes)."""

    times: tuple[float, ...]
    positions: tuple[tuple[float, float, float], ...]
    yaw: tuple[float, ...]
    description: str = ""
    ends: str = "rest"
    """``"rest"``: zero velocity and acceleration at the first and last waypoint;
    ``"not-a-knot"``: the ends follow the waypoints (for waypoints sampled from a
    curve that does not start or end at rest)."""

    def reference(self) -> SplineReference:
        """The reference through the waypoints (module docstring)."""
        from scipy.interpolate import PPoly, make_interp_spline

        t = np.asarray(self.times, np.float64)
        values = np.column_stack([np.asarray(self.positions, np.float64),
                                  np.asarray(self.yaw, np.float64)])  # fmt: skip
        rest = [(1, np.zeros(4)), (2, np.zeros(4))]
        ends = (rest, rest) if self.ends == "rest" else "not-a-knot"
        spline = make_interp_spline(t, values, k=DEGREE, bc_type=ends)
        axes = [PPoly.from_spline((spline.t, spline.c[:, j], DEGREE)) for j in range(4)]
        x = axes[0].x
        # the pieces of the waypoints' intervals only (the B-spline's end knots repeat)
        keep = (x[:-1] >= t[0]) & (x[1:] <= t[-1]) & (np.diff(x) > 0)
        breaks = np.append(x[:-1][keep], t[-1])
        coefficients = np.stack([np.asarray(axis.c)[:, keep] for axis in axes], axis=-1)
        return SplineReference(breaks, coefficients, self.fingerprint())

    @property
    def end(self) -> float:
        """The last waypoint's time, s (held after it)."""
        return self.times[-1]

    def fingerprint(self) -> str:
        """A digest of the waypoints (the reference's name in a run's fingerprint)."""
        text = json.dumps([self.times, self.positions, self.yaw, self.ends])
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def peaks(self, until: float | None = None, samples_per_second: int = 100) -> dict:
        """Peak speed (m/s), acceleration (m/s^2) and implied tilt (rad) of
        :meth:`reference` over the waypoints' span (held still after it, so ``until``
        changes nothing): the tilt is that of the thrust direction ``(a_x, a_y, a_z + g)``
        the acceleration asks for, ``g = 9.81``."""
        reference = self.reference()
        return _peaks(reference.derivative, self.times[0], self.times[-1], samples_per_second,
                      reference.breaks)  # fmt: skip

    def to_dict(self) -> dict:
        return {"description": self.description, "times": list(self.times),
                "positions": [list(p) for p in self.positions], "yaw": list(self.yaw),
                "ends": self.ends}  # fmt: skip


class SplineReference:
    """``t -> (4,)`` ``(x_r, y_r, z_r, psi_r)``: piecewise polynomials (JAX, differentiable
    in ``t``), the last waypoint held after the last break. breaks: ``(m + 1,)`` s.
    coefficients: ``(degree + 1, m, 4)``, highest power first, in ``t - breaks[i]``.
    ``__name__`` names the waypoints (a run's fingerprint)."""

    def __init__(self, breaks: np.ndarray, coefficients: np.ndarray, digest: str):
        self.breaks = np.asarray(breaks, np.float64)
        self.coefficients = np.asarray(coefficients, np.float64)
        self.__name__ = f"waypoints_{digest}"

    def __call__(self, t):
        import jax.numpy as jnp

        t = jnp.asarray(t)
        dtype = t.dtype if jnp.issubdtype(t.dtype, jnp.floating) else jnp.result_type(float)
        t = t.astype(dtype)
        breaks = jnp.asarray(self.breaks, dtype)
        last = breaks[-1]
        held = jnp.where(t <= last, t, last)  # at the last break its left derivatives
        index = jnp.clip(jnp.searchsorted(breaks, held, side="right") - 1, 0,
                         self.coefficients.shape[1] - 1)  # fmt: skip
        s = held - breaks[index]
        c = jnp.asarray(self.coefficients, dtype)[:, index, :]  # (degree + 1, 4)
        value = c[0]
        for row in c[1:]:
            value = value * s + row
        return value

    def derivative(self, t: np.ndarray, order: int) -> np.ndarray:
        """``(len(t), 4)`` the ``order``-th derivative at the times ``t`` (NumPy, for
        reports; the laws differentiate :meth:`__call__` itself)."""
        t = np.minimum(np.asarray(t, np.float64), self.breaks[-1])
        index = np.clip(np.searchsorted(self.breaks, t, side="right") - 1, 0,
                        self.coefficients.shape[1] - 1)  # fmt: skip
        s = t - self.breaks[index]
        degree = self.coefficients.shape[0] - 1
        out = np.zeros((t.size, 4))
        for row, power in enumerate(range(degree, -1, -1)):
            if power < order:
                continue
            factor = math.factorial(power) / math.factorial(power - order)
            out += factor * self.coefficients[row, index, :] * (s ** (power - order))[:, None]
        return out


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def parse(data: Mapping, source: str = "reference") -> Waypoints | Builtin:
    """The :class:`Waypoints` (or :class:`Builtin`) of a reference file's content;
    :class:`ReferenceError` listing every problem, each naming its list."""
    problems: list[str] = []
    if not isinstance(data, Mapping):
        raise ReferenceError(f"{source}: expected a table, got {type(data).__name__}")
    unknown = sorted(set(data) - {"description", "reference"})
    if unknown:
        problems.append(f"unknown top-level key(s) {', '.join(unknown)} (expected "
                        "description, reference)")  # fmt: skip
    description = data.get("description", "")
    if not isinstance(description, str):
        problems.append(f"description: expected a string, got {description!r}")
        description = ""
    table = data.get("reference")
    if not isinstance(table, Mapping):
        raise ReferenceError(
            _message(
                source,
                problems
                + [
                    "missing [reference] table (time, x, y, z, yaw: lists with units; "
                    "or builtin = a name)"
                ],
            )
        )
    if "builtin" in table:
        name = table["builtin"]
        if name not in BUILTINS:
            problems.append(f"reference.builtin: expected one of {', '.join(BUILTINS)}, got "
                            f"{name!r}")  # fmt: skip
        others = sorted(set(table) - {"builtin"})
        if others:
            problems.append(f"reference: builtin names the whole reference; remove "
                            f"{', '.join(others)}")  # fmt: skip
        if problems:
            raise ReferenceError(_message(source, problems))
        return Builtin(name, description or BUILTINS[name][1])
    unknown = sorted(set(table) - set(AXES) - {"ends"})
    if unknown:
        problems.append(f"reference: unknown list(s) {', '.join(unknown)} (the lists: "
                        f"{', '.join(AXES)})")  # fmt: skip
    lists: dict[str, list[float]] = {}
    for name, units in AXES.items():
        where, names = f"reference.{name}", ", ".join(f'"{u}"' for u in units)
        entry = table.get(name)
        if entry is None:
            problems.append(f"{where}: missing (a list with a unit among {names})")
            continue
        if not isinstance(entry, Mapping) or set(entry) != {"value", "unit"}:
            problems.append(f"{where}: expected {{ value = [...], unit = ... }} with a unit "
                            f"among {names}, got {entry!r}")  # fmt: skip
            continue
        if entry["unit"] not in units:
            problems.append(f"{where}: unit {entry['unit']!r} is not one of {names}")
            continue
        value = entry["value"]
        if not (isinstance(value, list) and value and all(_number(v) for v in value)):
            problems.append(f"{where}: expected a list of numbers, got {value!r}")
            continue
        if not all(math.isfinite(v) for v in value):
            problems.append(f"{where}: every value must be finite, got {value!r}")
            continue
        lists[name] = [float(v) * units[entry["unit"]] for v in value]
    if len(lists) == len(AXES):
        sizes = {name: len(v) for name, v in lists.items()}
        if len(set(sizes.values())) > 1:
            problems.append(
                "reference: the lists differ in length ("
                + ", ".join(f"{k} {v}" for k, v in sizes.items())
                + ")"
            )
        elif sizes["time"] < 2:
            problems.append("reference: at least two waypoints are needed")
        else:
            times = lists["time"]
            if times[0] != 0:
                problems.append(
                    f"reference.time: the first waypoint must be at 0 s, got {times[0]}"
                )
            steps = np.diff(times)
            if np.any(steps <= 0):
                i = int(np.argmax(steps <= 0))
                problems.append(
                    f"reference.time: times must increase; waypoint {i + 1} "
                    f"({times[i + 1]} s) is not after waypoint {i} ({times[i]} s)"
                )
    ends = table.get("ends", "rest")
    if ends not in ENDS:
        problems.append(f"reference.ends: expected one of {', '.join(ENDS)}, got {ends!r}")
    elif ends == "not-a-knot" and len(lists.get("time", ())) < DEGREE + 1:
        problems.append(f"reference.ends: not-a-knot needs at least {DEGREE + 1} waypoints")
    if problems:
        raise ReferenceError(_message(source, problems))
    positions = tuple(zip(lists["x"], lists["y"], lists["z"], strict=True))
    return Waypoints(tuple(lists["time"]), positions, tuple(lists["yaw"]), description, ends)


def _message(source: str, problems: list[str]) -> str:
    return f"{source} is not a usable reference file:\n" + "\n".join(f"  {p}" for p in problems)


def load(path: str | os.PathLike) -> Waypoints | Builtin:
    """The :class:`Waypoints` (or :class:`Builtin`) of the TOML file at ``path``;
    :class:`ReferenceError` (one message, every problem) for a file that cannot be read or
    used."""
    data = _files.read_table(path, ReferenceError, "reference file")
    return parse(data, str(path))
