"""The sum-of-exponentials (kernel compression) operator, the default method."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from fojax.fractional._common import (
    ORDER_FLOOR,
    Array,
    align,
    check_positive_finite,
    expint_moments_np,
    float_dtype,
    lead,
    per_order,
    select,
)


class SOECoefficients(NamedTuple):
    """Order-dependent weights of :class:`SumOfExponentials`.

    For orders of shape ``O`` (one per channel; the leaves' own axes first):

    history: ``(modes,) + O`` weights applied to the mode states ``y_j(t_{k-1})``.
    local: ``(3,) + O`` weights of ``(u_k, u_{k-1}, u_{k-2})`` (last-step product
        integration, plus the history's boundary term for derivatives).
    first: ``O`` weight of ``u_0`` at ``t_0`` (1 for the identity, else 0).
    """

    history: Array
    local: Array
    first: Array


class SOEState(NamedTuple):
    """Memory of :class:`SumOfExponentials` for a signal of shape ``S``.

    modes: ``(modes,) + S`` the exponentially weighted integrals
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
    log_step: float = 0.8
    tail_modes: int = 5
    z_max: float = 20.0

    def __post_init__(self) -> None:
        dt = check_positive_finite("dt", self.dt)
        horizon = check_positive_finite("horizon", self.horizon)
        check_positive_finite("log_step", self.log_step)
        check_positive_finite("z_max", self.z_max)
        if not isinstance(self.tail_modes, int | np.integer) or not 2 <= self.tail_modes <= 16:
            raise ValueError(f"tail_modes must be an integer in [2, 16], got {self.tail_modes!r}")
        if self.log_step > 2.0:
            raise ValueError(f"log_step must be <= 2 (accuracy collapses), got {self.log_step}")
        # Always cover at least one step of history.
        object.__setattr__(self, "horizon", max(horizon, dt))

    method = "soe"
    order_range = (-1.0, 1.0)
    option_names = ("log_step", "tail_modes", "z_max")
    shares_modes = True
    """Every order reads the same modes (:meth:`output`, :meth:`advance`)."""

    @classmethod
    def build(cls, dt: float, horizon: float, **options: Any) -> SumOfExponentials:
        return cls(dt=dt, horizon=horizon, **options)

    def integral_with_rate(self) -> SOEIntegralWithRate:
        """The fused integral-and-rate memory over this operator's modes."""
        return SOEIntegralWithRate(self)

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
        j0, j1, j2 = expint_moments_np(z)
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
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
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
        return per_order(self._coefficients, alpha, dtype)

    def _coefficients(self, alpha: Array, dtype: Any) -> SOECoefficients:
        tb = self._tables
        dt = float(self.dt)
        decay = jnp.asarray(tb["decay"], dtype)
        rates = jnp.asarray(tb["rates"], dtype)

        # Integral of order b = -alpha (b = 0: identity).
        b = jnp.clip(-alpha, 0.0, 1.0 - ORDER_FLOOR)
        w_int = self.kernel_weights(b, 1.0 - b, dtype)
        lead_int = jnp.exp(b * math.log(dt) - gammaln(b + 1.0))  # dt^b / Gamma(b + 1)
        local_int = lead_int * jnp.stack(
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
        a = jnp.clip(alpha, ORDER_FLOOR, 1.0 - ORDER_FLOOR)
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
        return select(alpha <= 0, int_coeffs, der_coeffs)

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> SOEState:
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
        shape = tuple(shape)
        return SOEState(
            modes=jnp.zeros((self.n_modes,) + shape, dtype),
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
        n = u.ndim
        u_prev2 = self._previous2(state, u)
        weights = align(coeffs.local, 1, n)
        local = weights[0] * u + weights[1] * state.u_prev + weights[2] * u_prev2
        history = jnp.sum(state.modes * align(coeffs.history, 1, n), 0)
        return jnp.where(state.count > 0, history + local, align(coeffs.first, 0, n) * u)

    def advance(self, state: SOEState, u: Array) -> SOEState:
        """Consume ``u = u(t_k)``: advance the modes to ``t_k``."""
        tb = self._tables
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        u_prev2 = self._previous2(state, u)
        n = u.ndim

        def table(name):
            return lead(jnp.asarray(tb[name], dtype), n)

        increment = (
            table("gain_u") * u + table("gain_u1") * state.u_prev + table("gain_u2") * u_prev2
        )
        # y + (exp(-z) - 1) y keeps slow modes exact in float32 (exp(-z) ~ 1 - 1e-6).
        modes = state.modes + (
            table("decay_m1") * state.modes + jnp.where(state.count > 0, increment, 0.0)
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


# ----------------------------------------------- an integral and its rate, fused
#
# The fused memory keeps its own axes first and the signal's shape last: the modes of a
# signal of shape ``S`` are one ``(modes,) + S`` array. A closed loop over a batch of
# draws passes signals of shape ``(channels, draws)`` (batch last), so that every
# ``(mode, channel)`` row is one contiguous run over the draws: the update is one
# vectorised pass over the whole array and the read-out a sum over its leading axis.


def _unbroadcast(cotangent: Array, shape: tuple[int, ...]) -> Array:
    """``cotangent`` summed down to ``shape`` (the adjoint of broadcasting to its shape)."""
    extra = cotangent.ndim - len(shape)
    axes = tuple(range(extra)) + tuple(
        extra + i for i, n in enumerate(shape) if n == 1 and cotangent.shape[extra + i] != 1
    )
    return jnp.sum(cotangent, axis=axes).reshape(shape) if axes else cotangent


def _drive(taps: Array, samples: tuple) -> Array:
    """``sum_i taps_i u_i``: the unscaled growth of every mode, ``(modes,) + S``, as
    explicit multiply-adds (they fuse with their neighbours)."""
    ndim = samples[0].ndim
    return sum(lead(taps[i], ndim) * sample for i, sample in enumerate(samples))


def _contract(table: Array, values: Array) -> Array:
    """``table`` ``(k, modes)`` contracted with ``values`` ``(modes,) + S`` over the modes:
    ``(k,) + S``, one ``(k, modes) x (modes, prod(S))`` product. XLA's CPU backend hands
    it to its matrix-product library, which streams the modes once for all ``k`` rows;
    written as sums over the mode axis they became ``k`` library reductions several
    times slower, and written as explicit additions they were fused into (and
    recomputed by) every kernel reading them (docs/performance.md, designs tried and not kept)."""
    return jnp.tensordot(table, values, axes=1)


def _readout(rates: Array) -> Array:
    """``(2, modes)``: the integral's history ``sum_j z_j`` and the rate's
    ``-sum_j s_j z_j`` of the scaled modes."""
    return jnp.stack([jnp.ones_like(rates), -rates])


def _local(local: Array, samples: tuple) -> tuple:
    """The last step's product-integration terms ``sum_i local[j, i] x_i`` of the
    integral (``j = 0``) and the rate (``j = 1``)."""
    return tuple(sum(local[j, i] * x for i, x in enumerate(samples)) for j in range(2))


@jax.custom_vjp
def _memory_step(modes, weights, local, taps, rates, decay_m1, drive, samples, active, started):
    """One step of the fused memory: advance the scaled modes ``(modes,) + S`` over one
    interval from the ``drive`` samples (the growth only where ``active``), read the two
    histories out and add the last step's terms of the ``samples``; returns ``(modes,
    integral, rate)``, the outputs zero where not ``started``.

    ``modes + (decay_m1 modes + weights sum_i taps_i drive_i)`` (``z + (exp(-z) - 1) z``
    keeps slow modes exact in float32, where ``exp(-z) ~ 1 - 1e-6``). The map is linear
    in the modes, so its adjoint is the same recursion run backwards over the
    cotangents: the reverse pass keeps no mode state, only the samples, and its work is
    one pass over the modes plus one product for the samples' cotangents. ``taps``,
    ``rates`` and ``decay_m1`` are fixed tables of the operator (not functions of the
    order): they get no cotangent. ``weights`` and ``local`` may be shared by the
    signal's entries (axes of size 1): their cotangents are then summed over them.
    """
    ndim = modes.ndim - 1
    growth = jnp.where(active, weights * _drive(taps, drive), 0.0)
    modes = modes + (lead(decay_m1, ndim) * modes + growth)
    history = _contract(_readout(rates), modes)
    terms = _local(local, samples)
    integral, rate = (jnp.where(started, history[j] + terms[j], 0.0) for j in range(2))
    return modes, integral, rate


def _memory_step_fwd(modes, weights, local, taps, rates, decay_m1, drive, samples, active, started):
    out = _memory_step(
        modes, weights, local, taps, rates, decay_m1, drive, samples, active, started
    )
    return out, (weights, local, taps, rates, decay_m1, drive, samples, active, started)


def _memory_step_bwd(residuals, cotangents):
    weights, local, taps, rates, decay_m1, drive, samples, active, started = residuals
    ct_modes_out, ct_integral, ct_rate = cotangents
    ndim = ct_modes_out.ndim - 1
    ct_out = (jnp.where(started, ct_integral, 0.0), jnp.where(started, ct_rate, 0.0))
    ct_local = _unbroadcast(
        jnp.stack([jnp.stack([ct * x for x in samples]) for ct in ct_out]), local.shape
    )
    ct_samples = tuple(
        local[0, i] * ct_out[0] + local[1, i] * ct_out[1] for i in range(len(samples))
    )
    total = ct_modes_out + (ct_out[0] - lead(rates, ndim) * ct_out[1])
    ct_growth = jnp.where(active, total, 0.0)
    ct_weights = _unbroadcast(ct_growth * _drive(taps, drive), weights.shape)
    ct_drive = _contract(taps, ct_growth * weights)
    ct_modes = total + lead(decay_m1, ndim) * total
    zeros = jax.tree.map(jnp.zeros_like, (taps, rates, decay_m1))
    return (
        ct_modes,
        ct_weights,
        ct_local,
        *zeros,
        tuple(ct_drive[i] for i in range(len(drive))),
        ct_samples,
        None,
        None,
    )


_memory_step.defvjp(_memory_step_fwd, _memory_step_bwd)


class RatePairCoefficients(NamedTuple):
    """Weights of :class:`SOEIntegralWithRate` over the :class:`SumOfExponentials` modes.

    For channel orders of shape ``O`` (broadcast against the signal's shape ``S`` by
    numpy's rule, aligned on the last axes):

    mode_weights: ``(modes,) + O`` the scales ``w_j(b) exp(-s_j dt)`` of the modes
        ``z_j = w_j exp(-s_j dt) y_j``: the only order-dependent part of the update.
    taps: ``(3, modes)`` gains of ``(u_k, u_{k-1}, u_{k-2})`` into the unscaled modes
        ``y_j`` (the same for every order): ``z_j`` grows by
        ``mode_weights_j * sum_i taps_ij u_(k-i)``.
    rates: ``(modes,)`` the decay rates ``s_j``: the integral's history is
        ``sum_j z_j``, the rate's ``-sum_j s_j z_j`` (the same for every order).
    local: ``(2, 3) + O`` weights of ``(u_k, u_{k-1}, u_{k-2})`` for (integral, rate).

    Keeping the order-dependent weights apart from the fixed taps makes the gradient
    with respect to the orders accumulate one ``(modes,) + O`` array per step instead
    of ``(3, modes) + O`` (docs/performance.md).
    """

    mode_weights: Array
    taps: Array
    rates: Array
    local: Array


class RatePairState(NamedTuple):
    """Memory of :class:`SOEIntegralWithRate` for a signal of shape ``S``.

    The modes lag one sample behind (see :class:`SOEIntegralWithRate`):

    modes: ``(modes,) + S`` scaled modes ``z_j`` at ``t_{k-2}`` when ``u_k`` comes next.
    u_prev, u_prev2, u_prev3: ``S`` the samples ``u_{k-1}``, ``u_{k-2}``, ``u_{k-3}``.
    count: ``()`` int32, number of samples consumed (``k``); any shape broadcasting
        against ``S`` (a batch of memories started together may carry one per draw).
    """

    modes: Array
    u_prev: Array
    u_prev2: Array
    u_prev3: Array
    count: Array


@dataclasses.dataclass(frozen=True)
class SOEIntegralWithRate:
    """:class:`fojax.fractional.IntegralWithRate` fused over the modes of a
    :class:`SumOfExponentials` (what ``integral_with_rate(operator)`` returns for it).

    Both orders share the kernel weights ``w_j(b)``, so the modes are stored scaled,
    ``z_j = w_j exp(-s_j dt) y_j``: the integral's history is then ``sum_j z_j`` and the
    rate's ``-sum_j s_j z_j``, two sums over the modes with fixed weights for every
    channel and order, and each mode is read and written once per step. The modes are
    one ``(modes,) + S`` array, the mode axis first (see the note above).

    The step advances the modes over the interval before last, ``[t_{k-2}, t_{k-1}]``,
    with samples it already holds, then reads them out: the same arithmetic as
    advancing them at the end of the previous step, but the update of the modes (the
    bulk of the work) depends on stored values only, never on the sample ``u_k`` just
    computed. Compiled, it is then one pass over the modes that does not recompute the
    expressions producing ``u_k`` for every mode.

    ``coefficients(b)`` takes the integral orders ``b`` in ``(0, 1)`` (any shape ``O``,
    one per channel, broadcasting against the signal: ``(12, 1)`` for a ``(12, draws)``
    signal); ``step(coeffs, state, u) -> (state, (integral, rate))``.
    """

    operator: SumOfExponentials

    @property
    def n_modes(self) -> int:
        return self.operator.n_modes

    def coefficients(self, b: Any, dtype: Any = None) -> Any:
        """Weights for integral orders ``b`` (rate order ``1 - b``)."""
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
        b = jnp.asarray(b, dtype)
        op = self.operator
        tb = op._tables
        integral = op.coefficients(-b, dtype)
        rate = op.coefficients(1.0 - b, dtype)
        taps = jnp.stack(
            [jnp.asarray(tb[name], dtype) for name in ("gain_u", "gain_u1", "gain_u2")]
        )  # (3, modes)
        return RatePairCoefficients(
            mode_weights=integral.history,
            taps=taps,
            rates=jnp.asarray(tb["rates"], dtype),
            local=jnp.stack([integral.local, rate.local]),
        )

    def init(self, shape: tuple[int, ...] = (), dtype: Any = None) -> Any:
        dtype = float_dtype(jnp.result_type(float) if dtype is None else dtype)
        shape = tuple(shape)
        zeros = jnp.zeros(shape, dtype)
        return RatePairState(
            modes=jnp.zeros((self.n_modes,) + shape, dtype),
            u_prev=zeros,
            u_prev2=zeros,
            u_prev3=zeros,
            count=jnp.zeros((), jnp.int32),
        )

    def step(self, coeffs: Any, state: Any, u: Array) -> tuple[Any, tuple[Array, Array]]:
        dtype = state.modes.dtype
        u = jnp.asarray(u, dtype)
        ndim = state.modes.ndim - 1
        count = state.count
        # The advance that the previous step (sample u_{k-1}, count k - 1) owed: the
        # interval [t_{k-2}, t_{k-1}] against the quadratic through u_{k-3}, u_{k-2},
        # u_{k-1} (on the first interval, the line through u_{k-2}, u_{k-1}); the modes
        # are then at t_{k-1}.
        u_before = jnp.where(count > 2, state.u_prev3, 2.0 * state.u_prev2 - state.u_prev)
        # On the first step, extrapolate linearly so that the quadratic is the line.
        u_prev2 = jnp.where(count > 1, state.u_prev2, 2.0 * state.u_prev - u)
        modes, integral, rate = _memory_step(
            state.modes,
            align(coeffs.mode_weights, 1, ndim),
            align(coeffs.local, 2, ndim),
            coeffs.taps,
            coeffs.rates,
            jnp.asarray(self.operator._tables["decay_m1"], dtype),
            (state.u_prev, state.u_prev2, u_before),
            (u, state.u_prev, u_prev2),
            count > 1,
            count > 0,
        )
        new_state = RatePairState(
            modes=modes,
            u_prev=u,
            u_prev2=state.u_prev,
            u_prev3=state.u_prev2,
            count=count + 1,
        )
        return new_state, (integral, rate)
