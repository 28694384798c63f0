"""``fojax tune``: input checks before compiling or writing, one tiny end-to-end run,
resume and its refusals."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import usage_error

from fojax import cli, optimize
from fojax.cli import simulate, tune
from fojax.controllers import gains_io
from fojax.controllers.afonftsmc import paper_gains
from fojax.optimize import strategies as st
from fojax.optimize.strategies import METHODS

# The same small problem as tests/test_optimize.py (shares its compiled code through
# the persistent compilation cache).
SMALL = [
    "--scenario", "2", "--controller", "afonftsmc", "--horizon", "0.3",
    "--seed", "5", "--dtype", "float64", "--effort-weight", "1e-3",
    "--chattering-weight", "1e-3", "--attitude-weight", "2", "--init", "naive",
]  # fmt: skip


def _write(path, document):
    path.write_text(json.dumps(document))
    return path


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--objective", "median"], "invalid choice: 'median'"),
        (["--steps", "0"], "expected a positive integer, got 0"),
        (["--draws", "0"], "expected a positive integer, got 0"),
        (["--draws", "4"], "--draws does not apply to --method auto"),
        (["--method", "cma-lbfgs", "--steps", "3", "--switch", "3"], "leave no L-BFGS step"),
        (["--patience", "5", "--validation-draws", "0"], "applies with validation draws only"),
        (["--controller", "pid"], "unknown controller 'pid'"),
        (["--scenario", "4"], "invalid choice"),
        (["--horizon", "0.0005"], "whole, positive number of steps"),
        (["--objective", "cvar", "--cvar-fraction", "2"], "cvar_fraction must be in (0, 1]"),
        (["--fields", "surface_c1,kp"], "unknown gain fields for afonftsmc: kp"),
        (["--share", "pairs"], "invalid choice"),
        (["--position-weight", "0", "--attitude-weight", "0", "--effort-weight", "0",
          "--chattering-weight", "0"], "at least one cost weight"),
        (["--learning-rate", "-1"], "finite number > 0"),
        (["--resume"], "nothing to resume"),
        # An option that would change nothing (the default method is auto).
        (["--learning-rate", "0.1"], "--learning-rate applies to --method adam only, not to "
         "--method auto"),
        (["--switch", "2"], "--switch applies to --method cma-lbfgs only"),
        (["--max-step", "2"], "--max-step applies to --method cma-lbfgs or lbfgs only"),
        (["--method", "lbfgs", "--clip-norm", "2"], "--clip-norm applies to --method adam only"),
        (["--anneal-start", "2"], "--anneal-start applies to --method adam only"),
        (["--method", "nelder-mead", "--sigma", "1"], "--sigma applies to --method auto or "
         "cma-lbfgs or cma-es"),
        (["--compile", "fast"], "--compile applies to --method cma-lbfgs or adam or lbfgs"),
        (["--cvar-fraction", "0.5"], "--cvar-fraction applies to --objective cvar only"),
        (["--validation-draws", "0", "--validate-every", "2"], "applies with validation draws"),
        (["--eval-draws", "0", "--eval-horizon", "1"], "--eval-draws is 0"),
        (["--outer-steps", "2"], "--outer-steps applies with --requirements FILE only"),
        (["--objective", "effort"], "--objective effort applies with --requirements FILE only"),
        (["--controller", "fl", "--fractional", "gl"], "--fractional does not apply to fl"),
        (["--controller", "bsmc", "--fractional", "soe"], "bsmc, which takes no fractional"),
        (["--controller", "fl", "--eval-switching", "sat"], "--eval-switching does not apply"),
        (["--controller", "fl", "--method", "lbfgs", "--anneal-end", "2"], "fl, which has no "
         "boundary layer"),
    ],
)  # fmt: skip
def test_bad_arguments_fail_before_anything_is_written(capsys, tmp_path, extra, message):
    out = tmp_path / "run"
    argv = SMALL + ["--steps", "2"] + extra + ["--out", str(out)]  # later options win
    err = usage_error(capsys, tune.parse_args, argv)
    assert message in err, err
    assert not out.exists()


def test_every_method_on_every_objective_is_one_declared_option_set():
    """Each option's default lives in the table, and a method is independent of the
    objective: every method parses with the weighted sum and with a requirement set."""
    names = [option.flag for option in tune.OPTIONS]
    assert len(names) == len(set(names))
    for method in tune.METHODS:
        run = tune.parse_args(SMALL + ["--method", method, "--out", "/nonexistent/run"])
        assert run.args.method == method and run.budget.steps == run.args.steps


def _help_of(parser) -> dict:
    """Each option's help as printed, on one line, by its first flag."""
    text = parser.format_help()
    chunks = re.split(r"\n  (?=-)", text.split("\noptions:\n", 1)[1])
    return {chunk.split()[0].rstrip(","): " ".join(chunk.split()) for chunk in chunks}


