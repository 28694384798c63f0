"""Rotor layouts, their allocation and authority against hand derivations; the '+' file
equal to the paper's plant draw for draw; the rotors' lag against its exact solution and
converging to instantaneous rotors."""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import vehicle_table

from fojax import observers, plant, rotors, scenarios, simulator, vehicle
from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains

PAPER = vehicle.Vehicle.paper()


def _table(rotor_table=None, **changes):
    """The paper's vehicle file (:func:`conftest.vehicle_table`) with ``changes``; with
    ``rotor_table`` its [[vehicle.rotors]] in place of ``arm_length``."""
    if rotor_table is not None:
        changes = {"arm_length": None, "rotors": rotor_table, **changes}
    return vehicle_table(**changes)


IRIS_ROTORS = [  # RotorS iris.xacro: front rotors at (0.13, -+0.22), rear at (-0.13, +-0.20)
    {"position": {"value": [0.13, -0.22], "unit": "m"}, "spin": "ccw"},
    {"position": {"value": [-0.13, 0.20], "unit": "m"}, "spin": "ccw"},
    {"position": {"value": [0.13, 0.22], "unit": "m"}, "spin": "cw"},
    {"position": {"value": [-0.13, -0.20], "unit": "m"}, "spin": "cw"},
]
IRIS = {"mass": {"value": 1.5, "unit": "kg"},
        "thrust_factor": {"value": 8.54858e-6, "unit": "N s^2"},
        "drag_factor": {"value": 1.36777e-7, "unit": "N m s^2"},
        "rotor_speed_limit": {"value": 838.0, "unit": "rad/s"}}  # fmt: skip


def test_the_plus_layout_is_eq_10():
    b, c, d = PAPER.thrust_factor, PAPER.drag_factor, PAPER.arm_length
    by_hand = np.array([[b, b, b, b], [0, -b * d, 0, b * d], [-b * d, 0, b * d, 0],
                        [-c, c, -c, c]])  # fmt: skip
    np.testing.assert_allclose(rotors.plus(d).allocation(b, c), by_hand, rtol=1e-15, atol=0)
    closed = np.asarray(plant.mixer(plant.nominal_params(jnp.float64)))
    general = np.asarray(plant.mixer(plant.nominal_params(jnp.float64)._replace(
        layout=rotors.plus(d))))  # fmt: skip
    np.testing.assert_allclose(general, closed, rtol=1e-15, atol=1e-18)


def test_an_x_layout_against_a_hand_derivation():
    """X at arm d: rotors at (h, h), (h, -h), (-h, -h), (-h, h), h = d / sqrt 2; thrust
    T_i = b w_i^2; tau_x = sum y_i T_i, tau_y = -sum x_i T_i, tau_z = -sum s_i c w_i^2."""
    d, b, c, top = 0.046, 2.88e-8, 1.7e-10, 2272.7**2
    parsed = vehicle.parse(_table(configuration="x", arm_length={"value": d, "unit": "m"},
                                  thrust_factor={"value": b, "unit": "N s^2"},
                                  drag_factor={"value": c, "unit": "N m s^2"},
                                  mass={"value": 0.027, "unit": "kg"},
                                  rotor_speed_limit={"value": 2272.7,
                                                     "unit": "rad/s"}))  # fmt: skip
    h = d / math.sqrt(2)
    by_hand = np.array([[b, b, b, b], [b * h, -b * h, -b * h, b * h],
                        [-b * h, -b * h, b * h, b * h], [-c, c, -c, c]])  # fmt: skip
    layout = parsed.rotor_layout()
    np.testing.assert_allclose(layout.allocation(b, c), by_hand, rtol=1e-12, atol=0)
    # the inverse allocation is exact: M^-1 M = I
    np.testing.assert_allclose(np.linalg.inv(layout.geometry()) @ layout.geometry(),
                               np.eye(4), atol=1e-12)  # fmt: skip
    authority = parsed.authority()
    # roll: the two rotors at y = +h at full speed, the others stopped
    assert authority.max_torque == pytest.approx((2 * b * h * top, 2 * b * h * top, 2 * c * top),
                                                 rel=1e-6)  # fmt: skip
    assert authority.thrust_to_weight == pytest.approx(4 * b * top / (0.027 * 9.81), rel=1e-6)
    # sqrt(2) more roll torque than the '+' of the same arm
    plus = dataclasses.replace(parsed, layout=None).authority()
    assert authority.max_torque[0] / plus.max_torque[0] == pytest.approx(math.sqrt(2), rel=1e-9)


