"""``fojax simulate --requirements`` and ``fojax tune --requirements``: bad files and
options end in exit status 2 before anything compiles; the yield in summary.json is the
count of its own per-draw metrics; a tiny tuning run writes gains that simulate reads."""

import json

import numpy as np
import pytest
from conftest import usage_error

from fojax import cli
from fojax import requirements as rq
from fojax.cli import simulate, tune
from fojax.optimize import driver, strategies  # noqa: F401 - imported (nothing compiles at import)

TINY = """
description = "tiny test set"
[settings]
thrust_to_weight = 2.0
[[requirements]]
name = "tilt"
metric = "max_tilt"
max = 5
unit = "deg"
[[requirements]]
name = "rotor limits"
metric = "rotor_saturation"
max = 2
unit = "%"
[[requirements]]
name = "overshoot"
metric = "position_overshoot"
max = 5
unit = "mm"
"""

BASE_SIMULATE = ["--scenario", "2", "--controller", "fl", "--draws", "4", "--horizon", "0.3"]
BASE_TUNE = ["--scenario", "2", "--controller", "fl", "--horizon", "0.3"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    path = tmp_path_factory.mktemp("requirements") / "tiny.toml"
    path.write_text(TINY)
    return path


BAD_FILES = [
    ('[[requirements]]\nname = "a"\nmetric = "overshoot"\nmax = 1\nunit = "m"\n',
     "unknown metric 'overshoot'"),
    ('[[requirements]]\nname = "a"\nmetric = "max_tilt"\nmax = 10\nunit = "m"\n',
     "write unit = 'rad' or 'deg'"),
    ('[[requirements]]\nname = "a"\nmetric = "rotor_saturation"\nmax = 120\nunit = "%"\n',
     "share in [0, 1]"),
    ('[settings]\nthrust_to_weight = 0.8\n[[requirements]]\nname = "a"\n'
     'metric = "max_tilt"\nmax = 10\nunit = "deg"\n', "cannot hover"),
    ("requirements = [", "is not valid TOML"),
]  # fmt: skip


@pytest.mark.parametrize("text, message", BAD_FILES)
@pytest.mark.parametrize("command", ["simulate", "tune"])
def test_bad_requirement_file_exits_2_before_compiling(
    tmp_path, capsys, monkeypatch, text, message, command
):
    import jax

    def no_compiling(*args, **kwargs):  # pragma: no cover - the test fails if reached
        raise AssertionError("compiled before the requirement file was checked")

    monkeypatch.setattr(jax, "jit", no_compiling)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    out = tmp_path / "out"
    base = BASE_SIMULATE if command == "simulate" else BASE_TUNE
    argv = [command, *base, "--requirements", str(path), "--out", str(out)]
    err = usage_error(capsys, cli.main, argv)
    assert "argument --requirements" in err and message in err
    assert not out.exists()


def test_missing_file_and_bad_rotor_limit(tmp_path, capsys, tiny):
    out = ["--out", str(tmp_path / "o")]
    err = usage_error(
        capsys,
        simulate.parse_args,
        [*BASE_SIMULATE, "--requirements", str(tmp_path / "none.toml"), *out],
    )
    assert "requirement file" in err and "does not exist" in err
    err = usage_error(capsys, simulate.parse_args, [*BASE_SIMULATE, "--rotor-limit", "1", *out])
    assert "argument --rotor-limit" in err and "cannot hover" in err
    err = usage_error(capsys, tune.parse_args, [*BASE_TUNE, "--rotor-limit", "abc", *out])
    assert "argument --rotor-limit" in err


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--position-weight", "2"], "--position-weight applies to the weighted-sum objective"),
        (["--steps", "3"], "--steps is set by --outer-steps and --inner-steps"),
        (["--cvar-fraction", "0.2"], "--cvar-fraction applies to --objective cvar only"),
        (["--resume"], "nothing to resume"),
        (["--objective", "mean"], "--objective mean is the weighted-sum objective's"),
        (["--method", "cma-es", "--learning-rate", "0.1"], "--learning-rate applies to"),
        (["--method", "lbfgs", "--clip-norm", "2"], "--clip-norm applies to --method adam"),
        (["--eval-horizon", "1"], "--eval-horizon applies to the weighted-sum objective"),
        (["--eval-switching", "sat"], "--eval-switching does not apply to fl"),
    ],
)
def test_tune_options_that_do_not_apply_with_requirements(tmp_path, capsys, tiny, extra, message):
    argv = [*BASE_TUNE, "--requirements", str(tiny), *extra, "--out", str(tmp_path / "o")]
    err = usage_error(capsys, tune.parse_args, argv)
    assert message in err
    assert err.strip().splitlines()[-1].startswith("fojax tune: error:")


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--rotor-limit", "2"], "--rotor-limit applies with --requirements FILE only"),
        (["--outer-steps", "2"], "--outer-steps applies with --requirements FILE only"),
        (["--objective", "effort"], "--objective effort applies with --requirements FILE only"),
    ],
)
def test_requirement_options_without_requirements(tmp_path, capsys, extra, message):
    argv = [*BASE_TUNE, *extra, "--out", str(tmp_path / "o")]
    assert message in usage_error(capsys, tune.parse_args, argv)