def test_the_help_and_the_docs_say_what_the_method_table_declares(monkeypatch):
    """``fojax tune --help``, docs/tuning.md's method table and its account of the default
    method hold the method table's numbers (:data:`METHODS`), each derived from it."""
    monkeypatch.setenv("COLUMNS", "10000")  # no line wrapped, no word broken
    help_of = _help_of(tune.build_parser())
    default = next(iter(METHODS))
    assert help_of["--method"].endswith(f"({default})")
    for name, method in METHODS.items():
        assert f"{name}: {method.summary}" in help_of["--method"]
        assert f"{name} {method.steps}" in help_of["--steps"]
        if method.patience:
            assert f"{name} {method.patience}, tolerance {method.tolerance * 100:g} %" in (
                help_of["--patience"])  # fmt: skip
        for option in method.options:  # each a fojax tune option, its defaults in its help
            flag = "--" + option.replace("_", "-")
            for constrained in (False, True):
                value = method.defaults(constrained)[option]
                assert st.words(option, value) in help_of[flag], (name, flag)
    auto = METHODS["auto"].plan()
    own = [draws for _, _, draws in auto["stages"]] + [auto["draws"]]
    assert f"auto takes its own ({' then '.join(map(str, own))})" in help_of["--draws"]
    # docs/tuning.md: the method table verbatim, and the default method's numbers
    docs = (Path(__file__).resolve().parent.parent / "docs" / "tuning.md").read_text()
    assert st.table() in docs, "docs/tuning.md: paste fojax.optimize.strategies.table()"
    words = {2: "twice", 4: "four"}
    ((generations, searches, draws),) = auto["stages"]
    method = METHODS["auto"]
    lam = st.CMAES().constants(33)["lam"]  # the AFONFTSMC's 33 parameters
    popsize = searches * (lam + 1) * draws // auto["draws"] - 1  # "fill": the same lanes
    text = " ".join(docs.split("## The default method", 1)[1].split("## ", 1)[0].split())
    for phrase in (
        f"in copies up to {words[searches]} searches",
        f"{generations} generations of the {words[searches]} CMA-ES searches",
        f"one fresh sample of {draws} draws a generation",
        f"at {words[auto['coarse']]} the step ({auto['coarse']} ms)",
        f"over its last {auto['window']} generations",
        "as a separable CMA-ES" if auto["diagonal"] else "as a CMA-ES",
        f"({popsize} candidates on {auto['draws']} draws)",
        f"improved by less than {method.tolerance * 100:g} % over {method.patience} generations",
        f"`--steps` ({method.steps},",
        f"at or below the first phase's {generations} generations",
        f"sample of {auto['draws']} draws per candidate",
        "one CMA-ES on fresh samples of `--draws` draws" if method.plan(True)["draws"] is None
        else "",
    ):
        assert phrase in text, phrase


