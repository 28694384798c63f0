"""Unconstrained tuning parameters mapped onto a controller's feasible gains.

A gradient (or derivative-free) tuner moves unconstrained real parameters ``u``; a
:class:`ParameterMap` turns them into gains that always satisfy the controller's
constraints (each field's declared :class:`fojax.controllers.Bounds`), and back:

* ``low < g`` (``high = inf``): ``g = low + exp(u)``, ``u = log(g - low)`` (log map: a
  step in ``u`` is a relative change of the gain, whatever its scale);
* ``low < g < high``: ``g = low + (high - low) sigmoid(u)``, ``u = logit((g - low) /
  (high - low))`` (``1 < p/q < 2``, ``0 < gamma < 1``: the fractional orders are tuned
  like any other gain);
* ``g < high`` (``low = -inf``): ``g = high - exp(u)``; no bound: ``g = u``.

``u`` is clipped to ``[-U_MAX, U_MAX]`` and the gain to the open interval (by one ulp)
so that finite precision never produces an infeasible gain (``sigmoid(17)`` is ``1.0``
in float32). Inside those limits the maps invert each other to rounding.

Axis sharing: fields whose leading axis is the six control axes ``(x, y, z, phi,
theta, psi)`` can share one parameter per group of axes. ``share="paper"`` ties
``x = y`` and ``phi = theta = psi`` as the paper's Section V does (its gains are in
the family); ``share="none"`` tunes every axis on its own. Other fields (any shape)
are tuned elementwise.

Parameters are a ``dict`` field -> array of shape ``(n_groups, *shape[1:])`` (or the
field's shape when it is not per-axis): a pytree with array leaves, ready for optax.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from fojax.controllers import registry
from fojax.controllers.gains import Bounds

Array = jax.Array

__all__ = [
    "AXIS_NAMES", "SHARING", "TUNED_ROLES", "FieldMap", "ParameterMap", "default_fields",
    "integer_order_gains", "make_parameter_map", "naive_gains",
]  # fmt: skip

AXIS_NAMES = ("x", "y", "z", "phi", "theta", "psi")
SHARING = {"paper": ((0, 1), (2,), (3, 4, 5)), "none": ((0,), (1,), (2,), (3,), (4,), (5,))}
"""Axis groups of each sharing mode (indices into :data:`AXIS_NAMES`)."""

TUNED_ROLES = ("design",)
"""Roles of the fields tuned by default (:data:`fojax.controllers.gains.ROLES`): not the
``"constant"`` ones (the paper's "small constant" ``mu``, not a design gain) nor the
``"smoothing"`` width, which the tuner anneals itself."""

U_MAX = 30.0
"""Unconstrained parameters are clipped to ``[-U_MAX, U_MAX]``."""


_MAPS = {  # kind: (forward(u, low, high), inverse(g, low, high), naive_gains' value)
    "log": (
        lambda u, low, high: low + jnp.exp(u),
        lambda g, low, high: np.log(g - low),
        lambda low, high: low + 1.0,
    ),
    "logit": (
        lambda u, low, high: low + (high - low) * jax.nn.sigmoid(u),
        lambda g, low, high: np.log((g - low) / (high - low)) - np.log1p(-(g - low) / (high - low)),
        lambda low, high: 0.5 * (low + high),
    ),
    "neglog": (
        lambda u, low, high: high - jnp.exp(u),
        lambda g, low, high: np.log(high - g),
        lambda low, high: high - 1.0,
    ),
    "identity": (lambda u, low, high: u, lambda g, low, high: g, lambda low, high: 0.0),
}


def _kind(bounds: Bounds) -> str:
    finite = (math.isfinite(bounds.low), math.isfinite(bounds.high))
    return {(True, True): "logit", (True, False): "log", (False, True): "neglog"}.get(
        finite, "identity"
    )


@dataclasses.dataclass(frozen=True)
class FieldMap:
    """How one gain field is parameterised.

    name: the field. shape: the field's shape. bounds: its feasible set.
    groups: axis groups over the leading axis (``None``: elementwise).
    """

    name: str
    shape: tuple[int, ...]
    bounds: Bounds
    groups: tuple[tuple[int, ...], ...] | None

    @property
    def kind(self) -> str:
        return _kind(self.bounds)

    @property
    def param_shape(self) -> tuple[int, ...]:
        if self.groups is None:
            return self.shape
        return (len(self.groups), *self.shape[1:])

    def labels(self) -> list[str]:
        """One readable name per scalar parameter, in ``ravel`` order."""
        if self.groups is None:
            return [f"{self.name}{list(i)}" for i in np.ndindex(*self.shape)] or [self.name]
        names = ["=".join(AXIS_NAMES[a] for a in axes) for axes in self.groups]
        rest = list(np.ndindex(*self.shape[1:]))
        return [
            f"{self.name}[{n}]" + (f"[{','.join(map(str, r))}]" if r else "")
            for n in names
            for r in rest
        ]

    # -- elementwise maps ------------------------------------------------------------
    def _interior(self, value: Array) -> Array:
        """Clamp to the open interval, one ulp inside each finite bound."""
        low, high = self.bounds.low, self.bounds.high
        dtype = value.dtype
        if math.isfinite(low):
            value = jnp.maximum(value, jnp.nextafter(jnp.asarray(low, dtype), jnp.inf))
        if math.isfinite(high):
            value = jnp.minimum(value, jnp.nextafter(jnp.asarray(high, dtype), -jnp.inf))
        return value

    def forward(self, u: Array) -> Array:
        """Unconstrained ``u`` -> feasible values (same shape)."""
        u = jnp.clip(u, -U_MAX, U_MAX)
        return self._interior(_MAPS[self.kind][0](u, self.bounds.low, self.bounds.high))

    def inverse(self, value: np.ndarray) -> np.ndarray:
        """Feasible values -> unconstrained (NumPy float64, before tracing)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return _MAPS[self.kind][1](
                np.asarray(value, np.float64), self.bounds.low, self.bounds.high
            )

    def expand(self, grouped: Array) -> Array:
        """Parameters of shape ``param_shape`` -> the field's shape (axes of a group
        share the group's value)."""
        if self.groups is None:
            return grouped
        index = np.zeros(len(AXIS_NAMES), np.int32)  # the group of each axis
        for g, axes in enumerate(self.groups):
            index[list(axes)] = g
        return jnp.take(grouped, jnp.asarray(index), axis=0)


@dataclasses.dataclass(frozen=True)
class ParameterMap:
    """The tuned fields of one controller's gains and their maps (static, hashable).

    controller: the registry name. fields: one :class:`FieldMap` per tuned field.
    share: the axis-sharing mode (:data:`SHARING`).
    """

    controller: str
    fields: tuple[FieldMap, ...]
    share: str

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @property
    def size(self) -> int:
        """Number of scalar parameters."""
        return int(sum(np.prod(f.param_shape, dtype=int) for f in self.fields))

    def labels(self) -> list[str]:
        """Readable names of the scalar parameters, in :meth:`ravel` order."""
        return [label for f in sorted(self.fields, key=lambda f: f.name) for label in f.labels()]

    def to_gains(self, params: dict[str, Array], base: Any) -> Any:
        """Unconstrained ``params`` -> gains: the tuned fields from ``params``, the
        others from ``base`` (a gains NamedTuple). Traceable, differentiable."""
        values = {}
        for f in self.fields:
            reference = jnp.asarray(getattr(base, f.name))
            u = jnp.asarray(params[f.name], reference.dtype)
            values[f.name] = f.expand(f.forward(u)).astype(reference.dtype)
        return base._replace(**values)

    def to_params(self, gains: Any, dtype: Any = None) -> dict[str, Array]:
        """Gains -> unconstrained parameters (the exact inverse of :meth:`to_gains`).

        Validated in Python: raises ``ValueError`` when the gains are infeasible, lie
        on a bound the maps cannot reach (``include_low`` fields at ``low``), or differ
        between axes that share a parameter.
        """
        registry.get_controller_class(self.controller).check_gains(gains)
        dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
        problems, params = [], {}
        for f in self.fields:
            value = np.asarray(getattr(gains, f.name), np.float64)
            if f.groups is not None:
                grouped = []
                for axes in f.groups:
                    block = value[list(axes)]
                    if not np.all(block == block[0]):
                        names = ", ".join(AXIS_NAMES[a] for a in axes)
                        problems.append(
                            f"{f.name} differs between the axes ({names}) that share one "
                            f"parameter under share={self.share!r}, got {block.tolist()}: "
                            "make them equal or use share='none'"
                        )
                    grouped.append(block[0])
                value = np.stack(grouped)
            u = f.inverse(value)
            if not np.all(np.isfinite(u)) or np.any(np.abs(u) > U_MAX):
                problems.append(
                    f"{f.name} = {value.tolist()} lies on or too close to a bound of its "
                    f"feasible set ({f.bounds.describe(f.name)}), which the tuner's "
                    "parameter map cannot represent: start it strictly inside or leave it "
                    "untuned"
                )
            params[f.name] = jnp.asarray(u, dtype)
        if problems:
            raise ValueError("cannot start tuning from these gains:\n  " + "\n  ".join(problems))
        return params

    def ravel(self, params: dict[str, Array]) -> tuple[Array, Any]:
        """Flatten to a ``(size,)`` vector and the function that undoes it."""
        return ravel_pytree(params)

    def tie(self, coarser: ParameterMap) -> np.ndarray:
        """``(size,)`` indices: parameter ``i`` of this map is parameter ``tie[i]`` of
        ``coarser`` (the same fields, coarser axis groups, e.g. ``share="paper"`` for
        ``"none"``): the vectors ``x = z[tie]`` are those whose tied axes agree."""
        if coarser.names != self.names:
            raise ValueError("a tie maps between parameter maps of the same fields")
        offsets, start = {}, 0
        for f in coarser.fields:
            offsets[f.name] = start
            start += int(np.prod(f.param_shape, dtype=int))
        tie = []
        for fine, coarse in zip(self.fields, coarser.fields, strict=True):
            rest = int(np.prod(fine.shape[1:], dtype=int)) if fine.groups else 1
            if fine.groups is None:
                tie += list(offsets[fine.name] + np.arange(int(np.prod(fine.shape, dtype=int))))
                continue
            group_of = {a: g for g, axes in enumerate(coarse.groups) for a in axes}
            for axes in fine.groups:
                if len({group_of[a] for a in axes}) != 1:
                    raise ValueError(f"{fine.name}: axis groups {axes} span coarser groups")
                first = offsets[fine.name] + group_of[axes[0]] * rest
                tie += list(first + np.arange(rest))
        return np.asarray(tie, np.int64)


def default_fields(controller: str) -> tuple[str, ...]:
    """Fields tuned by default: those whose declared role is in :data:`TUNED_ROLES`."""
    return registry.get_controller_class(controller).GAINS.with_role(*TUNED_ROLES)


def make_parameter_map(
    controller: str, fields: tuple[str, ...] | None = None, share: str = "paper",
    capped: bool = False,
) -> ParameterMap:
    """The :class:`ParameterMap` of ``controller`` for ``fields`` (default
    :func:`default_fields`), with axis sharing ``share``, each field within its bounds
    (``capped``: its search bounds over a flight envelope,
    :meth:`fojax.controllers.GainSpec.search_bounds`); ``ValueError`` on unknown names."""
    cls = registry.get_controller_class(controller)
    if share not in SHARING:
        raise ValueError(f"unknown sharing mode {share!r}; choose one of {', '.join(SHARING)}")
    spec = cls.GAINS
    fields = default_fields(controller) if fields is None else tuple(fields)
    if not fields:
        raise ValueError("no gain fields to tune: name at least one")
    unknown = [f for f in fields if f not in spec.names]
    if unknown:
        raise ValueError(
            f"unknown gain fields for {controller}: {', '.join(unknown)} "
            f"(valid: {', '.join(spec.names)})"
        )
    if len(set(fields)) != len(fields):
        raise ValueError(f"gain fields named twice: {', '.join(fields)}")
    maps = []
    for name in sorted(fields):
        shape = spec.shapes[name]
        per_axis = len(shape) >= 1 and shape[0] == len(AXIS_NAMES)
        bounds = spec.search_bounds(capped)[name]
        maps.append(FieldMap(name, shape, bounds, SHARING[share] if per_axis else None))
    return ParameterMap(controller, tuple(maps), share)


def integer_order_gains(gains: Any, margin: float = 0.01) -> Any:
    """``gains`` with every fractional order (the fields declaring ``integer_order``)
    moved ``margin`` of its bounds' span inside the bound where its operator is of
    integer order (for orders in (0, 1): 0.99 or 0.01), a start the parameter maps can
    represent."""
    spec = type(gains).spec
    values = {}
    for name, edge in spec.integer_orders.items():
        bounds, reference = spec.bounds[name], jnp.asarray(getattr(gains, name))
        inward = -1.0 if edge == bounds.high else 1.0
        value = edge + inward * margin * (bounds.high - bounds.low)
        values[name] = jnp.full(reference.shape, value, reference.dtype)
    return gains._replace(**values)


def naive_gains(controller: str, dtype: Any = None, capped: bool = False) -> Any:
    """A knowledge-free starting point: every bounded field at ``low + 1`` (positive
    gains at 1), ``(low + high) / 2`` for two-sided bounds (``p/q = 1.5``, ``gamma =
    0.5``) for the fields tuned by default (:data:`TUNED_ROLES`); the others keep the
    controller's defaults."""
    spec = registry.get_controller_class(controller).GAINS
    template = spec.default(dtype)
    values = {}
    for name, bounds in spec.search_bounds(capped).items():
        if name not in spec.with_role(*TUNED_ROLES):
            continue
        reference = jnp.asarray(getattr(template, name))
        fill = _MAPS[_kind(bounds)][2](bounds.low, bounds.high)
        values[name] = jnp.full(reference.shape, fill, reference.dtype)
    return template._replace(**values)
