"""Fractional-order integrals and derivatives as fixed-size recursive operators.

Every operator here is a static configuration object (a frozen dataclass, hashable,
settled in Python before tracing) with three pure functions:

``coefficients(alpha, dtype) -> Coefficients``
    Everything that depends on the order ``alpha``, as a pytree of arrays. It is
    traceable and differentiable in ``alpha``; compute it once per rollout.
``init(shape, dtype) -> State``
    The operator's memory for a signal of shape ``shape`` (the signal at one time
    step), all zeros: the signal is taken to be zero before ``t = 0``.
``step(coefficients, state, u) -> (state, y)``
    Consume the sample ``u = u(t_k)`` (shape ``shape``) and return the
    differintegral of order ``alpha`` at ``t_k``.

so that a closed loop can carry ``state`` in a :func:`jax.lax.scan`. ``alpha < 0`` is
a Riemann-Liouville integral of order ``-alpha``; ``alpha > 0`` is a
Riemann-Liouville derivative; ``alpha == 0`` is the identity.

Three families are provided:

* :class:`SumOfExponentials` (the default, ``method="soe"``): the kernel
  ``t**(b - 1) / Gamma(b)`` of the integral of order ``b`` is written as its
  diffusive (Laplace) representation, discretised with a trapezoidal rule in
  ``log s`` on fixed nodes; the part of the spectrum below ``1 / horizon`` is folded
  into a few fixed slow modes by interpolation in ``s``. Modes are fixed; the
  weights are closed-form functions of the order, so gradients in the order are
  exact. The last step is integrated exactly against a quadratic interpolant of
  the signal (product integration), the history through the modes, each updated
  exactly. Relative error below 1e-4 for every order in ``[0.01, 0.99]`` over 80 s
  at a 1 ms step (see ``docs/fractional.md``).
* :class:`Oustaloup` (``method="oustaloup"``): the Oustaloup/CRONE recursive
  approximation of ``s**alpha`` over a frequency band (the paper's Remark 4), and
  its refined variant; written in partial fractions and discretised exactly per
  mode for a piecewise-linear input.
* :class:`GrunwaldLetnikov` (``method="gl"``): the Grunwald-Letnikov sum with full
  memory (the reference) or a short-memory window, in a preallocated buffer.

:func:`differintegrate` applies any of them to a whole sampled signal.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.special import gammaln

Array = jax.Array

__all__ = [
    "GrunwaldLetnikov",
    "IntegralWithRate",
    "MultiOrder",
    "Oustaloup",
    "SumOfExponentials",
    "differintegrate",
    "make_operator",
    "METHODS",
]

METHODS = ("soe", "oustaloup", "gl")

# Orders closer to zero than this are treated as exactly zero inside the derivative
# branch, where the closed-form weights have a removable 0/0 at order 0.
_ORDER_FLOOR = 1e-6


# ----------------------------------------------------------------------------- checks


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_positive_finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    if v <= 0:
        raise ValueError(f"{name} must be > 0, got {v}")
    return v


def _check_order(alpha: Any, lower: float, upper: float, method: str) -> None:
    """Validate a concrete order; traced orders are the caller's responsibility."""
    if not _is_concrete(alpha):
        return
    a = np.asarray(alpha, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"order alpha must be finite, got {alpha!r}")
    if np.any(a <= lower) or np.any(a >= upper):
        raise ValueError(
            f"method {method!r} supports orders {lower} < alpha < {upper} "
            f"(alpha < 0 integrates, alpha > 0 differentiates); got alpha = {alpha!r}"
        )


def _float_dtype(dtype: Any) -> Any:
    dtype = jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.dtype(jnp.result_type(float))
    return dtype


def _per_order(build, alpha: Any, dtype: Any) -> Any:
    """``build(alpha_scalar, dtype)`` mapped over the entries of ``alpha``.

    The result's leaves get ``alpha.shape`` as leading axes, so one operator state of
    shape ``S + (modes,)`` can carry a different order per channel when
    ``alpha.shape`` broadcasts against ``S``.
    """
    dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
    alpha = jnp.asarray(alpha, dtype)
    if alpha.ndim == 0:
        return build(alpha, dtype)
    flat = jax.vmap(lambda a: build(a, dtype))(alpha.reshape(-1))
    return jax.tree.map(lambda leaf: leaf.reshape(alpha.shape + leaf.shape[1:]), flat)


