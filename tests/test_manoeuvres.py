"""Random minimum-jerk manoeuvres (fojax.manoeuvres): the draws (reproducible, one
stream per quantity, vmap equals a loop), the limits (analytic peaks, and a dense
numerical sample of the trajectory's derivatives), continuity and rest at every
waypoint, the box and the hover rate, autodiff against finite differences, finite
gradients everywhere, the batch-last layout, and the limits a vehicle gives."""

import functools
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax import manoeuvres, scenarios, vehicle
from fojax.manoeuvres import Limits

# Every limit binds for some moves: the acceleration for long ones, the speed for
# middling ones, the yaw limits for large turns, the minimum duration for short moves.
LIMITS = Limits(speed=1.5, acceleration=1.0, yaw_rate=0.8, yaw_acceleration=1.5,
                half_extent=1.5, z_range=(0.5, 2.0), yaw_range=(-1.0, 1.5), segments=5,
                hover_probability=0.3, hover_duration=(0.5, 2.0), initial_offset=0.2,
                min_duration=1.5, max_stretch=1.4)  # fmt: skip
SLACK = 1e-9  # relative
GRAVITY = 9.81


@functools.partial(jax.jit, static_argnums=(1, 2))
def _many(keys, limits, horizon=None):
    return jax.vmap(lambda key: manoeuvres.sample(key, limits, horizon))(keys)


def _keys(count, seed=0):
    return jax.random.split(jax.random.key(seed), count)


def _draw(batch, i):
    return jax.tree.map(lambda leaf: leaf[i], batch)


@jax.jit
def _derivatives(manoeuvre, times):
    """``(position, velocity, acceleration)``, each ``(len(times), 4)``, of one draw."""
    return jax.vmap(
        lambda t: scenarios.reference_with_derivatives(
            lambda s: manoeuvres.position(manoeuvre, s), t
        )
    )(times)


_derivatives_many = jax.jit(jax.vmap(_derivatives.__wrapped__))  # draws, then times


def _dense(batch, count=4000):
    """Each draw's derivatives at ``count`` times over ``[-0.02, 1.02]`` of its span."""
    ends = np.asarray(batch.starts[:, -1])
    times = ends[:, None] * np.linspace(-0.02, 1.02, count)[None, :]
    return times, _derivatives_many(batch, jnp.asarray(times))


def _peaks(batch):
    """Each draw's :func:`manoeuvres.peaks` of a batch-first batch, ``(draws, S)`` each."""
    return jax.vmap(manoeuvres.peaks)(batch)


def _hovers(batch):
    return np.all(np.diff(np.asarray(batch.waypoints), axis=-2) == 0, axis=-1)


# ------------------------------------------------------------------------------ the draws


def test_the_shape_s_and_its_peak_factors():
    u = np.linspace(0, 1, 200_001)
    first = 30 * u**2 * (1 - u) ** 2
    second = 60 * u * (1 - u) * (1 - 2 * u)
    np.testing.assert_allclose(manoeuvres.PEAK_SPEED, first.max(), rtol=1e-9)
    np.testing.assert_allclose(manoeuvres.PEAK_ACCELERATION, np.abs(second).max(), rtol=1e-9)
    one = manoeuvres.Manoeuvre(jnp.asarray([0.0, 2.0]), jnp.asarray([[0.0] * 4, [1.0] * 4]),
                               jnp.zeros(3))  # fmt: skip
    values = jax.vmap(lambda t: manoeuvres.position(one, t))(jnp.asarray(2.0 * u[::1000]))
    want = 10 * u[::1000] ** 3 - 15 * u[::1000] ** 4 + 6 * u[::1000] ** 5
    np.testing.assert_allclose(values, np.repeat(want[:, None], 4, axis=1), atol=1e-15)


