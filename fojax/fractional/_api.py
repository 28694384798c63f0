"""Operators by method name, and whole-signal differintegrals."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from fojax.fractional._common import (
    Array,
    check_finite,
    check_order,
    check_positive_finite,
    float_dtype,
)
from fojax.fractional._gl import GrunwaldLetnikov
from fojax.fractional._oustaloup import Oustaloup
from fojax.fractional._soe import SumOfExponentials

OPERATORS: dict[str, type] = {
    cls.method: cls for cls in (SumOfExponentials, Oustaloup, GrunwaldLetnikov)
}
"""Operator class of each method name; each has ``build(dt, horizon, **options)``,
``option_names`` and ``order_range``."""

METHODS = tuple(OPERATORS)


def _check_options(method: str, options: dict[str, Any]) -> None:
    valid = OPERATORS[method].option_names
    unknown = set(options) - set(valid)
    if unknown:
        raise TypeError(
            f"unknown option(s) {sorted(unknown)} for method {method!r}; valid: {sorted(valid)}"
        )
    for key, value in options.items():
        for v in value if isinstance(value, tuple | list) else (value,):
            if not isinstance(v, bool):
                check_finite(f"option {key}", v)


def make_operator(method: str, dt: float, horizon: float = 80.0, **options: Any):
    """Build the operator ``method`` for step ``dt`` over ``horizon`` seconds.

    ``method`` is ``"soe"`` (default accurate method), ``"oustaloup"`` or ``"gl"``
    (full memory over ``horizon`` unless ``memory=`` is given); see :data:`OPERATORS`.
    """
    if method not in OPERATORS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    check_positive_finite("dt", dt)
    check_positive_finite("horizon", horizon)
    _check_options(method, options)
    return OPERATORS[method].build(dt, horizon, **options)


def run(operator, alpha: Any, u: Array) -> Array:
    """Apply ``operator`` of order ``alpha`` to ``u`` sampled along axis 0 (a scan)."""
    u = jnp.asarray(u)
    coeffs = operator.coefficients(alpha, u.dtype)
    state = operator.init(u.shape[1:], u.dtype)

    def body(state, u_k):
        return operator.step(coeffs, state, u_k)

    _, y = lax.scan(body, state, u)
    return y


@functools.partial(jax.jit, static_argnums=0)
def _apply(operator, u: Array, alpha: Array) -> Array:
    whole = getattr(operator, "apply", None)  # a whole-signal form, where one exists
    return whole(alpha, u) if whole is not None else run(operator, alpha, u)


def differintegrate(u: Any, alpha: Any, dt: float, method: str = "soe", **options: Any) -> Array:
    """Riemann-Liouville differintegral of order ``alpha`` of a sampled signal.

    Args:
        u: ``(steps, ...)`` samples ``u[k] = u(k * dt)``; ``u = 0`` before ``t = 0``.
        alpha: order; ``alpha < 0`` integrates (order ``-alpha``), ``alpha > 0``
            differentiates, ``0`` is the identity. Methods ``"soe"`` and
            ``"oustaloup"`` take ``-1 < alpha < 1``; ``"gl"`` takes ``-2 < alpha < 2``.
            May be traced (differentiable); a traced order is not range-checked.
        dt: sampling step, > 0 (static).
        method: ``"soe"`` (default), ``"oustaloup"`` or ``"gl"``.
        **options: passed to the operator (:class:`SumOfExponentials`,
            :class:`Oustaloup`, :class:`GrunwaldLetnikov`); for ``"soe"`` the horizon
            defaults to the signal's length, for ``"gl"`` the memory to the whole
            signal.

    Returns:
        ``(steps, ...)`` the differintegral at the sample times, same dtype as ``u``.
        For derivatives with ``method="soe"`` the value at ``t = 0`` is 0 (the exact
        derivative is unbounded there unless ``u(0) = 0``).

    Differentiable in ``u`` and ``alpha``; usable under ``jit`` and ``vmap``.
    """
    if method not in OPERATORS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    dt = check_positive_finite("dt", dt)
    _check_options(method, {k: v for k, v in options.items() if k != "horizon" or method != "soe"})
    u = jnp.asarray(u)
    if u.ndim == 0 or u.shape[0] < 1:
        raise ValueError(f"u must have at least one sample along axis 0, got shape {u.shape}")
    u = u.astype(float_dtype(u.dtype))
    if isinstance(alpha, int | float):
        alpha = float(alpha)
    options = dict(options)
    horizon = options.pop("horizon", max(u.shape[0] - 1, 1) * dt)
    operator = make_operator(method, dt, horizon, **options)
    lo, hi = operator.order_range
    check_order(alpha, lo, hi, method)
    return _apply(operator, u, jnp.asarray(alpha, u.dtype))