def test_the_iris_layout_against_a_hand_derivation():
    parsed = vehicle.parse(_table(IRIS_ROTORS, **IRIS))
    assert parsed.layout.name == "rotors"
    b, c = 8.54858e-6, 1.36777e-7
    by_hand = np.array([[b, b, b, b], [-0.22 * b, 0.20 * b, 0.22 * b, -0.20 * b],
                        [-0.13 * b, 0.13 * b, -0.13 * b, 0.13 * b], [-c, -c, c, c]])  # fmt: skip
    np.testing.assert_allclose(parsed.rotor_layout().allocation(b, c), by_hand, rtol=1e-12)
    top = b * 838.0**2  # one rotor's full thrust, 6.003 N
    roll, pitch, yaw = parsed.authority().max_torque
    assert roll == pytest.approx(top * (0.22 + 0.20), rel=1e-6)
    assert pitch == pytest.approx(top * (0.13 + 0.13), rel=1e-6)
    assert yaw == pytest.approx(2 * c * 838.0**2, rel=1e-6)
    assert (roll, pitch) == pytest.approx((2.52, 1.56), rel=1e-2)  # the figures
    assert parsed.arm_length == pytest.approx(np.mean([math.hypot(0.13, 0.22)] * 2
                                                      + [math.hypot(0.13, 0.20)] * 2))  # fmt: skip
    # the layout round-trips through its record
    assert parsed.to_dict()["vehicle"]["rotors"][0] == {"position": [0.13, -0.22], "spin": "ccw"}


def test_the_allocation_in_the_plant_inverts_and_saturates_by_the_layout():
    parsed = vehicle.parse(_table(IRIS_ROTORS, **IRIS))
    params = parsed.params(jnp.float64)
    m = np.asarray(plant.mixer(params))
    w2 = np.array([4.1e5, 4.6e5, 3.9e5, 5.2e5])
    np.testing.assert_allclose(m, parsed.rotor_layout().allocation(params.thrust_factor,
                                                                   params.drag_factor))
    np.testing.assert_allclose(plant.rotor_speeds_squared(params, jnp.asarray(m @ w2)), w2,
                               rtol=1e-12)  # fmt: skip
    # a command past the limit: clipped speeds, recomputed through the allocation
    command = m @ np.array([9e5, 1e5, -2e4, 3e5])
    applied = plant.saturate_inputs(params, tuple(jnp.asarray(command)), 838.0)
    clipped = np.clip(np.linalg.solve(m, command), 0, 838.0**2)
    np.testing.assert_allclose(np.stack(applied), m @ clipped, rtol=1e-12)
    speeds = np.sqrt(w2)
    omega = plant.rotor_speed_sum(params, jnp.asarray(m @ w2))
    assert float(omega) == pytest.approx(speeds[0] + speeds[1] - speeds[2] - speeds[3])


@pytest.mark.parametrize(
    "changes, named",
    [
        ({"configuration": "h"}, "vehicle.configuration: expected one of 'plus', 'x'"),
        ({"rotor_speed_limit": {"value": 10, "unit": "rpm"}},
         "vehicle.rotor_speed_limit: 1.047 rad/s (10 rpm) cannot lift the vehicle: hover "
         "needs 24.6 rad/s (234.9 rpm)"),
        ({"rotor_time_constant": {"value": -1, "unit": "ms"}},
         "vehicle.rotor_time_constant: every value must be finite and >= 0"),
        ({"rotor_time_constant": {"value": 2, "unit": "s"}},
         "vehicle.rotor_time_constant: expected a lag below 1 s"),
        ({"configuration": ["x"]}, "vehicle.configuration: expected one of"),
        ({"arm_length": None,
          "rotors": {"position": {"value": [0.1, 0.1], "unit": "m"}, "spin": "cw"}},
         "vehicle.rotors: expected [[vehicle.rotors]] tables"),
        ({"tilt_limit": {"value": 95, "unit": "deg"}},
         "vehicle.tilt_limit: expected an angle above 0 and below 90 deg"),
    ],
)
def test_a_bad_rotor_entry_is_one_error_naming_it(changes, named):
    with pytest.raises(vehicle.VehicleError) as caught:
        vehicle.parse(_table(**changes), "v.toml")
    message = str(caught.value)
    assert named in message and message.count("\n") == 1, message


@pytest.mark.parametrize(
    "rotor_table, named",
    [
        (IRIS_ROTORS[:3], "vehicle.rotors: a quadrotor has four rotors, got 3"),
        ([*IRIS_ROTORS[:3], {**IRIS_ROTORS[3], "spin": "left"}],
         "vehicle.rotors[4].spin: expected \"ccw\" or \"cw\""),
        ([*IRIS_ROTORS[:3], {**IRIS_ROTORS[3], "position": {"value": [1, 2], "unit": "in"}}],
         "vehicle.rotors[4].position: unit 'in' is not one of"),
        ([{**r, "spin": "ccw"} for r in IRIS_ROTORS], "allocation is singular"),
        ([{"position": {"value": [x, 0.0], "unit": "m"}, "spin": s}
          for x, s in ((0.1, "ccw"), (0.2, "cw"), (0.3, "ccw"), (0.4, "cw"))],
         "allocation is singular"),
        ([{"position": {"value": [x + 0.5, y], "unit": "m"}, "spin": s}
          for (x, y), s in (((0.1, 0.1), "ccw"), ((0.1, -0.1), "cw"), ((-0.1, -0.1), "ccw"),
                            ((-0.1, 0.1), "cw"))],
         "the centre of mass must lie inside the rotors"),
    ],
)
def test_bad_listed_rotors_are_one_error_naming_them(rotor_table, named):
    with pytest.raises(vehicle.VehicleError) as caught:
        vehicle.parse(_table(rotor_table, **IRIS), "v.toml")
    message = str(caught.value)
    assert named in message and message.count("\n") == 1, message