def test_the_same_key_gives_the_same_manoeuvre_and_other_keys_differ():
    sample = jax.jit(manoeuvres.sample, static_argnums=1)
    first = sample(jax.random.key(3), LIMITS)
    again = sample(jax.random.key(3), LIMITS)
    other = sample(jax.random.key(4), LIMITS)
    for a, b, c in zip(first, again, other, strict=True):
        np.testing.assert_array_equal(a, b)
        assert not np.array_equal(a, c)
    assert first.starts.shape == (LIMITS.segments + 1,)
    assert first.waypoints.shape == (LIMITS.segments + 1, 4)
    assert first.offset.shape == (3,)
    assert first.starts[0] == 0 and np.all(np.diff(first.starts) > 0)
    eager = manoeuvres.sample(jax.random.key(3), LIMITS)
    for a, b in zip(first, eager, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14)


def test_vmap_over_keys_equals_a_loop_of_single_draws():
    keys = _keys(6, seed=1)
    batch = _many(keys, LIMITS, 20.0)
    for i in range(6):
        one = manoeuvres.sample(keys[i], LIMITS, 20.0)
        for name, a, b in zip(one._fields, _draw(batch, i), one, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14, err_msg=name)
    # raw uint32 keys too
    raw = jax.random.PRNGKey(5)
    np.testing.assert_array_equal(manoeuvres.sample(raw, LIMITS).starts,
                                  _many(raw[None], LIMITS).starts[0])  # fmt: skip


def test_each_quantity_draws_from_its_own_stream():
    keys = _keys(50, seed=2)
    base = _many(keys, LIMITS)
    # Another hover probability or segment count leaves the offset and P_0 as they were.
    for change in ({"hover_probability": 0.8}, {"segments": 3}, {"max_stretch": 1.0}):
        other = _many(keys, Limits(**{**_fields(LIMITS), **change}))
        np.testing.assert_array_equal(other.offset, base.offset, err_msg=str(change))
        np.testing.assert_array_equal(other.waypoints[:, 0], base.waypoints[:, 0])
    # Another stretch changes the times, not the places.
    other = _many(keys, Limits(**{**_fields(LIMITS), "max_stretch": 3.0}))
    np.testing.assert_array_equal(other.waypoints, base.waypoints)
    assert not np.array_equal(other.starts, base.starts)


def _fields(limits):
    return {name: getattr(limits, name) for name in limits.__dataclass_fields__}


def test_float32_draws_stay_float32_and_within_the_limits():
    sample = jax.vmap(lambda key: manoeuvres.sample(key, LIMITS, dtype=jnp.float32))
    batch = jax.jit(sample)(_keys(64, seed=9))
    assert all(leaf.dtype == jnp.float32 for leaf in batch)
    for name, values in _peaks(batch).items():
        assert np.all(np.asarray(values) <= getattr(LIMITS, name) * (1 + 1e-5)), name
    value = manoeuvres.position(_draw(batch, 0), jnp.float32(3.0))
    assert value.dtype == jnp.float32 and np.all(np.isfinite(value))


# ----------------------------------------------------------------------------- the limits


def test_analytic_peaks_are_within_the_limits_and_each_move_is_as_short_as_they_allow():
    tight = Limits(**{**_fields(LIMITS), "max_stretch": 1.0})
    for limits in (LIMITS, tight):
        batch = _many(_keys(500, seed=3), limits, None)
        found = _peaks(batch)
        ratios = np.stack([np.asarray(found[name]) / getattr(limits, name)
                           for name in ("speed", "acceleration", "yaw_rate",
                                        "yaw_acceleration")])  # fmt: skip
        assert ratios.max() <= 1 + SLACK
        if limits is tight:
            durations = np.diff(np.asarray(batch.starts), axis=1)
            moves = ~_hovers(batch)
            # each move is limited by one of the four peaks, or lasts min_duration
            binding = np.isclose(ratios.max(axis=0), 1, rtol=1e-12, atol=0)
            shortest = np.isclose(durations, limits.min_duration, rtol=1e-12)
            assert np.all((binding | shortest)[moves])
            # and each limit binds somewhere (the check above is not vacuous)
            bound = np.isclose(ratios, 1, rtol=1e-12, atol=0) & moves[None]
            assert np.all(bound.any(axis=(1, 2))), bound.sum(axis=(1, 2))
            assert np.any(shortest & moves)


