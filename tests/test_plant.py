"""Tests of fojax.plant: eq. (10)-(11) against an independent float64 evaluation."""

import jax

jax.config.update("jax_enable_x64", True)

import math  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from fojax import plant  # noqa: E402

# Section V constants and J_r (notes items 2-3), written out again on purpose.
M, I11, I22, I33 = 0.74, 0.4e-2, 0.4e-2, 0.84e-2
KP = (1e-2, 1e-2, 1e-2)
KPHI = (1.2e-2, 1.2e-2, 1.2e-2)
RHO_B, RHO_C, ARM, J_R, G = 3e-3, 3.24e-2, 0.21, 2.8385e-5, 9.81


def reference_derivatives(state, inputs, dist, kp=KP, kphi=KPHI, m=M, inertia=(I11, I22, I33)):
    """Eq. (11) with the notes' corrections, in plain float64 Python."""
    x, y, z, phi, theta, psi, vx, vy, vz, p, q, r = (float(v) for v in state)
    u_f, tx, ty, tz = (float(v) for v in inputs)
    i11, i22, i33 = inertia
    # Closed-form inverse of the mixer (10).
    w2 = [
        u_f / (4 * RHO_B) - ty / (2 * RHO_B * ARM) - tz / (4 * RHO_C),
        u_f / (4 * RHO_B) - tx / (2 * RHO_B * ARM) + tz / (4 * RHO_C),
        u_f / (4 * RHO_B) + ty / (2 * RHO_B * ARM) - tz / (4 * RHO_C),
        u_f / (4 * RHO_B) + tx / (2 * RHO_B * ARM) + tz / (4 * RHO_C),
    ]
    w = [math.sqrt(max(v, 0.0)) for v in w2]
    omega_r = w[0] - w[1] + w[2] - w[3]
    dphi = (
        (i22 - i33) / i11 * q * r
        - J_R / i11 * q * omega_r
        - kphi[0] / i11 * p * abs(p)
        + tx / i11
        + dist[3]
    )
    dtheta = (
        (i33 - i11) / i22 * p * r
        + J_R / i22 * p * omega_r
        - kphi[1] / i22 * q * abs(q)
        + ty / i22
        + dist[4]
    )
    dpsi = (i11 - i22) / i33 * p * q - kphi[2] / i33 * r * abs(r) + tz / i33 + dist[5]
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    ax = (cp * st * cf + sp * sf) * u_f / m - kp[0] / m * vx + dist[0]
    ay = (sp * st * cf - cp * sf) * u_f / m - kp[1] / m * vy + dist[1]
    az = -G + ct * cf * u_f / m - kp[2] / m * vz + dist[2]
    return np.array([vx, vy, vz, p, q, r, ax, ay, az, dphi, dtheta, dpsi])


def random_case(rng):
    state = np.concatenate(
        [
            rng.normal(0, 1, 3),
            rng.uniform(-0.5, 0.5, 3),
            rng.normal(0, 1, 3),
            rng.normal(0, 2, 3),
        ]
    )
    inputs = np.array([M * G, 0.0, 0.0, 0.0]) * rng.uniform(0.5, 1.5, 4)
    inputs[1:] = rng.normal(0, 0.05, 3)
    dist = rng.normal(0, 0.5, 6)
    return state, inputs, dist


def test_nominal_params_values_and_dtype():
    p = plant.nominal_params()
    assert p.mass.dtype == jnp.float64
    assert plant.nominal_params(jnp.float32).inertia.dtype == jnp.float32
    np.testing.assert_allclose(p.inertia, [I11, I22, I33])
    np.testing.assert_allclose(
        [p.mass, p.thrust_factor, p.drag_factor, p.arm_length, p.rotor_inertia, p.gravity],
        [M, RHO_B, RHO_C, ARM, J_R, G],
    )


def test_hover_is_equilibrium():
    p = plant.nominal_params()
    state = plant.hover_state(position=(1.0, -2.0, 3.0), yaw=0.5)
    u = plant.hover_inputs(p)
    np.testing.assert_allclose(u, [M * G, 0, 0, 0], rtol=1e-15)
    deriv = plant.derivatives(p, state, u, jnp.zeros(6))
    np.testing.assert_allclose(deriv, 0.0, atol=1e-14)
    stepped = plant.rk4_step(p, state, u, jnp.zeros(6), 0.01)
    np.testing.assert_allclose(stepped, state, atol=1e-14)


