"""Requirements as data: the metric catalogue, units, :class:`Requirement`,
:class:`RequirementSet`, parsing (TOML, JSON, Python) and validation.

Everything here is plain Python: a requirement file is checked completely (every
problem listed in one :class:`RequirementError`) before anything is traced or compiled.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterable, Mapping
from typing import Any

from fojax import _files

__all__ = [
    "BOUNDS",
    "METRICS",
    "MetricInfo",
    "Requirement",
    "RequirementError",
    "RequirementSet",
    "Settings",
    "UNITS",
    "load",
    "parse",
]

BOUNDS = ("upper", "lower")
"""``upper``: the metric must be ``<= value``; ``lower``: ``>= value``."""

# Canonical unit -> {accepted spelling: factor to the canonical unit}.
UNITS: dict[str, dict[str, float]] = {
    "m": {"m": 1.0, "cm": 1e-2, "mm": 1e-3},
    "rad": {"rad": 1.0, "deg": math.pi / 180.0},
    "s": {"s": 1.0, "ms": 1e-3},
    "1": {"1": 1.0, "%": 1e-2},
    "rad/s": {"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0},
    "N": {"N": 1.0},
    "N m": {"N m": 1.0, "Nm": 1.0, "N*m": 1.0},
    "N/s": {"N/s": 1.0},
    "N m/s": {"N m/s": 1.0, "Nm/s": 1.0, "N*m/s": 1.0},
}


@dataclasses.dataclass(frozen=True)
class MetricInfo:
    """One metric a requirement can bound (one number per draw).

    unit: canonical unit (a key of :data:`UNITS`). share: the metric is a fraction in
    ``[0, 1]``. scale: a typical small magnitude (canonical unit), the normaliser of the
    smooth violation when the bound itself is 0 (:func:`fojax.requirements.violations`).
    definition: what it measures (docs/requirements.md lists these).
    """

    unit: str
    definition: str
    scale: float
    share: bool = False
    nonnegative: bool = True


METRICS: dict[str, MetricInfo] = {
    "position_overshoot": MetricInfo(
        "m",
        "largest excursion past the position reference over x, y, z: per axis, the most "
        "the error goes past zero against the sign of its first error larger than 1 mm "
        "(fojax.metrics' overshoot), the largest of the three axes",
        0.01,
    ),
    "settling_time": MetricInfo(
        "s",
        "the latest, over x, y, z, of the first time after which the position error "
        "stays within the settling band (settings.position_band, default 0.05 m) to the "
        "end of the run; the horizon when it is outside the band at the last sample",
        0.1,
    ),
    "steady_state_error": MetricInfo(
        "m",
        "largest Euclidean position error |e_p| over the last settings.steady_fraction "
        "(default 20 %) of the horizon",
        0.01,
    ),
    "max_position_error": MetricInfo(
        "m", "largest Euclidean position error |e_p| of the run", 0.01
    ),
    "position_rmse": MetricInfo("m", "sqrt(1/T int |e_p|^2 dt), |.| over x, y, z", 0.01),
    "attitude_rmse": MetricInfo(
        "rad",
        "sqrt(1/T int |e_att|^2 dt) over (phi, theta, psi), against the attitude "
        "reference the attitude loop tracks",
        0.01,
    ),
    "max_tilt": MetricInfo(
        "rad",
        "largest tilt of the body z axis from the vertical, arccos(cos phi cos theta), "
        "over the run",
        0.01,
    ),
    "rotor_saturation": MetricInfo(
        "1",
        "share of the control steps whose command needs a squared rotor speed outside "
        "[0, w_max^2] (the simulated plant's inverted mixer (10); w_max from "
        "settings.thrust_to_weight or settings.rotor_speed_limit, without one only "
        "negative squared speeds count)",
        0.01,
        share=True,
    ),
    "peak_rotor_speed": MetricInfo(
        "rad/s",
        "largest commanded rotor speed sqrt(max(w_i^2, 0)) over the four rotors and the "
        "run (the command before any actuator clipping)",
        1.0,
    ),
    "thrust_chattering": MetricInfo(
        "N/s",
        "total variation of the thrust command per second, sum_k |u_F,k - u_F,k-1| / T",
        0.1,
    ),
    "torque_chattering": MetricInfo(
        "N m/s",
        "total variation of the three torque commands per second, "
        "sum_k sum_i |tau_i,k - tau_i,k-1| / T",
        0.01,
    ),
    "thrust_effort": MetricInfo(
        "N",
        "RMS of the thrust command's deviation from the nominal hover thrust, "
        "sqrt(1/T int (u_F - m g)^2 dt)",
        0.01,
    ),
    "torque_effort": MetricInfo("N m", "RMS of the torque command, sqrt(1/T int |tau|^2 dt)", 1e-3),
}


class RequirementError(ValueError):
    """A requirement set that cannot be used; the message lists every problem and what
    to change."""


def _unit_help(canonical: str) -> str:
    accepted = list(UNITS[canonical])
    return " or ".join(repr(u) for u in accepted)


@dataclasses.dataclass(frozen=True)
class Requirement:
    """A bound on one per-draw metric.

    name: unique within a set. metric: a key of :data:`METRICS`. bound: ``"upper"``
    (metric ``<= value``) or ``"lower"`` (``>= value``). value, unit: the bound as
    written (``unit`` one of the metric's accepted spellings, :data:`UNITS`).
    Checked on construction (:meth:`problems` lists what is wrong).
    """

    name: str
    metric: str
    bound: str
    value: float
    unit: str

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise RequirementError("; ".join(problems))
        object.__setattr__(self, "value", float(self.value))

    def problems(self) -> list[str]:
        """What is wrong with this requirement (empty when it is usable)."""
        label = f"requirement {self.name!r}"
        out = []
        if not isinstance(self.name, str) or not self.name.strip():
            out.append(f"requirement {self.name!r}: give it a non-empty name")
        info = METRICS.get(self.metric) if isinstance(self.metric, str) else None
        if info is None:
            out.append(
                f"{label}: unknown metric {self.metric!r}; known metrics: "
                + ", ".join(sorted(METRICS))
            )
        if self.bound not in BOUNDS:
            out.append(f"{label}: bound must be 'upper' (max) or 'lower' (min), got {self.bound!r}")
        value = self.value
        if isinstance(value, bool) or not isinstance(value, int | float):
            out.append(f"{label}: the bound must be a number, got {value!r}")
            return out
        if not math.isfinite(value):
            out.append(f"{label}: the bound must be a finite number, got {value!r}")
            return out
        if info is None:
            return out
        if self.unit not in UNITS[info.unit]:
            out.append(
                f"{label}: metric {self.metric!r} is in {info.unit!r}; write unit = "
                f"{_unit_help(info.unit)}, got {self.unit!r}"
            )
            return out
        canonical = value * UNITS[info.unit][self.unit]
        if info.share and not 0.0 <= canonical <= 1.0:
            out.append(
                f"{label}: {self.metric} is a share in [0, 1] (0 % to 100 %); the bound "
                f"{value:g} {self.unit} is outside it"
            )
        elif info.nonnegative and self.bound == "upper" and canonical < 0:
            out.append(
                f"{label}: {self.metric} is never negative, so an upper bound of {value:g} "
                f"{self.unit} can never be met; use a bound >= 0"
            )
        elif info.nonnegative and self.bound == "lower" and canonical <= 0:
            out.append(
                f"{label}: {self.metric} is never negative, so a lower bound of {value:g} "
                f"{self.unit} is always met; remove it or use a bound > 0"
            )
        return out

    @property
    def info(self) -> MetricInfo:
        return METRICS[self.metric]

    @property
    def canonical_value(self) -> float:
        """The bound in the metric's canonical unit (:attr:`MetricInfo.unit`)."""
        return self.value * UNITS[self.info.unit][self.unit]

    @property
    def scale(self) -> float:
        """Normaliser of the smooth violation: ``max(|bound|, metric scale)`` (canonical)."""
        return max(abs(self.canonical_value), self.info.scale)

    def describe(self) -> str:
        sign = "<=" if self.bound == "upper" else ">="
        return f"{self.metric} {sign} {self.value:g} {self.unit}"

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "metric": self.metric,
            "max" if self.bound == "upper" else "min": self.value,
            "unit": self.unit,
        }


