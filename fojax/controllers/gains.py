"""Gains declared once: each field's default, feasible set and role.

A control law lists its gain fields as :class:`GainField` s in a :class:`GainSpec`;
everything else follows from that declaration: the gains type (a NamedTuple of arrays,
so gains can be batched, sampled and differentiated), the defaults, the checks with
messages in words, the tuner's parameter map (``bounds``, ``role``) and the gains
files (:mod:`fojax.controllers.gains_io`).

Roles: ``"design"`` gains are what a tuner tunes by default; ``"smoothing"`` is the
width of a smooth switching function (a tuner anneals it rather than tunes it);
``"constant"`` is a small constant of the law that is not a design gain (the
reaching law's ``mu``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

__all__ = ["ROLES", "Bounds", "GainField", "GainSpec", "per_axis"]

ROLES = ("design", "smoothing", "constant")
AXES = ("x", "y", "z", "phi", "theta", "psi")


class Bounds(NamedTuple):
    """The feasible set of one gain field: ``low < value < high`` elementwise.

    ``include_low``: ``low <= value`` instead. ``symbol``: the name used in messages
    (for instance ``"p/q"``). Tuners map unconstrained parameters onto these sets.
    """

    low: float
    high: float = math.inf
    include_low: bool = False
    symbol: str | None = None

    def describe(self, name: str) -> str:
        symbol = self.symbol or name
        low_op = "<=" if self.include_low else "<"
        if math.isinf(self.high):
            return f"{symbol} must be {'>=' if self.include_low else '>'} {self.low:g}"
        return f"{symbol} must satisfy {self.low:g} {low_op} {symbol} < {self.high:g}"

    def contains(self, value: np.ndarray) -> np.ndarray:
        above = value >= self.low if self.include_low else value > self.low
        return above & (value < self.high)


def per_axis(xy: float, z: float, attitude: float) -> tuple[float, ...]:
    """``(6,)`` per-axis values over ``(x, y, z, phi, theta, psi)``: one for x and y,
    one for z, one for the three attitude axes (the paper's Section V pattern)."""
    return (xy, xy, z, attitude, attitude, attitude)


@dataclasses.dataclass(frozen=True)
class GainField:
    """One gain field.

    name: the field's name. default: its default value (a number or nested
    sequence; its shape is the field's shape, ``(6,)`` per axis or ``(6, 3)``).
    bounds: its feasible set. role: one of :data:`ROLES`. doc: symbol and meaning.
    integer_order: for a fractional order, the bound at which its operator is of
    integer order (the limit the order approaches there; ``None``: not an order).
    search_high: the largest value a tuner over a flight envelope searches
    (``fojax.envelope``; ``None``: the bounds' own), for the rate of a state that
    integrates without leakage (an adaptive bound): a faster rate grows the state over
    the envelope's longest case beyond what the tuning horizon sees.
    """

    name: str
    default: Any
    bounds: Bounds
    role: str = "design"
    doc: str = ""
    integer_order: float | None = None
    search_high: float | None = None

    def __post_init__(self) -> None:
        if self.role not in ROLES:
            raise ValueError(f"gain field {self.name!r}: role must be one of {ROLES}")
        value = np.asarray(self.default, np.float64)
        if not np.all(self.bounds.contains(value)):
            raise ValueError(f"gain field {self.name!r}: its default breaks its bounds")
        if self.integer_order not in (None, self.bounds.low, self.bounds.high):
            raise ValueError(f"gain field {self.name!r}: integer_order must be one of its bounds")
        high = self.search_high
        if high is not None and not (self.bounds.low < high <= self.bounds.high
                                     and np.all(value < high)):  # fmt: skip
            raise ValueError(f"gain field {self.name!r}: search_high must lie inside its bounds, "
                             "above its default")  # fmt: skip
        object.__setattr__(self, "default", value)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.default.shape)


