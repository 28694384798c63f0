"""What a vehicle and a reference can fly, checked before anything compiles: a vehicle
that cannot hover and a reference past the vehicle's thrust or tilt are one usage error
each, naming the numbers, with nothing written; the vehicle's authority printed and in
summary.json."""

import json
import math

import numpy as np
import pytest
from conftest import usage_error

from fojax import reference, vehicle
from fojax.cli import simulate, tune

SIMULATE = ["--scenario", "2", "--controller", "afonftsmc", "--draws", "2", "--horizon", "0.3",
            "--keep", "0", "--quiet", "--no-figures"]  # fmt: skip
TUNE = ["--scenario", "2", "--controller", "afonftsmc", "--quiet"]
IRIS = "examples/vehicles/iris.toml"
CRAZYFLIE = "examples/vehicles/crazyflie.toml"


def _waypoints(path, times, x=None, z=None):
    """A reference file through ``times`` with ``x`` and ``z`` lists (others still)."""
    zeros = [0.0] * len(times)
    lists = {"x": x or zeros, "y": zeros, "z": z or zeros}
    text = f'[reference]\ntime = {{ value = {list(times)}, unit = "s" }}\n'
    text += "".join(f'{k} = {{ value = {v}, unit = "m" }}\n' for k, v in lists.items())
    text += f'yaw = {{ value = {zeros}, unit = "rad" }}\n'
    path.write_text(text)
    return path


def test_the_iris_authority_is_printed_and_in_the_summary(tmp_path, capsys):
    assert simulate.main([*SIMULATE, "--vehicle", IRIS, "--out", str(tmp_path / "o")]) == 0
    record = json.loads((tmp_path / "o" / "summary.json").read_text())["vehicle"]
    assert record["max_torque"][:2] == pytest.approx([2.52, 1.56], rel=1e-2)
    assert record["thrust_to_weight"] == pytest.approx(1.632, rel=1e-3)
    assert len(record["vehicle"]["rotors"]) == 4
    assert record["vehicle"]["rotor_time_constant"] == 0.025
    out = capsys.readouterr().out
    assert "rotors as listed at 0.247 m, rotors lag 25 ms" in out
    assert ("vehicle authority: thrust-to-weight 1.63, largest torques roll 2.521, pitch "
            "1.561") in out


def test_the_published_vehicles_can_fly_the_papers_references():
    """Both published vehicles hover within their limits and fly (54)-(55) and (57)
    smoothed within their thrust and tilt."""
    for path in (IRIS, CRAZYFLIE):
        flown = vehicle.load(path)
        assert vehicle.hover_problems(flown) == []
        for name in ("paper-54-55", "paper-57-smoothed"):
            peaks = reference.Builtin(name).peaks(50.0)
            assert reference.problems_for(peaks, flown) == [], (path, name)


def test_a_requirement_limit_below_hover_stops_simulate_and_tune(tmp_path, capsys):
    file = tmp_path / "slow.toml"
    file.write_text('[settings]\nrotor_speed_limit = 20\n\n[[requirements]]\nname = "tilt"\n'
                    'metric = "max_tilt"\nmax = 30\nunit = "deg"\n')  # fmt: skip
    out = tmp_path / "out"
    for main, argv in ((simulate.main, SIMULATE), (tune.main, TUNE)):
        err = usage_error(capsys, main, [*argv, "--requirements", str(file), "--out", str(out)])
        assert ("the vehicle cannot fly: the requirement file's rotor limit: 20 rad/s (191 rpm) "
                "cannot lift the vehicle: hover needs 24.6 rad/s") in err, err  # fmt: skip
        assert "0.661 times the weight" in err and "Traceback" not in err
        assert not out.exists()


