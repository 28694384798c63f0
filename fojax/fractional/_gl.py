"""The Grunwald-Letnikov sum: full memory (the reference) or a short-memory window."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from fojax.fractional._common import (
    Array,
    align,
    check_positive_finite,
    float_dtype,
    per_order,
)


class GLCoefficients(NamedTuple):
    """``weights``: ``(memory,) + O`` ``dt**-alpha * (-1)**j binom(alpha, j)`` for orders
    of shape ``O``."""

    weights: Array


class GLState(NamedTuple):
    """``history``: ``(memory,) + S`` the last samples, newest first."""

    history: Array


def _gl_weights(alpha: Array, length: int, dt: float, dtype: Any) -> Array:
    j = jnp.arange(1, length, dtype=dtype)
    factors = 1.0 - (alpha + 1.0) / j
    w = jnp.concatenate([jnp.ones((1,), dtype), jnp.cumprod(factors)])
    return w * jnp.exp(-alpha * math.log(dt))


@dataclasses.dataclass(frozen=True)
class GrunwaldLetnikov:
    """Grunwald-Letnikov differintegral ``dt**-alpha sum_j (-1)^j C(alpha, j) u_{k-j}``.

    First-order accurate. With ``memory`` equal to the number of samples of the whole
    run this is the full-memory reference; a smaller ``memory`` is the short-memory
    principle (the sum is truncated to the last ``memory`` samples).

    Args:
        dt: sampling step (s), > 0.
        memory: number of samples kept, >= 1 (the buffer is preallocated).
    """

    dt: float
    memory: int

    method = "gl"
    order_range = (-2.0, 2.0)
    option_names = ("memory",)

    @classmethod
    def build(cls, dt: float, horizon: float, memory: int | None = None) -> GrunwaldLetnikov:
        """Full memory over ``horizon`` unless ``memory`` (samples) is given."""
        return cls(dt=dt, memory=int(round(horizon / dt)) + 1 if memory is None else memory)

    def __post_init__(self) -> None:
        check_positive_finite("dt", self.dt)
        if not isinstance(self.memory, int | np.integer) or self.memory < 1:
            raise ValueError(f"memory must be a positive integer, got {self.memory!r}")

    @property
    def n_modes(self) -> int:
        return int(self.memory)

    def coefficients(self, alpha: Any, dtype: Any = None) -> GLCoefficients:
        """Weights for order ``alpha`` (any shape: one order per channel)."""
        return per_order(
            lambda a, dt_: GLCoefficients(_gl_weights(a, self.memory, self.dt, dt_)), alpha, dtype
        )

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> GLState:
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
        return GLState(jnp.zeros((self.memory,) + tuple(shape), dtype))

    def step(self, coeffs: GLCoefficients, state: GLState, u: Array) -> tuple[GLState, Array]:
        u = jnp.asarray(u, state.history.dtype)
        history = jnp.concatenate([u[None], state.history[:-1]], axis=0)
        return GLState(history), jnp.sum(history * align(coeffs.weights, 1, u.ndim), 0)

    def cost(self) -> dict[str, int]:
        m = int(self.memory)
        return {"modes": m, "flops_per_step": 2 * m, "state_floats": m}

    def apply(self, alpha: Array, u: Array) -> Array:
        """The whole signal ``u`` (axis 0) at once, by zero-padded FFT convolution."""
        n = u.shape[0]
        length = min(self.memory, n)
        w = _gl_weights(alpha, length, self.dt, u.dtype)
        size = 1 << int(math.ceil(math.log2(max(2, n + length - 1))))
        wf = jnp.fft.rfft(w, size)
        uf = jnp.fft.rfft(u, size, axis=0)
        wf = wf.reshape((-1,) + (1,) * (u.ndim - 1))
        return jnp.fft.irfft(uf * wf, size, axis=0)[:n].astype(u.dtype)