@dataclasses.dataclass(frozen=True)
class Settings:
    """How the metrics are measured, part of a requirement set.

    rotor_speed_limit: ``w_max`` (rad/s) of the rotors, or ``None``; thrust_to_weight:
    alternatively, the thrust-to-weight ratio at ``w_max`` (all four rotors at full
    speed, the nominal plant: :func:`fojax.requirements.rotor_speed_limit`); give at most
    one. rotor_limited: simulate rotor-limited actuators (the command's squared rotor
    speeds clipped to ``[0, w_max^2]``, :class:`fojax.SimulationConfig`'s
    ``rotor_speed_limit``) when a limit is given (default true). position_band: settling
    band (m). steady_fraction: the final share of the horizon ``steady_state_error``
    looks at, in ``(0, 1]``.
    """

    rotor_speed_limit: float | None = None
    thrust_to_weight: float | None = None
    rotor_limited: bool = True
    position_band: float = 0.05
    steady_fraction: float = 0.2

    def problems(self) -> list[str]:
        out = []
        for label in ("rotor_speed_limit", "thrust_to_weight"):
            value = getattr(self, label)
            if value is not None and not (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
                and value > 0
            ):
                out.append(f"settings: {label} must be a number > 0, got {value!r}")
        if self.rotor_speed_limit is not None and self.thrust_to_weight is not None:
            out.append("settings: give rotor_speed_limit or thrust_to_weight, not both")
        if self.thrust_to_weight is not None and isinstance(self.thrust_to_weight, int | float):
            if self.thrust_to_weight <= 1:
                out.append(
                    f"settings: thrust_to_weight {self.thrust_to_weight:g} <= 1 cannot hover; "
                    "use a ratio > 1 (2 is a typical minimum)"
                )
        if not isinstance(self.rotor_limited, bool):
            out.append(f"settings: rotor_limited must be true or false, got {self.rotor_limited!r}")
        band = self.position_band
        if not (isinstance(band, int | float) and math.isfinite(band) and band > 0):
            out.append(f"settings: position_band must be a number > 0 (m), got {band!r}")
        fraction = self.steady_fraction
        if not (isinstance(fraction, int | float) and 0 < fraction <= 1):
            out.append(f"settings: steady_fraction must be in (0, 1], got {fraction!r}")
        return out

    def speed_limit(self, params=None) -> float | None:
        """``w_max`` (rad/s), or ``None`` when neither limit is given; a thrust-to-weight
        ratio is one of the plant ``params`` (default the paper's)."""
        if self.rotor_speed_limit is not None:
            return float(self.rotor_speed_limit)
        if self.thrust_to_weight is not None:
            from fojax.plant import rotor_speed_limit

            return rotor_speed_limit(self.thrust_to_weight, params)
        return None

    def simulation_limit(self, params=None) -> float | None:
        """The ``rotor_speed_limit`` the simulation should use (``None``: ideal)."""
        return self.speed_limit(params) if self.rotor_limited else None


