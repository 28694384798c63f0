"""Vehicle files: the paper's file is the paper's plant, units convert, and every bad
file is one error naming its field."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import vehicle_table

from fojax import plant, vehicle

PAPER_FILE = "examples/vehicles/paper.toml"


_table = vehicle_table


def test_the_paper_file_is_the_paper_plant():
    loaded = vehicle.Vehicle.from_file(PAPER_FILE)
    assert loaded == vehicle.Vehicle.paper()
    for dtype in ("float32", "float64"):
        got, want = loaded.params(dtype), plant.nominal_params(dtype)
        assert got.layout is None and want.layout is None  # the '+' of eq. (10)
        for name, a, b in zip(vehicle.FIELDS, got, want, strict=False):
            assert a.dtype == b.dtype and np.array_equal(a, b), name


def test_units_convert_to_si():
    parsed = vehicle.parse(_table(
        mass={"value": 30, "unit": "g"},
        inertia={"value": [16.6, 16.6, 29.3], "unit": "g cm^2"},
        arm_length={"value": 46, "unit": "mm"},
        rotor_speed_limit={"value": 6000, "unit": "rpm"},
    ))  # fmt: skip
    assert parsed.mass == pytest.approx(0.030, rel=1e-15)
    assert parsed.inertia == pytest.approx((16.6e-7, 16.6e-7, 29.3e-7), rel=1e-15)
    assert parsed.arm_length == pytest.approx(0.046, rel=1e-15)
    assert parsed.speed_limit() == pytest.approx(6000 * 2 * math.pi / 60, rel=1e-15)


def test_thrust_to_weight_gives_the_plants_rotor_speed_limit():
    parsed = vehicle.parse(_table(thrust_to_weight=2.0))
    assert parsed.speed_limit() == pytest.approx(plant.rotor_speed_limit(2.0), rel=1e-12)
    assert vehicle.Vehicle.paper().speed_limit() is None


@pytest.mark.parametrize(
    "changes, named",
    [
        ({"mass": None}, "vehicle.mass: missing"),
        ({"mass": 0.74}, "vehicle.mass: expected { value = ..., unit = ... }"),
        ({"mass": {"value": 0.74}}, "vehicle.mass: missing unit"),
        ({"mass": {"value": 0.74, "unit": "lb"}}, "vehicle.mass: unit 'lb' is not one of"),
        ({"mass": {"value": -0.74, "unit": "kg"}}, "vehicle.mass: every value must be finite"),
        ({"mass": {"value": math.nan, "unit": "kg"}}, "vehicle.mass: every value must be"),
        ({"mass": {"value": math.inf, "unit": "kg"}}, "vehicle.mass: every value must be"),
        ({"mass": {"value": "0.74", "unit": "kg"}}, "vehicle.mass: expected a number"),
        ({"inertia": {"value": [0.004, 0.004], "unit": "kg m^2"}},
         "vehicle.inertia: expected a list of 3 numbers"),
        ({"inertia": {"value": [0.004, 0.0, 0.0084], "unit": "kg m^2"}},
         "vehicle.inertia: every value must be finite and > 0"),
        ({"gravity": {"value": 9.81, "unit": "m/s^2", "sigma": 1}},
         "vehicle.gravity: unknown key(s) sigma"),
        ({"wingspan": {"value": 1, "unit": "m"}}, "vehicle: unknown field(s) wingspan"),
        ({"thrust_to_weight": 1.0}, "vehicle.thrust_to_weight: expected a number > 1"),
        ({"thrust_to_weight": 0.5}, "vehicle.thrust_to_weight: expected a number > 1"),
        ({"thrust_to_weight": 2.0, "rotor_speed_limit": {"value": 40, "unit": "rad/s"}},
         "give rotor_speed_limit or thrust_to_weight, not both"),
        ({"rotor_speed_limit": {"value": 40, "unit": "rad"}},
         "vehicle.rotor_speed_limit: unit 'rad' is not one of"),
    ],
)  # fmt: skip
def test_a_bad_vehicle_is_one_error_naming_its_field(changes, named):
    with pytest.raises(vehicle.VehicleError) as caught:
        vehicle.parse(_table(**changes), "v.toml")
    message = str(caught.value)
    assert message.startswith("v.toml is not a usable vehicle file:") and named in message
    assert message.count("\n") == 1  # the one problem, on a line of its own


def test_every_problem_of_a_file_in_one_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[vehicle]\nmass = { value = -1, unit = "kg" }\n')
    with pytest.raises(vehicle.VehicleError) as caught:
        vehicle.load(bad)
    message = str(caught.value)
    assert "vehicle.mass: every value must be finite and > 0" in message
    for name in set(vehicle.FIELDS) - {"mass"}:
        assert f"vehicle.{name}: missing" in message
    assert "missing [vehicle] table" in str(pytest.raises(vehicle.VehicleError,
                                                           vehicle.parse, {}).value)  # fmt: skip
    broken = tmp_path / "broken.toml"
    broken.write_text("[vehicle\n")
    with pytest.raises(vehicle.VehicleError, match="is not valid TOML"):
        vehicle.load(broken)
    with pytest.raises(vehicle.VehicleError, match="cannot read the vehicle file"):
        vehicle.load(tmp_path / "none.toml")


def test_a_vehicle_flies_as_the_paper_plant_with_its_values():
    """A vehicle of another mass and inertia: its draws and rollout are those of the
    paper's plant with those values put in by hand (float64: the draws' uncertainty
    multiplies the vehicle's values; the controller's model is the vehicle's)."""
    import jax

    from fojax import observers, scenarios, simulator
    from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains

    mass, inertia = 1.1, (0.006, 0.0065, 0.011)
    heavy = vehicle.parse(_table(mass={"value": mass, "unit": "kg"},
                                 inertia={"value": list(inertia), "unit": "kg m^2"}))  # fmt: skip
    scenario = dataclasses.replace(scenarios.get_scenario(2), horizon=0.2)
    config = simulator.SimulationConfig(dt=1e-3, horizon=0.2, save_every=100)
    keys = scenarios.draw_keys(3, range(4))
    dtype = jax.numpy.float64
    theirs = scenarios.sample_draws(scenario.on(heavy), keys, config.dt, dtype)
    paper = scenarios.sample_draws(scenario, keys, config.dt, dtype)
    nominal = plant.nominal_params(dtype)
    by_hand_mass = paper.params.mass / nominal.mass * mass
    by_hand_inertia = paper.params.inertia / nominal.inertia[:, None] * np.asarray(inertia)[:, None]
    np.testing.assert_allclose(theirs.params.mass, by_hand_mass, rtol=1e-14)
    np.testing.assert_allclose(theirs.params.inertia, by_hand_inertia, rtol=1e-14)
    model = nominal._replace(mass=jax.numpy.asarray(mass, dtype),
                             inertia=jax.numpy.asarray(inertia, dtype))  # fmt: skip
    by_hand = paper._replace(params=paper.params._replace(mass=by_hand_mass,
                                                          inertia=by_hand_inertia))  # fmt: skip
    controller = AFONFTSMC(dt=config.dt, horizon=config.horizon)
    gains = paper_gains(dtype)
    ise = observers.TrackingISE(config.dt)
    got = simulator.rollout(controller, gains, scenario.on(heavy).plant_params(dtype),
                            scenario.on(heavy), theirs, config, ise)  # fmt: skip
    want = simulator.rollout(controller, gains, model, scenario, by_hand, config, ise)
    np.testing.assert_allclose(got.final_state, want.final_state, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(got.outputs, want.outputs, rtol=1e-12, atol=1e-15)
    # and the vehicle matters: the paper's plant ends elsewhere
    other = simulator.rollout(controller, gains, nominal, scenario, paper, config, ise)
    assert not np.allclose(other.final_state, got.final_state, rtol=1e-6)


SIMULATE = ["simulate", "--scenario", "2", "--controller", "afonftsmc", "--draws", "3",
            "--horizon", "0.3", "--keep", "0", "--quiet"]  # fmt: skip


def test_simulate_with_the_paper_file_equals_the_default_draw_for_draw(tmp_path, capsys):
    from fojax import cli

    assert cli.main([*SIMULATE, "--out", str(tmp_path / "a")]) == 0
    assert cli.main([*SIMULATE, "--vehicle", PAPER_FILE, "--out", str(tmp_path / "b")]) == 0
    a, b = (np.load(tmp_path / name / "draws.npz") for name in "ab")
    assert sorted(a.files) == sorted(b.files)
    for name in a.files:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    authority = {"max_torque": None, "thrust_to_weight": None, "hover_speed_rad_s": 24.59}
    assert summary["vehicle"] == {**vehicle.Vehicle.paper().to_dict(), **authority} | {
        "hover_speed_rad_s": pytest.approx(24.59, abs=0.01)}
    default = json.loads((tmp_path / "a" / "summary.json").read_text())["vehicle"]
    assert default == summary["vehicle"]
    out = capsys.readouterr().out
    assert "vehicle: the paper's quadrotor (Section V) (m = 0.74 kg, '+' at 0.21 m)" in out
    assert "vehicle authority: ideal actuators (no rotor speed limit); hover at 24.6 rad/s" in out


COMMANDS = {
    "simulate": SIMULATE[1:],
    "tune": ["--scenario", "2", "--controller", "afonftsmc"],
    "reproduce": ["--draws", "2"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize(
    "text, named",
    [
        ('[vehicle]\nmass = { value = 0.74, unit = "lb" }\n', "vehicle.mass: unit 'lb' is not"),
        ("[vehicle\nmass = 1\n", "is not valid TOML"),
        (None, "does not exist"),
    ],
)  # fmt: skip
def test_a_bad_vehicle_file_stops_every_command_before_anything_is_written(
    tmp_path, capsys, command, text, named
):
    import importlib

    from conftest import usage_error

    module = importlib.import_module(f"fojax.cli.{command}")
    bad = tmp_path / "bad.toml"
    if text is not None:
        bad.write_text(text)
    out = tmp_path / "out"
    err = usage_error(capsys, module.main, [*COMMANDS[command], "--vehicle", str(bad), "--out",
                                            str(out)])  # fmt: skip
    assert "argument --vehicle" in err and named in err and "Traceback" not in err
    assert not out.exists()


def test_the_documented_vehicle_file_is_the_paper_file():
    import pathlib
    import re
    import tomllib

    text = pathlib.Path("docs/model.md").read_text()
    (block,) = [b for b in re.findall(r"```toml\n(.*?)```", text, re.S) if "[vehicle]" in b]
    assert vehicle.parse(tomllib.loads(block)) == vehicle.Vehicle.paper()


TUNE = ["tune", "--scenario", "2", "--controller", "afonftsmc", "--horizon", "0.3", "--seed",
        "5", "--dtype", "float64", "--init", "naive", "--method", "cma-es", "--steps", "1",
        "--popsize", "4", "--draws", "2", "--validation-draws", "2", "--eval-draws", "2",
        "--quiet"]  # fmt: skip


def test_tune_with_the_paper_file_equals_the_default_and_resume_names_it(tmp_path, capsys):
    from conftest import usage_error

    from fojax import cli
    from fojax.cli import tune
    from fojax.controllers import gains_io

    assert cli.main([*TUNE, "--out", str(tmp_path / "a")]) == 0
    assert cli.main([*TUNE, "--vehicle", PAPER_FILE, "--out", str(tmp_path / "b")]) == 0
    (_, a, _), (_, b, metadata) = (gains_io.load_gains(tmp_path / d / "gains.json") for d in "ab")
    for field in a._fields:
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    evaluations = [json.loads((tmp_path / d / "evaluation.json").read_text()) for d in "ab"]
    assert evaluations[0]["tuned"] == evaluations[1]["tuned"]
    assert metadata["settings"]["objective"]["problem"]["vehicle"]["mass"] == 0.74
    heavy = tmp_path / "heavy.toml"
    heavy.write_text(Path(PAPER_FILE).read_text().replace("value = 0.74,", "value = 0.9,"))
    err = usage_error(capsys, tune.parse_args, [*TUNE[1:], "--vehicle", str(heavy), "--resume",
                                                "--out", str(tmp_path / "b")])  # fmt: skip
    assert "objective.problem.vehicle.mass: checkpoint 0.74, now 0.9" in err


@pytest.mark.slow
def test_reproduce_with_the_paper_file_equals_the_default(tmp_path):
    from fojax import cli

    argv = ["reproduce", "--draws", "2", "--device-batch", "2", "--keep", "0", "--horizon",
            "0.2", "--seed", "4", "--scenarios", "2", "--quiet"]  # fmt: skip
    assert cli.main([*argv, "--out", str(tmp_path / "a")]) == 0
    assert cli.main([*argv, "--vehicle", PAPER_FILE, "--out", str(tmp_path / "b")]) == 0
    a, b = (json.loads((tmp_path / d / "report.json").read_text()) for d in "ab")

    def timeless(tree):  # every number but the wall times
        if isinstance(tree, dict):
            return {k: timeless(v) for k, v in tree.items() if k != "wall_time_s"}
        return [timeless(v) for v in tree] if isinstance(tree, list) else tree

    assert timeless(a["scenarios"]) == timeless(b["scenarios"])
    assert timeless(a["claims"]) == timeless(b["claims"])
    assert vehicle.Vehicle.paper().to_dict().items() <= b["settings"]["vehicle"].items()
    assert b["settings"]["vehicle"]["max_torque"] is None


@pytest.mark.parametrize(
    "uncertainty, named",
    [
        ({"gravity": {"value": 1, "unit": "%"}}, "uncertainty: unknown field(s) gravity"),
        ({"mass": 0.1}, "uncertainty.mass: expected { value = ..., unit = ... } with a unit"),
        ({"mass": {"value": 5, "unit": "kg"}}, "uncertainty.mass: unit 'kg' is not one of"),
        ({"mass": {"value": 100, "unit": "%"}}, "uncertainty.mass: expected a relative "
         "half-width below 100 %, got 100 %"),
        ({"mass": {"value": -0.1, "unit": "1"}}, "uncertainty.mass: every value must be finite "
         "and > 0"),
        ({"mass": {"value": "5", "unit": "%"}}, "uncertainty.mass: expected a number"),
        ("5 %", "uncertainty: expected a table of fields"),
    ],
)  # fmt: skip
def test_a_bad_uncertainty_is_one_error_naming_its_field(uncertainty, named):
    with pytest.raises(vehicle.VehicleError) as caught:
        vehicle.parse({**_table(), "uncertainty": uncertainty}, "v.toml")
    message = str(caught.value)
    assert named in message and message.count("\n") == 1


def test_a_vehicles_uncertainty_varies_each_draws_plant_within_its_bounds():
    import jax.numpy as jnp

    from fojax import draws, scenarios

    table = {**_table(), "uncertainty": {"thrust_factor": {"value": 10, "unit": "%"},
                                         "inertia": {"value": 0.2, "unit": "1"}}}  # fmt: skip
    uncertain = vehicle.parse(table)
    assert uncertain.uncertainty == (("inertia", 0.2), ("thrust_factor", 0.1))
    assert uncertain.to_dict()["uncertainty"] == {"inertia": 0.2, "thrust_factor": 0.1}
    base = scenarios.get_scenario(2)
    keys = scenarios.draw_keys(0, jnp.arange(2000))
    plain = draws.sample_draws(base.on(vehicle.parse(_table())), keys, 1e-3, jnp.float64)
    varied = draws.sample_draws(base.on(uncertain), keys, 1e-3, jnp.float64)
    paper = vehicle.Vehicle.paper()
    thrust = np.asarray(varied.params.thrust_factor) / paper.thrust_factor
    inertia = np.asarray(varied.params.inertia) / np.asarray(paper.inertia)[:, None]
    # U[1 - a, 1 + a]: inside the bounds, spread over them, mean 1, axes independent
    assert thrust.min() >= 0.9 and thrust.max() <= 1.1 and np.ptp(thrust) > 0.19
    assert abs(thrust.mean() - 1) < 3 * 0.1 / math.sqrt(3 * 2000)
    assert inertia.min() >= 0.8 and inertia.max() <= 1.2
    assert abs(np.corrcoef(inertia[0], inertia[1])[0, 1]) < 0.1
    # the other fields and the scenario's own processes are drawn as without it
    np.testing.assert_array_equal(varied.params.mass, plain.params.mass)
    np.testing.assert_array_equal(varied.params.arm_length, plain.params.arm_length)
    np.testing.assert_array_equal(varied.drag_multipliers, plain.drag_multipliers)
    np.testing.assert_array_equal(varied.noise_accel, plain.noise_accel)