def test_derivatives_match_independent_eq_11():
    rng = np.random.default_rng(0)
    p = plant.nominal_params()
    f = jax.jit(plant.derivatives)
    for _ in range(20):
        state, inputs, dist = random_case(rng)
        got = f(p, jnp.asarray(state), jnp.asarray(inputs), jnp.asarray(dist))
        want = reference_derivatives(state, inputs, dist)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_gyroscopic_term_is_present():
    # Unequal rotor speeds: Omega_r != 0 couples theta' into phi''.
    p = plant.nominal_params()
    inputs = np.array([M * G, 0.02, 0.0, 0.3])
    state = np.zeros(12)
    state[10] = 3.0  # theta'
    omega_r = float(plant.rotor_speed_sum(p, jnp.asarray(inputs)))
    assert abs(omega_r) > 0.1
    got = plant.derivatives(p, jnp.asarray(state), jnp.asarray(inputs), jnp.zeros(6))
    want = reference_derivatives(state, inputs, np.zeros(6))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    # phi'' = tau_x / I11 - (J_r / I11) theta' Omega_r here (no other term is active).
    gyroscopic = -J_R / I11 * 3.0 * omega_r
    assert abs(gyroscopic) > 1e-3
    np.testing.assert_allclose(got[9], 0.02 / I11 + gyroscopic, rtol=1e-12)


def test_drag_overrides_and_clipped_rotors():
    rng = np.random.default_rng(1)
    p = plant.nominal_params()
    state, inputs, dist = random_case(rng)
    inputs[1] = 1.5  # large roll torque: some w_i^2 < 0 get clipped
    kp, kphi = (0.02, 0.011, 0.009), (0.01, 0.014, 0.013)
    assert np.min(plant.rotor_speeds_squared(p, jnp.asarray(inputs))) < 0
    got = plant.derivatives(
        p,
        jnp.asarray(state),
        jnp.asarray(inputs),
        jnp.asarray(dist),
        jnp.array(kp),
        jnp.array(kphi),
    )
    want = reference_derivatives(state, inputs, dist, kp=kp, kphi=kphi)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_mixer_round_trip():
    p = plant.nominal_params()
    m = np.asarray(plant.mixer(p))
    np.testing.assert_allclose(m[0], [RHO_B] * 4)
    np.testing.assert_allclose(m[1], [0, -RHO_B * ARM, 0, RHO_B * ARM])
    np.testing.assert_allclose(m[2], [-RHO_B * ARM, 0, RHO_B * ARM, 0])
    np.testing.assert_allclose(m[3], [-RHO_C, RHO_C, -RHO_C, RHO_C])
    rng = np.random.default_rng(2)
    for _ in range(5):
        inputs = jnp.asarray(rng.normal(0, 1, 4))
        squared = plant.rotor_speeds_squared(p, inputs)
        np.testing.assert_allclose(m @ np.asarray(squared), inputs, rtol=1e-12, atol=1e-14)
        w2 = jnp.asarray(rng.uniform(0, 1000, 4))
        np.testing.assert_allclose(plant.rotor_speeds_squared(p, m @ w2), w2, rtol=1e-12)


def test_rotor_speed_sum_gradient_finite_at_zero():
    p = plant.nominal_params()
    grad = jax.grad(lambda u: plant.rotor_speed_sum(p, u))
    for inputs in (jnp.zeros(4), jnp.array([0.0, 0.01, 0.0, 0.0]), plant.hover_inputs(p)):
        g = grad(inputs)
        assert np.all(np.isfinite(g)), g
    # Hover: equal rotor speeds, Omega_r = 0, nonzero sensitivity to yaw torque.
    assert abs(float(plant.rotor_speed_sum(p, plant.hover_inputs(p)))) < 1e-12
    assert abs(float(grad(plant.hover_inputs(p))[3])) > 0
    # Gradient through a whole derivative evaluation at zero thrust is finite too.
    state = plant.hover_state()
    g = jax.grad(lambda u: jnp.sum(plant.derivatives(p, state, u, jnp.zeros(6))))(jnp.zeros(4))
    assert np.all(np.isfinite(g))


def _integrate(p, state, inputs, dist, dt, n_steps):
    def body(x, _):
        return plant.rk4_step(p, x, inputs, dist, dt), None

    return jax.lax.scan(body, state, None, length=n_steps)[0]


def test_rk4_fourth_order():
    p = plant.nominal_params()
    # Rates stay away from zero (w|w| is only C1 there); inputs keep every rotor on.
    state = plant.make_state((0.1, -0.2, 1.0), (0.1, -0.05, 0.3), (0.5, 0.2, -0.3), (1.0, 0.8, 0.6))
    inputs = jnp.array([M * G * 1.1, 0.01, 0.008, 0.005])
    dist = jnp.array([0.1, -0.1, 0.05, 0.3, 0.2, 0.1])
    horizon = 0.8
    integrate = jax.jit(_integrate, static_argnums=(5,))
    fine = integrate(p, state, inputs, dist, horizon / 640, 640)
    errors = []
    for n in (20, 40, 80):
        coarse = integrate(p, state, inputs, dist, horizon / n, n)
        errors.append(float(jnp.max(jnp.abs(coarse - fine))))
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    assert errors[2] < 1e-6
    for ratio in ratios:
        assert 13.0 < ratio < 19.0, (errors, ratios)


