"""The Oustaloup / CRONE recursive approximation (the paper's Remark 4)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from fojax.fractional._common import (
    ORDER_FLOOR,
    Array,
    align,
    check_positive_finite,
    expint_moments,
    float_dtype,
    per_order,
    select,
)


class ModalCoefficients(NamedTuple):
    """A rational transfer function in partial fractions, discretised for a
    piecewise-linear input.

    decay: ``(modes,)`` ``exp(p_k dt)`` per pole ``p_k``.
    gain_u, gain_u1: ``(modes,)`` input gains of ``u_k`` and ``u_{k-1}``.
    residue: ``(modes,)`` output weights (partial-fraction residues).
    direct: ``()`` direct feedthrough.
    """

    decay: Array
    gain_u: Array
    gain_u1: Array
    residue: Array
    direct: Array


class ModalState(NamedTuple):
    """``modes``: ``S + (modes,)`` mode states; ``u_prev``: ``S``; ``count``: ``()``."""

    modes: Array
    u_prev: Array
    count: Array


def _partial_fractions(zeros: Array, poles: Array, gain: Array) -> tuple[Array, Array]:
    """Residues and direct term of ``gain * prod(s - z) / prod(s - p)``, distinct poles.

    Requires ``len(zeros) <= len(poles)``; the direct term is ``gain`` when the
    degrees are equal, else 0.
    """
    diff_pp = poles[:, None] - poles[None, :]
    n = poles.shape[0]
    diff_pp = jnp.where(jnp.eye(n, dtype=bool), 1.0, diff_pp)
    num = jnp.prod(poles[:, None] - zeros[None, :], axis=1)
    residues = gain * num / jnp.prod(diff_pp, axis=1)
    direct = gain if zeros.shape[0] == n else jnp.zeros_like(gain)
    return residues, direct


@dataclasses.dataclass(frozen=True)
class Oustaloup:
    """Oustaloup (CRONE) recursive approximation of ``s**alpha`` over a band.

    ``s**gamma ~ K prod_{k=-N}^{N} (s + w'_k) / (s + w_k)`` with
    ``w'_k = w_b (w_h/w_b)^((k + N + (1 - gamma)/2) / (2N + 1))``,
    ``w_k = w_b (w_h/w_b)^((k + N + (1 + gamma)/2) / (2N + 1))``, ``K = w_h**gamma``
    (Oustaloup et al. 2000), for ``-1 < gamma < 1``: 2N + 1 poles and zeros.

    ``refined=True`` is the refined (modified) Oustaloup filter of Xue, Zhao & Chen
    (2006): the product above times
    ``(d s^2 + b w_h s) / (d (1 - gamma) s^2 + b w_h s + d gamma)`` with gain
    ``(d w_h / b)**gamma``, valid for ``0 < gamma < 1``; integrals of order ``beta``
    use ``s**-beta = s**(1 - beta) / s``.

    The transfer function is written in partial fractions and each first-order mode
    is discretised exactly for an input that is linear between samples (first-order
    hold), so the discrete filter has no error beyond the approximation itself.

    Args:
        dt: sampling step (s), > 0.
        band: ``(w_b, w_h)`` in rad/s, ``0 < w_b < w_h``. Default: the paper's
            ``(0.01, 100)``.
        order: ``N``; the filter has ``2N + 1`` poles. Default 5 (11 poles: the
            paper's "order 10", read as the nearest Oustaloup order).
        refined: use the refined variant.
        refined_b, refined_d: the refined variant's ``b`` and ``d`` (10 and 9).
    """

    dt: float
    band: tuple[float, float] = (0.01, 100.0)
    order: int = 5
    refined: bool = False
    refined_b: float = 10.0
    refined_d: float = 9.0

    method = "oustaloup"
    order_range = (-1.0, 1.0)
    option_names = ("band", "order", "refined", "refined_b", "refined_d")

    @classmethod
    def build(cls, dt: float, horizon: float, **options: Any) -> Oustaloup:
        """The filter for step ``dt`` (its band does not depend on ``horizon``)."""
        if "band" in options:
            options["band"] = tuple(options["band"])
        return cls(dt=dt, **options)

    def __post_init__(self) -> None:
        check_positive_finite("dt", self.dt)
        try:
            lo, hi = (float(v) for v in self.band)
        except (TypeError, ValueError):
            raise ValueError(f"band must be a pair (w_low, w_high), got {self.band!r}") from None
        check_positive_finite("band[0]", lo)
        check_positive_finite("band[1]", hi)
        if not lo < hi:
            raise ValueError(f"band must satisfy w_low < w_high, got {self.band!r}")
        object.__setattr__(self, "band", (lo, hi))
        if not isinstance(self.order, int | np.integer) or not 1 <= self.order <= 30:
            raise ValueError(f"order N must be an integer in [1, 30], got {self.order!r}")
        check_positive_finite("refined_b", self.refined_b)
        check_positive_finite("refined_d", self.refined_d)

    @property
    def n_modes(self) -> int:
        return 2 * self.order + 1 + (2 if self.refined else 0)

    def _zpk(self, gamma: Array, dtype: Any) -> tuple[Array, Array, Array]:
        """Zeros, poles and gain approximating ``s**gamma`` (plain Oustaloup)."""
        lo, hi = self.band
        n = self.order
        k = jnp.arange(-n, n + 1, dtype=dtype)
        ratio = math.log(hi / lo)
        zeros = -lo * jnp.exp(ratio * (k + n + (1.0 - gamma) / 2.0) / (2 * n + 1))
        poles = -lo * jnp.exp(ratio * (k + n + (1.0 + gamma) / 2.0) / (2 * n + 1))
        return zeros, poles, jnp.exp(gamma * math.log(hi))

    def _transfer(self, alpha: Array, dtype: Any) -> tuple[Array, Array, Array]:
        """Poles, residues and direct term for order ``alpha``."""
        if not self.refined:
            zeros, poles, gain = self._zpk(alpha, dtype)
            residues, direct = _partial_fractions(zeros, poles, gain)
            return poles, residues, direct
        _, hi = self.band
        bb, dd = self.refined_b, self.refined_d

        def refined(gamma: Array, integral: bool) -> tuple[Array, Array, Array]:
            zeros, poles, _ = self._zpk(gamma, dtype)
            gain = jnp.exp(gamma * math.log(dd * hi / bb))
            # Roots of d(1-gamma) s^2 + b w_h s + d gamma, computed stably.
            qa, qb, qc = dd * (1.0 - gamma), bb * hi, dd * gamma
            q = -0.5 * (qb + jnp.sqrt(qb * qb - 4.0 * qa * qc))
            extra_poles = jnp.stack([q / qa, qc / q])
            lead = gain / (1.0 - gamma)  # d / (d (1 - gamma))
            extra_zeros = [jnp.asarray(-bb * hi / dd, dtype)[None]]
            if not integral:
                extra_zeros.append(jnp.zeros((1,), dtype))
            all_zeros = jnp.concatenate([zeros] + extra_zeros)
            all_poles = jnp.concatenate([poles, extra_poles])
            res, direct = _partial_fractions(all_zeros, all_poles, lead)
            return all_poles, res, direct

        beta = jnp.clip(-alpha, ORDER_FLOOR, 1.0 - ORDER_FLOOR)
        gamma = jnp.clip(alpha, ORDER_FLOOR, 1.0 - ORDER_FLOOR)
        integral = refined(1.0 - beta, integral=True)
        derivative = refined(gamma, integral=False)
        identity = (
            integral[0],
            jnp.zeros_like(integral[1]),
            jnp.ones_like(integral[2]),
        )
        out = select(alpha < 0, integral, derivative)
        return select(alpha == 0, identity, out)

    def coefficients(self, alpha: Any, dtype: Any = None) -> ModalCoefficients:
        """Discretised filter for order ``alpha`` (any shape: one order per channel)."""
        return per_order(self._coefficients, alpha, dtype)

    def _coefficients(self, alpha: Array, dtype: Any) -> ModalCoefficients:
        poles, residues, direct = self._transfer(alpha, dtype)
        z = -poles * self.dt
        j0, j1 = expint_moments(z)
        return ModalCoefficients(
            decay=jnp.exp(-z),
            gain_u=self.dt * (j0 - j1),
            gain_u1=self.dt * j1,
            residue=residues,
            direct=jnp.asarray(direct, dtype),
        )

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> ModalState:
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
        shape = tuple(shape)
        return ModalState(
            modes=jnp.zeros((self.n_modes,) + shape, dtype),
            u_prev=jnp.zeros(shape, dtype),
            count=jnp.zeros((), jnp.int32),
        )

    def step(
        self, coeffs: ModalCoefficients, state: ModalState, u: Array
    ) -> tuple[ModalState, Array]:
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        n = u.ndim
        increment = align(coeffs.gain_u, 1, n) * u + align(coeffs.gain_u1, 1, n) * state.u_prev
        modes = align(coeffs.decay, 1, n) * state.modes + jnp.where(
            state.count > 0, increment, 0.0
        )
        y = align(coeffs.direct, 0, n) * u + jnp.sum(modes * align(coeffs.residue, 1, n), 0)
        return ModalState(modes=modes, u_prev=u, count=state.count + 1), y

    def cost(self) -> dict[str, int]:
        m = self.n_modes
        return {"modes": m, "flops_per_step": 5 * m + 2, "state_floats": m + 2}
