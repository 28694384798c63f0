"""A quadrotor's physical parameters, from a file of its own (:class:`Vehicle`).

A vehicle file is TOML: an optional ``description``, a ``[vehicle]`` table with every
quantity of :class:`fojax.plant.PlantParams` as ``{ value = ..., unit = "..." }``, and
optionally the rotors' limit as ``rotor_speed_limit`` (rad/s or rpm) or
``thrust_to_weight`` (a plain number, the ratio of full thrust to the weight)::

    description = "the paper's quadrotor (Section V)"

    [vehicle]
    mass = { value = 0.74, unit = "kg" }
    inertia = { value = [0.004, 0.004, 0.0084], unit = "kg m^2" }
    arm_length = { value = 0.21, unit = "m" }
    drag_position = { value = [0.01, 0.01, 0.01], unit = "N s/m" }
    drag_attitude = { value = [0.012, 0.012, 0.012], unit = "N m s^2" }
    thrust_factor = { value = 3e-3, unit = "N s^2" }
    drag_factor = { value = 3.24e-2, unit = "N m s^2" }
    rotor_inertia = { value = 2.8385e-5, unit = "kg m^2" }
    gravity = { value = 9.81, unit = "m/s^2" }

The rotors are the paper's ``+`` at ``arm_length`` unless the table says otherwise:
``configuration = "x"`` turns them by 45 degrees, or ``[[vehicle.rotors]]`` lists the
four one by one (instead of ``arm_length`` and ``configuration``), each with its
position in the body frame (``x`` forward, ``y`` left) and its spin seen from above
(:mod:`fojax.rotors` derives the allocation)::

    [[vehicle.rotors]]
    position = { value = [0.13, -0.22], unit = "m" }
    spin = "ccw"

Two optional quantities describe the rotors further: ``rotor_time_constant`` (s or
ms), the first-order lag of a rotor's speed behind its command (absent or 0:
instantaneous rotors), and ``tilt_limit`` (deg or rad, default
:data:`DEFAULT_TILT_LIMIT`), the largest tilt a reference may ask of the vehicle
(:func:`fojax.reference.problems_for`).

An optional ``[uncertainty]`` table gives relative half-widths of the fields (not
gravity) that vary from draw to draw, as a per cent or a plain share::

    [uncertainty]
    mass = { value = 5, unit = "%" }
    thrust_factor = { value = 0.1, unit = "1" }

Every field is required (a vehicle is never half the paper's); units are converted to
SI by the factors of :data:`FIELDS`. :func:`load` checks the whole file and raises one
:class:`VehicleError` listing every problem (the field, what is wrong, what to write),
before anything is simulated; among them a vehicle whose rotors cannot hold it in
hover within their speed limit.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from typing import Any

from fojax import _files, plant, rotors
from fojax._files import Field
from fojax._files import number as _number
from fojax._files import quantity as _quantity

__all__ = [
    "DEFAULT_TILT_LIMIT", "FIELDS", "UNCERTAIN", "Field", "Vehicle", "VehicleError", "load",
    "parse",
]  # fmt: skip


class VehicleError(ValueError):
    """A vehicle file or table that cannot be used; the message lists every problem."""


_MASS = {"kg": 1.0, "g": 1e-3}
_INERTIA = {"kg m^2": 1.0, "g m^2": 1e-3, "g cm^2": 1e-7, "g mm^2": 1e-9}
_LENGTH = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_TORQUE_S2 = {"N m s^2": 1.0}

FIELDS: dict[str, Field] = {
    f.name: f
    for f in (
        Field("mass", None, _MASS, "m", "the vehicle's mass"),
        Field("inertia", 3, _INERTIA, "I", "the diagonal of the inertia about the body axes"),
        Field("arm_length", None, _LENGTH, "d", "from the centre to a rotor's axis"),
        Field("drag_position", 3, {"N s/m": 1.0}, "K_p", "translational drag, per axis"),
        Field("drag_attitude", 3, _TORQUE_S2, "K_phi",
              "rotational drag, torque per w|w| of the body rates"),  # fmt: skip
        Field("thrust_factor", None, {"N s^2": 1.0}, "rho_b",
              "a rotor's thrust per squared speed (rad/s)"),  # fmt: skip
        Field("drag_factor", None, _TORQUE_S2, "rho_c",
              "a rotor's drag torque per squared speed (rad/s)"),  # fmt: skip
        Field("rotor_inertia", None, _INERTIA, "J_r", "a rotor's inertia about its axis"),
        Field("gravity", None, {"m/s^2": 1.0}, "g", "the gravitational acceleration"),
    )
}
"""The quantities of a vehicle file (each a field of :class:`fojax.plant.PlantParams`)."""

_SPEED = {"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0}
_RELATIVE = {"1": 1.0, "%": 1e-2}
UNCERTAIN = tuple(name for name in FIELDS if name != "gravity")
"""The fields an ``[uncertainty]`` table may name."""
_LIMITS = ("rotor_speed_limit", "thrust_to_weight")
_ROTORS = ("configuration", "rotors", "rotor_time_constant", "tilt_limit")
_CONFIGURATIONS = ("plus", "x")
_TIME_CONSTANT = Field("rotor_time_constant", None, {"s": 1.0, "ms": 1e-3}, "T_r",
                       "a rotor speed's first-order lag behind its command")  # fmt: skip
_TILT = Field("tilt_limit", None, {"deg": math.pi / 180.0, "rad": 1.0}, "theta_max",
              "the largest tilt a reference may ask for")  # fmt: skip
DEFAULT_TILT_LIMIT = math.radians(45.0)
"""The largest tilt (rad) a reference may ask of a vehicle whose file states none: the
thrust then keeps ``cos 45 deg = 0.71`` of itself for holding altitude, and the
attitude loop a margin to 90 degrees (where a draw is flagged ``tilt_limit``)."""


@dataclasses.dataclass(frozen=True)
class Vehicle:
    """A quadrotor: its :data:`FIELDS` in SI units (floats; tuples for vectors), the
    rotors' speed limit (rad/s) or thrust-to-weight ratio where it has one, and a
    description. :meth:`params` is the simulator's :class:`fojax.plant.PlantParams`.
    uncertainty: ``((field, a), ...)``, relative half-widths in :data:`FIELDS` order:
    every draw's plant has ``field (1 + U[-a, a])``, independently per component
    (:meth:`perturb`); the controllers keep the nominal values as their model."""

    mass: float
    inertia: tuple[float, float, float]
    arm_length: float
    drag_position: tuple[float, float, float]
    drag_attitude: tuple[float, float, float]
    thrust_factor: float
    drag_factor: float
    rotor_inertia: float
    gravity: float
    rotor_speed_limit: float | None = None
    thrust_to_weight: float | None = None
    description: str = ""
    uncertainty: tuple[tuple[str, float], ...] = ()
    layout: rotors.Layout | None = None
    """``None``: the paper's ``+`` at :attr:`arm_length`; else the rotors'
    :class:`fojax.rotors.Layout` (``configuration = "x"`` or listed rotors)."""
    rotor_time_constant: float | None = None
    """The rotors' first-order lag (s); ``None`` (or 0): instantaneous rotors."""
    tilt_limit: float | None = None
    """The largest tilt (rad) a reference may ask for; ``None``: :data:`DEFAULT_TILT_LIMIT`."""

    @classmethod
    def paper(cls) -> Vehicle:
        """The paper's vehicle (Section V; :func:`fojax.plant.nominal_params`)."""
        values = {name: _python(getattr(plant, constant)) for name, constant in _PAPER.items()}
        return cls(**values, description="the paper's quadrotor (Section V)")

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> Vehicle:
        """:func:`load`."""
        return load(path)

    def params(self, dtype=None) -> plant.PlantParams:
        """The plant's parameters (leaves of ``dtype``, default float32 or float64 with
        x64 enabled), as :func:`fojax.plant.nominal_params` builds the paper's."""
        import jax.numpy as jnp

        dtype = plant._default_float(dtype)
        return plant.PlantParams(**{name: jnp.asarray(getattr(self, name), dtype)
                                    for name in FIELDS}, layout=self.layout)  # fmt: skip

    def rotor_layout(self) -> rotors.Layout:
        """The rotors' :class:`fojax.rotors.Layout` (the ``+`` at :attr:`arm_length` where
        the file gives none)."""
        return self.layout if self.layout is not None else rotors.plus(self.arm_length)

    def authority(self, speed_limit: float | None = ...) -> rotors.Authority:
        """The :class:`fojax.rotors.Authority` of the nominal vehicle at ``speed_limit``
        (rad/s; default :meth:`speed_limit`, ``None``: unlimited rotors)."""
        limit = self.speed_limit() if speed_limit is ... else speed_limit
        return rotors.authority(self.rotor_layout(), self.mass, self.gravity,
                                self.thrust_factor, self.drag_factor, limit)  # fmt: skip

    def max_tilt(self) -> float:
        """The largest tilt (rad) a reference may ask of this vehicle."""
        return DEFAULT_TILT_LIMIT if self.tilt_limit is None else self.tilt_limit

    def lag(self) -> float | None:
        """The rotors' time constant (s) where they lag, else ``None``."""
        return self.rotor_time_constant or None

    def perturb(self, params: plant.PlantParams, key) -> plant.PlantParams:
        """``params`` with every field of :attr:`uncertainty` multiplied by ``1 + U[-a,
        a]`` (one factor per component), drawn from ``key``; ``params`` itself without
        uncertainty. Pure; ``vmap``-able over ``key``."""
        import jax

        changes = {}
        for name, half_width in self.uncertainty:
            value = getattr(params, name)
            subkey = jax.random.fold_in(key, UNCERTAIN.index(name))
            factor = jax.random.uniform(subkey, value.shape, value.dtype, -half_width, half_width)
            changes[name] = value * (1.0 + factor)
        return params._replace(**changes)

    def speed_limit(self) -> float | None:
        """``w_max`` in rad/s: the given one, or the one at which four rotors give
        :attr:`thrust_to_weight` times the weight; ``None`` for unlimited rotors."""
        if self.rotor_speed_limit is not None:
            return self.rotor_speed_limit
        if self.thrust_to_weight is None:
            return None
        weight = self.mass * self.gravity
        return math.sqrt(self.thrust_to_weight * weight / (4.0 * self.thrust_factor))

    def to_dict(self) -> dict:
        """The file's content in SI units (what a run's fingerprint records)."""
        out = {name: _listed(getattr(self, name)) for name in FIELDS}
        for name in _LIMITS:
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        if self.layout is not None:
            out.update(self.layout.to_dict())
        for name in ("rotor_time_constant", "tilt_limit"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        uncertainty = {"uncertainty": dict(self.uncertainty)} if self.uncertainty else {}
        return {"description": self.description, "vehicle": out, **uncertainty}


_PAPER = {
    "mass": "_NOMINAL_MASS",
    "inertia": "_NOMINAL_INERTIA",
    "arm_length": "_NOMINAL_ARM_LENGTH",
    "drag_position": "_NOMINAL_DRAG_POSITION",
    "drag_attitude": "_NOMINAL_DRAG_ATTITUDE",
    "thrust_factor": "_NOMINAL_THRUST_FACTOR",
    "drag_factor": "_NOMINAL_DRAG_FACTOR",
    "rotor_inertia": "_NOMINAL_ROTOR_INERTIA",
    "gravity": "_GRAVITY",
}


def _python(value: Any):
    if isinstance(value, tuple | list):
        return tuple(float(v) for v in value)
    return float(value)


def _listed(value: Any):
    return list(value) if isinstance(value, tuple) else value


def parse(data: Mapping, source: str = "vehicle") -> Vehicle:
    """The :class:`Vehicle` of a vehicle file's content (module docstring);
    :class:`VehicleError` listing every problem, each naming its field."""
    description, table, problems = _files.header(
        data, source, "vehicle", VehicleError, "vehicle file",
        "the vehicle's quantities, with units", ("uncertainty",),
    )  # fmt: skip
    unknown = sorted(set(table) - set(FIELDS) - set(_LIMITS) - set(_ROTORS))
    if unknown:
        problems.append(
            f"vehicle: unknown field(s) {', '.join(unknown)} (the fields: "
            f"{', '.join([*FIELDS, *_LIMITS, *_ROTORS])})"
        )
    values: dict[str, Any] = {}
    listed = "rotors" in table
    for name, field in FIELDS.items():
        if name == "arm_length" and listed:
            if name in table:
                problems.append("vehicle: give arm_length (with configuration) or the rotors "
                                "one by one, not both")  # fmt: skip
            continue
        if name not in table:
            problems.append(f"vehicle.{name}: missing ({field.summary}, {field.symbol}, "
                            f"in {field.unit})")  # fmt: skip
            continue
        values[name] = _quantity(field, table[name], problems)
    if all(name in table for name in _LIMITS):
        problems.append("vehicle: give rotor_speed_limit or thrust_to_weight, not both")
    if "rotor_speed_limit" in table:
        limit = Field("rotor_speed_limit", None, _SPEED, "w_max", "the rotors' speed limit")
        values["rotor_speed_limit"] = _quantity(limit, table["rotor_speed_limit"], problems)
    if "thrust_to_weight" in table:
        ratio = table["thrust_to_weight"]
        if not (_number(ratio) and math.isfinite(ratio) and ratio > 1):
            problems.append(
                f"vehicle.thrust_to_weight: expected a number > 1 (full thrust over the "
                f"weight; at or below 1 the vehicle cannot hover), got {ratio!r}"
            )
        else:
            values["thrust_to_weight"] = float(ratio)
    layout = _layout(table, values.get("arm_length"), problems)
    if listed and layout is not None:
        values["arm_length"] = layout.arm()
    for field in (_TIME_CONSTANT, _TILT):
        if field.name in table:
            values[field.name] = _quantity(field, table[field.name], problems, zero=True)
    lag = values.get("rotor_time_constant")
    if lag is not None and lag >= 1.0:
        problems.append(f"vehicle.rotor_time_constant: expected a lag below 1 s (a rotor "
                        f"follows its command in tens of milliseconds), got {lag:g} s")  # fmt: skip
    tilt = values.get("tilt_limit")
    if tilt is not None and not 0 < tilt < 0.5 * math.pi:
        problems.append(f"vehicle.tilt_limit: expected an angle above 0 and below 90 deg, got "
                        f"{math.degrees(tilt):g} deg")  # fmt: skip
    uncertainty = _uncertainty(data.get("uncertainty", {}), problems)
    if problems:
        raise VehicleError(_message(source, problems))
    vehicle = Vehicle(**values, description=description, uncertainty=uncertainty,
                      layout=None if layout is None or layout.name == "plus" else layout)
    problems = hover_problems(vehicle)
    if problems:
        raise VehicleError(_message(source, problems))
    return vehicle


def hover_problems(vehicle: Vehicle, speed_limit: float | None = ...,
                   where: str = "vehicle.rotor_speed_limit") -> list[str]:  # fmt: skip
    """Why ``vehicle``'s rotors cannot hold it in level hover at ``speed_limit`` (rad/s;
    default its own, ``None``: unlimited; ``where`` names the limit's source): a rotor
    that would have to turn faster than the limit, or backwards (the centre of mass
    outside the rotors); empty when it can hover."""
    limit = vehicle.speed_limit() if speed_limit is ... else speed_limit
    squared = rotors.hover_speeds_squared(vehicle.rotor_layout(), vehicle.mass,
                                          vehicle.gravity, vehicle.thrust_factor)  # fmt: skip
    if float(min(squared)) <= 0:
        return [
            "vehicle.rotors: in level hover a rotor would have to push down (squared hover "
            f"speeds {', '.join(f'{w:.4g}' for w in squared)} rad^2/s^2); the centre of mass "
            "must lie inside the rotors"
        ]
    if limit is None:
        return []
    needed = math.sqrt(float(max(squared)))
    if needed < limit:
        return []
    ratio = vehicle.authority(limit).thrust_to_weight
    return [
        f"{where}: {limit:.4g} rad/s ({limit * 60 / (2 * math.pi):.4g} rpm) cannot lift the "
        f"vehicle: hover needs {needed:.4g} rad/s ({needed * 60 / (2 * math.pi):.4g} rpm) "
        f"from its fastest rotor, and full thrust is {ratio:.3g} times the weight "
        f"({vehicle.mass:g} kg x {vehicle.gravity:g} m/s^2); raise the limit or check "
        "thrust_factor and mass"
    ]


def _layout(table: Mapping, arm: float | None, problems: list[str]) -> rotors.Layout | None:
    """The layout of ``configuration`` (with ``arm``) or of the listed ``rotors``."""
    listed = table.get("rotors")
    configuration = table.get("configuration", "plus")
    if listed is not None:
        if "configuration" in table:
            problems.append("vehicle: give configuration or the rotors one by one, not both")
        return _listed_rotors(listed, problems)
    if configuration not in _CONFIGURATIONS:
        problems.append(f"vehicle.configuration: expected one of "
                        f"{', '.join(repr(c) for c in _CONFIGURATIONS)} (or list the rotors "
                        f"as [[vehicle.rotors]]), got {configuration!r}")  # fmt: skip
        return None
    if arm is None:
        return None
    return rotors.plus(arm) if configuration == "plus" else rotors.x(arm)


_POSITION = Field("position", 2, _LENGTH, "r_i", "a rotor's position (x forward, y left)")


def _listed_rotors(listed: Any, problems: list[str]) -> rotors.Layout | None:
    """The layout of ``[[vehicle.rotors]]`` (four tables of position and spin)."""
    if not (isinstance(listed, list) and all(isinstance(r, Mapping) for r in listed)):
        problems.append("vehicle.rotors: expected [[vehicle.rotors]] tables, each with a "
                        "position and a spin")  # fmt: skip
        return None
    if len(listed) != 4:
        problems.append(f"vehicle.rotors: a quadrotor has four rotors, got {len(listed)}")
        return None
    positions, spins, ok = [], [], True
    for i, rotor in enumerate(listed, 1):
        where = f"rotors[{i}]"
        unknown = sorted(set(rotor) - {"position", "spin"})
        if unknown:
            problems.append(f"vehicle.{where}: unknown key(s) {', '.join(unknown)} "
                            "(expected position, spin)")  # fmt: skip
        position = _quantity(_POSITION, rotor.get("position"), problems, f"vehicle.{where}",
                             signed=True)  # fmt: skip
        spin = rotor.get("spin")
        if spin not in rotors.SPINS:
            problems.append(f"vehicle.{where}.spin: expected \"ccw\" or \"cw\" (seen from "
                            f"above), got {spin!r}")  # fmt: skip
            ok = False
        ok = ok and position is not None
        positions.append(position)
        spins.append(rotors.SPINS.get(spin))
    if not ok:
        return None
    try:
        return rotors.Layout(tuple(positions), tuple(spins))
    except rotors.LayoutError as error:
        problems.append(f"vehicle.rotors: {error}")
        return None


def _uncertainty(table: Any, problems: list[str]) -> tuple[tuple[str, float], ...]:
    """The ``[uncertainty]`` table's relative half-widths in :data:`FIELDS` order."""
    if not isinstance(table, Mapping):
        problems.append(f"uncertainty: expected a table of fields, got {table!r}")
        return ()
    unknown = sorted(set(table) - set(UNCERTAIN))
    if unknown:
        problems.append(f"uncertainty: unknown field(s) {', '.join(unknown)} (the fields: "
                        f"{', '.join(UNCERTAIN)})")  # fmt: skip
    found = []
    for name in (n for n in UNCERTAIN if n in table):
        relative = Field(name, None, _RELATIVE, "a", "relative half-width")
        share = _quantity(relative, table[name], problems, "uncertainty")
        if share is None:
            continue
        if share >= 1:
            problems.append(f"uncertainty.{name}: expected a relative half-width below 100 %, "
                            f"got {table[name]['value']!r} {table[name]['unit']}")  # fmt: skip
            continue
        found.append((name, share))
    return tuple(found)


def _message(source: str, problems: list[str]) -> str:
    return _files.message(source, "vehicle file", problems)


def load(path: str | os.PathLike) -> Vehicle:
    """The :class:`Vehicle` of the TOML file at ``path``; :class:`VehicleError` (one
    message, every problem) for a file that cannot be read or used."""
    data = _files.read_table(path, VehicleError, "vehicle file")
    return parse(data, str(path))