def test_tune_defaults_with_requirements(tmp_path, tiny):
    run = tune.parse_args([*BASE_TUNE, "--requirements", str(tiny), "--out", str(tmp_path)])
    args = run.args
    assert (args.objective, args.method, args.draws, args.eval_draws) == ("effort", "auto", 8, 128)
    strategy = run.strategy
    assert (strategy.outer_steps, strategy.inner_steps, strategy.formulation) == (10, 10, "mean")
    assert run.budget.steps == 1 + 10 * 11 and args.validate_every == 11
    assert run.objective.rotor_speed_limit == pytest.approx(rq.rotor_speed_limit(2.0))
    # --rotor-limit replaces the file's limit, in the simulation and in the metric.
    run = tune.parse_args(
        [*BASE_TUNE, "--requirements", str(tiny), "--rotor-limit", "3", "--out", str(tmp_path)]
    )
    assert run.objective.rotor_speed_limit == pytest.approx(rq.rotor_speed_limit(3.0))
    assert run.objective.requirements.settings.thrust_to_weight == 3.0
    # Any method, inside the augmented Lagrangian; without --requirements the weighted sum.
    for method in tune.METHODS:
        argv = [*BASE_TUNE, "--requirements", str(tiny), "--method", method, "--out", str(tmp_path)]
        assert tune.parse_args(argv).strategy.inner.name != "augmented-lagrangian"
    args = tune.parse_args([*BASE_TUNE, "--out", str(tmp_path / "w")]).args
    assert (args.objective, args.method, args.draws) == ("mean", "auto", 16)


def test_with_requirements_every_method_samples_draws(tmp_path, tiny):
    """``--draws`` applies to every method with requirements, ``auto`` and the CMA-ES of
    ``cma-lbfgs`` included (without requirements they take samples of their own)."""
    for method in tune.METHODS:
        argv = [*BASE_TUNE, "--requirements", str(tiny), "--method", method, "--draws", "3",
                "--out", str(tmp_path)]  # fmt: skip
        run = tune.parse_args(argv)
        inner = run.strategy.inner
        request = inner.ask(inner.init(run.x0))
        assert len(run.objective.sample(request.sample, request.draws)) == 3, method


@pytest.fixture(scope="module")
def tuned(tmp_path_factory, tiny):
    """A tiny requirement tuning run of the FL (the cheapest controller to compile)."""
    out = tmp_path_factory.mktemp("tuned")
    argv = [
        "tune", *BASE_TUNE, "--requirements", str(tiny), "--method", "adam", "--draws", "2",
        "--outer-steps", "2", "--inner-steps", "2", "--validation-draws", "4",
        "--eval-draws", "4", "--quiet", "--out", str(out),
    ]  # fmt: skip
    assert cli.main(argv) == 0
    return out


def test_tune_to_requirements_writes_gains_and_heldout_yield(tuned, tiny):
    document = json.loads((tuned / "gains.json").read_text())
    assert document["controller"] == "fl"
    meta = document["metadata"]
    assert meta["tuned_to"] == "requirements" and meta["objective"] == "effort"
    assert meta["actuators"]["rotor_limited"] is True
    assert meta["requirements"]["requirements"][0]["name"] == "tilt"
    history = (tuned / "history.csv").read_text().splitlines()
    assert len(history) == 1 + 1 + 2 * 3  # the scale, then 2 x (2 steps and a measurement)
    assert "constraints" in history[0] and "multipliers" in history[0]
    evaluation = json.loads((tuned / "evaluation.json").read_text())
    for label in ("initial", "tuned"):
        entry = evaluation[label]
        assert entry["draws"] == 4
        assert entry["interval"] == pytest.approx(list(rq.clopper_pearson(entry["passed"], 4)))
        assert set(entry["failures"]) == {"tilt", "rotor limits", "overshoot"}


