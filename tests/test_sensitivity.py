"""``python -m experiments.sensitivity``: the plan's sharing, the settings, the runner
against ``fojax.study.run``, the report's logic, one tiny end-to-end run."""

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import run_python, usage_error

from experiments import sensitivity, sensitivity_report


def _setting(key):
    return next(s for s in sensitivity.SETTINGS if s.key == key)


# ------------------------------------------------------------------------ settings


def test_rotor_speed_limit_gives_twice_the_weight():
    w_max = sensitivity.rotor_speed_limit()
    assert w_max == pytest.approx(math.sqrt(2 * 0.74 * 9.81 / (4 * 3e-3)))
    assert w_max == pytest.approx(34.78, abs=0.01)
    hover = sensitivity.rotor_speed_limit(1.0)
    assert hover == pytest.approx(24.6, abs=0.05)
    config = sensitivity.simulation_config(_setting("rotor-limited"), 2.0)
    assert config.rotor_speed_limit == pytest.approx(w_max)
    assert sensitivity.simulation_config(_setting("default"), 2.0).rotor_speed_limit is None


def test_scenario_variants():
    from fojax import scenarios

    loud = sensitivity.scenario_variant(2, "sigma-x5", 3.0)
    assert loud.horizon == 3.0
    assert loud.noise_std_position == pytest.approx(0.5)
    assert loud.noise_std_attitude == pytest.approx(0.5)
    smooth = sensitivity.scenario_variant(3, "smoothed", 3.0)
    assert smooth.reference is scenarios.reference_57_smoothed
    assert sensitivity.scenario_variant(3, None, 3.0).reference is scenarios.reference_57
    with pytest.raises(ValueError, match="unknown scenario variant"):
        sensitivity.scenario_variant(1, "louder", 3.0)


def test_every_choice_of_the_issue_is_a_setting():
    keys = set(sensitivity.SETTING_KEYS)
    assert {
        "default",
        "dt-0.1ms",
        "guard-0.5g",
        "filter-25",
        "filter-100",
        "oustaloup",
        "sat",
        "rotor-limited",
        "s3-smoothed",
        "sigma-x5",
        "tuned",
        "float64",
    } <= keys
    for setting in sensitivity.SETTINGS:
        assert setting.reference in ("", *keys)


# ----------------------------------------------------------------------------- plan


def test_plan_shares_programs_and_runs():
    plan = sensitivity.make_plan(sensitivity.SETTINGS, 30.0, 32, 16, 0)
    assert len(plan.jobs) == 41  # 5 default, 5 each for dt, guard, 2 filters, rotor, f64,
    # 2 Oustaloup (AFONFTSMC, FOBSMC), 4 sat (not the FL)

    def run(key, scenario, name):
        return plan.cells[(key, scenario, name)][0]

    default = {n: run("default", 1, n).job for n in plan.controllers}
    # The default programs carry the smoothed scenario 3 and scenario 2 with sigma x5.
    for job in default.values():
        assert len(job.members) == 5 and job.draws == 32
    for s in (1, 2, 3):
        for n in plan.controllers:
            assert run("tuned", s, n).job is run("default", s, n).job
            assert run("tuned", s, n) is not run("default", s, n)
            assert run("default-reduced", s, n) is run("default", s, n)
            assert plan.cells[("default-reduced", s, n)][1] == 16
    # Settings that leave a controller unchanged reuse its default runs.
    for s in (1, 2, 3):
        assert run("sat", s, "fl") is run("default", s, "fl")
        for n in ("anftsmc", "bsmc", "fl"):
            assert run("oustaloup", s, n) is run("default", s, n)
        assert run("oustaloup", s, "afonftsmc") is not run("default", s, "afonftsmc")
    # Scenario settings reuse the default's other scenarios.
    assert run("s3-smoothed", 1, "fl") is run("default", 1, "fl")
    assert run("s3-smoothed", 3, "fl") is not run("default", 3, "fl")
    assert run("s3-smoothed", 3, "fl").job is default["fl"]
    assert run("sigma-x5", 2, "bsmc").job is default["bsmc"]
    assert run("sigma-x5", 1, "bsmc") is run("default", 1, "bsmc")
    # The 0.1 ms step: its own programs, fewer draws, the controllers' step too.
    job = run("dt-0.1ms", 1, "afonftsmc").job
    assert job.config.dt == 1e-4 and job.controller.dt == 1e-4 and job.draws == 16
    assert {j.dtype for j in plan.jobs} == {"float32", "float64"}


def test_lanes_cover_every_program_once_float64_apart():
    plan = sensitivity.make_plan(sensitivity.SETTINGS, 30.0, 32, 16, 0)
    lanes = sensitivity.assign_lanes(plan, 2)
    assigned = sorted(i for jobs in lanes.values() for i in jobs)
    assert assigned == list(range(len(plan.jobs)))
    assert all(plan.jobs[i].dtype == "float64" for i in lanes["f64"])
    assert all(plan.jobs[i].dtype == "float32" for k in ("0", "1") for i in lanes[k])
    tuned = [j.index for j in plan.jobs if any(r.gains == "tuned" for r in j.runs)]
    assert lanes["0"][: len(tuned)] == tuned


