"""Tests of fojax.scenarios: references (54)-(55), (57), disturbances (53), (56), draws."""

import jax

jax.config.update("jax_enable_x64", True)

import dataclasses  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from conftest import close_normwise  # noqa: E402

from fojax import plant  # noqa: E402
from fojax import scenarios as sc  # noqa: E402
from fojax import vehicle as vehicle_module  # noqa: E402

TIMES = (0.0, 3.3, 7.0, 7.5, 12.0, 29.9, 44.4, 79.0)


def closed_form_54_55(t):
    w = math.pi / 20
    pos = [0.5 * math.cos(w * t), 0.5 * math.sin(w * t), 2 - 2 * math.cos(w * t), 0.5]
    vel = [-0.5 * w * math.sin(w * t), 0.5 * w * math.cos(w * t), 2 * w * math.sin(w * t), 0]
    acc = [-0.5 * w**2 * math.cos(w * t), -0.5 * w**2 * math.sin(w * t),
           2 * w**2 * math.cos(w * t), 0]  # fmt: skip
    return pos, vel, acc


def closed_form_57(t):
    a, b = 2 * math.pi / 23, 4 * math.pi / 23
    z = [7 * (1 - math.exp(-0.3 * t)), 2.1 * math.exp(-0.3 * t), -0.63 * math.exp(-0.3 * t)]
    if t <= 7:
        x = y = [0.0, 0.0, 0.0]
    else:
        s = t - 7
        x = [10 * (1 - math.cos(a * s)), 10 * a * math.sin(a * s), 10 * a**2 * math.cos(a * s)]
        y = [5 * math.sin(b * s), 5 * b * math.cos(b * s), -5 * b**2 * math.sin(b * s)]
    return [[x[k], y[k], z[k], 0.5 if k == 0 else 0.0] for k in range(3)]


@pytest.mark.parametrize(
    "reference_fn, closed_form",
    [(sc.reference_54_55, closed_form_54_55), (sc.reference_57, closed_form_57)],
)
def test_reference_and_autodiff_derivatives(reference_fn, closed_form):
    evaluate = jax.jit(lambda t: sc.reference_with_derivatives(reference_fn, t))
    for t in TIMES:
        got = evaluate(jnp.asarray(t))
        np.testing.assert_allclose(reference_fn(t), closed_form(t)[0], rtol=1e-12, atol=1e-12)
        for got_k, want_k in zip(got, closed_form(t), strict=True):
            np.testing.assert_allclose(got_k, want_k, rtol=1e-12, atol=1e-12)


def test_reference_57_left_derivative_at_switch_and_float32():
    _, vel, acc = sc.reference_with_derivatives(sc.reference_57, 7.0)
    np.testing.assert_allclose(vel[:2], 0.0)
    np.testing.assert_allclose(acc[:2], 0.0)
    _, vel, _ = sc.reference_with_derivatives(sc.reference_57, 7.0 + 1e-9)
    np.testing.assert_allclose(vel[1], 20 * math.pi / 23, rtol=1e-6)
    out = sc.reference_with_derivatives(sc.reference_57, jnp.float32(8.0))
    assert all(o.dtype == jnp.float32 and o.shape == (4,) for o in out)


def closed_form_53(t):
    d = [0.0] * 6
    if 10 <= t <= 30:
        d[0] = -(
            0.08 * math.sin(0.11 * t - 3.0403)
            + 0.04 * math.sin(0.5 * t - 13.5)
            + 0.008 * math.sin(1.6 * t - 15 * math.pi)
            + 0.006 * math.sin(0.3 * t - 8.6)
        )
    if 10 <= t <= 50:
        d[1] = 0.05 * math.sin(0.4 * t) + 0.05 * math.cos(0.7 * t)
    if 0 <= t <= 80:
        d[2] = 0.05 * math.cos(0.7 * t) + 0.07 * math.sin(0.3)
        d[3] = 0.5 * math.cos(0.4 * t) + 1
        d[4] = 0.5 * math.sin(0.5 * t) + 1
        d[5] = 0.05 * math.sin(0.7 * t) + 0.1
    return d