def test_tune_to_requirements_resumes_to_the_uninterrupted_gains(tmp_path, tuned, tiny, capsys):
    """One outer step, then --resume with two: the gains of the two-step run in one go
    (the ``tuned`` fixture), and the checkpoint refuses what does not match."""
    out = tmp_path / "r"

    def argv(outer, *extra, folder=out):
        return [
            "tune", *BASE_TUNE, "--requirements", str(tiny), "--method", "adam", "--draws",
            "2", "--outer-steps", str(outer), "--inner-steps", "2", "--validation-draws", "4",
            "--eval-draws", "4", "--quiet", "--out", str(folder), *extra,
        ]  # fmt: skip

    assert cli.main(argv(1)) == 0
    assert "holds the checkpoint of an earlier run" in usage_error(capsys, cli.main, argv(2))
    assert cli.main(argv(2, "--resume")) == 0
    got = json.loads((out / "gains.json").read_text())
    want = json.loads((tuned / "gains.json").read_text())
    assert got["gains"] == want["gains"]
    assert got["metadata"]["validation"] == want["metadata"]["validation"]
    history = (out / "history.csv").read_text().splitlines()
    assert history == (tuned / "history.csv").read_text().splitlines() or len(history) == 8
    assert len(json.loads((out / "run.json").read_text())["sessions"]) == 2
    changed = usage_error(capsys, cli.main, argv(2, "--resume", "--margin", "0.1"))
    assert "differs in:" in changed and "strategy.margin: checkpoint 0.05, now 0.1" in changed
    missing = usage_error(capsys, cli.main, argv(1, "--resume", folder=tmp_path / "none"))
    assert "nothing to resume" in missing


def test_simulate_requirements_yield_matches_per_draw_metrics(tmp_path, tiny, tuned, capsys):
    out = tmp_path / "sim"
    argv = [
        "simulate", *BASE_SIMULATE, "--requirements", str(tiny), "--gains",
        str(tuned / "gains.json"), "--keep", "0", "--quiet", "--out", str(out),
    ]  # fmt: skip
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "requirements (3: tilt, rotor limits, overshoot)" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["gains"]["fl"]["source"].endswith("gains.json")
    assert summary["actuators"]["rotor_limited"] is True
    assert summary["actuators"]["rotor_speed_limit_rad_s"] == pytest.approx(
        rq.rotor_speed_limit(2.0)
    )
    assert [r["name"] for r in summary["requirements"]["requirements"]] == [
        "tilt",
        "rotor limits",
        "overshoot",
    ]
    entry = summary["controllers"]["fl"]["requirements"]
    # Recount from the saved per-draw metrics, by hand.
    per_draw = np.load(out / "requirements.npz")
    reqs = rq.load(tiny)
    bounds = {r.name: (r.metric, r.canonical_value) for r in reqs}
    meets = {
        name: np.isfinite(per_draw[f"fl.{metric}"]) & (per_draw[f"fl.{metric}"] <= bound)
        for name, (metric, bound) in bounds.items()
    }
    passed = np.all(np.stack(list(meets.values())), 0)
    assert entry["draws"] == 4
    assert entry["passed"] == int(np.sum(passed))
    assert entry["yield"] == pytest.approx(np.mean(passed))
    assert entry["failures"] == {name: int(np.sum(~ok)) for name, ok in meets.items()}
    assert entry["interval"] == pytest.approx(list(rq.clopper_pearson(entry["passed"], 4)))
    assert np.array_equal(per_draw["fl.passed"], passed)
    worst = max(entry["failures"].values())
    if worst:
        assert entry["failures"][entry["most_failed"]] == worst
    else:
        assert entry["most_failed"] is None
    # The same draws and actuators as the study: metrics shared with fojax.metrics agree.
    draws = np.load(out / "draws.npz")
    np.testing.assert_allclose(per_draw["fl.position_rmse"], draws["fl.position_rmse"], rtol=1e-4)
    assert (out / "requirements.png").is_file()
    assert "requirements.png" in summary["figures"]


def test_tune_cma_es_baseline_writes_gains(tmp_path, tiny):
    out = tmp_path / "cma"
    argv = [
        "tune", *BASE_TUNE, "--requirements", str(tiny), "--method", "cma-es",
        "--outer-steps", "1", "--inner-steps", "1", "--draws", "2", "--validation-draws", "2",
        "--eval-draws", "0", "--quiet", "--out", str(out),
    ]  # fmt: skip
    assert cli.main(argv) == 0
    document = json.loads((out / "gains.json").read_text())
    assert document["metadata"]["method"] == "cma-es"
    assert document["metadata"]["returned_step"] in (0, 3)  # the start, or the last answer
    history = (out / "history.csv").read_text().splitlines()
    assert len(history) == 4  # header, the scale, one generation, the measurement
    assert [row.split(",")[2] for row in history[1:]] != ["1", "1", "1"]  # a population
    assert not (out / "evaluation.json").exists()