_SETTINGS_FIELDS = tuple(f.name for f in dataclasses.fields(Settings))


@dataclasses.dataclass(frozen=True)
class RequirementSet:
    """An immutable, validated set of requirements plus how the metrics are measured.

    Build with :func:`parse` (a dict), :func:`load` (a TOML or JSON file) or directly
    (``RequirementSet((Requirement(...), ...), Settings(...))``); every problem is
    reported at once, as one :class:`RequirementError`.
    """

    requirements: tuple[Requirement, ...]
    settings: Settings = Settings()
    description: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "requirements", tuple(self.requirements))
        problems = list(self.settings.problems())
        problems += _set_problems(self.requirements)
        if problems:
            raise RequirementError("\n  ".join(["invalid requirement set:", *problems]))

    def __len__(self) -> int:
        return len(self.requirements)

    def __iter__(self):
        return iter(self.requirements)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(r.name for r in self.requirements)

    @property
    def metrics(self) -> tuple[str, ...]:
        """The metrics the set bounds, each once, in order of first use."""
        return tuple(dict.fromkeys(r.metric for r in self.requirements))

    def to_dict(self) -> dict:
        settings = {k: v for k, v in dataclasses.asdict(self.settings).items() if v is not None}
        return {
            "description": self.description,
            "settings": settings,
            "requirements": [r.to_dict() for r in self.requirements],
        }


def _set_problems(requirements: Iterable[Requirement]) -> list[str]:
    out = []
    requirements = list(requirements)
    if not requirements:
        out.append("no requirements: give at least one")
    seen: dict[str, int] = {}
    for r in requirements:
        if not isinstance(r, Requirement):
            out.append(f"not a Requirement: {r!r}")
            continue
        seen[r.name] = seen.get(r.name, 0) + 1
    for name, count in seen.items():
        if count > 1:
            out.append(f"requirement name {name!r} is used {count} times; names must be unique")
    by_metric: dict[str, dict[str, list[Requirement]]] = {}
    for r in requirements:
        if isinstance(r, Requirement):
            by_metric.setdefault(r.metric, {}).setdefault(r.bound, []).append(r)
    for metric, bounds in by_metric.items():
        uppers, lowers = bounds.get("upper", []), bounds.get("lower", [])
        if uppers and lowers:
            upper = min(uppers, key=lambda r: r.canonical_value)
            lower = max(lowers, key=lambda r: r.canonical_value)
            if lower.canonical_value >= upper.canonical_value:
                out.append(
                    f"{metric}: lower bound {lower.name!r} ({lower.describe()}) is not below "
                    f"upper bound {upper.name!r} ({upper.describe()}); no draw can meet both"
                )
    return out