def closed_form_56(t):
    return [
        0.3 * math.sin(2 * t) + 0.1 * math.sin(3 * t),
        0.2 * math.cos(2 * t) + 0.2 * math.sin(2 * t),
        0.5 * math.cos(2 * t) + 0.7 * math.sin(3 * t),
        0.9 * math.cos(0.4 * t) + 2.2 * math.sin(2 * t),
        0.8 * math.sin(t) + 1.4 * math.cos(2 * t),
        1.3 * math.sin(5 * t) + 1.5 * math.cos(3 * t),
    ]


EDGE_TIMES = (0.0, 5.0, 9.999, 10.0, 20.0, 30.0, 30.001, 49.999, 50.0, 50.001, 80.0, 80.001)


def test_disturbances_53_with_windows():
    f = jax.jit(sc.disturbances_53)
    for t in EDGE_TIMES:
        np.testing.assert_allclose(f(t), closed_form_53(t), rtol=1e-12, atol=1e-15)
    assert float(f(10.0)[0]) != 0.0 and float(f(9.999)[0]) == 0.0
    assert float(f(30.0)[0]) != 0.0 and float(f(30.001)[0]) == 0.0
    assert float(f(50.0)[1]) != 0.0 and float(f(50.001)[1]) == 0.0
    np.testing.assert_array_equal(f(80.001), 0.0)


def test_disturbances_56():
    f = jax.jit(sc.disturbances_56)
    for t in EDGE_TIMES:
        np.testing.assert_allclose(f(t), closed_form_56(t), rtol=1e-12, atol=1e-15)


def test_get_scenario_fields_and_bad_id():
    s1, s2, s3 = (sc.get_scenario(i) for i in (1, 2, 3))
    assert (s1.horizon, s2.horizon, s3.horizon) == (80.0, 80.0, 50.0)
    assert s1.reference is sc.reference_54_55 and s3.reference is sc.reference_57
    assert s1.disturbance is sc.disturbances_53 and s3.disturbance is sc.disturbances_56
    assert s1.has_drag_variation and not s1.has_noise
    assert s2.has_drag_variation and s2.has_noise
    assert s3.mass_uncertainty == s3.inertia_uncertainty == 0.3
    np.testing.assert_allclose(
        sc.initial_state(s3), [0.05, 0.01, 0, 0.01, 0.01, 0.1, 0, 0, 0, 0, 0, 0]
    )
    hash(s2)  # usable as a static jit argument
    for bad in (0, 4, "x", None):
        with pytest.raises(ValueError, match="unknown scenario"):
            sc.get_scenario(bad)


def _assert_draws_equal(a, b, rtol=0.0):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=rtol, atol=0.0)


def test_draw_determinism_and_independence_of_batch_size():
    scenario = sc.get_scenario(2)
    keys_few, keys_many = sc.draw_keys(7, range(8)), sc.draw_keys(7, range(1000))
    np.testing.assert_array_equal(keys_few, keys_many[:8])
    sample_one = jax.jit(lambda k: sc.sample_draw(scenario, k, 0.01))
    many = jax.jit(jax.vmap(sample_one))(keys_many)
    for i in (0, 3, 7):
        one = sample_one(keys_few[i])
        _assert_draws_equal(one, sample_one(sc.draw_keys(7, [i])[0]))  # same key, same draw
        # Same random bits; a batched and a single compiled transform could round the
        # Gaussian's inverse-erf differently in the last ulp, hence the tiny tolerance.
        _assert_draws_equal(jax.tree.map(lambda x, i=i: x[i], many), one, rtol=1e-14)
    assert not np.array_equal(many.noise_accel[0], many.noise_accel[1])
    other_seed = sample_one(sc.draw_keys(8, [0])[0])
    assert not np.array_equal(other_seed.noise_accel, many.noise_accel[0])


