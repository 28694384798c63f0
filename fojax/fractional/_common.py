"""Shared checks and helpers of the fractional operators."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

# Orders closer to zero than this are treated as exactly zero inside the derivative
# branch, where the closed-form weights have a removable 0/0 at order 0.
ORDER_FLOOR = 1e-6


def is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def check_positive_finite(name: str, value: Any) -> float:
    v = check_finite(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be > 0, got {v}")
    return v


def check_order(alpha: Any, lower: float, upper: float, method: str) -> None:
    """Validate a concrete order; traced orders are the caller's responsibility."""
    if not is_concrete(alpha):
        return
    a = np.asarray(alpha, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"order alpha must be finite, got {alpha!r}")
    if np.any(a <= lower) or np.any(a >= upper):
        raise ValueError(
            f"method {method!r} supports orders {lower} < alpha < {upper} "
            f"(alpha < 0 integrates, alpha > 0 differentiates); got alpha = {alpha!r}"
        )


def float_dtype(dtype: Any) -> Any:
    dtype = jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.dtype(jnp.result_type(float))
    return dtype


def per_order(build, alpha: Any, dtype: Any) -> Any:
    """``build(alpha_scalar, dtype)`` mapped over the entries of ``alpha``.

    The result's leaves keep their own axes first and get ``alpha.shape`` as trailing
    axes (``(modes,) + alpha.shape``), the layout of the operators' states (their own
    axes first, the signal's shape ``S`` last): one state can carry a different order
    per channel when ``alpha.shape`` broadcasts against ``S`` (:func:`align`).
    """
    dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
    alpha = jnp.asarray(alpha, dtype)
    if alpha.ndim == 0:
        return build(alpha, dtype)
    flat = jax.vmap(lambda a: build(a, dtype))(alpha.reshape(-1))
    return jax.tree.map(
        lambda leaf: jnp.moveaxis(leaf, 0, -1).reshape(leaf.shape[1:] + alpha.shape), flat
    )


def align(x: Array, own: int, signal_ndim: int) -> Array:
    """``x`` of shape ``own axes + O`` (a coefficient: its ``own`` leading axes, then the
    orders' shape ``O``) with ones inserted after its own axes so that ``O`` lines up
    with the last axes of a signal of ``signal_ndim`` axes, numpy's rule: an order per
    channel ``(12, 1)`` against signals ``(12, draws)``, one order ``()`` against any."""
    missing = own + signal_ndim - x.ndim
    if missing < 0:
        raise ValueError(
            f"orders of shape {x.shape[own:]} have more axes than the signal ({signal_ndim})"
        )
    return x.reshape(x.shape[:own] + (1,) * missing + x.shape[own:])


def lead(table: Array, signal_ndim: int) -> Array:
    """A ``(modes,)`` table shaped ``(modes,) + (1,) * signal_ndim``: one value per mode,
    broadcast over the signal."""
    return table.reshape(table.shape + (1,) * signal_ndim)


def select(pred: Array, on_true: Any, on_false: Any) -> Any:
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


# ----------------------------------------------------- exponential integrals J_m(z)


def expint_moments_np(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``J_m(z) = int_0^1 exp(-z theta) theta**m dtheta`` for m = 0, 1, 2, in float64."""
    z = np.asarray(z, dtype=np.float64)
    small = z < 0.1
    zs = np.where(small, 1.0, z)
    e = np.exp(-zs)
    j0 = -np.expm1(-zs) / zs
    j1 = (1.0 - e * (1.0 + zs)) / zs**2
    j2 = (2.0 - e * (2.0 + 2.0 * zs + zs**2)) / zs**3
    # Series for small z: sum_k (-z)^k / (k! (k + m + 1)).
    k = np.arange(12)
    fact = np.array([math.factorial(i) for i in k], dtype=np.float64)
    pw = (-z[..., None]) ** k / fact
    s0 = np.sum(pw / (k + 1), axis=-1)
    s1 = np.sum(pw / (k + 2), axis=-1)
    s2 = np.sum(pw / (k + 3), axis=-1)
    return np.where(small, s0, j0), np.where(small, s1, j1), np.where(small, s2, j2)


def expint_moments(z: Array) -> tuple[Array, Array]:
    """``J_0(z)`` and ``J_1(z)`` in JAX, safe (and differentiable) down to ``z = 0``."""
    small = z < 0.1
    zs = jnp.where(small, 1.0, z)
    e = jnp.exp(-zs)
    j0 = -jnp.expm1(-zs) / zs
    j1 = (1.0 - e * (1.0 + zs)) / zs**2
    s0 = 1.0 - z / 2 + z**2 / 6 - z**3 / 24 + z**4 / 120 - z**5 / 720
    s1 = 0.5 - z / 3 + z**2 / 8 - z**3 / 30 + z**4 / 144 - z**5 / 840
    return jnp.where(small, s0, j0), jnp.where(small, s1, j1)