def test_a_budget_within_auto_s_first_phase_runs_that_phase_and_says_so(tmp_path):
    """``--steps`` at or below auto's first phase run that phase alone: the announcement's
    plan and the summary (printed with ``--quiet`` too) say so; a longer run's plan has
    the convergence phase, and its summary no plan."""
    ((generations, searches, _),) = METHODS["auto"].plan()["stages"]
    run = tune.parse_args(SMALL + ["--steps", "30", "--out", str(tmp_path / "a")])
    lam = st.CMAES().constants(run.objective.size)["lam"]
    plan = (f"plan: the first phase alone: {searches} CMA-ES searches ({lam} candidates and "
            f"the mean each) for 30 of its {generations} generations")  # fmt: skip
    assert plan in tune._announce(run)
    result = optimize.Result(run.x0, run.x0, [], 30, 0, None, 0, 0.0, None)
    assert plan in tune._summary(run, result, 1.0)
    run = tune.parse_args(SMALL + ["--out", str(tmp_path / "b")])
    assert "then the best continued alone (separable CMA-ES, " in tune._announce(run)
    assert "plan:" not in tune._summary(run, result._replace(steps=run.budget.steps), 1.0)


def test_auto_tunes_fields_that_leave_an_order_out(tmp_path):
    """``--fields`` without ``gamma2``: auto's integer-order starts leave it as it is."""
    run = tune.parse_args(SMALL + ["--fields", "surface_c1,gamma1", "--out", str(tmp_path)])
    assert set(run.objective.param_map.names) == {"surface_c1", "gamma1"}
    for start in run.strategy.starts:
        np.testing.assert_array_equal(run.objective.gains(start).gamma2, run.init_gains.gamma2)


def test_initial_gains_files_are_validated(capsys, tmp_path):
    good = gains_io.gains_to_dict(paper_gains())
    out = tmp_path / "run"
    cases = {
        "ratio": ({"controller": "afonftsmc", "gains": {**good, "ratio": 2.5}}, "1 < p/q < 2"),
        "gamma": ({"controller": "afonftsmc", "gains": {**good, "gamma2": 1.0}}, "0 < gamma2 < 1"),
        "tied": (
            {"controller": "afonftsmc", "gains": {**good, "surface_c1": [1, 2, 3, 4, 4, 4]}},
            "differs between the axes (x, y)",
        ),
        "bound": (
            {"controller": "afonftsmc", "gains": {**good, "adaptation": 0.0}},
            "adaptation = ",
        ),
        "missing": ({"controller": "afonftsmc", "gains": {}}, "missing entries"),
    }
    for label, (document, message) in cases.items():
        path = _write(tmp_path / f"{label}.json", document)
        err = usage_error(
            capsys,
            tune.parse_args,
            SMALL + ["--steps", "2", "--init", str(path), "--out", str(out)],
        )
        assert message in err, (label, err)
    err = usage_error(
        capsys,
        tune.parse_args,
        SMALL + ["--steps", "2", "--init", str(tmp_path / "no.json"), "--out", str(out)],
    )
    assert "does not exist" in err
    assert not out.exists()


