"""Memory combinators: several orders of one signal, and an integral with its rate."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp

from fojax.fractional._common import Array, float_dtype


@dataclasses.dataclass(frozen=True)
class MultiOrder:
    """Several orders applied to the same signal.

    When the operator's modes do not depend on the order (``shares_modes``, as for
    :class:`fojax.fractional.SumOfExponentials`), one state serves every order (for
    instance ``D^(gamma-1) f`` and its time derivative ``D^gamma f``); other methods
    keep one state per order.

    ``coefficients(alphas)`` takes a sequence of ``n_orders`` orders (each of any
    shape broadcastable to the signal); ``step`` returns a tuple of ``n_orders``
    outputs.
    """

    operator: Any
    n_orders: int

    @property
    def shared(self) -> bool:
        return bool(getattr(self.operator, "shares_modes", False))

    def coefficients(self, alphas, dtype: Any = None) -> tuple:
        if len(alphas) != self.n_orders:
            raise ValueError(f"expected {self.n_orders} orders, got {len(alphas)}")
        return tuple(self.operator.coefficients(a, dtype) for a in alphas)

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> Any:
        if self.shared:
            return self.operator.init(shape, dtype)
        return tuple(self.operator.init(shape, dtype) for _ in range(self.n_orders))

    def step(self, coeffs: tuple, state: Any, u: Array) -> tuple[Any, tuple]:
        if self.shared:
            outputs = tuple(self.operator.output(c, state, u) for c in coeffs)
            return self.operator.advance(state, u), outputs
        pairs = [self.operator.step(c, s, u) for c, s in zip(coeffs, state, strict=True)]
        return tuple(p[0] for p in pairs), tuple(p[1] for p in pairs)


@dataclasses.dataclass(frozen=True)
class IntegralWithRate:
    """``I^b u`` and its time derivative ``d/dt I^b u = D^(1-b) u`` from one memory.

    The pair that a sliding surface and its derivative need: ``D^(gamma - 1) f`` with
    ``D^gamma f``, or ``I^gamma g`` with ``D^(1 - gamma) g``: :class:`MultiOrder` with
    orders ``(-b, 1 - b)``. Build it with :func:`integral_with_rate`, which returns an
    operator's own fused form where it has one.

    ``coefficients(b)`` takes the integral orders ``b`` in ``(0, 1)`` (any shape, one
    per channel); ``step(coeffs, state, u) -> (state, (integral, rate))``.
    """

    operator: Any

    @property
    def _orders(self) -> MultiOrder:
        return MultiOrder(self.operator, 2)

    def coefficients(self, b: Any, dtype: Any = None) -> tuple:
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
        b = jnp.asarray(b, dtype)
        return self._orders.coefficients((-b, 1.0 - b), dtype)

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> Any:
        return self._orders.init(shape, dtype)

    def step(self, coeffs: tuple, state: Any, u: Array) -> tuple[Any, tuple[Array, Array]]:
        return self._orders.step(coeffs, state, u)


def integral_with_rate(operator: Any) -> Any:
    """The integral-and-rate memory of ``operator``: its fused form
    (``operator.integral_with_rate()``) where it has one, :class:`IntegralWithRate`
    otherwise. Both have the same ``coefficients``/``init``/``step``."""
    fused = getattr(operator, "integral_with_rate", None)
    return fused() if fused is not None else IntegralWithRate(operator)
