"""fojax.fractional against exact Riemann-Liouville results.

Long-horizon accuracy runs once per method (80 s at 1 ms, all orders batched with
vmap); gradients and structural checks use short horizons.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal
from jax import lax
from scipy.special import digamma, gamma

from fojax import fractional
from fojax.cli import references as ref
from fojax.fractional import GrunwaldLetnikov, Oustaloup, SumOfExponentials, differintegrate

DT = 1e-3
STEPS = 80_001  # 80 s
T = np.arange(STEPS) * DT
ORDERS = (0.01, 0.1, 0.5, 0.9, 0.99)
ALPHAS = tuple(-o for o in ORDERS) + ORDERS
OMEGA_SIN, OMEGA_COS = 1.7, 0.4

# Signals, one per column: sin, cos, step, ramp, t^2/80 (scaled to O(1)).
SIGNALS = np.stack(
    [np.sin(OMEGA_SIN * T), np.cos(OMEGA_COS * T), np.ones_like(T), T, T**2 / 80.0], axis=1
)


def exact(alpha: float) -> np.ndarray:
    return np.stack(
        [
            ref.sine(T, OMEGA_SIN, alpha),
            ref.cosine(T, OMEGA_COS, alpha),
            ref.power(T, 0.0, alpha),
            ref.power(T, 1.0, alpha),
            ref.power(T, 2.0, alpha) / 80.0,
        ],
        axis=1,
    )


def rel_error(y: np.ndarray, y_exact: np.ndarray, skip: int = 1) -> np.ndarray:
    """Worst error over t >= skip*dt, relative to the largest |exact| there (per column)."""
    err = np.max(np.abs(y[skip:] - y_exact[skip:]), axis=0)
    return err / np.max(np.abs(y_exact[skip:]), axis=0)


@jax.jit
def _soe_all_orders(u, alphas):
    return jax.vmap(lambda a: differintegrate(u, a, DT))(alphas)


@jax.jit
def _gl_all_orders(u, alphas):
    return jax.vmap(lambda a: differintegrate(u, a, DT, method="gl"))(alphas)


@pytest.fixture(scope="module")
def soe_long():
    return np.asarray(_soe_all_orders(jnp.asarray(SIGNALS), jnp.asarray(ALPHAS)))


@pytest.fixture(scope="module")
def gl_long():
    return np.asarray(_gl_all_orders(jnp.asarray(SIGNALS), jnp.asarray(ALPHAS)))


# -------------------------------------------------------------- exact references


def test_reference_mittag_leffler_agrees_with_incomplete_gamma():
    # The ML-based references are checked against an independent mpmath route.
    for alpha in (-0.3, -0.9):
        for t in (0.5, 13.0, 79.9):
            z = ref.exp_imag_mpmath(t, OMEGA_SIN, alpha)
            tt = np.array([t])
            assert ref.sine(tt, OMEGA_SIN, alpha)[0] == pytest.approx(z.imag, abs=1e-9)
            assert ref.cosine(tt, OMEGA_SIN, alpha)[0] == pytest.approx(z.real, abs=1e-9)


# -------------------------------------------------------------- sum of exponentials


@pytest.mark.parametrize("index", range(len(ALPHAS)))
def test_soe_matches_exact_over_80s(soe_long, index):
    alpha = ALPHAS[index]
    errors = rel_error(soe_long[index], exact(alpha))
    # The requirement: 1e-4 (the default's worst case is 5.6e-5, docs/fractional.md).
    assert np.all(errors < 1e-4), (alpha, errors)


@pytest.mark.parametrize("order", (0.1, 0.5, 0.9))
def test_soe_relaxation_identity(order):
    # I^a E_a(-lam t^a) = (1 - E_a(-lam t^a)) / lam, and
    # D^a E_a(-lam t^a) = -lam E_a(-lam t^a) + t^-a / Gamma(1 - a)   (Riemann-Liouville).
    lam = 1.3
    relax = ref.mittag_leffler(-lam * T**order, order)
    y = np.asarray(_soe_all_orders(jnp.asarray(relax), jnp.asarray([-order, order])))
    integral_exact = (1.0 - relax) / lam
    derivative_exact = np.full_like(T, np.nan)
    derivative_exact[1:] = -lam * relax[1:] + T[1:] ** (-order) / gamma(1.0 - order)
    # The input behaves like 1 - c t^a at t = 0, which no polynomial interpolant
    # resolves on the first steps; the error there decays with t (docs/fractional.md
    # lists the whole-range figures). Stated tolerance: 1e-4 from t = 1 s on.
    one_second = int(round(1.0 / DT))
    assert rel_error(y[0], integral_exact, skip=one_second) < 1e-4
    assert rel_error(y[1], derivative_exact, skip=one_second) < 1e-4


def test_soe_semigroup():
    # I^a I^b u = I^(a+b) u.
    u = jnp.asarray(SIGNALS[:, :2])
    alphas = jnp.asarray([-0.3, -0.45, -0.75])
    once = _soe_all_orders(u, alphas)
    twice = _soe_all_orders(once[0], alphas[1:2])[0]
    # I^0.3 cos behaves like t^0.3 at 0 (see test_soe_relaxation_identity): from 1 s on.
    errors = rel_error(np.asarray(twice), np.asarray(once[2]), skip=int(round(1.0 / DT)))
    assert errors.max() < 1e-4


def test_soe_mode_count_and_kernel():
    op = SumOfExponentials(dt=DT, horizon=80.0)
    assert op.n_modes == 23  # 18 trapezoidal + 5 tail modes at 1 ms over 80 s
    t = np.geomspace(DT, 80.0, 500)
    for b in (0.01, 0.3, 0.7, 0.99):
        w = np.asarray(op.kernel_weights(b, 1.0 - b, jnp.float64))
        rates = op._tables["rates"]
        approx = np.exp(-np.outer(t, rates)) @ w
        kernel = t ** (b - 1.0) / gamma(b)
        assert np.max(np.abs(approx / kernel - 1.0)) < 1e-4  # 6.1e-5 worst over [0.01, 0.99]


def test_order_gradient_is_exact():
    # d/d alpha of D^alpha t = t^(1-alpha)/Gamma(2-alpha) is y (psi(2-alpha) - log t).
    steps = 20_001
    t = np.arange(steps) * DT
    u = jnp.asarray(t)
    for alpha in (-0.8, -0.3, 0.4, 0.9):
        dy = jax.jacfwd(lambda a: differintegrate(u, a, DT))(jnp.asarray(alpha))
        y_exact = ref.power(t, 1.0, alpha)
        dy_exact = y_exact * (digamma(2.0 - alpha) - np.log(np.where(t > 0, t, 1.0)))
        assert rel_error(np.asarray(dy), dy_exact) < 1e-5, alpha


def test_soe_float32_accuracy():
    u = jnp.asarray(SIGNALS[:, 0], jnp.float32)
    y = _soe_all_orders(u, jnp.asarray(ALPHAS, jnp.float32))
    assert y.dtype == jnp.float32
    for i, alpha in enumerate(ALPHAS):
        error = rel_error(np.asarray(y[i], np.float64), exact(alpha)[:, 0])
        # float32 floor: derivatives of order near 1 lose ~3 digits to cancellation
        # (like a difference quotient at dt = 1e-3).
        assert error < (3e-4 if alpha >= 0.5 else 5e-5), (alpha, error)


# -------------------------------------------------------------- Grunwald-Letnikov


@pytest.mark.parametrize("index", range(len(ALPHAS)))
def test_gl_full_memory_matches_exact(gl_long, index):
    alpha = ALPHAS[index]
    # First-order method: stated tolerance 5e-2 over 80 s at 1 ms (steps and
    # derivatives of the constant excluded: GL's error there is O(1) at t = dt).
    errors = rel_error(gl_long[index][:, [0, 3, 4]], exact(alpha)[:, [0, 3, 4]])
    assert np.all(errors < 5e-2), (alpha, errors)


def test_gl_is_first_order():
    t_end = 2.0
    errors = []
    for dt in (1e-2, 5e-3):
        t = np.arange(int(round(t_end / dt)) + 1) * dt
        y = differintegrate(jnp.asarray(np.sin(t)), 0.5, dt, method="gl")
        errors.append(abs(float(y[-1]) - ref.sine(t, 1.0, 0.5)[-1]))  # at t = 2 s
    assert 0.4 < errors[1] / errors[0] < 0.6


def test_gl_step_short_memory_matches_direct_sum():
    rng = np.random.default_rng(0)
    u = rng.normal(size=60)
    alpha, dt, memory = -0.4, 0.05, 17
    op = GrunwaldLetnikov(dt=dt, memory=memory)
    y_step = np.asarray(fractional.run(op, alpha, jnp.asarray(u)))
    y_fft = np.asarray(differintegrate(jnp.asarray(u), alpha, dt, method="gl", memory=memory))
    w = [1.0]
    for j in range(1, memory):
        w.append(w[-1] * (1.0 - (alpha + 1.0) / j))
    direct = [
        dt**-alpha * sum(w[j] * u[k - j] for j in range(min(k + 1, memory))) for k in range(60)
    ]
    np.testing.assert_allclose(y_step, direct, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(y_fft, direct, rtol=1e-10, atol=1e-10)


# -------------------------------------------------------------- Oustaloup


def _oustaloup_cascade(gamma_, band=(0.01, 100.0), n=5):
    """Independent state space: a cascade of sections (s + z)/(s + p), times w_h^gamma."""
    lo, hi = band
    k = np.arange(-n, n + 1)
    zeros = lo * (hi / lo) ** ((k + n + 0.5 * (1 - gamma_)) / (2 * n + 1))
    poles = lo * (hi / lo) ** ((k + n + 0.5 * (1 + gamma_)) / (2 * n + 1))
    m = len(poles)
    a = np.zeros((m, m))
    b = np.zeros((m, 1))
    c = np.zeros((1, m))
    # section i: x_i' = -p_i x_i + v_i ; v_{i+1} = v_i + (z_i - p_i) x_i ; v_0 = u
    for i in range(m):
        a[i, i] = -poles[i]
        b[i, 0] = 1.0
        for j in range(i):
            a[i, j] = zeros[j] - poles[j]
    c[0, :] = zeros - poles
    gain = hi**gamma_
    return scipy.signal.StateSpace(a, b * 1.0, c * gain, np.array([[gain]])), zeros, poles


@pytest.mark.parametrize("gamma_", (0.5, -0.5, 0.9))
def test_oustaloup_discretisation_is_exact(gamma_):
    # For an input linear between samples the per-mode exponential update is exact:
    # compare with scipy's first-order-hold simulation of an independent realisation.
    dt = 1e-3
    t = np.arange(20_001) * dt
    u = np.sin(1.7 * t) + 0.3 * t
    system, _, _ = _oustaloup_cascade(gamma_)
    _, y_ref, _ = scipy.signal.lsim(system, u, t, interp=True)
    y = np.asarray(differintegrate(jnp.asarray(u), gamma_, dt, method="oustaloup"))
    assert np.max(np.abs(y - y_ref)) / np.max(np.abs(y_ref)) < 1e-7


@pytest.mark.parametrize("refined", (False, True))
@pytest.mark.parametrize("gamma_", (0.5, -0.5))
def test_oustaloup_frequency_response_in_band(refined, gamma_):
    op = Oustaloup(dt=1e-3, refined=refined)
    poles, residues, direct = (
        np.asarray(v) for v in op._transfer(jnp.asarray(gamma_), jnp.float64)
    )
    for w in (0.5, 1.0, 2.0):
        response = direct + np.sum(residues / (1j * w - poles))
        target = (1j * w) ** gamma_
        if not refined:
            _, zeros, plain_poles = _oustaloup_cascade(gamma_)
            product = 100.0**gamma_ * np.prod((1j * w + zeros) / (1j * w + plain_poles))
            assert abs(response - product) < 1e-9 * abs(product)
            assert abs(abs(response) / abs(target) - 1.0) < 0.01
        else:
            # Refined filter: mid-band gain (d/b)^|gamma| below the target (Xue et al.).
            assert abs(abs(response) / abs(target) - 1.0) < 0.1
        assert abs(np.angle(response) - np.angle(target)) < math.radians(2.0)


# -------------------------------------------------------------- gradients, vmap, dtypes

SHORT_DT = 0.01
SHORT_T = np.arange(101) * SHORT_DT
SHORT_U = np.sin(2.0 * SHORT_T) + 0.5 * SHORT_T
WEIGHTS = np.cos(SHORT_T)

CASES = [
    ("soe", {}),
    ("oustaloup", {}),
    ("oustaloup", {"refined": True}),
    ("gl", {}),
    ("gl", {"memory": 30}),
]


def _loss(u, alpha, method, options):
    return jnp.sum(jnp.asarray(WEIGHTS) * differintegrate(u, alpha, SHORT_DT, method, **options))


@pytest.mark.parametrize("method,options", CASES)
def test_gradients_match_finite_differences(method, options):
    u = jnp.asarray(SHORT_U)
    grad = jax.grad(_loss, argnums=(0, 1))
    direction = np.random.default_rng(1).normal(size=u.shape)
    eps = 1e-6
    for alpha in (-0.7, -0.2, 0.3, 0.8):
        g_u, g_alpha = grad(u, alpha, method, options)
        fd_alpha = (
            _loss(u, alpha + eps, method, options) - _loss(u, alpha - eps, method, options)
        ) / (2 * eps)
        assert float(g_alpha) == pytest.approx(float(fd_alpha), rel=1e-6, abs=1e-8)
        fd_u = (
            _loss(u + eps * direction, alpha, method, options)
            - _loss(u - eps * direction, alpha, method, options)
        ) / (2 * eps)
        assert float(jnp.dot(g_u, direction)) == pytest.approx(float(fd_u), rel=1e-6)


@pytest.mark.parametrize("method", ("soe", "oustaloup", "gl"))
def test_vmap_equals_loop(method):
    rng = np.random.default_rng(2)
    batch = jnp.asarray(rng.normal(size=(3, 101)))
    alphas = jnp.asarray([-0.6, 0.1, 0.7])
    batched = jax.vmap(lambda u, a: differintegrate(u, a, SHORT_DT, method))(batch, alphas)
    for i in range(3):
        single = differintegrate(batch[i], float(alphas[i]), SHORT_DT, method)
        np.testing.assert_allclose(batched[i], single, rtol=1e-12, atol=1e-12)
    # Trailing axes are independent channels.
    columns = differintegrate(batch.T, 0.4, SHORT_DT, method)
    for i in range(3):
        np.testing.assert_allclose(
            columns[:, i], differintegrate(batch[i], 0.4, SHORT_DT, method), rtol=1e-12, atol=1e-12
        )


@pytest.mark.parametrize("method", ("soe", "oustaloup", "gl"))
def test_identity_at_order_zero(method):
    u = jnp.asarray(SHORT_U)
    np.testing.assert_allclose(differintegrate(u, 0.0, SHORT_DT, method), u, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("method", ("soe", "oustaloup", "gl"))
def test_float32_and_float64(method):
    for dtype in (jnp.float32, jnp.float64):
        y = differintegrate(jnp.asarray(SHORT_U, dtype), -0.5, SHORT_DT, method)
        assert y.dtype == dtype
        assert np.all(np.isfinite(np.asarray(y)))
    y32 = differintegrate(jnp.asarray(SHORT_U, jnp.float32), -0.5, SHORT_DT, method)
    y64 = differintegrate(jnp.asarray(SHORT_U, jnp.float64), -0.5, SHORT_DT, method)
    np.testing.assert_allclose(np.asarray(y32), np.asarray(y64), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(
    "operator",
    [
        SumOfExponentials(dt=SHORT_DT, horizon=1.0),
        Oustaloup(dt=SHORT_DT),
        GrunwaldLetnikov(dt=SHORT_DT, memory=101),
    ],
)
def test_init_step_in_scan_matches_differintegrate(operator):
    u = jnp.asarray(np.stack([SHORT_U, np.cos(SHORT_T)], axis=1))

    @jax.jit
    def closed_loop(alpha):
        coeffs = operator.coefficients(alpha, u.dtype)

        def body(state, u_k):
            return operator.step(coeffs, state, u_k)

        return lax.scan(body, operator.init((2,), u.dtype), u)[1]

    options = {"soe": {"horizon": 1.0}, "oustaloup": {}, "gl": {}}[operator.method]
    for alpha in (-0.35, 0.65):
        np.testing.assert_allclose(
            closed_loop(alpha),
            differintegrate(u, alpha, SHORT_DT, operator.method, **options),
            rtol=1e-10,
            atol=1e-10,
        )


def test_no_recompilation_for_new_orders():
    u = jnp.asarray(SHORT_U)
    differintegrate(u, 0.3, SHORT_DT)
    size = fractional._api._apply._cache_size()
    differintegrate(u, 0.45, SHORT_DT)
    differintegrate(u, -0.2, SHORT_DT)
    assert fractional._api._apply._cache_size() == size


# -------------------------------------------------------------- input validation


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"alpha": 1.5}, "supports orders"),
        ({"alpha": -1.0, "method": "oustaloup"}, "supports orders"),
        ({"alpha": float("nan")}, "finite"),
        ({"dt": 0.0}, "dt must be > 0"),
        ({"dt": -1e-3}, "dt must be > 0"),
        ({"dt": float("inf")}, "dt must be finite"),
        ({"method": "crone"}, "unknown method"),
        ({"log_step": float("nan")}, "finite"),
        ({"method": "oustaloup", "band": (100.0, 0.01)}, "w_low < w_high"),
        ({"method": "oustaloup", "order": 0}, "order N"),
        ({"method": "gl", "memory": 0}, "memory"),
    ],
)
def test_bad_input_is_rejected_before_compiling(kwargs, match):
    args = {"u": jnp.asarray(SHORT_U), "alpha": 0.5, "dt": SHORT_DT, "method": "soe"}
    args.update(kwargs)
    size = fractional._api._apply._cache_size()
    with pytest.raises(ValueError, match=match):
        differintegrate(**args)
    assert fractional._api._apply._cache_size() == size


def test_unknown_option_is_rejected():
    with pytest.raises(TypeError, match="unknown option"):
        differintegrate(jnp.asarray(SHORT_U), 0.5, SHORT_DT, method="soe", band=(1, 2))


@pytest.mark.parametrize("method", ("soe", "oustaloup"))
def test_multi_order_and_per_channel_orders(method):
    # One memory, several orders, a different order per channel: equal to separate runs.
    op = fractional.make_operator(method, SHORT_DT, 1.0)
    multi = fractional.MultiOrder(op, 2)
    u = jnp.asarray(np.stack([SHORT_U, np.cos(SHORT_T)], axis=1))
    orders = (jnp.asarray([-0.3, -0.6]), jnp.asarray([0.7, 0.4]))
    coeffs = multi.coefficients(orders, u.dtype)
    _, (first, second) = lax.scan(
        lambda s, u_k: multi.step(coeffs, s, u_k), multi.init((2,), u.dtype), u
    )
    for out, alphas in ((first, orders[0]), (second, orders[1])):
        for channel in range(2):
            expected = differintegrate(
                u[:, channel],
                float(alphas[channel]),
                SHORT_DT,
                method,
                **({"horizon": 1.0} if method == "soe" else {}),
            )
            np.testing.assert_allclose(out[:, channel], expected, rtol=1e-10, atol=1e-10)
    assert multi.shared == (method == "soe")


def test_integral_with_rate_reverse_pass_equals_autodiff():
    """The hand-written reverse pass of the fused memory (the linear recursion run
    backwards over the cotangents) equals autodiff of the same step, float64, for the
    cotangents of the orders, the signal and the initial memory."""
    from fojax.fractional import _soe

    op = SumOfExponentials(dt=1e-3, horizon=1.0)
    pair = fractional.integral_with_rate(op)
    rng = np.random.default_rng(3)
    u = jnp.asarray(rng.normal(size=(60, 4)))
    probe = jnp.asarray(rng.normal(size=(60, 4, 2)))

    def loss(b, u, modes0, advance):
        coeffs = pair.coefficients(b, jnp.float64)
        state = pair.init((4,), jnp.float64)._replace(modes=modes0)
        original = _soe._memory_step
        _soe._memory_step = advance
        try:
            _, (integral, rate) = lax.scan(lambda s, x: pair.step(coeffs, s, x), state, u)
        finally:
            _soe._memory_step = original
        return jnp.sum(jnp.stack([integral, rate], -1) * probe)

    b = jnp.asarray([0.01, 0.3, 0.7, 0.99])
    modes0 = jnp.asarray(rng.normal(size=(pair.n_modes, 4)))
    custom = jax.grad(loss, argnums=(0, 1, 2))(b, u, modes0, _soe._memory_step)
    plain = jax.grad(loss, argnums=(0, 1, 2))(b, u, modes0, _soe._memory_step.fun)
    for got, want in zip(custom, plain, strict=True):
        assert float(jnp.max(jnp.abs(want))) > 0
        np.testing.assert_allclose(
            got, want, rtol=1e-11, atol=1e-13 * float(jnp.max(jnp.abs(want)))
        )