def test_a_reference_past_the_thrust_is_refused_unless_allowed(tmp_path, capsys):
    """A climb whose peak vertical acceleration asks about 1.5 weights of thrust, flown by
    a vehicle whose rotors give 1.2: refused naming both numbers; flown with the
    override."""
    t = np.arange(0.0, 6.0 + 1e-9, 0.5)
    climb = (5.0 * (1 - np.cos(math.pi * t / 3))).tolist()
    file = _waypoints(tmp_path / "climb.toml", t.tolist(), z=climb)
    peaks = reference.load(file).peaks()
    assert 1.2 < peaks["thrust"] < 2 and peaks["tilt"] < 1e-9
    weak = tmp_path / "weak.toml"
    weak.write_text(open("examples/vehicles/paper.toml").read() + "thrust_to_weight = 1.2\n")
    out = tmp_path / "out"
    given = ["--horizon", "6", "--reference", str(file), "--vehicle", str(weak)]
    for main, argv in ((simulate.main, SIMULATE), (tune.main, TUNE)):
        err = usage_error(capsys, main, [*argv, *given, "--out", str(out)])
        assert f"asks for {peaks['thrust']:.3g} times the weight in thrust" in err
        assert "the vehicle's rotors give 1.2 times it" in err
        assert "--allow-infeasible-reference" in err and not out.exists()
    assert simulate.main([*SIMULATE, *given, "--allow-infeasible-reference", "--out",
                          str(out)]) == 0  # fmt: skip


def test_a_reference_past_the_tilt_limit_is_refused_and_a_vehicle_may_raise_it(tmp_path, capsys):
    file = _waypoints(tmp_path / "dash.toml", [0.0, 1.0, 2.0], x=[0.0, 4.0, 8.0])
    tilt = math.degrees(reference.load(file).peaks()["tilt"])
    assert 45 < tilt < 70
    out = tmp_path / "out"
    argv = [*SIMULATE, "--horizon", "2", "--reference", str(file), "--out", str(out)]
    err = usage_error(capsys, simulate.main, argv)
    assert f"asks for a tilt of {tilt:.1f} deg, past the vehicle's 45 deg (the default" in err
    assert not out.exists()
    steep = tmp_path / "steep.toml"
    steep.write_text(open("examples/vehicles/paper.toml").read()
                     + 'tilt_limit = { value = 70, unit = "deg" }\n')  # fmt: skip
    assert simulate.main([*argv, "--vehicle", str(steep)]) == 0
    # the override without a reference changes nothing: refused
    err = usage_error(capsys, simulate.main, [*SIMULATE, "--allow-infeasible-reference",
                                              "--out", str(tmp_path / "o2")])  # fmt: skip
    assert "--allow-infeasible-reference applies with --reference only" in err


@pytest.mark.parametrize(
    "text, named",
    [
        ('rotor_speed_limit = { value = 10, unit = "rpm" }\n',
         "vehicle.rotor_speed_limit: 1.047 rad/s (10 rpm) cannot lift the vehicle"),
        ('configuration = "y"\n', "vehicle.configuration: expected one of 'plus', 'x'"),
        ('rotor_time_constant = { value = 20, unit = "min" }\n',
         "vehicle.rotor_time_constant: unit 'min' is not one of"),
    ],
)  # fmt: skip
def test_a_vehicle_that_cannot_fly_stops_every_command(tmp_path, capsys, text, named):
    import importlib

    paper = open("examples/vehicles/paper.toml").read()
    bad = tmp_path / "bad.toml"
    bad.write_text(paper + text)
    for command, argv in (("simulate", SIMULATE), ("tune", TUNE), ("reproduce", ["--draws", "2"])):
        module = importlib.import_module(f"fojax.cli.{command}")
        out = tmp_path / command
        err = usage_error(capsys, module.main, [*argv, "--vehicle", str(bad), "--out", str(out)])
        assert "argument --vehicle" in err and named in err and "Traceback" not in err
        assert err.count(named) == 1 and not out.exists()


def test_a_short_waypoint_piece_has_its_analytic_peaks(tmp_path):
    """Two waypoints at rest, 1 m apart in 10 ms: the quintic between them is the
    minimum-jerk move, peak speed 1.875 D/T and acceleration (10 / sqrt 3) D/T^2, however
    short the piece (sampled in every piece, not only per 10 ms)."""
    file = _waypoints(tmp_path / "jump.toml", [0.0, 0.01], x=[0.0, 1.0])
    peaks = reference.load(file).peaks()
    assert peaks["speed"] == pytest.approx(1.875 / 0.01, rel=1e-6)
    assert peaks["acceleration"] == pytest.approx(10 / math.sqrt(3) / 0.01**2, rel=1e-3)
    assert peaks["thrust"] == pytest.approx(math.hypot(peaks["acceleration"], 9.81) / 9.81,
                                            rel=1e-3)  # fmt: skip