_ENTRY_KEYS = ("name", "metric", "max", "min", "unit")


def _requirement_from(entry: Any, index: int, problems: list[str]) -> Requirement | None:
    where = f"requirement #{index + 1}"
    if not isinstance(entry, Mapping):
        problems.append(f"{where}: must be a table (name, metric, max or min, unit)")
        return None
    name = entry.get("name")
    if isinstance(name, str):
        where = f"requirement {name!r}"
    unknown = sorted(set(entry) - set(_ENTRY_KEYS))
    if unknown:
        problems.append(
            f"{where}: unknown keys {', '.join(map(repr, unknown))}; a requirement has "
            + ", ".join(_ENTRY_KEYS)
        )
    missing = [k for k in ("name", "metric", "unit") if k not in entry]
    if missing:
        problems.append(f"{where}: missing {', '.join(missing)}")
    has_max, has_min = "max" in entry, "min" in entry
    if has_max == has_min:
        problems.append(
            f"{where}: give exactly one of max (an upper bound) or min (a lower bound)"
            + ("; for both, write two requirements" if has_max else "")
        )
    if missing or has_max == has_min:
        return None
    bound, value = ("upper", entry["max"]) if has_max else ("lower", entry["min"])
    candidate = Requirement.__new__(Requirement)
    for field, v in (
        ("name", name),
        ("metric", entry["metric"]),
        ("bound", bound),
        ("value", value),
        ("unit", entry["unit"]),
    ):
        object.__setattr__(candidate, field, v)
    found = candidate.problems()
    if found:
        problems.extend(found)
        return None
    return Requirement(name, entry["metric"], bound, value, entry["unit"])


def parse(data: Mapping, source: str = "requirements") -> RequirementSet:
    """A :class:`RequirementSet` from a dict (the parsed TOML or JSON document).

    Layout: ``requirements``: a list of tables, each ``name``, ``metric``, ``max`` or
    ``min``, ``unit``; optional ``settings`` (the fields of :class:`Settings`) and
    ``description``. Every problem is collected into one :class:`RequirementError`.
    """
    problems: list[str] = []
    if not isinstance(data, Mapping):
        raise RequirementError(f"{source}: the document must be a table, got {type(data).__name__}")
    unknown = sorted(set(data) - {"requirements", "settings", "description"})
    if unknown:
        problems.append(
            f"unknown top-level keys {', '.join(map(repr, unknown))}; use requirements "
            "(a list: [[requirements]] in TOML), settings and description"
        )
    entries = data.get("requirements")
    if not isinstance(entries, list):
        problems.append(
            "requirements must be a list of tables ([[requirements]] in TOML, a JSON array)"
        )
        entries = []
    requirements = [_requirement_from(e, i, problems) for i, e in enumerate(entries)]
    raw_settings = data.get("settings", {})
    settings = Settings()
    if not isinstance(raw_settings, Mapping):
        problems.append("settings must be a table")
    else:
        bad = sorted(set(raw_settings) - set(_SETTINGS_FIELDS))
        if bad:
            problems.append(
                f"settings: unknown keys {', '.join(map(repr, bad))}; known: "
                + ", ".join(_SETTINGS_FIELDS)
            )
        settings = Settings(**{k: v for k, v in raw_settings.items() if k in _SETTINGS_FIELDS})
    description = data.get("description", "")
    if not isinstance(description, str):
        problems.append("description must be a string")
        description = ""
    valid = [r for r in requirements if r is not None]
    problems += settings.problems()
    names = [e.get("name") for e in entries if isinstance(e, Mapping)]
    for name in dict.fromkeys(n for n in names if isinstance(n, str)):
        if names.count(name) > 1:
            problems.append(
                f"requirement name {name!r} is used {names.count(name)} times; names must be unique"
            )
    if entries:
        problems += [
            p
            for p in _set_problems(valid)
            if not p.startswith(("no requirements", "requirement name"))
        ]
    elif isinstance(data.get("requirements"), list):
        problems.append("no requirements: give at least one")
    if problems:
        raise RequirementError("\n  ".join([f"invalid requirement set ({source}):", *problems]))
    return RequirementSet(tuple(valid), settings, description)


def load(path: str | os.PathLike) -> RequirementSet:
    """A :class:`RequirementSet` from a ``.toml`` or ``.json`` file (:func:`parse`)."""
    data = _files.read_table(path, RequirementError, "requirement file", (".toml", ".json"))
    return parse(data, str(path))
