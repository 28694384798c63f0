"""A flight envelope: the cases a controller is tuned and judged over (:class:`Envelope`).

An envelope is a list of cases, each a :class:`fojax.scenarios.Scenario`, flown as one
union (:func:`fojax.scenarios.union`: one compiled rollout, draw ``i`` of case ``i mod
cases``):

* the paper's scenarios, as they are (``scenarios = [1, 2, 3]``);
* cases of random manoeuvres (``manoeuvres = N``, :mod:`fojax.manoeuvres`): every draw
  flies a manoeuvre of its own, drawn from its key, within limits set relative to the
  vehicle (:meth:`fojax.manoeuvres.Limits.from_vehicle` at ``fraction`` of its
  authority; any limit may be given in ``[envelope.limits]``), under the random
  processes and deterministic disturbances of scenario ``under``, ``horizon`` s long
  (the manoeuvre's own length, whatever the run's);
* windows of the paper's scenarios (``windows``, :func:`fojax.scenarios.window`): a
  scenario from a later time on, starting on its reference: its later disturbances and
  manoeuvres in steady flight, within a tuning horizon shorter than the scenario;
* reference files (``references``, :mod:`fojax.reference`), each flown under scenario
  ``under``'s processes and disturbances;
* the paper's scenarios flown with the paper's ``sign`` switching (``sign = [2]``): the
  tuner judges its gains with the boundary-layer law (``sat``), so a case flown with
  ``sign`` keeps the tuned gains stable under the law the paper flies
  (:data:`SIGN_WIDTH`).

An envelope file is TOML::

    description = "the paper's scenarios and random manoeuvres"

    [envelope]
    scenarios = [1, 2, 3]
    manoeuvres = 1
    under = 2
    horizon = { value = 30, unit = "s" }
    fraction = 0.5
    windows = [{ scenario = 3, start = { value = 20, unit = "s" } }]
    sign = [2]
    references = ["examples/references/paper_54_55.toml"]   # relative to the file

    [envelope.limits]
    speed = { value = 1.5, unit = "m/s" }

:func:`load` checks the whole file and raises one :class:`EnvelopeError` listing every
problem, before anything compiles.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fojax import _files

__all__ = ["LIMIT_FIELDS", "SIGN_WIDTH", "Envelope", "EnvelopeError", "load", "parse"]

SIGN_WIDTH = 1e-9
"""A ``sign`` case's boundary layer, as a share of the gains': ``sat(S / (1e-9 b))``
equals ``sign(S)`` wherever ``|S| >= 1e-9 b`` (one compiled rollout serves both laws)."""


class EnvelopeError(ValueError):
    """An envelope file or table that cannot be used; the message lists every problem."""


_S = {"s": 1.0}
_M = {"m": 1.0, "cm": 1e-2}
_RAD = {"rad": 1.0, "deg": math.pi / 180.0}
LIMIT_FIELDS: dict[str, _files.Field | None] = {
    "speed": _files.Field("speed", None, {"m/s": 1.0}, "v_max", "peak speed"),
    "acceleration": _files.Field("acceleration", None, {"m/s^2": 1.0}, "a_max",
                                 "peak acceleration"),  # fmt: skip
    "yaw_rate": _files.Field("yaw_rate", None, {"rad/s": 1.0, "deg/s": math.pi / 180.0},
                             "r_max", "peak yaw rate"),  # fmt: skip
    "yaw_acceleration": _files.Field("yaw_acceleration", None,
                                     {"rad/s^2": 1.0, "deg/s^2": math.pi / 180.0}, "r'_max",
                                     "peak yaw acceleration"),  # fmt: skip
    "half_extent": _files.Field("half_extent", None, _M, "", "the waypoints' horizontal box"),
    "z_range": _files.Field("z_range", 2, _M, "", "the waypoints' heights"),
    "yaw_range": _files.Field("yaw_range", 2, _RAD, "", "the waypoints' yaw"),
    "hover_duration": _files.Field("hover_duration", 2, _S, "", "a hover's duration"),
    "initial_offset": _files.Field("initial_offset", None, _M, "", "the start's offset"),
    "min_duration": _files.Field("min_duration", None, _S, "", "a move's least duration"),
    "segments": None,
    "hover_probability": None,
    "max_stretch": None,
}
"""The fields of ``[envelope.limits]`` (:class:`fojax.manoeuvres.Limits`): a quantity with
its unit, or a plain number (``None`` here)."""


@dataclasses.dataclass(frozen=True)
class Envelope:
    """The cases of a flight envelope (module docstring).

    scenarios: the paper's scenario numbers flown as they are. manoeuvres: how many
    cases of random manoeuvres. under: the paper scenario whose random processes and
    disturbances the manoeuvres and references fly under. horizon: a manoeuvre's length
    (s). fraction: of the vehicle's acceleration and yaw authority the manoeuvres may
    ask for. limits: ``((field, value), ...)`` overriding the limits from the vehicle.
    references: :mod:`fojax.reference` waypoints or built-ins. windows: ``((scenario,
    start), ...)``: the paper's scenario from ``start`` (s) on
    (:func:`fojax.scenarios.window`). sign: the paper's scenarios flown again with the
    paper's ``sign`` switching (:data:`SIGN_WIDTH`). description: text.
    """

    scenarios: tuple[int, ...] = (1, 2, 3)
    manoeuvres: int = 1
    under: int = 2
    horizon: float = 30.0
    fraction: float = 0.5
    limits: tuple[tuple[str, Any], ...] = ()
    references: tuple[Any, ...] = ()
    windows: tuple[tuple[int, float], ...] = ()
    sign: tuple[int, ...] = ()
    description: str = ""

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise EnvelopeError("not a usable envelope:\n" + "\n".join(f"  {p}" for p in problems))

    def problems(self) -> list[str]:
        from fojax import scenarios

        out = []
        for i in self.scenarios:
            if i not in scenarios.SCENARIO_IDS:
                out.append(f"envelope.scenarios: {i!r} is not one of the paper's scenarios "
                           f"{list(scenarios.SCENARIO_IDS)}")  # fmt: skip
        if self.under not in scenarios.SCENARIO_IDS:
            out.append(f"envelope.under: expected one of {list(scenarios.SCENARIO_IDS)}, got "
                       f"{self.under!r}")  # fmt: skip
        if not (isinstance(self.manoeuvres, int) and 0 <= self.manoeuvres <= 16):
            out.append(f"envelope.manoeuvres: expected a whole number of cases from 0 to 16, "
                       f"got {self.manoeuvres!r}")  # fmt: skip
        if not (_files.number(self.horizon) and 0 < self.horizon < math.inf):
            out.append(f"envelope.horizon: expected a duration > 0, got {self.horizon!r}")
        if not (_files.number(self.fraction) and 0 < self.fraction <= 1):
            out.append(f"envelope.fraction: expected a share in (0, 1], got {self.fraction!r}")
        for i in self.sign:
            if i not in scenarios.SCENARIO_IDS:
                out.append(f"envelope.sign: {i!r} is not one of the paper's scenarios "
                           f"{list(scenarios.SCENARIO_IDS)}")  # fmt: skip
        for entry in self.windows:
            i, start = entry if isinstance(entry, tuple) and len(entry) == 2 else (None, None)
            if i not in scenarios.SCENARIO_IDS:
                out.append(f"envelope.windows: {entry!r} is not (one of the paper's scenarios "
                           f"{list(scenarios.SCENARIO_IDS)}, a start)")  # fmt: skip
                continue
            horizon = scenarios.get_scenario(i).horizon
            if not (_files.number(start) and 0 < start < horizon):
                out.append(f"envelope.windows: scenario {i}'s window must start within (0, "
                           f"{horizon:g}) s, got {start!r}")  # fmt: skip
        if not out and not self.cases_count():
            out.append("envelope: no case (give scenarios, manoeuvres or references)")
        return out

    def cases_count(self) -> int:
        return (len(self.scenarios) + len(self.windows) + len(self.sign) + self.manoeuvres
                + len(self.references))  # fmt: skip

    def laws(self) -> tuple[str, ...]:
        """Per case of :meth:`cases`, ``"sign"`` where it is flown with the paper's sign
        switching, else ``"tuned"`` (the tuner's law)."""
        before = len(self.scenarios) + len(self.windows)
        tuned = self.cases_count() - before - len(self.sign)
        return ("tuned",) * before + ("sign",) * len(self.sign) + ("tuned",) * tuned

    def manoeuvre_limits(self, vehicle=None, speed_limit: float | None = ...):
        """The :class:`fojax.manoeuvres.Limits` of the manoeuvres on ``vehicle`` (``None``:
        the paper's) with its rotors limited to ``speed_limit`` (default its own)."""
        from fojax import manoeuvres
        from fojax.vehicle import Vehicle

        flown = Vehicle.paper() if vehicle is None else vehicle
        return manoeuvres.Limits.from_vehicle(
            flown, speed_limit=speed_limit, fraction=self.fraction, **dict(self.limits)
        )

    def cases(self, vehicle=None, speed_limit: float | None = ...) -> tuple:
        """``((name, scenario), ...)`` of every case on ``vehicle`` (``None``: the
        paper's), in the union's order."""
        from fojax import scenarios

        under = scenarios.get_scenario(self.under)
        out = [(f"scenario {i}", scenarios.get_scenario(i)) for i in self.scenarios]
        out += [(f"scenario {i} from {start:g} s", scenarios.window(scenarios.get_scenario(i),
                 start)) for i, start in self.windows]  # fmt: skip
        out += [(f"scenario {i} (sign)", scenarios.get_scenario(i)) for i in self.sign]
        if self.manoeuvres:
            limits = self.manoeuvre_limits(vehicle, speed_limit)
            for j in range(self.manoeuvres):
                name = "random manoeuvres" + (f" ({j + 1})" if self.manoeuvres > 1 else "")
                label = f"{name} under scenario {self.under}"
                case = scenarios.manoeuvre_scenario(limits, under, self.horizon, label)
                out.append((name, case))
        for j, flown in enumerate(self.references):
            name = f"reference {j + 1}" + (f": {flown.description}" if flown.description else "")
            horizon = max(under.horizon, flown.end or 0.0)
            out.append((name, dataclasses.replace(
                under, scenario_id=0, name=f"{name} under scenario {self.under}",
                reference=flown.reference(), horizon=horizon)))  # fmt: skip
        return tuple((name, case.on(vehicle)) for name, case in out)

    def scenario(self, vehicle=None, speed_limit: float | None = ...):
        """The union of :meth:`cases` (one case: itself)."""
        from fojax import scenarios

        found = [case for _, case in self.cases(vehicle, speed_limit)]
        return found[0] if len(found) == 1 else scenarios.union(*found)

    def to_dict(self) -> dict:
        """JSON-ready (a run's fingerprint)."""
        return {
            "description": self.description,
            "scenarios": list(self.scenarios),
            "manoeuvres": self.manoeuvres,
            "under": self.under,
            "horizon_s": self.horizon,
            "fraction": self.fraction,
            "limits": {k: list(v) if isinstance(v, tuple) else v for k, v in self.limits},
            "references": [r.to_dict() for r in self.references],
            **({"windows": [{"scenario": i, "start_s": t} for i, t in self.windows]}
               if self.windows else {}),
            **({"sign": list(self.sign)} if self.sign else {}),
        }


_KEYS = ("scenarios", "windows", "sign", "manoeuvres", "under", "horizon", "fraction",
         "limits", "references")


def parse(data: Mapping, source: str = "envelope", root: Path | None = None) -> Envelope:
    """The :class:`Envelope` of an envelope file's content; reference files are read
    relative to ``root`` (default the working directory). :class:`EnvelopeError`
    listing every problem."""
    from fojax import reference

    description, table, problems = _files.header(data, source, "envelope", EnvelopeError,
                                                 "envelope file", "its cases")  # fmt: skip
    unknown = sorted(set(table) - set(_KEYS))
    if unknown:
        problems.append(f"envelope: unknown key(s) {', '.join(unknown)} (the keys: "
                        f"{', '.join(_KEYS)})")  # fmt: skip
    values: dict[str, Any] = {}
    ids = table.get("scenarios", [1, 2, 3])
    if not (isinstance(ids, list) and all(isinstance(i, int) for i in ids)):
        problems.append(f"envelope.scenarios: expected a list of scenario numbers, got {ids!r}")
    else:
        values["scenarios"] = tuple(ids)
    sign = table.get("sign", [])
    if not (isinstance(sign, list) and all(isinstance(i, int) for i in sign)):
        problems.append(f"envelope.sign: expected a list of scenario numbers, got {sign!r}")
    else:
        values["sign"] = tuple(sign)
    windows = table.get("windows", [])
    if not (isinstance(windows, list) and all(isinstance(w, Mapping) for w in windows)):
        problems.append(f"envelope.windows: expected a list of tables {{ scenario = N, start = "
                        f"{{ value = T, unit = \"s\" }} }}, got {windows!r}")  # fmt: skip
        windows = []
    found_windows = []
    for j, entry in enumerate(windows):
        extra = sorted(set(entry) - {"scenario", "start"})
        if extra or "scenario" not in entry or "start" not in entry:
            problems.append(f"envelope.windows[{j}]: expected the keys scenario and start, got "
                            f"{sorted(entry)}")  # fmt: skip
            continue
        start = _files.quantity(_files.Field("start", None, _S, "", "the window's start"),
                                entry["start"], problems, f"envelope.windows[{j}]")  # fmt: skip
        if start is not None:
            found_windows.append((entry["scenario"], start))
    values["windows"] = tuple(found_windows)
    for name in ("manoeuvres", "under", "fraction"):
        if name in table:
            values[name] = table[name]
    if "horizon" in table:
        horizon = _files.quantity(_files.Field("horizon", None, _S, "", "a manoeuvre's length"),
                                  table["horizon"], problems, "envelope")  # fmt: skip
        if horizon is not None:
            values["horizon"] = horizon
    limits = table.get("limits", {})
    if not isinstance(limits, Mapping):
        problems.append(f"envelope.limits: expected a table of limits, got {limits!r}")
        limits = {}
    found = []
    for name, entry in limits.items():
        if name not in LIMIT_FIELDS:
            problems.append(f"envelope.limits: unknown limit {name!r} (the limits: "
                            f"{', '.join(LIMIT_FIELDS)})")  # fmt: skip
            continue
        field = LIMIT_FIELDS[name]
        if field is None:
            if not _files.number(entry):
                problems.append(f"envelope.limits.{name}: expected a plain number, got {entry!r}")
                continue
            found.append((name, entry))
            continue
        value = _files.quantity(field, entry, problems, "envelope.limits",
                                signed=name == "yaw_range",
                                zero=name == "initial_offset")  # fmt: skip
        if value is not None:
            found.append((name, value))
    values["limits"] = tuple(found)
    files = table.get("references", [])
    if not (isinstance(files, list) and all(isinstance(f, str) for f in files)):
        problems.append(f"envelope.references: expected a list of file names, got {files!r}")
        files = []
    flown = []
    for name in files:
        path = Path(name) if root is None or Path(name).is_absolute() else root / name
        try:
            flown.append(reference.load(path))
        except ValueError as error:
            problems.append(f"envelope.references: {error}")
    values["references"] = tuple(flown)
    if problems:
        raise EnvelopeError(_message(source, problems))
    try:
        envelope = Envelope(**values, description=description)
        if envelope.manoeuvres:
            envelope.manoeuvre_limits()  # the limits' own checks, on the paper's vehicle
    except ValueError as error:
        raise EnvelopeError(f"{source} is not a usable envelope file: {error}") from None
    return envelope


def _message(source: str, problems: list[str]) -> str:
    return _files.message(source, "envelope file", problems)


def load(path: str | os.PathLike) -> Envelope:
    """The :class:`Envelope` of the TOML file at ``path`` (its reference files relative
    to it); :class:`EnvelopeError` (one message, every problem)."""
    data = _files.read_table(path, EnvelopeError, "envelope file")
    return parse(data, str(path), Path(path).parent)