@pytest.mark.parametrize("horizon", [None, 18.0])
def test_dense_samples_of_velocity_and_acceleration_never_exceed_the_limits(horizon):
    batch = _many(_keys(48, seed=4), LIMITS, horizon)
    _, (_, velocity, acceleration) = _dense(batch)
    velocity, acceleration = np.asarray(velocity), np.asarray(acceleration)
    speed = np.linalg.norm(velocity[..., :3], axis=-1)
    accel = np.linalg.norm(acceleration[..., :3], axis=-1)
    found = {"speed": speed, "acceleration": accel, "yaw_rate": np.abs(velocity[..., 3]),
             "yaw_acceleration": np.abs(acceleration[..., 3])}  # fmt: skip
    analytic = _peaks(batch)
    for name, values in found.items():
        limit = getattr(LIMITS, name)
        assert values.max() <= limit * (1 + SLACK), (name, values.max(), limit)
        # the sampling is dense enough to find each draw's analytic peak
        np.testing.assert_allclose(values.max(axis=1), np.asarray(analytic[name]).max(axis=1),
                                   rtol=1e-3, err_msg=name)  # fmt: skip


def test_a_horizon_stretches_the_manoeuvre_to_fill_it():
    keys = _keys(200, seed=5)
    free = _many(keys, LIMITS, None)
    filled = _many(keys, LIMITS, 18.0)
    ends = np.asarray(free.starts[:, -1])
    assert np.any(ends < 18) and np.any(ends > 18)
    np.testing.assert_array_equal(filled.waypoints, free.waypoints)
    np.testing.assert_array_less(18 * (1 - 1e-12), filled.starts[:, -1])
    factor = np.maximum(1.0, 18.0 / ends)
    np.testing.assert_allclose(filled.starts, free.starts * factor[:, None], rtol=1e-12)
    long = ends >= 18  # already long enough: unchanged
    np.testing.assert_array_equal(filled.starts[long], free.starts[long])


# --------------------------------------------------------------------- the trajectory


def test_continuity_across_boundaries_and_rest_at_every_waypoint():
    batch = _many(_keys(20, seed=6), LIMITS, None)
    eps = 1e-6
    for i in range(20):
        m = _draw(batch, i)
        starts = np.asarray(m.starts)
        waypoints = np.asarray(m.waypoints)
        at = _derivatives(m, jnp.asarray(starts))
        np.testing.assert_allclose(at[0], waypoints, atol=1e-12)
        np.testing.assert_allclose(at[1], 0, atol=1e-12)  # rest at each waypoint
        np.testing.assert_allclose(at[2], 0, atol=1e-12)
        before = _derivatives(m, jnp.asarray(starts - eps))
        after = _derivatives(m, jnp.asarray(starts + eps))
        for order, tolerance in enumerate((1e-12, 1e-9, 1e-4)):
            np.testing.assert_allclose(before[order], after[order], atol=tolerance,
                                       err_msg=f"draw {i}, derivative {order}")  # fmt: skip
        # before 0 at P_0, after the end at the last waypoint, at rest
        outside = _derivatives(m, jnp.asarray([-5.0, -1e-9, starts[-1] + 1e-9, starts[-1] + 50]))
        np.testing.assert_allclose(outside[0], waypoints[[0, 0, -1, -1]], atol=1e-12)
        np.testing.assert_allclose(outside[1], 0, atol=1e-12)
        np.testing.assert_allclose(outside[2], 0, atol=1e-12)


def test_the_path_is_a_straight_line_and_hovers_hold_their_waypoint():
    m = _draw(_many(_keys(40, seed=7), LIMITS, None), 0)
    starts, waypoints = np.asarray(m.starts), np.asarray(m.waypoints)
    for j in range(LIMITS.segments):
        times = starts[j] + (starts[j + 1] - starts[j]) * np.linspace(0, 1, 11)
        values = np.asarray(_derivatives(m, jnp.asarray(times))[0])
        step = waypoints[j + 1] - waypoints[j]
        u = np.linspace(0, 1, 11)
        fraction = 10 * u**3 - 15 * u**4 + 6 * u**5
        np.testing.assert_allclose(values, waypoints[j] + fraction[:, None] * step, atol=1e-12)