def test_rk4_is_jittable_vmappable_differentiable_and_keeps_dtype():
    p32 = plant.nominal_params(jnp.float32)
    state32 = plant.hover_state(dtype=jnp.float32)
    out = jax.jit(plant.rk4_step)(
        p32, state32, plant.hover_inputs(p32), jnp.zeros(6, jnp.float32), 0.01
    )
    assert out.dtype == jnp.float32
    p = plant.nominal_params()
    states = jnp.stack([plant.hover_state(position=(float(i), 0.0, 0.0)) for i in range(3)])
    batched = jax.jit(jax.vmap(plant.rk4_step, in_axes=(None, 0, None, None, None)))(
        p, states, plant.hover_inputs(p), jnp.zeros(6), 0.01
    )
    assert batched.shape == (3, 12)

    def final_height(mass):
        q = p._replace(mass=mass)
        x = _integrate(q, plant.hover_state(), plant.hover_inputs(p), jnp.zeros(6), 0.01, 10)
        return x[2]

    # Heavier than the thrust: falls; d z / d m < 0 and matches finite differences.
    height, g = jax.jit(jax.value_and_grad(final_height))(jnp.asarray(M))
    shifted = jax.jit(jax.vmap(final_height))(jnp.array([M + 1e-6, M - 1e-6]))
    fd = (shifted[0] - shifted[1]) / 2e-6
    assert abs(float(height)) < 1e-12
    assert float(g) < 0
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_split_state_and_make_state_layout():
    state = plant.make_state((0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10, 11))
    np.testing.assert_array_equal(state, np.arange(12.0))
    position, attitude, velocity, rate = plant.split_state(state)
    np.testing.assert_array_equal(position, [0, 1, 2])
    np.testing.assert_array_equal(attitude, [3, 4, 5])
    np.testing.assert_array_equal(velocity, [6, 7, 8])
    np.testing.assert_array_equal(rate, [9, 10, 11])


def test_rotor_limited_inputs():
    params = plant.nominal_params(jnp.float64)
    hover = tuple(plant.hover_inputs(params))
    # A feasible command passes unchanged (to rounding).
    np.testing.assert_allclose(plant.saturate_inputs(params, hover, 1e3), hover, atol=1e-12)
    # A roll torque larger than the rotors give: rotor 2 is clipped at 0, and the
    # thrust and torque recomputed from the clipped speeds.
    command = (hover[0], 5.0, 0.0, 0.0)
    squared = np.asarray(plant.rotor_speeds_squared(params, jnp.asarray(command)))
    assert squared[1] < 0 < squared[3]
    applied = plant.saturate_inputs(params, command, 1e3)
    clipped = np.clip(squared, 0.0, 1e6)
    np.testing.assert_allclose(np.asarray(plant.mixer(params)) @ clipped, applied, rtol=1e-12)
    assert float(applied[1]) < 5.0
    # The upper limit: every rotor at w_max gives 4 rho_b w_max^2 of thrust.
    top = plant.saturate_inputs(params, (1e3, 0.0, 0.0, 0.0), 20.0)
    assert float(top[0]) == pytest.approx(4 * 3e-3 * 400.0, rel=1e-12)


def test_rk4_stages_are_reverse_pass_boundaries(capsys):
    """Every RK4 stage's state, trig and derivative is kept by the simulator's
    checkpoint policy, and the boundary changes no value or derivative (reverse and
    forward mode, against central finite differences)."""
    from fojax import simulator
    from fojax._arrays import KEPT, reverse_pass_boundary

    values = (jnp.arange(3.0), {"b": jnp.ones((2, 2))})
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.all(a == b)), values,
                                     reverse_pass_boundary(values)))  # fmt: skip

    p = plant.nominal_params()
    state = plant.make_state((0.1, -0.2, 1.0), (0.1, -0.05, 0.3), (0.5, 0.2, -0.3), (1.0, 0.8, 0.6))
    inputs = jnp.array([M * G * 1.1, 0.01, 0.008, 0.005])
    dist = jnp.array([0.1, -0.1, 0.05, 0.3, 0.2, 0.1])

    def step(x):
        return plant.rk4_step(p, x, inputs, dist, 0.01)

    checkpointed = jax.checkpoint(step, policy=simulator._save_expensive)
    reverse = jax.jacrev(checkpointed)(state)
    forward = jax.jacfwd(step)(state)
    np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-14)
    eye = np.eye(12)
    central = np.stack(
        [(step(state + 1e-6 * e) - step(state - 1e-6 * e)) / 2e-6 for e in eye], axis=1
    )
    np.testing.assert_allclose(reverse, central, rtol=1e-7, atol=1e-9)

    jax.ad_checkpoint.print_saved_residuals(lambda x: jnp.sum(checkpointed(x)), state)
    kept = capsys.readouterr().out.count(f"named '{KEPT}'")
    # Of the 4 derivatives, 3 stage states and 3 stage trigs, the entries the reverse
    # pass reads (at least one stage's worth) and each only once.
    assert 12 <= kept <= 4 * 12 + 3 * 12 + 3 * 6, kept