def test_scenario_3_mass_inertia_bounds_and_nominal_drag():
    scenario = sc.get_scenario(3)
    draws = jax.jit(jax.vmap(lambda k: sc.sample_draw(scenario, k, 0.001)))(
        sc.draw_keys(0, range(200))
    )
    nominal = plant.nominal_params()
    mass_ratio = np.asarray(draws.params.mass) / float(nominal.mass)
    inertia_ratio = np.asarray(draws.params.inertia) / np.asarray(nominal.inertia)
    for ratio in (mass_ratio, inertia_ratio):
        assert ratio.min() >= 1.0 and ratio.max() <= 1.3
        assert ratio.max() - ratio.min() > 0.2  # actually spread over the range
    assert not np.allclose(inertia_ratio[:, 0], inertia_ratio[:, 1])  # independent axes
    draw = jax.tree.map(lambda x: x[0], draws)
    drag_p, drag_phi = sc.drag_at(scenario, draw, 12.0)
    np.testing.assert_array_equal(drag_p, nominal.drag_position)
    np.testing.assert_array_equal(drag_phi, nominal.drag_attitude)
    np.testing.assert_allclose(sc.disturbance_at(scenario, draw, 1.3), closed_form_56(1.3))
    # Scenarios 1-2 keep the nominal mass and inertia.
    d1 = sc.sample_draw(sc.get_scenario(1), sc.draw_keys(0, [0])[0], 0.01)
    np.testing.assert_array_equal(d1.params.mass, nominal.mass)
    np.testing.assert_array_equal(d1.params.inertia, nominal.inertia)