def test_run_keys_are_the_same_in_another_process():
    plan = sensitivity.make_plan(sensitivity.SETTINGS[:4], 0.2, 3, 2, 0)
    keys = [sensitivity.run_key(r, None, 0) for r in plan.runs]
    assert len(set(keys)) == len(keys)
    code = (
        "from experiments import sensitivity as s; "
        "p = s.make_plan(s.SETTINGS[:4], 0.2, 3, 2, 0); "
        "print(' '.join(s.run_key(r, None, 0) for r in p.runs))"
    )
    assert run_python("-c", code).split() == keys


# --------------------------------------------------------------------------- runner


def test_union_runner_equals_study_run_float64():
    """A member of the study's union program gives fojax.study.run's numbers for its
    scenario alone (float64)."""
    import jax.numpy as jnp

    from fojax import make_controller, study

    horizon = 0.05
    setting = _setting("default")
    config = sensitivity.simulation_config(setting, horizon)
    controller = make_controller("fobsmc", dt=config.dt, horizon=horizon)
    s1, s3 = (sensitivity.scenario_variant(i, None, horizon) for i in (1, 3))
    job = sensitivity.Job(0, controller, config, "float64", members=[s1, s3], draws=3)
    run = sensitivity.Run(job, "ours", s3)
    job.runs.append(run)
    compiled, _ = sensitivity.compile_job(job)
    gains = controller.default_gains(jnp.float64)
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        sensitivity.execute(compiled, run, gains, 0, Path(tmp))
        status, mine = study.ChunkStore.existing(tmp).read(3)
    alone = study.run(
        controller,
        gains,
        s3,
        config,
        draws=3,
        seed=0,
        device_batch=3,
        keep=0,
        progress=False,
        dtype=jnp.float64,
        metrics_config=sensitivity.metrics_config(config),
    )
    np.testing.assert_array_equal(status, alone.status)
    for name, values in alone.per_draw.items():
        np.testing.assert_allclose(mine[name], values, rtol=1e-12, atol=1e-12, err_msg=name)


# --------------------------------------------------------------------------- report


def _claims(verdicts, outcomes=None):
    ids = list(sensitivity_report.SHORT_CLAIMS)
    claims = []
    for cid, verdict in zip(ids, verdicts, strict=True):
        claim = {"id": cid, "verdict": verdict}
        if cid not in ("R2-chatter-free", "C-finite-time"):
            comps = [
                {"controller": "fl", "metric": "position_rmse", "outcome": o}
                for o in (outcomes or {}).get(cid, ["better"])
            ]
            claim["comparisons"] = comps
            claim["counts"] = {
                k: sum(c["outcome"] == k for c in comps)
                for k in ("better", "worse", "equivalent", "inconclusive")
            }
        claims.append(claim)
    return claims


def test_flips_and_outcome_changes_against_each_reference():
    plan = sensitivity.make_plan(
        [_setting(k) for k in ("default", "default-reduced", "dt-0.1ms", "sat")], 0.2, 3, 2, 0
    )
    base = ["does not hold"] * 5 + ["does not hold", "does not hold"]
    evaluated = {
        "default": {"claims": _claims(base)},
        "default-reduced": {"claims": _claims(["inconclusive"] + base[1:])},
        "dt-0.1ms": {"claims": _claims(["inconclusive"] + base[1:])},
        "sat": {
            "claims": _claims(base[:5] + ["holds", "does not hold"], {"S1-transient": ["worse"]})
        },
    }
    found = sensitivity_report.flips(plan, evaluated)
    # dt is compared with the default on its own draws: no flip there.
    assert found == {"R2-chatter-free": [("sat", "does not hold", "holds")]}
    changes = sensitivity_report.outcome_changes(plan, evaluated)
    assert changes["dt-0.1ms"] == []
    assert changes["sat"] == [("S1-transient", "fl", "position_rmse", "better", "worse")]


def _result(values, status=None):
    from fojax import study

    values = np.asarray(values, float)
    n = values.size
    per_draw = {"position_rmse": values, "chattering": np.ones((n, 4))}
    return study.MonteCarloResult(
        "x", np.zeros(n, np.int32) if status is None else status, per_draw, None, 0.0, 0.0
    )