def _select(pred: Array, on_true: Any, on_false: Any) -> Any:
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


# ------------------------------------------------------- exponential integrals J_m(z)


def _expint_moments_np(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def _expint_moments(z: Array) -> tuple[Array, Array]:
    """``J_0(z)`` and ``J_1(z)`` in JAX, safe (and differentiable) down to ``z = 0``."""
    small = z < 0.1
    zs = jnp.where(small, 1.0, z)
    e = jnp.exp(-zs)
    j0 = -jnp.expm1(-zs) / zs
    j1 = (1.0 - e * (1.0 + zs)) / zs**2
    s0 = 1.0 - z / 2 + z**2 / 6 - z**3 / 24 + z**4 / 120 - z**5 / 720
    s1 = 0.5 - z / 3 + z**2 / 8 - z**3 / 30 + z**4 / 144 - z**5 / 840
    return jnp.where(small, s0, j0), jnp.where(small, s1, j1)


# ------------------------------------------------------------------ sum of exponentials


class SOECoefficients(NamedTuple):
    """Order-dependent weights of :class:`SumOfExponentials`.

    history: ``(modes,)`` weights applied to the mode states ``y_j(t_{k-1})``.
    local: ``(3,)`` weights of ``(u_k, u_{k-1}, u_{k-2})`` (last-step product
        integration, plus the history's boundary term for derivatives).
    first: ``()`` weight of ``u_0`` at ``t_0`` (1 for the identity, else 0).
    """

    history: Array
    local: Array
    first: Array


class SOEState(NamedTuple):
    """Memory of :class:`SumOfExponentials` for a signal of shape ``S``.

    modes: ``S + (modes,)`` the exponentially weighted integrals
        ``y_j(t) = int_0^t exp(-s_j (t - tau)) u(tau) dtau`` at the previous sample.
    u_prev, u_prev2: ``S`` the two previous samples.
    count: ``()`` int32, number of samples consumed.
    """

    modes: Array
    u_prev: Array
    u_prev2: Array
    count: Array


@dataclasses.dataclass(frozen=True)
class SumOfExponentials:
    """Kernel-compression (sum-of-exponentials) fractional operator.

    The kernel of the Riemann-Liouville integral of order ``b`` in ``(0, 1)`` has
    the diffusive representation

    ``t**(b-1) / Gamma(b) = sin(pi b) / pi * int exp((1 - b) x) exp(-exp(x) t) dx``.

    The trapezoidal rule with step ``log_step`` on the fixed nodes
    ``x_j = -log(horizon) + j * log_step`` (j = 1 ... until ``exp(x) * dt``
    exceeds ``z_max``) gives modes with rates ``s_j = exp(x_j)`` and weights
    ``sin(pi b)/pi * log_step * exp((1 - b) x_j)``. The trapezoidal nodes below
    ``1 / horizon`` form an infinite geometric tail; on ``t <= horizon`` the
    function ``exp(-s t)`` is smooth in ``s`` there, so the tail is interpolated at
    ``tail_modes`` fixed Chebyshev rates in ``[0, 1/horizon]`` with weights that are
    closed-form sums of the tail's moments. A derivative of order ``a`` is the time
    derivative of the integral of order ``1 - a``; the modes give it in closed form
    (``dy_j/dt = u - s_j y_j``).

    The kernel is approximated on ``[dt, horizon]``; the last step ``[t_{k-1}, t_k]``
    is integrated exactly against the quadratic interpolant of
    ``(u_{k-2}, u_{k-1}, u_k)`` (linear on the first step). Beyond ``horizon`` the
    operator keeps running, with slowly growing error.

    Args:
        dt: sampling step (s), > 0.
        horizon: longest time (s) over which the kernel must be accurate, > dt.
        log_step: trapezoidal step in ``log s``; smaller is more accurate.
        tail_modes: number of slow modes that carry the spectrum below ``1/horizon``.
        z_max: largest ``s * dt`` kept.
    """

    dt: float
    horizon: float = 80.0
    log_step: float = 0.6
    tail_modes: int = 8
    z_max: float = 20.0

    def __post_init__(self) -> None:
        dt = _check_positive_finite("dt", self.dt)
        horizon = _check_positive_finite("horizon", self.horizon)
        _check_positive_finite("log_step", self.log_step)
        _check_positive_finite("z_max", self.z_max)
        if not isinstance(self.tail_modes, int | np.integer) or not 2 <= self.tail_modes <= 16:
            raise ValueError(f"tail_modes must be an integer in [2, 16], got {self.tail_modes!r}")
        if self.log_step > 2.0:
            raise ValueError(f"log_step must be <= 2 (accuracy collapses), got {self.log_step}")
        # Always cover at least one step of history.
        object.__setattr__(self, "horizon", max(horizon, dt))

    method = "soe"
    order_range = (-1.0, 1.0)

    # -- fixed tables (float64 numpy, built once per configuration) --------------------
    @functools.cached_property
    def _tables(self) -> dict[str, np.ndarray]:
        h = float(self.log_step)
        x_tail = -math.log(self.horizon)  # node x_0 of the tail, rate 1/horizon
        x_top = math.log(self.z_max / self.dt)
        n = max(1, int(math.ceil((x_top - x_tail) / h)))
        x = x_tail + h * np.arange(1, n + 1)
        K = int(self.tail_modes)
        kk = np.arange(K)
        rho = 0.5 * (1.0 - np.cos((2 * kk + 1) * np.pi / (2 * K)))  # in (0, 1)
        tail_rate = math.exp(x_tail)
        # Lagrange basis at the Chebyshev points, in the variable v = s / tail_rate.
        vander = np.vander(rho, K, increasing=True)  # vander[k, m] = rho_k^m
        basis = np.linalg.inv(vander).T  # L_k(v) = sum_m basis[k, m] v^m
        # The tail nodes are v_i = exp(-i h), i >= 0. The first n_explicit are summed
        # explicitly (L_k evaluated in float64), the rest through monomial moments,
        # which are small there, so no cancellation occurs in low precision.
        n_explicit = int(math.ceil(7.0 / h))
        v = np.exp(-h * np.arange(n_explicit))
        lagrange_at_tail = basis @ np.vander(v, K, increasing=True).T  # (K, n_explicit)
        rates = np.concatenate([np.exp(x), tail_rate * rho])
        z = rates * self.dt
        j0, j1, j2 = _expint_moments_np(z)
        dt = self.dt
        return {
            "x": x,
            "rates": rates,
            "decay": np.exp(-z),
            "decay_m1": np.expm1(-z),
            "gain_u": dt * (j0 - 1.5 * j1 + 0.5 * j2),
            "gain_u1": dt * (2.0 * j1 - j2),
            "gain_u2": dt * (-0.5 * j1 + 0.5 * j2),
            "basis": basis,
            "lagrange_at_tail": lagrange_at_tail,
            "n_explicit": np.array(n_explicit),
            "x_tail": np.array(x_tail),
            "h": np.array(h),
        }

    @property
    def n_modes(self) -> int:
        return int(self._tables["rates"].shape[0])

    def kernel_weights(self, b: Array, one_minus_b: Array, dtype: Any = None) -> Array:
        """Weights ``w_j(b)``, ``(modes,)``, with ``sum_j w_j exp(-s_j t) ~ t**(b-1)/Gamma(b)``.

        ``one_minus_b`` is passed separately so that orders near 1 keep full precision.
        """
        dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
        tb = self._tables
        b = jnp.asarray(b, dtype)
        omb = jnp.asarray(one_minus_b, dtype)
        h = float(tb["h"])
        scale = jnp.sin(jnp.pi * jnp.minimum(b, omb)) / jnp.pi
        trap = h * jnp.exp(omb * jnp.asarray(tb["x"], dtype))
        n_exp = int(tb["n_explicit"])
        x_tail = float(tb["x_tail"])
        i = jnp.arange(n_exp, dtype=dtype)
        explicit = h * jnp.exp(omb * (x_tail - h * i))  # (n_explicit,)
        tail = jnp.asarray(tb["lagrange_at_tail"], dtype) @ explicit
        m = jnp.arange(self.tail_modes, dtype=dtype)
        # sum_{i >= n_exp} h exp((1-b)(x_tail - i h)) exp(-i h m)
        moments = h * jnp.exp(omb * x_tail - n_exp * h * (m + omb)) / (-jnp.expm1(-(m + omb) * h))
        tail = tail + jnp.asarray(tb["basis"], dtype) @ moments
        return scale * jnp.concatenate([trap, tail])

    def coefficients(self, alpha: Any, dtype: Any = None) -> SOECoefficients:
        """Weights for order ``alpha`` (any shape: one order per channel)."""
        return _per_order(self._coefficients, alpha, dtype)

    def _coefficients(self, alpha: Array, dtype: Any) -> SOECoefficients:
        tb = self._tables
        dt = float(self.dt)
        decay = jnp.asarray(tb["decay"], dtype)
        rates = jnp.asarray(tb["rates"], dtype)

        # Integral of order b = -alpha (b = 0: identity).
        b = jnp.clip(-alpha, 0.0, 1.0 - _ORDER_FLOOR)
        w_int = self.kernel_weights(b, 1.0 - b, dtype)
        lead = jnp.exp(b * math.log(dt) - gammaln(b + 1.0))  # dt^b / Gamma(b + 1)
        local_int = lead * jnp.stack(
            [
                1.0 - 1.5 * b / (b + 1.0) + 0.5 * b / (b + 2.0),
                2.0 * b / (b + 1.0) - b / (b + 2.0),
                -0.5 * b / (b + 1.0) + 0.5 * b / (b + 2.0),
            ]
        )
        int_coeffs = SOECoefficients(
            history=w_int * decay,
            local=local_int,
            first=jnp.where(alpha == 0, 1.0, 0.0).astype(dtype),
        )

        # Derivative of order a = alpha: d/dt of the integral of order 1 - a.
        a = jnp.clip(alpha, _ORDER_FLOOR, 1.0 - _ORDER_FLOOR)
        bd = 1.0 - a
        w_der = self.kernel_weights(bd, a, dtype) * decay
        lead_d = jnp.exp(-a * math.log(dt) - gammaln(2.0 - a))  # dt^-a / Gamma(2 - a)
        frac = bd / (bd + 1.0)
        local_der = lead_d * jnp.stack([1.5 - frac, -(2.0 - 2.0 * frac), 0.5 - frac])
        local_der = local_der + jnp.stack([0.0, jnp.sum(w_der), 0.0]).astype(dtype)
        der_coeffs = SOECoefficients(
            history=-w_der * rates,
            local=local_der,
            first=jnp.zeros((), dtype),
        )
        return _select(alpha <= 0, int_coeffs, der_coeffs)

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> SOEState:
        dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
        shape = tuple(shape)
        return SOEState(
            modes=jnp.zeros(shape + (self.n_modes,), dtype),
            u_prev=jnp.zeros(shape, dtype),
            u_prev2=jnp.zeros(shape, dtype),
            count=jnp.zeros((), jnp.int32),
        )

    def output(self, coeffs: SOECoefficients, state: SOEState, u: Array) -> Array:
        """The differintegral at ``t_k`` for sample ``u = u(t_k)``, without advancing.

        Any number of orders can be read from one state: the modes do not depend on
        the order.
        """
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        u_prev2 = self._previous2(state, u)
        local = (
            coeffs.local[..., 0] * u
            + coeffs.local[..., 1] * state.u_prev
            + coeffs.local[..., 2] * u_prev2
        )
        history = jnp.sum(state.modes * coeffs.history, axis=-1)
        return jnp.where(state.count > 0, history + local, coeffs.first * u)

    def advance(self, state: SOEState, u: Array) -> SOEState:
        """Consume ``u = u(t_k)``: advance the modes to ``t_k``."""
        tb = self._tables
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        u_prev2 = self._previous2(state, u)
        increment = (
            jnp.asarray(tb["gain_u"], dtype) * u[..., None]
            + jnp.asarray(tb["gain_u1"], dtype) * state.u_prev[..., None]
            + jnp.asarray(tb["gain_u2"], dtype) * u_prev2[..., None]
        )
        # y + (exp(-z) - 1) y keeps slow modes exact in float32 (exp(-z) ~ 1 - 1e-6).
        modes = state.modes + (
            jnp.asarray(tb["decay_m1"], dtype) * state.modes
            + jnp.where(state.count > 0, increment, 0.0)
        )
        return SOEState(modes=modes, u_prev=u, u_prev2=state.u_prev, count=state.count + 1)

    @staticmethod
    def _previous2(state: SOEState, u: Array) -> Array:
        # On the first step, extrapolate linearly so that the quadratic is the line.
        return jnp.where(state.count > 1, state.u_prev2, 2.0 * state.u_prev - u)

    def step(self, coeffs: SOECoefficients, state: SOEState, u: Array) -> tuple[SOEState, Array]:
        return self.advance(state, u), self.output(coeffs, state, u)

    def cost(self) -> dict[str, int]:
        """Work and memory per step for one scalar channel."""
        m = self.n_modes
        return {
            "modes": m,
            "flops_per_step": 5 * m + 8,  # 3 mul-add update + 1 mul-add output per mode
            "state_floats": m + 3,
        }


# ----------------------------------------------------------------- Oustaloup / CRONE


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

    def __post_init__(self) -> None:
        _check_positive_finite("dt", self.dt)
        try:
            lo, hi = (float(v) for v in self.band)
        except (TypeError, ValueError):
            raise ValueError(f"band must be a pair (w_low, w_high), got {self.band!r}") from None
        _check_positive_finite("band[0]", lo)
        _check_positive_finite("band[1]", hi)
        if not lo < hi:
            raise ValueError(f"band must satisfy w_low < w_high, got {self.band!r}")
        object.__setattr__(self, "band", (lo, hi))
        if not isinstance(self.order, int | np.integer) or not 1 <= self.order <= 30:
            raise ValueError(f"order N must be an integer in [1, 30], got {self.order!r}")
        _check_positive_finite("refined_b", self.refined_b)
        _check_positive_finite("refined_d", self.refined_d)

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

        beta = jnp.clip(-alpha, _ORDER_FLOOR, 1.0 - _ORDER_FLOOR)
        gamma = jnp.clip(alpha, _ORDER_FLOOR, 1.0 - _ORDER_FLOOR)
        integral = refined(1.0 - beta, integral=True)
        derivative = refined(gamma, integral=False)
        identity = (
            integral[0],
            jnp.zeros_like(integral[1]),
            jnp.ones_like(integral[2]),
        )
        out = _select(alpha < 0, integral, derivative)
        return _select(alpha == 0, identity, out)

    def coefficients(self, alpha: Any, dtype: Any = None) -> ModalCoefficients:
        """Discretised filter for order ``alpha`` (any shape: one order per channel)."""
        return _per_order(self._coefficients, alpha, dtype)

    def _coefficients(self, alpha: Array, dtype: Any) -> ModalCoefficients:
        poles, residues, direct = self._transfer(alpha, dtype)
        z = -poles * self.dt
        j0, j1 = _expint_moments(z)
        return ModalCoefficients(
            decay=jnp.exp(-z),
            gain_u=self.dt * (j0 - j1),
            gain_u1=self.dt * j1,
            residue=residues,
            direct=jnp.asarray(direct, dtype),
        )

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> ModalState:
        dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
        shape = tuple(shape)
        return ModalState(
            modes=jnp.zeros(shape + (self.n_modes,), dtype),
            u_prev=jnp.zeros(shape, dtype),
            count=jnp.zeros((), jnp.int32),
        )

    def step(
        self, coeffs: ModalCoefficients, state: ModalState, u: Array
    ) -> tuple[ModalState, Array]:
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        increment = coeffs.gain_u * u[..., None] + coeffs.gain_u1 * state.u_prev[..., None]
        modes = coeffs.decay * state.modes + jnp.where(state.count > 0, increment, 0.0)
        y = coeffs.direct * u + jnp.sum(modes * coeffs.residue, axis=-1)
        return ModalState(modes=modes, u_prev=u, count=state.count + 1), y

    def cost(self) -> dict[str, int]:
        m = self.n_modes
        return {"modes": m, "flops_per_step": 5 * m + 2, "state_floats": m + 2}


# --------------------------------------------------------------- Grunwald-Letnikov


class GLCoefficients(NamedTuple):
    """``weights``: ``(memory,)`` ``dt**-alpha * (-1)**j binom(alpha, j)``."""

    weights: Array


class GLState(NamedTuple):
    """``history``: ``S + (memory,)`` the last samples, newest first."""

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

    def __post_init__(self) -> None:
        _check_positive_finite("dt", self.dt)
        if not isinstance(self.memory, int | np.integer) or self.memory < 1:
            raise ValueError(f"memory must be a positive integer, got {self.memory!r}")

    @property
    def n_modes(self) -> int:
        return int(self.memory)

    def coefficients(self, alpha: Any, dtype: Any = None) -> GLCoefficients:
        """Weights for order ``alpha`` (any shape: one order per channel)."""
        return _per_order(
            lambda a, dt_: GLCoefficients(_gl_weights(a, self.memory, self.dt, dt_)), alpha, dtype
        )

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> GLState:
        dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
        return GLState(jnp.zeros(tuple(shape) + (self.memory,), dtype))

    def step(self, coeffs: GLCoefficients, state: GLState, u: Array) -> tuple[GLState, Array]:
        u = jnp.asarray(u, state.history.dtype)
        history = jnp.concatenate([u[..., None], state.history[..., :-1]], axis=-1)
        return GLState(history), jnp.sum(history * coeffs.weights, axis=-1)

    def cost(self) -> dict[str, int]:
        m = int(self.memory)
        return {"modes": m, "flops_per_step": 2 * m, "state_floats": m}


# ------------------------------------------------------------- several orders, one signal


@dataclasses.dataclass(frozen=True)
class MultiOrder:
    """Several orders applied to the same signal.

    With :class:`SumOfExponentials` the memory is shared: the modes do not depend on
    the order, so one state serves every order (for instance ``D^(gamma-1) f`` and
    its time derivative ``D^gamma f``). Other methods keep one state per order.

    ``coefficients(alphas)`` takes a sequence of ``n_orders`` orders (each of any
    shape broadcastable to the signal); ``step`` returns a tuple of ``n_orders``
    outputs.
    """

    operator: Any
    n_orders: int

    @property
    def shared(self) -> bool:
        return isinstance(self.operator, SumOfExponentials)

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


# ------------------------------------------- an integral and its rate, one memory


class RatePairCoefficients(NamedTuple):
    """Weights of :class:`IntegralWithRate` over the :class:`SumOfExponentials` modes.

    For channel orders of shape ``S`` (``S`` broadcast against the signal):

    mode_weights: ``S + (modes,)`` the scales ``w_j(b) exp(-s_j dt)`` of the modes
        ``z_j = w_j exp(-s_j dt) y_j``: the only order-dependent part of the update.
    taps: ``(3, modes)`` gains of ``(u_k, u_{k-1}, u_{k-2})`` into the unscaled modes
        ``y_j`` (the same for every order): ``z_j`` grows by
        ``mode_weights_j * sum_i taps_ij u_(k-i)``.
    readout: ``(2, modes)`` ``(1, -s_j)``: the integral's history is ``sum_j z_j``, the
        rate's history ``-sum_j s_j z_j`` (the same for every order).
    local: ``S + (2, 3)`` weights of ``(u_k, u_{k-1}, u_{k-2})`` for (integral, rate).

    Keeping the order-dependent weights apart from the fixed taps makes the gradient
    with respect to the orders accumulate one ``S + (modes,)`` array per step instead of
    ``S + (3, modes)`` (docs/performance.md).
    """

    mode_weights: Array
    taps: Array
    readout: Array
    local: Array


class RatePairState(NamedTuple):
    """Memory of :class:`IntegralWithRate` for a signal of shape ``S``.

    The modes lag one sample behind (see :class:`IntegralWithRate`):

    modes: ``S + (modes,)`` scaled modes ``z_j`` at ``t_{k-2}`` when ``u_k`` comes next.
    u_prev, u_prev2, u_prev3: ``S`` the samples ``u_{k-1}``, ``u_{k-2}``, ``u_{k-3}``.
    count: ``()`` int32, number of samples consumed (``k``).
    """

    modes: Array
    u_prev: Array
    u_prev2: Array
    u_prev3: Array
    count: Array


@dataclasses.dataclass(frozen=True)
class IntegralWithRate:
    """``I^b u`` and its time derivative ``d/dt I^b u = D^(1-b) u`` from one memory.

    The pair that a sliding surface and its derivative need: ``D^(gamma - 1) f`` with
    ``D^gamma f``, or ``I^gamma g`` with ``D^(1 - gamma) g``. ``step`` returns the same
    values as :class:`MultiOrder` with orders ``(-b, 1 - b)``.

    With :class:`SumOfExponentials` both orders share the kernel weights ``w_j(b)``,
    so the modes are stored scaled, ``z_j = w_j exp(-s_j dt) y_j``: the integral's
    history is then ``sum_j z_j`` and the rate's ``-sum_j s_j z_j``, one contraction
    ``(2, modes)`` with fixed weights for every channel and order (one small matrix
    product per step), and each mode is read and written once per step. Other methods
    fall back to :class:`MultiOrder`.

    The step advances the modes over the interval before last, ``[t_{k-2}, t_{k-1}]``,
    with samples it already holds, then reads them out: the same arithmetic as
    advancing them at the end of the previous step, but the update of the modes (the
    bulk of the work) depends on stored values only, never on the sample ``u_k`` just
    computed. Compiled, it is then one pass over the modes that does not recompute the
    expressions producing ``u_k`` for every mode.

    ``coefficients(b)`` takes the integral orders ``b`` in ``(0, 1)`` (any shape, one
    per channel); ``step(coeffs, state, u) -> (state, (integral, rate))``.
    """

    operator: Any

    @property
    def fused(self) -> bool:
        return isinstance(self.operator, SumOfExponentials)

    @property
    def _fallback(self) -> MultiOrder:
        return MultiOrder(self.operator, 2)

    def coefficients(self, b: Any, dtype: Any = None) -> Any:
        """Weights for integral orders ``b`` (rate order ``1 - b``)."""
        dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
        b = jnp.asarray(b, dtype)
        if not self.fused:
            return self._fallback.coefficients((-b, 1.0 - b), dtype)
        op = self.operator
        tb = op._tables
        integral = op.coefficients(-b, dtype)
        rate = op.coefficients(1.0 - b, dtype)
        gains = jnp.stack(
            [jnp.asarray(tb[name], dtype) for name in ("gain_u", "gain_u1", "gain_u2")]
        )  # (3, modes)
        rates = jnp.asarray(tb["rates"], dtype)
        return RatePairCoefficients(
            mode_weights=integral.history,
            taps=gains,
            readout=jnp.stack([jnp.ones_like(rates), -rates]),
            local=jnp.stack([integral.local, rate.local], axis=-2),
        )

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> Any:
        if not self.fused:
            return self._fallback.init(shape, dtype)
        dtype = _float_dtype(jnp.result_type(float) if dtype is None else dtype)
        shape = tuple(shape)
        zeros = jnp.zeros(shape, dtype)
        return RatePairState(
            modes=jnp.zeros(shape + (self.operator.n_modes,), dtype),
            u_prev=zeros,
            u_prev2=zeros,
            u_prev3=zeros,
            count=jnp.zeros((), jnp.int32),
        )

    def step(self, coeffs: Any, state: Any, u: Array) -> tuple[Any, tuple[Array, Array]]:
        if not self.fused:
            return self._fallback.step(coeffs, state, u)
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        count = state.count
        # The advance that the previous step (sample u_{k-1}, count k - 1) owed: the
        # interval [t_{k-2}, t_{k-1}] against the quadratic through u_{k-3}, u_{k-2},
        # u_{k-1} (on the first interval, the line through u_{k-2}, u_{k-1}).
        u_before = jnp.where(count > 2, state.u_prev3, 2.0 * state.u_prev2 - state.u_prev)
        # Written as explicit multiply-adds (not contractions over the 3 samples), so
        # that they fuse with their neighbours instead of becoming small matrix products.
        taps = coeffs.taps
        increment = coeffs.mode_weights * sum(
            taps[i] * sample[..., None]
            for i, sample in enumerate((state.u_prev, state.u_prev2, u_before))
        )
        increment = jnp.where(count > 1, increment, 0.0)
        decay_m1 = jnp.asarray(self.operator._tables["decay_m1"], dtype)
        # z + (exp(-z) - 1) z keeps slow modes exact in float32 (exp(-z) ~ 1 - 1e-6).
        modes = state.modes + (decay_m1 * state.modes + increment)  # now at t_{k-1}
        history = modes @ coeffs.readout.T  # S + (2,)

        # On the first step, extrapolate linearly so that the quadratic is the line.
        u_prev2 = jnp.where(count > 1, state.u_prev2, 2.0 * state.u_prev - u)
        local = sum(
            coeffs.local[..., i] * sample[..., None]
            for i, sample in enumerate((u, state.u_prev, u_prev2))
        )
        outputs = jnp.where(count > 0, history + local, 0.0)
        new_state = RatePairState(
            modes=modes,
            u_prev=u,
            u_prev2=state.u_prev,
            u_prev3=state.u_prev2,
            count=count + 1,
        )
        return new_state, (outputs[..., 0], outputs[..., 1])


# ------------------------------------------------------------------- whole signals


_OPTION_NAMES = {
    "soe": {"log_step", "tail_modes", "z_max"},
    "oustaloup": {"band", "order", "refined", "refined_b", "refined_d"},
    "gl": {"memory"},
}


def _check_options(method: str, options: dict[str, Any]) -> None:
    unknown = set(options) - _OPTION_NAMES[method]
    if unknown:
        raise TypeError(
            f"unknown option(s) {sorted(unknown)} for method {method!r}; "
            f"valid: {sorted(_OPTION_NAMES[method])}"
        )
    for key, value in options.items():
        values = value if isinstance(value, tuple | list) else (value,)
        for v in values:
            if isinstance(v, bool):
                continue
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise TypeError(f"option {key}={value!r} must be numeric") from None
            if not math.isfinite(fv):
                raise ValueError(f"option {key}={value!r} must be finite")


def make_operator(method: str, dt: float, horizon: float = 80.0, **options: Any):
    """Build the operator ``method`` for step ``dt`` over ``horizon`` seconds.

    ``method`` is ``"soe"`` (default accurate method), ``"oustaloup"`` or ``"gl"``
    (full memory over ``horizon`` unless ``memory=`` is given).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    _check_positive_finite("dt", dt)
    _check_positive_finite("horizon", horizon)
    _check_options(method, options)
    if method == "soe":
        return SumOfExponentials(dt=dt, horizon=horizon, **options)
    if method == "oustaloup":
        if "band" in options:
            options["band"] = tuple(options["band"])
        return Oustaloup(dt=dt, **options)
    memory = options.pop("memory", None)
    if memory is None:
        memory = int(round(horizon / dt)) + 1
    return GrunwaldLetnikov(dt=dt, memory=memory)


def run(operator, alpha: Any, u: Array) -> Array:
    """Apply ``operator`` of order ``alpha`` to ``u`` sampled along axis 0 (a scan)."""
    u = jnp.asarray(u)
    coeffs = operator.coefficients(alpha, u.dtype)
    state = operator.init(u.shape[1:], u.dtype)

    def body(state, u_k):
        return operator.step(coeffs, state, u_k)

    _, y = lax.scan(body, state, u)
    return y


def _gl_convolve(alpha: Array, u: Array, dt: float, memory: int) -> Array:
    """Grunwald-Letnikov by zero-padded FFT convolution along axis 0."""
    n = u.shape[0]
    length = min(memory, n)
    w = _gl_weights(alpha, length, dt, u.dtype)
    size = 1 << int(math.ceil(math.log2(max(2, n + length - 1))))
    wf = jnp.fft.rfft(w, size)
    uf = jnp.fft.rfft(u, size, axis=0)
    wf = wf.reshape((-1,) + (1,) * (u.ndim - 1))
    return jnp.fft.irfft(uf * wf, size, axis=0)[:n].astype(u.dtype)


@functools.partial(jax.jit, static_argnums=0)
def _apply(operator, u: Array, alpha: Array) -> Array:
    if isinstance(operator, GrunwaldLetnikov):
        return _gl_convolve(alpha, u, operator.dt, operator.memory)
    return run(operator, alpha, u)


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
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    dt = _check_positive_finite("dt", dt)
    _check_options(method, {k: v for k, v in options.items() if k != "horizon" or method != "soe"})
    u = jnp.asarray(u)
    if u.ndim == 0 or u.shape[0] < 1:
        raise ValueError(f"u must have at least one sample along axis 0, got shape {u.shape}")
    u = u.astype(_float_dtype(u.dtype))
    if isinstance(alpha, int | float):
        alpha = float(alpha)
    options = dict(options)
    horizon = options.pop("horizon", max(u.shape[0] - 1, 1) * dt)
    operator = make_operator(method, dt, horizon, **options)
    lo, hi = operator.order_range
    _check_order(alpha, lo, hi, method)
    return _apply(operator, u, jnp.asarray(alpha, u.dtype))