def test_tune_end_to_end_resume_and_refusals(capsys, tmp_path):
    out = tmp_path / "run"
    argv = SMALL + ["--method", "cma-lbfgs", "--draws", "3", "--steps", "3", "--switch", "2",
                    "--popsize", "4",
                    "--checkpoint-every", "1", "--eval-draws", "2", "--validate-every", "2",
                    "--quiet"]  # fmt: skip
    assert cli.main(["tune"] + argv + ["--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "held-out (2 draws" in printed
    name, gains, metadata = gains_io.load_gains(out / "gains.json")
    assert name == "afonftsmc" and metadata["tuned_by"] == "fojax tune"
    assert metadata["method"] == "cma-lbfgs" and metadata["init"] == "naive"
    assert metadata["settings"]["objective"]["problem"]["draws"] == 3
    rows = (out / "history.csv").read_text().strip().splitlines()
    assert len(rows) == 4 and rows[0].startswith("step,loss,points,")
    # Two CMA-ES generations of 4 candidates, then an L-BFGS step.
    columns = rows[0].split(",")
    table = [dict(zip(columns, row.split(","), strict=True)) for row in rows[1:]]
    assert [r["phase"] for r in table] == ["cma-lbfgs", "cma-lbfgs", "lbfgs"]
    assert [r["points"] for r in table] == ["4", "4", "1"] and table[2]["grad_norm"]
    # The returned gains are the best validated ones, and say which step they are from.
    validation = metadata["validation"]
    returned = metadata["returned_step"]
    assert returned == validation["returned_step"] == int(table[-1]["returned_step"])
    assert float(table[-1]["validation"]) == pytest.approx(validation["final"]["cost"])
    assert validation["draws"] == 32 and validation["switching"] == "sat"
    assert "returned " in printed and "validation cost" in printed
    evaluation = json.loads((out / "evaluation.json").read_text())
    assert evaluation["tuned"]["diverged"] == 0
    # What the run needs to be redone: the initial gains and the session's provenance.
    record = json.loads((out / "run.json").read_text())
    assert record["init"] == "naive" and record["init_gains"]["source"] == "naive"
    assert set(record["init_gains"]["values"]) == set(gains._fields)
    (session,) = record["sessions"]
    assert session["command"].startswith("fojax tune --scenario 2 --controller afonftsmc")
    for key in ("fojax_version", "jax", "jaxlib", "backend", "device_count", "process_count"):
        assert session[key] is not None, key
    assert metadata["provenance"] == session and metadata["init_gains"] == record["init_gains"]
    assert evaluation["provenance"] == session
    # Its convergence, drawn from history.csv, PNG and PDF.
    assert (out / "convergence.png").stat().st_size > 10_000
    assert (out / "convergence.pdf").read_bytes().startswith(b"%PDF")
    assert "convergence.png" in printed
    # fojax simulate reads the tuned gains.
    study, _ = simulate.parse_args(
        ["--scenario", "2", "--controller", "afonftsmc", "--draws", "2",
         "--gains", str(out / "gains.json"), "--out", str(tmp_path / "sim")]
    )  # fmt: skip
    np.testing.assert_allclose(
        np.asarray(study.gains["afonftsmc"].surface_c1), np.asarray(gains.surface_c1), rtol=1e-7
    )
    checkpoint = out / "checkpoint.npz"
    before = checkpoint.read_bytes()
    # A fresh start over the checkpoint, or a resume with other settings, is refused.
    err = usage_error(capsys, tune.parse_args, argv + ["--out", str(out)])
    assert "pass --resume" in err
    err = usage_error(
        capsys, tune.parse_args, argv + ["--resume", "--max-step", "0.5", "--out", str(out)]
    )
    assert "another configuration" in err
    assert "strategy.second.max_step: checkpoint 1.0, now 0.5" in err
    err = usage_error(
        capsys, tune.parse_args, argv + ["--resume", "--objective", "cvar", "--out", str(out)]
    )
    assert 'objective.problem.cost.objective: checkpoint "mean", now "cvar"' in err
    assert checkpoint.read_bytes() == before
    # Resuming a finished run changes nothing (its sessions are logged in run.json).
    text = (out / "gains.json").read_text()
    assert cli.main(["tune"] + argv + ["--resume", "--eval-draws", "0", "--out", str(out)]) == 0
    assert (out / "gains.json").read_text() == text
    sessions = json.loads((out / "run.json").read_text())["sessions"]
    assert len(sessions) == 2 and "--resume" in sessions[1]["command"]


def test_tuning_study_smoke(tmp_path):
    from experiments import tune_paper_gains

    out = tmp_path / "study"
    assert tune_paper_gains.main(["--tiny", "--quiet", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["evaluation"]) == {"scenario 2", "unseen reference", "scenario 3"}
    names = {"paper", "naive", "default", "gradient", "cma-es", "nelder-mead"}
    for setting in results["evaluation"].values():
        assert set(setting["gains"]) == names
    tuners = results["tuners"]
    budget = 40 * tuners["gradient"]["draw_steps"]
    assert 0 < tuners["cma-es"]["draw_steps"] <= budget
    assert 0 < tuners["nelder-mead"]["draw_steps"] <= budget
    assert (out / "tuning.png").stat().st_size > 0 and "| gradient |" in (
        out / "table.md"
    ).read_text()
    # The same command again gives the same held-out costs, every tuner's row included
    # (the tuners' draws are fixed by the seed, the gradient tuner's sample too).
    again = tmp_path / "again"
    assert tune_paper_gains.main(["--tiny", "--quiet", "--out", str(again)]) == 0
    rerun = json.loads((again / "results.json").read_text())
    for name, setting in results["evaluation"].items():
        for gains, value in setting["gains"].items():
            again_value = rerun["evaluation"][name]["gains"][gains]
            assert json.dumps(again_value) == json.dumps(value), (name, gains)  # NaN == NaN
    # Started again in the same folder, the study reuses its tuners' runs (their wall
    # times are the stored ones) and gives the same table.
    assert tune_paper_gains.main(["--tiny", "--quiet", "--out", str(out)]) == 0
    reused = json.loads((out / "results.json").read_text())
    assert reused["tuners"] == results["tuners"] and reused["curves"] == results["curves"]
    assert json.dumps(reused["evaluation"]) == json.dumps(results["evaluation"])


# ------------------------------------------------------- limits that hold (slow tier)

LIMITS = ["--scenario", "2", "--controller", "afonftsmc", "--init", "naive", "--horizon", "2",
          "--eval-draws", "0", "--quiet", "--no-compile-cache"]  # fmt: skip
"""A short problem; every program compiled afresh, as on a first run (Ctrl-C may come
while one is compiling)."""


def _tune(argv, **options):
    import subprocess
    import sys

    # Ctrl-C as a terminal delivers it: a test run started in the background of a
    # non-interactive shell (as CI may start it) ignores SIGINT, and its children inherit
    # that (Python then installs no KeyboardInterrupt handler); `python -m fojax.cli` else
    start = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "from fojax.cli import entry; entry()")  # fmt: skip
    command = [sys.executable, "-c", start, "tune", *argv]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **options)


def _interrupt_after(process, history, rows: int) -> tuple[float, str]:
    """Ctrl-C once ``history`` holds ``rows`` steps; the seconds the process then took
    to end."""
    import signal
    import time

    while process.poll() is None:
        if history.is_file() and len(history.read_text().splitlines()) > rows:
            break
        time.sleep(0.05)
    t0 = time.perf_counter()
    process.send_signal(signal.SIGINT)
    text = process.communicate(timeout=120)[0].decode()
    return time.perf_counter() - t0, text


@pytest.mark.slow
def test_a_time_limit_ends_the_run_within_two_seconds(tmp_path):
    out = tmp_path / "timed"
    # long enough for the validation's program to be compiled before the limit on a
    # loaded machine: a run ends with a validation, however late that program is ready
    process = _tune(LIMITS + ["--seconds", "20", "--out", str(out)])
    text = process.communicate(timeout=300)[0].decode()
    assert process.returncode == 0, text
    metadata = json.loads((out / "gains.json").read_text())["metadata"]
    # within 2 s either side: a request expected to overrun the limit is not started
    assert 18 <= metadata["wall_time_s"] <= 22, metadata["wall_time_s"]
    assert metadata["steps"] < tune.METHODS["auto"].steps  # the time, not the steps, ended it


@pytest.mark.slow
@pytest.mark.parametrize(
    "method, rows",
    [(["--steps", "30"], 5), (["--method", "cma-lbfgs", "--draws", "4", "--switch", "2",
                              "--steps", "4"], 2)],
    ids=["auto", "cma-lbfgs-while-its-gradient-compiles"],
)  # fmt: skip
def test_ctrl_c_ends_the_run_within_two_seconds_and_resumes_exactly(tmp_path, method, rows):
    full, cut = tmp_path / "full", tmp_path / "cut"
    process = _tune(LIMITS + method + ["--out", str(full)])
    assert process.communicate(timeout=600)[0] is not None and process.returncode == 0
    process = _tune(LIMITS + method + ["--checkpoint-every", "1", "--out", str(cut)])
    seconds, text = _interrupt_after(process, cut / "history.csv", rows)
    assert process.returncode == 130 and seconds <= 2.0, (seconds, text)
    assert (cut / "checkpoint.npz").is_file() and not (cut / "gains.json").exists()
    process = _tune(LIMITS + method + ["--checkpoint-every", "1", "--resume", "--out", str(cut)])
    process.communicate(timeout=600)
    assert process.returncode == 0
    gains = [json.loads((d / "gains.json").read_text())["gains"] for d in (full, cut)]
    assert gains[0] == gains[1]