def test_precision_table_measures_the_float32_shift_against_the_margin():
    plan = sensitivity.make_plan(
        [_setting("default"), _setting("float64")], 10.0, 4, 2, 0, ("afonftsmc", "fl")
    )
    results = {}
    for s in (1, 2, 3):
        for name in plan.controllers:
            base = np.array([0.1, 0.2, 0.3, 0.4])
            shift = 0.004 if (s, name) == (3, "fl") else 0.0
            results[("float64", s, name)] = _result(base)
            results[("default", s, name)] = _result(base + shift)
    rows = {r["metric"]: r for r in sensitivity_report.precision_table(plan, results)}
    row = rows["position_rmse"]
    # margin: max(1 mm, 5 % of 0.25) = 12.5 mm; shift 4 mm -> 0.32 of it: not trusted.
    assert row["worst"]["scenario"] == 3 and row["worst"]["controller"] == "fl"
    assert row["worst"]["shift_over_margin"] == pytest.approx(0.004 / 0.0125)
    assert not row["trusted"]
    assert rows["chattering_thrust"]["trusted"]


def test_document_keeps_the_text_above_the_marker(tmp_path):
    doc = tmp_path / "docs" / "sensitivity.md"
    doc.parent.mkdir()
    doc.write_text("# Title\n\nOur reading.\n\n" + sensitivity_report.MARKER + "\nSTALE\n")
    plan = sensitivity.make_plan([_setting("default")], 0.2, 3, 2, 0, ("afonftsmc", "fl"))
    evaluated = {"default": {"missing": ["s1 fl"]}}
    meta = {
        "draws": 3,
        "dt_draws": 2,
        "horizon_s": 0.2,
        "seed": 0,
        "rotor_speed_limit": 34.78,
        "thrust_to_weight": 2.0,
        "tuning": {"source": "x.json"},
        "programs": 2,
        "runs": 6,
        "wall_s": 1.0,
        "load_average_start": [1.0, 1.0, 1.0],
        "load_average_end": [1.0, 1.0, 1.0],
        "cpus": 2,
        "command": "python -m experiments.sensitivity",
    }
    (tmp_path / "out").mkdir()
    sensitivity_report.write(tmp_path / "out", plan, evaluated, meta, doc, {})
    text = doc.read_text()
    assert text.startswith("# Title\n\nOur reading.\n\n" + sensitivity_report.MARKER)
    assert "STALE" not in text and "missing s1 fl" in text
    assert json.loads((tmp_path / "out" / "report.json").read_text())["meta"]["draws"] == 3


# ------------------------------------------------------------------------- arguments


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--settings", "dt"], "--settings must be among"),
        (["--controllers", "fl,bsmc"], "--controllers must be among"),
        (["--horizon", "0.00015"], "whole number of 0.1 ms steps"),
        (["--draws", "4", "--dt-draws", "8"], "--dt-draws must not exceed"),
        (["--tuned-gains", "no/such/file.json"], "no file"),
    ],
)
def test_bad_arguments(capsys, argv, message):
    assert message in usage_error(capsys, sensitivity.parse_args, argv)


def test_a_setting_brings_its_reference():
    args = sensitivity.parse_args(["--settings", "dt-0.1ms"])
    assert [s.key for s in args.selected] == ["default-reduced", "dt-0.1ms"]


# ------------------------------------------------------------------------ end to end


@pytest.mark.slow
def test_tiny_study_end_to_end_and_resumed(tmp_path):
    from fojax.controllers import gains_io, registry

    gains = {
        name: {"tuned": gains_io.gains_to_dict(registry.get_controller_class(name).default_gains())}
        for name in ("afonftsmc", "fl")
    }
    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"gains": gains}))
    out, doc = tmp_path / "out", tmp_path / "docs" / "sensitivity.md"
    argv = [
        "--out", str(out), "--doc", str(doc), "--draws", "3", "--dt-draws", "2",
        "--horizon", "0.05", "--controllers", "afonftsmc,fl", "--workers", "1",
        "--settings", "default,sat,tuned,float64", "--tuned-gains", str(tuned), "--quiet",
    ]  # fmt: skip
    assert sensitivity.main(argv) == 0
    report = json.loads((out / "report.json").read_text())
    verdicts = report["verdicts"]
    assert set(verdicts) == {"default", "sat", "tuned", "float64"}
    assert all(len(v) == 7 for v in verdicts.values())
    # The tuned gains are the defaults here: the same numbers, the same verdicts.
    assert verdicts["tuned"] == verdicts["default"]
    assert report["precision"] and (doc.parent / "sensitivity.png").stat().st_size > 0
    files = sorted((out / "runs").glob("*/draws_*.npz"))
    # default 6 (afonftsmc and FL, 3 scenarios), sat 3 (the FL's are the default's),
    # float64 6; the tuned runs equal the default's gains, hence the default's keys.
    assert len(files) == 15
    stamps = {p: p.stat().st_mtime_ns for p in files}
    assert sensitivity.main(argv) == 0  # resumed: nothing is run again
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/draws_*.npz")} == stamps
    assert "sat switching" in doc.read_text()


def test_default_settings_are_stated():
    args = sensitivity.parse_args([])
    assert (args.draws, args.dt_draws, args.horizon) == (32, 16, 30.0)
    assert args.selected == sensitivity.SETTINGS
    assert dataclasses.asdict(_setting("tuned"))["gains"] == "tuned"
