"""References from waypoints: the quintic spline through them, its smoothness and ends,
its peaks against the exact curve, and one error per bad file."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax import reference, scenarios

SAMPLED = np.arange(0.0, 81.0, 2.0)


def _paper_waypoints(ends="not-a-knot"):
    """(54)-(55) sampled every 2 s over 80 s."""
    values = np.array([np.asarray(scenarios.reference_54_55(jnp.asarray(t))) for t in SAMPLED])
    return reference.Waypoints(tuple(SAMPLED), tuple(map(tuple, values[:, :3])),
                               tuple(values[:, 3]), ends=ends), values  # fmt: skip


def _table(**changes):
    table = {"time": {"value": [0, 5, 10], "unit": "s"}, "x": {"value": [0, 1, 1], "unit": "m"},
             "y": {"value": [0, 0, 1], "unit": "m"}, "z": {"value": [0, 1, 1], "unit": "m"},
             "yaw": {"value": [0, 0, 0], "unit": "rad"}}  # fmt: skip
    for name, value in changes.items():
        if value is None:
            table.pop(name)
        else:
            table[name] = value
    return {"description": "test", "reference": table}


def test_the_spline_passes_through_the_waypoints_with_four_continuous_derivatives():
    waypoints, values = _paper_waypoints("rest")
    spline = waypoints.reference()
    at = np.array([np.asarray(spline(jnp.asarray(t))) for t in SAMPLED])
    np.testing.assert_allclose(at, values, atol=1e-12)
    inner = SAMPLED[1:-1]
    for order in range(5):  # value and four derivatives agree on both sides of each break
        left = spline.derivative(inner - 1e-9, order)
        right = spline.derivative(inner + 1e-9, order)
        scale = np.max(np.abs(left)) + 1e-12
        assert np.max(np.abs(left - right)) < 1e-6 * scale + 1e-7, order
    # at rest at both ends, then held
    for t in (0.0, SAMPLED[-1]):
        _, velocity, acceleration = scenarios.reference_with_derivatives(spline, jnp.asarray(t))
        np.testing.assert_allclose(velocity, 0, atol=1e-12)
        np.testing.assert_allclose(acceleration, 0, atol=1e-12)
    np.testing.assert_allclose(spline(jnp.asarray(200.0)), values[-1], atol=1e-12)


def test_autodiff_derivatives_equal_the_polynomials_and_jit_equals_eager():
    spline = _paper_waypoints()[0].reference()
    times = np.linspace(0, 80, 97)
    _, velocity, acceleration = jax.vmap(lambda t: scenarios.reference_with_derivatives(spline, t))(
        jnp.asarray(times)
    )
    np.testing.assert_allclose(velocity, spline.derivative(times, 1), atol=1e-12)
    np.testing.assert_allclose(acceleration, spline.derivative(times, 2), atol=1e-12)
    eager = np.array([np.asarray(spline(jnp.asarray(t))) for t in times])
    np.testing.assert_allclose(jax.jit(jax.vmap(spline))(jnp.asarray(times)), eager, atol=1e-14)


def test_sampled_from_the_paper_curve_it_follows_the_curve_and_its_peaks():
    waypoints, _ = _paper_waypoints()
    spline = waypoints.reference()
    times = np.linspace(0, 80, 1601)
    exact = np.array([np.asarray(scenarios.reference_54_55(jnp.asarray(t))) for t in times])
    np.testing.assert_allclose(np.asarray(jax.vmap(spline)(jnp.asarray(times))), exact, atol=1e-4)
    # (54)-(55): |v| = (pi/20) sqrt(0.25 + 4 sin^2), |a| = (pi/20)^2 sqrt(0.25 + 4 cos^2)
    w = math.pi / 20
    peaks = waypoints.peaks()
    assert peaks["speed"] == pytest.approx(w * math.sqrt(4.25), rel=1e-3)
    assert peaks["acceleration"] == pytest.approx(w * w * math.sqrt(4.25), rel=1e-3)
    tilt = max(math.atan2(w * w * 0.5, 9.81 + w * w * 2 * c) for c in np.cos(w * times))
    assert peaks["tilt"] == pytest.approx(tilt, rel=1e-2)


def test_a_waypoint_reference_flies_in_a_scenario():
    from fojax import observers, plant, simulator
    from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains

    spline = _paper_waypoints()[0].reference()
    base = dataclasses.replace(scenarios.get_scenario(2), horizon=0.2)
    config = simulator.SimulationConfig(dt=1e-3, horizon=0.2, save_every=100)
    keys = scenarios.draw_keys(0, range(2))
    controller = AFONFTSMC(dt=1e-3, horizon=0.2)
    runs = [
        simulator.rollout_from_keys(
            controller,
            paper_gains(),
            plant.nominal_params(),
            s,
            keys,
            config,
            observers.TrackingISE(config.dt),
        )  # fmt: skip
        for s in (base, dataclasses.replace(base, reference=spline))
    ]
    # the spline is within 1e-4 m of (54)-(55): the closed loops' positions and tracking
    # errors agree to about that
    np.testing.assert_allclose(runs[1].final_state[:3], runs[0].final_state[:3], atol=1e-3)
    np.testing.assert_allclose(runs[1].outputs, runs[0].outputs, rtol=0.05, atol=1e-6)


@pytest.mark.parametrize(
    "changes, named",
    [
        ({"time": None}, "reference.time: missing"),
        ({"x": [0, 1, 1]}, "reference.x: expected { value = [...], unit = ... }"),
        ({"x": {"value": [0, 1, 1], "unit": "ft"}}, "reference.x: unit 'ft' is not one of"),
        ({"x": {"value": [0, 1], "unit": "m"}}, "the lists differ in length"),
        ({"y": {"value": [0, math.nan, 1], "unit": "m"}}, "reference.y: every value must be"),
        ({"z": {"value": [0, "1", 1], "unit": "m"}}, "reference.z: expected a list of numbers"),
        ({"time": {"value": [0, 5, 5], "unit": "s"}}, "reference.time: times must increase"),
        ({"time": {"value": [0, 5, 4], "unit": "s"}}, "waypoint 2 (4.0 s) is not after"),
        ({"time": {"value": [1, 5, 10], "unit": "s"}}, "the first waypoint must be at 0 s"),
        ({"speed": {"value": [1], "unit": "m/s"}}, "reference: unknown list(s) speed"),
        ({"ends": "free"}, "reference.ends: expected one of rest, not-a-knot"),
        ({"ends": "not-a-knot"}, "not-a-knot needs at least 6 waypoints"),
    ],
)  # fmt: skip
def test_a_bad_reference_is_one_error_naming_its_list(changes, named):
    with pytest.raises(reference.ReferenceError) as caught:
        reference.parse(_table(**changes), "r.toml")
    message = str(caught.value)
    assert message.startswith("r.toml is not a usable reference file:") and named in message
    assert message.count("\n") == 1


def test_units_convert_and_files_load(tmp_path):
    parsed = reference.parse(_table(x={"value": [0, 100, 100], "unit": "cm"},
                                    yaw={"value": [0, 90, 90], "unit": "deg"}))  # fmt: skip
    assert [p[0] for p in parsed.positions] == [0.0, 1.0, 1.0]
    assert parsed.yaw[1] == pytest.approx(math.pi / 2)
    good = tmp_path / "r.toml"
    good.write_text('[reference]\ntime = { value = [0, 4], unit = "s" }\n'
                    + "".join(f'{a} = {{ value = [0, 1], unit = "m" }}\n' for a in "xyz")
                    + 'yaw = { value = [0, 0], unit = "rad" }\n')  # fmt: skip
    assert reference.load(good).times == (0.0, 4.0)
    broken = tmp_path / "broken.toml"
    broken.write_text("[reference\n")
    with pytest.raises(reference.ReferenceError, match="is not valid TOML"):
        reference.load(broken)
    with pytest.raises(reference.ReferenceError, match="missing \\[reference\\] table"):
        reference.parse({})


SIMULATE = ["--scenario", "2", "--controller", "afonftsmc", "--draws", "4", "--horizon", "10",
            "--keep", "0", "--quiet"]  # fmt: skip


def _sampled_file(path, span=10.0, step=1.0, climb=1.0):
    """(54)-(55) sampled every ``step`` s over ``span`` s; ``climb`` scales ``z_r`` (a
    negative one dives: below -g its acceleration asks for a tilt past 90 deg)."""
    t = np.arange(0.0, span + 1e-9, step)
    w = math.pi * t / 20
    lists = {"x": 0.5 * np.cos(w), "y": 0.5 * np.sin(w), "z": climb * (2 - 2 * np.cos(w))}
    text = '[reference]\nends = "not-a-knot"\n'
    text += f'time = {{ value = {t.tolist()}, unit = "s" }}\n'
    text += "".join(f'{k} = {{ value = {v.tolist()}, unit = "m" }}\n' for k, v in lists.items())
    text += f'yaw = {{ value = {[0.5] * t.size}, unit = "rad" }}\n'
    path.write_text(text)
    return path


def test_simulate_with_sampled_waypoints_tracks_as_the_built_in_reference(tmp_path, capsys):
    import json

    from fojax.cli import simulate

    file = _sampled_file(tmp_path / "r.toml")
    assert simulate.main([*SIMULATE, "--out", str(tmp_path / "a")]) == 0
    assert simulate.main([*SIMULATE, "--reference", str(file), "--out", str(tmp_path / "b")]) == 0
    rmse = [json.loads((tmp_path / d / "summary.json").read_text())["controllers"]["afonftsmc"]
            ["metrics"]["position_rmse"]["mean"] for d in "ab"]  # fmt: skip
    assert rmse[1] == pytest.approx(rmse[0], rel=0.01)
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["reference"]["ends"] == "not-a-knot" and len(summary["reference"]["times"]) == 11
    assert "reference: 11 waypoints over 10 s; peak speed" in capsys.readouterr().out


def test_bad_references_stop_simulate_before_anything_is_written(tmp_path, capsys):
    from conftest import usage_error

    from fojax.cli import simulate

    out = tmp_path / "out"
    late = _sampled_file(tmp_path / "late.toml", span=12.0)
    err = usage_error(
        capsys, simulate.main, [*SIMULATE, "--reference", str(late), "--out", str(out)]
    )
    assert "its last waypoint (12 s) is after the end of the run (10 s)" in err
    steep = _sampled_file(tmp_path / "steep.toml", climb=-1e3)
    err = usage_error(
        capsys, simulate.main, [*SIMULATE, "--reference", str(steep), "--out", str(out)]
    )
    assert "at or beyond the plant's limit of 90 deg" in err
    bad = tmp_path / "bad.toml"
    bad.write_text('[reference]\ntime = { value = [0, 1], unit = "min" }\n')
    err = usage_error(
        capsys, simulate.main, [*SIMULATE, "--reference", str(bad), "--out", str(out)]
    )
    assert "argument --reference" in err and "reference.time: unit 'min' is not one of" in err
    assert not out.exists()


def test_the_documented_reference_file_parses_and_the_example_is_the_paper_curve():
    import pathlib
    import re
    import tomllib

    text = pathlib.Path("docs/model.md").read_text()
    (block,) = [b for b in re.findall(r"```toml\n(.*?)```", text, re.S) if "[reference]" in b]
    documented = reference.parse(tomllib.loads(block))
    assert documented.ends == "rest" and documented.times[-1] == 25.0
    assert documented.peaks()["tilt"] < 0.5 * math.pi
    example = reference.load("examples/references/paper_54_55.toml")
    assert example.times == tuple(SAMPLED)
    expected = _paper_waypoints()[0]
    np.testing.assert_allclose(example.positions, expected.positions, atol=1e-6)
    np.testing.assert_allclose(example.yaw, expected.yaw, atol=0)


def _builtin_file(path, name="paper-54-55", extra=""):
    path.write_text(f'[reference]\nbuiltin = "{name}"\n{extra}')
    return path


def test_a_builtin_reference_is_the_scenarios_function_with_its_analytic_peaks(tmp_path):
    from fojax import reference, scenarios

    found = reference.load(_builtin_file(tmp_path / "b.toml"))
    assert isinstance(found, reference.Builtin) and found.end is None
    assert found.reference() is scenarios.reference_54_55
    assert found.description == reference.BUILTINS["paper-54-55"][1]
    # (54)-(55) over 10 s, w = pi / 20: speed^2 = (0.5 w)^2 + (2 w sin(w t))^2, largest
    # at 10 s; acceleration w^2 sqrt(0.5^2 + (2 cos(w t))^2), largest at 0 s; the tilt
    # atan2(0.5 w^2, g + 2 w^2 cos(w t)), largest at 10 s.
    w = math.pi / 20
    peaks = found.peaks(10.0)
    assert peaks["speed"] == pytest.approx(w * math.hypot(0.5, 2.0), rel=1e-5)
    assert peaks["acceleration"] == pytest.approx(w**2 * math.hypot(0.5, 2.0), rel=1e-5)
    assert peaks["tilt"] == pytest.approx(math.atan2(0.5 * w**2, 9.81), rel=1e-4)
    assert reference.load(_builtin_file(tmp_path / "c.toml", "paper-57")).reference() is (
        scenarios.reference_57
    )
    with pytest.raises(reference.ReferenceError, match="reference.builtin: expected one of"):
        reference.load(_builtin_file(tmp_path / "d.toml", "paper-56"))
    with pytest.raises(reference.ReferenceError, match="builtin names the whole reference; "
                       "remove ends"):  # fmt: skip
        reference.load(_builtin_file(tmp_path / "e.toml", extra='ends = "rest"\n'))


def test_simulate_with_the_builtin_file_equals_the_default_draw_for_draw(tmp_path, capsys):
    import json

    from fojax.cli import simulate

    file = _builtin_file(tmp_path / "r.toml")
    assert simulate.main([*SIMULATE, "--out", str(tmp_path / "a")]) == 0
    assert simulate.main([*SIMULATE, "--reference", str(file), "--out", str(tmp_path / "b")]) == 0
    a, b = (np.load(tmp_path / d / "draws.npz") for d in "ab")
    assert set(a.files) == set(b.files) and a.files
    for name in a.files:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["reference"]["builtin"] == "paper-54-55"
    assert summary["reference"]["peaks"]["speed_m_per_s"] == pytest.approx(0.3238, abs=1e-4)
    assert "reference: built-in paper-54-55; peak speed 0.324 m/s" in capsys.readouterr().out


TUNE = ["--scenario", "2", "--controller", "afonftsmc", "--horizon", "0.3", "--seed", "5",
        "--dtype", "float64", "--init", "naive", "--method", "cma-es", "--steps", "1",
        "--popsize", "4", "--draws", "2", "--validation-draws", "2", "--eval-draws", "2",
        "--quiet"]  # fmt: skip


def test_tune_flies_a_reference_file_and_a_resume_with_another_is_refused(tmp_path, capsys):
    from conftest import usage_error

    from fojax.cli import tune
    from fojax.controllers import gains_io

    builtin = _builtin_file(tmp_path / "b.toml")
    assert tune.main([*TUNE, "--out", str(tmp_path / "a")]) == 0
    assert tune.main([*TUNE, "--reference", str(builtin), "--out", str(tmp_path / "b")]) == 0
    (_, a, _), (_, b, metadata) = (gains_io.load_gains(tmp_path / d / "gains.json") for d in "ab")
    for field in a._fields:  # the built-in (54)-(55) is scenario 2's own reference
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert metadata["settings"]["objective"]["problem"]["reference"]["name"] == "paper-54-55"
    waypoints = _sampled_file(tmp_path / "w.toml", span=0.3, step=0.05)
    err = usage_error(capsys, tune.parse_args,
                      [*TUNE, "--reference", str(waypoints), "--resume", "--out",
                       str(tmp_path / "b")])  # fmt: skip
    assert 'objective.problem.reference.name: checkpoint "paper-54-55", now "<absent>"' in err
    late = _sampled_file(tmp_path / "late.toml", span=1.0, step=0.1)
    out = tmp_path / "c"
    err = usage_error(capsys, tune.parse_args,
                      [*TUNE, "--reference", str(late), "--out", str(out)])  # fmt: skip
    assert "its last waypoint (1 s) is after the end of the run (0.3 s)" in err
    assert "longer --horizon" in err and not out.exists()