def test_waypoints_stay_in_the_box_and_the_offset_within_its_width():
    batch = _many(_keys(1000, seed=8), LIMITS, None)
    w = np.asarray(batch.waypoints)
    assert np.all(np.abs(w[..., :2]) <= LIMITS.half_extent)
    assert np.all((w[..., 2] >= LIMITS.z_range[0]) & (w[..., 2] <= LIMITS.z_range[1]))
    assert np.all((w[..., 3] >= LIMITS.yaw_range[0]) & (w[..., 3] <= LIMITS.yaw_range[1]))
    assert np.all(np.abs(np.asarray(batch.offset)) <= LIMITS.initial_offset)
    # the box is used, not a corner of it
    assert np.ptp(w[..., 0]) > 2.8 and np.ptp(w[..., 2]) > 1.4 and np.ptp(w[..., 3]) > 2.4
    start = jax.vmap(manoeuvres.initial_position)(batch)
    np.testing.assert_allclose(start, w[:, 0, :3] + np.asarray(batch.offset), rtol=0, atol=0)
    durations = np.diff(np.asarray(batch.starts), axis=1)
    hovers = _hovers(batch)
    assert np.all(durations[hovers] >= LIMITS.hover_duration[0] * (1 - 1e-12))
    assert np.all(durations[hovers] <= LIMITS.hover_duration[1] * (1 + 1e-12))
    assert np.all(durations[~hovers] >= LIMITS.min_duration * (1 - 1e-12))


@pytest.mark.parametrize("probability", [0.0, 0.3, 1.0])
def test_hover_segments_come_at_their_probability(probability):
    limits = Limits(**{**_fields(LIMITS), "hover_probability": probability})
    batch = _many(_keys(2000, seed=10), limits, None)
    hovers = _hovers(batch)
    share = hovers.mean()
    sigma = math.sqrt(probability * (1 - probability) / hovers.size)
    assert abs(share - probability) <= 5 * sigma + 1e-12, share
    # a hover is one segment whose two waypoints are equal in all four axes
    if 0 < probability < 1:
        assert np.all(np.any(np.diff(np.asarray(batch.waypoints), axis=-2) != 0, axis=-1)[~hovers])


def test_autodiff_derivatives_equal_finite_differences():
    batch = _many(_keys(8, seed=11), LIMITS, None)
    h = 1e-5
    rng = np.random.default_rng(0)
    for i in range(8):
        m = _draw(batch, i)
        times = rng.uniform(0, float(m.starts[-1]), 40)
        _, velocity, acceleration = _derivatives(m, jnp.asarray(times))
        p = [np.asarray(_derivatives(m, jnp.asarray(times + k * h))[0]) for k in (-1, 1)]
        v = [np.asarray(_derivatives(m, jnp.asarray(times + k * h))[1]) for k in (-1, 1)]
        np.testing.assert_allclose(velocity, (p[1] - p[0]) / (2 * h), atol=1e-8)
        np.testing.assert_allclose(acceleration, (v[1] - v[0]) / (2 * h), atol=1e-8)


def test_gradients_are_finite_everywhere_boundaries_and_ends_included():
    m = _draw(_many(_keys(4, seed=12), LIMITS, None), 1)
    starts = np.asarray(m.starts)
    times = np.concatenate([starts, [-3.0, -1e-12, starts[-1] + 1e-12, starts[-1] + 100.0],
                            0.5 * (starts[1:] + starts[:-1])])  # fmt: skip

    def cost(manoeuvre, t):
        p, v, a = scenarios.reference_with_derivatives(
            lambda s: manoeuvres.position(manoeuvre, s), t
        )
        return jnp.sum(p**2) + jnp.sum(v**2) + jnp.sum(jnp.sin(a))

    by_time = jax.jit(jax.vmap(jax.grad(cost, argnums=1), in_axes=(None, 0)))(m, times)
    assert np.all(np.isfinite(by_time)), by_time
    by_leaves = jax.jit(jax.vmap(jax.grad(cost), in_axes=(None, 0)))(m, times)
    for leaf in by_leaves:
        assert np.all(np.isfinite(leaf))
    # a third derivative (the jerk) exists and is finite too
    jerk = jax.jit(jax.vmap(jax.jacfwd(lambda t: _derivatives.__wrapped__(m, t[None])[2][0])))(
        jnp.asarray(times)
    )
    assert np.all(np.isfinite(jerk))