def test_drag_and_noise_tables_are_held_and_indexed_by_step():
    dt = 0.001
    scenario = sc.get_scenario(2)
    draw = sc.sample_draw(scenario, sc.draw_keys(3, [5])[0], dt)
    assert draw.drag_multipliers.shape == (81, 6) and draw.noise_accel.shape == (801, 6)
    assert int(draw.drag_hold_steps) == 1000 and int(draw.noise_hold_steps) == 100
    m = np.asarray(draw.drag_multipliers)
    assert m.min() >= 0.8 and m.max() <= 1.2
    noise = np.asarray(draw.noise_accel)
    assert 0.08 < noise.std() < 0.12 and abs(noise.mean()) < 0.02

    disturbance = jax.jit(lambda t: sc.disturbance_at(scenario, draw, t))
    drag = jax.jit(lambda t: sc.drag_at(scenario, draw, t))
    nominal = plant.nominal_params()
    for k in (0, 99, 100, 12_345, 79_999, 80_000):
        t = k * dt
        want = np.asarray(closed_form_53(t)) + noise[k // 100]
        np.testing.assert_allclose(disturbance(t), want, rtol=1e-12, atol=1e-15)
        drag_p, drag_phi = drag(t)
        np.testing.assert_allclose(drag_p, nominal.drag_position * m[k // 1000, :3], rtol=1e-15)
        np.testing.assert_allclose(drag_phi, nominal.drag_attitude * m[k // 1000, 3:], rtol=1e-15)
    # Hold boundaries snap to the step grid even with float32 time.
    t32 = jnp.arange(0, 2000, dtype=jnp.float32) * jnp.float32(dt)
    rows = jax.vmap(lambda t: sc.drag_at(scenario, draw, t)[0][0])(t32)
    assert np.all(np.asarray(rows[:1000]) == rows[0]) and np.all(
        np.asarray(rows[1000:]) == rows[1000]
    )
    # Scenario 1 has no Gaussian part.
    s1 = sc.get_scenario(1)
    d1 = sc.sample_draw(s1, sc.draw_keys(3, [5])[0], dt)
    np.testing.assert_allclose(sc.disturbance_at(s1, d1, 12.0), closed_form_53(12.0))
    assert d1.noise_accel.shape == (1, 6)


def test_draw_float32():
    draw = sc.sample_draw(sc.get_scenario(2), sc.draw_keys(0, [0])[0], 0.01, dtype=jnp.float32)
    assert draw.noise_accel.dtype == jnp.float32 and draw.params.mass.dtype == jnp.float32


# ------------------------------------------------------------------- union scenarios


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_a_union_runs_each_member_as_it_runs_alone(dtype):
    """One compiled rollout for three scenarios of different horizons: every member's
    draws give the metrics, status and snapshots of that scenario alone, bit for bit in
    float64. In float32 the union computes the members' time-only references apart and
    selects one, where a scenario alone lets XLA fold its reference into the per-draw
    kernels: the same arithmetic, rounded once differently, which the closed loop
    carries to about 1e-5 relative over 0.3 s."""
    from fojax import metrics, simulator
    from fojax.controllers import make_controller

    dt, save_every = 1e-3, 50
    members = (
        dataclasses.replace(sc.get_scenario(1), horizon=0.3),
        dataclasses.replace(sc.get_scenario(2), horizon=0.3),
        dataclasses.replace(sc.get_scenario(3), horizon=0.2),
    )
    bank = sc.union(*members)
    assert bank.horizon == 0.3 and bank.member_index(members[2]) == 2
    controller = make_controller("afonftsmc", dt=dt, horizon=0.3, switching="sat")
    gains = controller.default_gains(dtype)
    model = plant.nominal_params(dtype)
    keys = sc.draw_keys(4, range(3))

    @functools.partial(jax.jit, static_argnums=(0, 1))
    def run(scenario, horizon, keys, member):
        config = simulator.SimulationConfig(dt=dt, horizon=horizon, save_every=save_every)
        observer = metrics.Metrics(metrics.MetricsConfig(dt=dt, steps=config.steps))

        def one(key):
            draw = sc.sample_draw(scenario, key, dt, dtype, member)
            return simulator.rollout(controller, gains, model, scenario, draw, config, observer)

        return jax.vmap(one)(keys)

    for index, member in enumerate(members):
        together = run(bank, bank.horizon, keys, index)
        alone = run(member, member.horizon, keys, 0)
        blocks = alone.trajectory.time.shape[1]
        assert blocks == round(member.horizon / dt) // save_every
        same = np.testing.assert_array_equal if dtype == jnp.float64 else close_normwise
        np.testing.assert_array_equal(together.status, alone.status)
        for name, value in alone.outputs.items():
            same(together.outputs[name], value, err_msg=name)
        for got, want in zip(
            jax.tree.leaves(together.trajectory), jax.tree.leaves(alone.trajectory), strict=True
        ):
            same(np.asarray(got)[:, :blocks], want)
    # The members really differ (the comparison is not vacuous).
    a, b = run(bank, bank.horizon, keys, 0), run(bank, bank.horizon, keys, 2)
    assert not np.allclose(a.outputs["position_rmse"], b.outputs["position_rmse"])


def test_smoothed_reference_57_is_continuous_in_velocity_and_equals_57_after_the_ramp():
    t = jnp.asarray([6.9, 7.0, 7.001, 8.0, 9.0, 9.5, 30.0])
    printed = jax.vmap(lambda s: sc.reference_with_derivatives(sc.reference_57, s))(t)
    smooth = jax.vmap(lambda s: sc.reference_with_derivatives(sc.reference_57_smoothed, s))(t)
    # Identical before the start and from the end of the ramp on.
    for k in (0, 5, 6):
        for p_, s_ in zip(printed, smooth, strict=True):
            np.testing.assert_allclose(s_[k], p_[k], rtol=1e-12, atol=1e-12)
    # The printed y_r' jumps by 20 pi / 23 at t = 7; the smoothed one does not.
    assert float(printed[1][2, 1]) == pytest.approx(20 * np.pi / 23, rel=1e-2)
    assert abs(float(smooth[1][2, 1])) < 1e-3


# --------------------------------------------------------------- manoeuvre scenarios


def _manoeuvre_scenario(horizon=0.3):
    from fojax import manoeuvres

    limits = manoeuvres.Limits.from_vehicle(vehicle_module.Vehicle.paper())
    return sc.manoeuvre_scenario(limits, horizon=horizon)


def test_each_draw_flies_its_own_manoeuvre_from_its_start(tmp_path):
    """Every draw's reference is its manoeuvre's (drawn from its key, the other
    processes drawn as without it); it starts at rest, level, at the manoeuvre's start
    plus its offset; a batch rollout equals the rollout of a draw alone."""
    from fojax import manoeuvres, metrics, simulator
    from fojax.controllers import make_controller

    dt, horizon = 1e-3, 0.2
    flying = _manoeuvre_scenario(horizon)
    base = dataclasses.replace(sc.get_scenario(2), horizon=horizon)
    keys = sc.draw_keys(7, range(3))
    draws = sc.sample_draws(flying, keys, dt, jnp.float64)
    plain = sc.sample_draws(base, keys, dt, jnp.float64)
    assert plain.manoeuvre is None
    for got, want in zip(jax.tree.leaves(draws._replace(manoeuvre=None)), jax.tree.leaves(plain),
                         strict=True):  # fmt: skip
        np.testing.assert_array_equal(got, want)
    one = jax.jit(lambda k: sc.sample_draw(flying, k, dt, jnp.float64))(keys[1])
    np.testing.assert_array_equal(one.manoeuvre.waypoints, draws.manoeuvre.waypoints[..., 1])
    assert not np.allclose(draws.manoeuvre.waypoints[..., 0], draws.manoeuvre.waypoints[..., 1])

    state0 = sc.initial_states(flying, draws, jnp.float64, (3,))
    start = manoeuvres.initial_position(draws.manoeuvre)
    np.testing.assert_array_equal(state0[:3], start)
    np.testing.assert_array_equal(state0[5], draws.manoeuvre.waypoints[0, 3])
    np.testing.assert_array_equal(state0[np.r_[3, 4, 6:12]], 0.0)

    controller = make_controller("afonftsmc", dt=dt, horizon=horizon, switching="sat")
    gains, model = controller.default_gains(jnp.float64), plant.nominal_params(jnp.float64)
    config = simulator.SimulationConfig(dt=dt, horizon=horizon, save_every=50)
    observer = metrics.Metrics(metrics.MetricsConfig(dt=dt, steps=config.steps))
    run = jax.jit(lambda d: simulator.rollout(controller, gains, model, flying, d, config,
                                              observer))  # fmt: skip
    batch = run(draws)
    t = np.asarray(batch.trajectory.time[:, 0]) - dt  # a snapshot's reference: its last step's
    want = np.stack([np.stack([np.asarray(manoeuvres.position(
        jax.tree.map(lambda x, i=i: x[..., i], draws.manoeuvre), s)) for s in t])
        for i in range(3)], axis=-1)  # fmt: skip
    np.testing.assert_allclose(batch.trajectory.reference, want, rtol=1e-12, atol=1e-14)
    alone = run(jax.tree.map(lambda x: x[..., 1], draws))
    np.testing.assert_allclose(batch.final_state[:, 1], alone.final_state, rtol=1e-10,
                               atol=1e-12)  # fmt: skip


@pytest.mark.slow
def test_a_union_with_manoeuvres_runs_each_member_as_alone():
    """Scenario 2 and random manoeuvres in one compiled rollout: each member's draws are
    those of the member alone (float64, bit for bit)."""
    from fojax import metrics, simulator
    from fojax.controllers import make_controller

    dt, horizon = 1e-3, 0.2
    members = (dataclasses.replace(sc.get_scenario(2), horizon=horizon),
               _manoeuvre_scenario(horizon))  # fmt: skip
    bank = sc.union(*members)
    controller = make_controller("afonftsmc", dt=dt, horizon=horizon, switching="sat")
    gains, model = controller.default_gains(jnp.float64), plant.nominal_params(jnp.float64)
    keys = sc.draw_keys(2, range(2))
    config = simulator.SimulationConfig(dt=dt, horizon=horizon, save_every=50)
    observer = metrics.Metrics(metrics.MetricsConfig(dt=dt, steps=config.steps))
    for index, member in enumerate(members):
        together = simulator.rollout(controller, gains, model, bank,
                                     sc.sample_draws(bank, keys, dt, jnp.float64, index),
                                     config, observer)  # fmt: skip
        alone = simulator.rollout(controller, gains, model, member,
                                  sc.sample_draws(member, keys, dt, jnp.float64), config,
                                  observer)  # fmt: skip
        np.testing.assert_array_equal(together.trajectory.reference, alone.trajectory.reference)
        np.testing.assert_allclose(together.final_state, alone.final_state, rtol=1e-12,
                                   atol=1e-14)  # fmt: skip
    with pytest.raises(ValueError, match="must have as many segments"):
        other = dataclasses.replace(members[1].manoeuvres, segments=3)
        sc.union(members[1], dataclasses.replace(members[1], manoeuvres=other, name="b"))