class GainSpec:
    """The gain fields of one control law; ``type`` is the gains NamedTuple.

    Args:
        type_name: name of the gains type (for instance ``"AFONFTSMCGains"``).
        fields: the :class:`GainField` s, in order.
        label: the law's name in messages.
    """

    def __init__(self, type_name: str, fields: Sequence[GainField], label: str):
        self.fields = tuple(fields)
        self.label = label
        names = [f.name for f in self.fields]
        if len(set(names)) != len(names):
            raise ValueError(f"{label}: gain fields named twice in {names}")
        lines = [f"Gains of the {label}, declared in its :class:`GainSpec`.", ""]
        lines += [f"{f.name}: ``{f.shape}``, {f.bounds.describe(f.name)}. {f.doc}" for f in fields]
        self.type = NamedTuple(type_name, [(name, Array) for name in names])
        self.type.__doc__ = "\n".join(lines)
        self.type.spec = self

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @property
    def bounds(self) -> dict[str, Bounds]:
        return {f.name: f.bounds for f in self.fields}

    def search_bounds(self, capped: bool) -> dict[str, Bounds]:
        """The bounds a tuner searches: :attr:`bounds`, with each field's
        ``search_high`` where ``capped`` (a flight envelope's tuning)."""
        out = dict(self.bounds)
        if capped:
            for f in self.fields:
                if f.search_high is not None:
                    out[f.name] = out[f.name]._replace(high=f.search_high)
        return out

    @property
    def shapes(self) -> dict[str, tuple[int, ...]]:
        return {f.name: f.shape for f in self.fields}

    @property
    def integer_orders(self) -> dict[str, float]:
        """Fractional-order fields and the bound at which each is of integer order."""
        return {f.name: f.integer_order for f in self.fields if f.integer_order is not None}

    def with_role(self, *roles: str) -> tuple[str, ...]:
        """Names of the fields with one of ``roles``."""
        return tuple(f.name for f in self.fields if f.role in roles)

    def default(self, dtype: Any = None) -> Any:
        """The default gains (float32, or float64 with x64 enabled, unless ``dtype``)."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        return self.type(*(jnp.asarray(f.default, dtype) for f in self.fields))

    def broadcast(self, gains: Any, batch_shape: tuple[int, ...]) -> Any:
        """``gains`` laid out for a rollout over a batch of shape ``batch_shape`` (the
        batch's axes last): a field with its declared shape is shared by the batch and
        gets trailing axes of size 1 (``(6,)`` -> ``(6, 1)``); a field given per draw has
        the declared shape followed by ``batch_shape`` and is kept. ``ValueError``
        otherwise. Shapes only: traceable."""
        batch_shape = tuple(batch_shape)
        if not batch_shape:
            return gains
        fields = []
        for f in self.fields:
            value = jnp.asarray(getattr(gains, f.name))
            if value.shape == f.shape:
                value = value.reshape(f.shape + (1,) * len(batch_shape))
            elif value.shape != f.shape + batch_shape:
                raise ValueError(
                    f"{self.label} gains: {f.name} must have shape {f.shape} (shared by the "
                    f"batch) or {f.shape + batch_shape} (one value per draw, the batch last), "
                    f"got {value.shape}"
                )
            fields.append(value)
        return self.type(*fields)

    def problems(self, gains: Any) -> list[str]:
        """Every way ``gains`` break the declaration, in words (empty when valid)."""
        if not isinstance(gains, tuple) or getattr(gains, "_fields", None) != self.names:
            got = type(gains).__name__
            fields = getattr(gains, "_fields", None)
            detail = f" with fields {', '.join(fields)}" if fields else ""
            return [
                f"expected {self.type.__name__} (fields {', '.join(self.names)}), got "
                f"{got}{detail}: build them with .default_gains() and ._replace(...)"
            ]
        problems = []
        for f in self.fields:
            raw = getattr(gains, f.name)
            if isinstance(raw, jax.core.Tracer):
                continue  # traced gains are checked by whoever made them
            try:
                value = np.asarray(raw, dtype=float)
            except (TypeError, ValueError):
                problems.append(f"{f.name} must be numeric, got {raw!r}")
                continue
            if value.shape != f.shape:
                what = "one value per axis (x, y, z, phi, theta, psi)" if f.shape == (6,) else ""
                problems.append(
                    f"{f.name} must have shape {f.shape}{': ' + what if what else ''}, got an "
                    f"array of shape {value.shape}"
                )
                continue
            if not np.all(np.isfinite(value)):
                problems.append(f"{f.name} must be finite, got {value.tolist()}")
                continue
            if not np.all(f.bounds.contains(value)):
                text = f.bounds.describe(f.name)
                if f.bounds.symbol:
                    text = f"{f.name}: {text}"
                problems.append(f"{text}, got {value.tolist()}")
        return problems

    def check(self, gains: Any) -> None:
        """Raise ``ValueError`` naming every entry that breaks the declaration."""
        problems = self.problems(gains)
        if problems:
            raise ValueError(f"invalid {self.label} gains:\n  " + "\n  ".join(problems))