@pytest.mark.slow
def test_batch_last_leaves_give_the_vmapped_result():
    batch = _many(_keys(7, seed=13), LIMITS, None)
    last = jax.tree.map(lambda leaf: jnp.moveaxis(leaf, 0, -1), batch)
    assert last.starts.shape == (LIMITS.segments + 1, 7)
    assert last.waypoints.shape == (LIMITS.segments + 1, 4, 7)
    assert last.offset.shape == (3, 7)
    mapped = jax.vmap(manoeuvres.position, in_axes=(-1, None), out_axes=-1)
    for t in (0.0, 1.3, 7.7, float(batch.starts[0, 2]), 1e3):
        t = jnp.asarray(t)
        direct = manoeuvres.position(last, t)
        assert direct.shape == (4, 7)
        np.testing.assert_allclose(direct, mapped(last, t), rtol=1e-14, atol=1e-14)
        for i in range(7):
            np.testing.assert_allclose(direct[:, i], manoeuvres.position(_draw(batch, i), t),
                                       rtol=1e-14, atol=1e-14)  # fmt: skip
        derivatives = scenarios.reference_with_derivatives(
            lambda s: manoeuvres.position(last, s), t
        )
        for i, value in enumerate(_derivatives(_draw(batch, 3), t[None])):
            np.testing.assert_allclose(derivatives[i][:, 3], value[0], rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(
        manoeuvres.initial_position(last),
        np.moveaxis(np.asarray(jax.vmap(manoeuvres.initial_position)(batch)), 0, -1),
    )
    peaks = manoeuvres.peaks(last)
    for name, values in _peaks(batch).items():
        np.testing.assert_allclose(peaks[name], np.moveaxis(np.asarray(values), 0, -1))


# ----------------------------------------------------------------------- Limits itself


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"speed": 0.0}, "speed must be > 0"),
        ({"acceleration": -1.0}, "acceleration must be > 0"),
        ({"yaw_rate": math.inf}, "yaw_rate must be finite"),
        ({"yaw_acceleration": "2"}, "yaw_acceleration must be a number"),
        ({"min_duration": 0}, "min_duration must be > 0"),
        ({"half_extent": -0.1}, "half_extent must be >= 0"),
        ({"initial_offset": -1.0}, "initial_offset must be >= 0"),
        ({"z_range": (2.0, 1.0)}, "swap them"),
        ({"z_range": (1.0,)}, "z_range must be two numbers"),
        ({"yaw_range": (0.0, math.nan)}, "yaw_range must be finite"),
        ({"hover_duration": (0.0, 1.0)}, "hover_duration must be > 0"),
        ({"segments": 0}, "segments must be an integer >= 1"),
        ({"segments": 2.0}, "segments must be an integer >= 1"),
        ({"segments": True}, "segments must be an integer >= 1"),
        ({"hover_probability": 1.5}, "hover_probability must lie in [0, 1]"),
        ({"max_stretch": 0.9}, "max_stretch must be >= 1"),
    ],
)
def test_bad_limits_are_refused_saying_what_to_change(change, words):
    with pytest.raises(ValueError, match=f"^Limits {next(iter(change))}") as info:
        Limits(**{**_fields(LIMITS), **change})
    assert words in str(info.value)


def test_limits_hash_and_take_lists_as_tuples():
    listed = Limits(**{**_fields(LIMITS), "z_range": [0.5, 2.0], "yaw_range": [-1, 1.5]})
    assert listed.z_range == (0.5, 2.0) and listed.yaw_range == (-1.0, 1.5)
    assert hash(listed) == hash(Limits(**{**_fields(LIMITS), "yaw_range": (-1.0, 1.5)}))


EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples" / "vehicles"
VEHICLES = {
    "crazyflie": lambda: vehicle.load(EXAMPLES / "crazyflie.toml"),
    "paper": vehicle.Vehicle.paper,
    "iris": lambda: vehicle.load(EXAMPLES / "iris.toml"),
}


@pytest.mark.parametrize("name", sorted(VEHICLES))
def test_limits_from_a_vehicle_are_finite_positive_and_flyable(name):
    flown = VEHICLES[name]()
    limits = Limits.from_vehicle(flown)
    for field in ("speed", "acceleration", "yaw_rate", "yaw_acceleration"):
        value = getattr(limits, field)
        assert math.isfinite(value) and value > 0, (field, value)
    g = flown.gravity
    # the tilt and thrust the peak acceleration may ask, in any direction
    assert math.asin(limits.acceleration / g) < flown.max_tilt()
    ratio = flown.authority().thrust_to_weight
    if ratio is not None:
        assert g + limits.acceleration < ratio * g
    # fraction 1 reaches the vehicle's limit exactly; 0.5 is half of it
    whole = Limits.from_vehicle(flown, fraction=1.0)
    np.testing.assert_allclose(whole.acceleration, 2 * limits.acceleration, rtol=1e-12)
    bound = min(math.sin(flown.max_tilt()), math.inf if ratio is None else ratio - 1)
    np.testing.assert_allclose(whole.acceleration, g * bound, rtol=1e-12)
    # and the sampled manoeuvres ask for no more, numerically
    batch = _many(_keys(24, seed=14), limits, None)
    _, (_, _, acceleration) = _dense(batch, 2000)
    a = np.asarray(acceleration)[..., :3]
    tilt = np.arctan2(np.hypot(a[..., 0], a[..., 1]), a[..., 2] + g)
    assert tilt.max() < flown.max_tilt()
    if ratio is not None:
        assert np.linalg.norm(a + np.array([0, 0, g]), axis=-1).max() / g < ratio


def test_from_vehicle_derives_the_yaw_acceleration_from_the_yaw_torque():
    crazyflie = VEHICLES["crazyflie"]()
    authority = crazyflie.authority()
    ratio = authority.thrust_to_weight
    share = min(1.0, 2 * min(1 - 1 / ratio, 1 / ratio))
    want = 0.5 * authority.max_torque[2] * share / crazyflie.inertia[2]
    np.testing.assert_allclose(Limits.from_vehicle(crazyflie).yaw_acceleration, want, rtol=1e-12)
    ideal = Limits.from_vehicle(crazyflie, speed_limit=None)
    assert ideal.yaw_acceleration == manoeuvres.IDEAL_YAW_ACCELERATION
    assert ideal.acceleration == pytest.approx(0.5 * crazyflie.gravity * math.sin(math.pi / 4))
    assert Limits.from_vehicle(VEHICLES["paper"]()).yaw_acceleration == (
        manoeuvres.IDEAL_YAW_ACCELERATION
    )


def test_from_vehicle_takes_overrides_and_refuses_what_it_cannot_use():
    paper = vehicle.Vehicle.paper()
    limits = Limits.from_vehicle(paper, speed=0.5, segments=9, z_range=(1.0, 3.0))
    assert (limits.speed, limits.segments, limits.z_range) == (0.5, 9, (1.0, 3.0))
    assert limits.acceleration == Limits.from_vehicle(paper).acceleration
    for fraction in (0.0, 1.5, math.nan, True):
        with pytest.raises(ValueError, match="fraction"):
            Limits.from_vehicle(paper, fraction=fraction)
    with pytest.raises(ValueError, match="unknown field.*top_speed"):
        Limits.from_vehicle(paper, top_speed=2.0)
    crazyflie = VEHICLES["crazyflie"]()
    hover = crazyflie.authority().hover_speed
    with pytest.raises(ValueError, match="not enough to hover"):
        Limits.from_vehicle(crazyflie, speed_limit=0.9 * hover)
    with pytest.raises(ValueError, match="Limits speed must be > 0"):
        Limits.from_vehicle(paper, speed=0.0)