def test_rotors_and_an_arm_together_are_refused():
    table = _table(IRIS_ROTORS, **IRIS)
    table["vehicle"]["arm_length"] = {"value": 0.2, "unit": "m"}
    with pytest.raises(vehicle.VehicleError, match="give arm_length .* or the rotors"):
        vehicle.parse(table)


# ------------------------------------------------------------------------- rollouts

HORIZON = 0.3
CONFIG = simulator.SimulationConfig(dt=1e-3, horizon=HORIZON, save_every=100)
SCENARIO = dataclasses.replace(scenarios.get_scenario(2), horizon=HORIZON)
KEYS = scenarios.draw_keys(5, range(3))


def _fly(flown: vehicle.Vehicle | None, config=CONFIG):
    dtype = jnp.float64
    scenario = SCENARIO.on(flown)
    draws = scenarios.sample_draws(scenario, KEYS, config.dt, dtype)
    controller = AFONFTSMC(dt=config.dt, horizon=config.horizon, switching="sat")
    return simulator.rollout(controller, paper_gains(dtype), scenario.plant_params(dtype),
                             scenario, draws, config, observers.TrackingISE(config.dt))  # fmt: skip


def test_the_plus_file_equals_the_paper_plant_draw_for_draw():
    explicit = vehicle.parse(_table(configuration="plus"))
    assert explicit == vehicle.parse(_table())  # "plus" is the default: the same program
    got, want = _fly(explicit), _fly(None)
    np.testing.assert_array_equal(got.final_state, want.final_state)
    np.testing.assert_array_equal(got.trajectory.state, want.trajectory.state)


def test_a_general_layout_of_the_plus_geometry_flies_as_eq_10():
    """The '+' geometry through the general allocation (G^-1 in float64) flies as the
    closed form of eq. (10), to rounding (amplified where the rotor limit clips)."""
    listed = [{"position": {"value": list(p), "unit": "m"}, "spin": "ccw" if s > 0 else "cw"}
              for p, s in zip(rotors.plus(PAPER.arm_length).positions, (1, -1, 1, -1), strict=True)]
    general = vehicle.parse(_table(listed))
    assert general.layout is not None
    limited = dataclasses.replace(CONFIG, rotor_speed_limit=40.0)
    for config in (CONFIG, limited):
        got, want = _fly(general, config), _fly(None, config)
        np.testing.assert_allclose(got.trajectory.state, want.trajectory.state,
                                   rtol=1e-7, atol=1e-9)  # fmt: skip


def test_an_x_vehicle_flies_otherwise_than_its_plus():
    x = vehicle.parse(_table(configuration="x"))
    got, want = _fly(x), _fly(None)
    # the command is the same law's; the gyroscopic term and nothing else differs
    assert np.all(np.isfinite(got.final_state))
    assert not np.array_equal(got.final_state, want.final_state)
    np.testing.assert_allclose(got.final_state, want.final_state, rtol=1e-3, atol=1e-5)


def test_a_zero_time_constant_is_no_lag_bit_for_bit():
    zero = vehicle.parse(_table(rotor_time_constant={"value": 0, "unit": "s"}))
    np.testing.assert_array_equal(_fly(zero).trajectory.state, _fly(None).trajectory.state)


@pytest.mark.slow
def test_small_time_constants_converge_to_no_lag():
    base = _fly(None)
    errors = []
    for constant in (1e-2, 1e-3, 1e-4, 1e-5):
        lagging = vehicle.parse(_table(rotor_time_constant={"value": constant,
                                                            "unit": "s"}))  # fmt: skip
        got = _fly(lagging)
        assert np.all(np.isfinite(got.trajectory.state))
        errors.append(float(np.max(np.abs(got.trajectory.state - base.trajectory.state))))
    assert errors[0] > 1e-6  # a 10 ms lag is felt
    # first order in T: each tenfold smaller constant, a tenfold smaller difference
    for larger, smaller in zip(errors, errors[1:], strict=False):
        assert smaller < 0.2 * larger, errors


def test_the_lag_weights_are_the_exact_solution():
    """One step of T q' = q_c - q from q_k: the end value and the step's mean against a
    fine quadrature of the exact solution."""
    constant, dt, start, command = 0.02, 1e-3, 9e4, 1.7e5
    decay, mean = rotors.lag_weights(constant, dt)
    s = np.linspace(0, dt, 200_001)
    q = command + (start - command) * np.exp(-s / constant)
    gap = start - command
    assert command + decay * gap == pytest.approx(q[-1], rel=1e-15)
    assert command + mean * gap == pytest.approx(np.trapezoid(q, s) / dt, rel=1e-12)
