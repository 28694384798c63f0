"""Reading the project's input files (vehicle, reference, requirement and envelope
files): one table of TOML (or JSON), or one error of the file's own kind that says why
not; a quantity with its unit (:class:`Field`, :func:`quantity`) in SI units, or the
problems that say what to write."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any


def read_table(path: str | os.PathLike, error: type[Exception], kind: str,
               formats: tuple[str, ...] = (".toml",)) -> object:  # fmt: skip
    """The content of the file at ``path``, parsed by its suffix among ``formats``
    (``.toml``; ``.json``); ``error(message)`` for a file that cannot be read, has
    another suffix (where several formats are accepted) or does not parse. ``kind``
    names the file in messages (``"requirement file"``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as failure:
        raise error(f"{path}: cannot read the {kind}: {failure.strerror or failure}") from None
    except UnicodeDecodeError as failure:
        raise error(f"{path} is not a text file: {failure}") from None
    suffix = path.suffix.lower() if len(formats) > 1 else formats[0]
    if suffix not in formats:
        raise error(f"{path}: the {kind} must end in {' or '.join(formats)}")
    try:
        return tomllib.loads(text) if suffix == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as failure:
        raise error(f"{path} is not valid {suffix[1:].upper()}: {failure}") from None


def header(
    data: Any, source: str, name: str, error: type[Exception], kind: str, missing: str,
    others: tuple[str, ...] = (),
) -> tuple[str, Mapping, list[str]]:
    """A file's ``description`` and its ``[name]`` table, with the problems found so far
    (top-level keys other than ``description``, ``name`` and ``others``, a description
    that is not text); ``error`` (its message
    ``"{source} is not a usable {kind}:"`` and every problem) when the content is no
    table or has no ``[name]`` table (``missing``: what that table holds)."""
    problems: list[str] = []
    if not isinstance(data, Mapping):
        raise error(f"{source}: expected a table, got {type(data).__name__}")
    expected = ("description", name, *others)
    unknown = sorted(set(data) - set(expected))
    if unknown:
        problems.append(f"unknown top-level key(s) {', '.join(unknown)} (expected "
                        f"{', '.join(expected)})")  # fmt: skip
    description = data.get("description", "")
    if not isinstance(description, str):
        problems.append(f"description: expected a string, got {description!r}")
        description = ""
    table = data.get(name)
    if not isinstance(table, Mapping):
        problems.append(f"missing [{name}] table ({missing})")
        raise error(message(source, kind, problems))
    return description, table, problems


def message(source: str, kind: str, problems: list[str]) -> str:
    """``"{source} is not a usable {kind}:"`` and every problem, one a line."""
    return f"{source} is not a usable {kind}:\n" + "\n".join(f"  {p}" for p in problems)


@dataclasses.dataclass(frozen=True)
class Field:
    """One quantity of a vehicle. size: ``None`` a scalar, else a vector's length.
    units: accepted units and their factors to the first (SI) one. symbol: the model's
    (docs/model.md)."""

    name: str
    size: int | None
    units: Mapping[str, float]
    symbol: str
    summary: str

    @property
    def unit(self) -> str:
        """The SI unit (the first of :attr:`units`)."""
        return next(iter(self.units))


def number(value: Any) -> bool:
    """Whether ``value`` is a number of a file (an int or a float, not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def quantity(field: Field, entry: Any, problems: list[str], table: str = "vehicle",
             signed: bool = False, zero: bool = False):  # fmt: skip
    """The SI value of ``entry`` (``{value, unit}``), or ``None`` with its problems (each
    naming ``table.field``); every value finite and > 0 (``zero``: >= 0; ``signed``: of
    any sign)."""
    where = f"{table}.{field.name}"
    units = ", ".join(f'"{u}"' for u in field.units)
    if not isinstance(entry, Mapping):
        problems.append(
            f"{where}: expected {{ value = ..., unit = ... }} with a unit among {units}, "
            f"got {entry!r}"
        )
        return None
    unknown = sorted(set(entry) - {"value", "unit"})
    if unknown:
        problems.append(f"{where}: unknown key(s) {', '.join(unknown)} (expected value, unit)")
    if "unit" not in entry:
        problems.append(f"{where}: missing unit (one of {units})")
        return None
    unit = entry["unit"]
    if unit not in field.units:
        problems.append(f"{where}: unit {unit!r} is not one of {units}")
        return None
    if "value" not in entry:
        problems.append(f"{where}: missing value")
        return None
    value, scale = entry["value"], field.units[unit]
    shape = "a number" if field.size is None else f"a list of {field.size} numbers"
    values = [value] if field.size is None else value
    if (
        (field.size is not None and not (isinstance(value, list) and len(value) == field.size))
        or not all(number(v) for v in values)
    ):
        problems.append(f"{where}: expected {shape}, got {value!r}")
        return None
    if not all(math.isfinite(v) and (signed or v > 0 or (zero and v == 0)) for v in values):
        bound = "" if signed else " and >= 0" if zero else " and > 0"
        problems.append(f"{where}: every value must be finite{bound}, got {value!r}")
        return None
    converted = [float(v) * scale for v in values]
    return converted[0] if field.size is None else tuple(converted)
