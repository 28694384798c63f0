"""``fojax reproduce``: input checks, the verdict rule, one tiny end-to-end run."""

import json

import numpy as np
import pytest

from experiments import cli, paper_figures, reproduce


def _error(capsys, argv):
    with pytest.raises(SystemExit) as info:
        reproduce.parse_args(argv)
    assert info.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--draws", "0"], "positive integer"),
        (["--scenarios", "4"], "scenarios must be among"),
        (["--scenarios", "one"], "expected scenario ids"),
        (["--horizon", "-1"], "finite number > 0"),
        (["--dt", "2", "--horizon", "1"], "must not exceed the horizon"),
        (["--horizon", "1.0005"], "whole number of steps"),
        (["--switching", "signum"], "invalid choice"),
        (["--fractional", "crone"], "invalid choice"),
    ],
)
def test_bad_arguments_fail_before_compiling(capsys, tmp_path, argv, message):
    assert message in _error(capsys, argv + ["--out", str(tmp_path)])


def test_default_run_covers_every_scenario_and_controller(tmp_path):
    studies, args = reproduce.parse_args(["--out", str(tmp_path)])
    assert [s.scenario_id for s in studies] == [1, 2, 3]
    assert [s.horizon for s in studies] == [80.0, 80.0, 50.0]
    assert args.draws == reproduce.DEFAULT_DRAWS and args.switching == "sign"
    for study in studies:
        assert study.controllers == ("afonftsmc", "anftsmc", "fobsmc", "bsmc", "fl")
        assert study.seed == 0 and study.save_every == 100


def _difference(low, high):
    return {"mean": (low + high) / 2, "ci95": [low, high], "n": 10}


def test_verdict_rule():
    assert reproduce._pair_verdict(_difference(0.1, 0.3)) == "better"  # other is higher
    assert reproduce._pair_verdict(_difference(-0.3, -0.1)) == "worse"
    assert reproduce._pair_verdict(_difference(-0.1, 0.3)) == "n.s."
    assert reproduce._pair_verdict({"mean": 1.0, "ci95": None, "n": 1}) == "n.s."
    assert reproduce._verdict({"better": 4, "worse": 0, "n.s.": 0}) == "holds"
    assert reproduce._verdict({"better": 3, "worse": 1, "n.s.": 0}) == "does not hold"
    assert reproduce._verdict({"better": 3, "worse": 0, "n.s.": 1}) == "inconclusive"
    assert reproduce._verdict({"better": 0, "worse": 0, "n.s.": 4}) == "inconclusive"


VERDICTS = {"holds", "does not hold", "inconclusive"}


def test_reproduce_end_to_end_tiny(tmp_path):
    out = tmp_path / "run"
    argv = ["reproduce", "--out", str(out), "--draws", "3", "--chunk", "2", "--keep", "2"]
    argv += ["--horizon", "0.2", "--seed", "4", "--quiet"]
    assert cli.main(argv) == 0
    report = json.loads((out / "report.json").read_text())
    text = (out / "report.md").read_text()
    assert "## Verdicts" in text
    ids = [c["id"] for c in report["claims"]]
    assert ids == [c["id"] for c in reproduce.CLAIMS] + ["R2-chatter-free", "C-finite-time"]
    for claim in report["claims"]:
        assert claim["verdict"] in VERDICTS, claim["id"]
        assert claim["text"] in text
    for scenario_id in ("1", "2", "3"):
        tables = report["scenarios"][scenario_id]
        assert list(tables["metrics"]) == ["afonftsmc", "anftsmc", "fobsmc", "bsmc", "fl"]
        assert list(tables["paired_differences"]) == ["anftsmc", "fobsmc", "bsmc", "fl"]
        summary = json.loads((out / f"s{scenario_id}" / "summary.json").read_text())
        for name, entry in summary["controllers"].items():
            assert entry["draws"] == 3
            assert tables["metrics"][name]["position_rmse"] == entry["metrics"]["position_rmse"]
        # Paired differences are computed on the same draws: check one by hand.
        with np.load(out / f"s{scenario_id}" / "draws.npz") as draws:
            want = np.mean(draws["fl.position_rmse"] - draws["afonftsmc.position_rmse"])
        got = tables["paired_differences"]["fl"]["position_rmse"]["mean"]
        assert got == pytest.approx(float(want), rel=1e-5)
    numbers = [n for numbers in paper_figures.FIGURE_NUMBERS.values() for n in numbers]
    assert report["figures"] == [
        p.name for p in sorted((out / "figures").glob("fig*.png"))
    ] and len(report["figures"]) == len(numbers)
    for name in report["figures"]:
        assert (out / "figures" / name).stat().st_size > 10_000
        assert f"figures/{name}" in text
    # Started again, the same command reuses every finished chunk and agrees.
    assert cli.main(argv) == 0
    again = json.loads((out / "report.json").read_text())

    def numbers(document):
        return {
            sid: {
                name: {k: v for k, v in table.items() if k != "wall_time_s"}
                for name, table in tables["metrics"].items()
            }
            for sid, tables in document["scenarios"].items()
        }

    assert numbers(again) == numbers(report)
    assert [c["verdict"] for c in again["claims"]] == [c["verdict"] for c in report["claims"]]
