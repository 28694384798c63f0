"""``fojax reproduce``: input checks, the verdict rule, one tiny end-to-end run."""

import dataclasses
import json

import numpy as np
import pytest
from conftest import usage_error
from scipy import stats

from fojax import cli
from fojax.cli import output, reproduce
from fojax.cli.reproduce import figures as paper_figures
from fojax.controllers import registry
from fojax.controllers.afonftsmc import AFONFTSMC


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
        (["--compare", "afonftsmc"], "afonftsmc is the baseline"),
        (["--compare", "fl,flx"], "unknown controller 'flx'"),
        (["--compare", "fl,fl"], "names a controller twice"),
    ],
)
def test_bad_arguments_fail_before_compiling(capsys, tmp_path, argv, message):
    assert message in usage_error(capsys, reproduce.parse_args, argv + ["--out", str(tmp_path)])


def test_default_run_covers_every_scenario_and_controller(tmp_path):
    studies, args = reproduce.parse_args(["--out", str(tmp_path)])
    assert [s.scenario_id for s in studies] == [1, 2, 3]
    assert [s.horizon for s in studies] == [80.0, 80.0, 50.0]
    assert args.draws == reproduce.DEFAULT_DRAWS and args.switching == "sign"
    for study in studies:
        assert study.controllers == ("afonftsmc", "anftsmc", "fobsmc", "bsmc", "fl")
        assert study.seed == 0 and study.save_every == 100


def test_default_reaching_band_is_twice_the_switching_step():
    from fojax.controllers.afonftsmc import paper_gains

    studies, _ = reproduce.parse_args(["--out", "unused"])
    gains = paper_gains()
    want = 2.0 * (np.asarray(gains.reaching_h1) + np.asarray(gains.mu)) * 1e-3
    for study in studies:
        np.testing.assert_allclose(study.reaching_band, want, rtol=1e-6)
    # The band sgn switching leaves at 1 ms: about 0.0052 (x, y), 0.032 (z), 0.31 (attitude).
    assert study.reaching_band[2] == pytest.approx(0.0323, abs=1e-4)


# ------------------------------------------------------------ the verdict rule, constructed


def _sample(mean, std, n=20):
    """``n`` values with exactly this mean and sample standard deviation."""
    z = np.linspace(-1.0, 1.0, n)
    z = (z - z.mean()) / z.std(ddof=1)
    return mean + std * z


def _family(differences, delta):
    comparisons = [reproduce.compare(d, delta) for d in differences]
    return comparisons


def _one_sided_mean(p, delta, std=1.0, n=20):
    """A mean whose 'worse' test (mean < -delta) has exactly the one-sided p-value p."""
    return -delta + stats.t.ppf(p, n - 1) * std / np.sqrt(n)


def test_margins():
    assert reproduce.margin("m", [0.001, 0.003], 80.0) == pytest.approx(1e-3)  # floor
    assert reproduce.margin("m", [0.1, 0.3], 80.0) == pytest.approx(0.01)  # 5 % of 0.2
    assert reproduce.margin("rad", [np.nan, 0.0], 80.0) == pytest.approx(1e-3)
    assert reproduce.margin("s", [1.0, 3.0], 80.0) == pytest.approx(0.1)
    assert reproduce.margin("s", [0.1], 80.0) == pytest.approx(0.05)
    assert reproduce.margin("m s^2", [0.0], 80.0) == pytest.approx(1e-3 * 80**2 / 2)
    assert reproduce.margin("m s", [0.0], 50.0) == pytest.approx(0.05)
    assert reproduce.margin("N", [2.0, 2.0], 80.0) == pytest.approx(0.1)  # relative only
    assert reproduce.margin("m", [np.nan], 80.0) == pytest.approx(1e-3)
    with pytest.raises(ValueError):
        reproduce.margin("furlong", [1.0], 80.0)


def test_tiny_difference_within_the_margin_is_equivalent():
    # 30 micrometres with a tiny spread (common random numbers): the earlier rule calls
    # it significant, the margin of 1 mm calls it equivalent.
    delta = 1e-3
    family = reproduce.decide(_family([_sample(-3e-5, 1e-6)] * 4, delta))
    assert [c["outcome"] for c in family] == ["equivalent"] * 4
    assert [c["ci_rule"] for c in family] == ["worse"] * 4
    assert reproduce.claim_verdict(c["outcome"] for c in family) == ("equivalent within the margin")


def test_large_difference_does_not_hold():
    delta = 1e-3
    differences = [_sample(0.05, 0.01)] * 3 + [_sample(-0.02, 0.001)]
    family = reproduce.decide(_family(differences, delta))
    assert [c["outcome"] for c in family] == ["better"] * 3 + ["worse"]
    assert reproduce.claim_verdict(c["outcome"] for c in family) == "does not hold"


def test_claim_outcomes():
    verdict = reproduce.claim_verdict
    assert verdict(["better"] * 4) == "holds"
    assert verdict(["better", "better", "equivalent"]) == "equivalent within the margin"
    assert verdict(["better", "worse", "equivalent"]) == "does not hold"
    assert verdict(["better", "inconclusive", "equivalent"]) == "inconclusive"
    assert verdict([]) == "inconclusive"
    delta = 0.01
    family = reproduce.decide(_family([_sample(0.05, 0.01)] * 3 + [_sample(0.0, 1e-3)], delta))
    assert [c["outcome"] for c in family] == ["better"] * 3 + ["equivalent"]
    # Better, but not demonstrably by more than the margin: undecided.
    family = reproduce.decide(_family([_sample(0.012, 0.01)], delta))
    assert family[0]["outcome"] == "inconclusive" and family[0]["ci_rule"] == "better"


def test_holm_changes_a_borderline_verdict():
    delta, n = 1e-3, 20
    # One comparison worse beyond the margin with a one-sided p-value of 0.01, three
    # clearly equivalent: 12 p-values in the family; the 0.01 is the 4th smallest and
    # Holm multiplies it by 12 - 4 + 1 = 9 (0.09 > 0.05).
    borderline = _sample(_one_sided_mean(0.01, delta), 1.0, n)
    equivalent = [_sample(0.0, 1e-4, n)] * 3
    raw = reproduce.decide(_family([borderline, *equivalent], delta), adjust=False)
    assert raw[0]["p"]["worse"] == pytest.approx(0.01, rel=1e-6)
    assert raw[0]["outcome"] == "worse"
    assert reproduce.claim_verdict(c["outcome"] for c in raw) == "does not hold"
    adjusted = reproduce.decide(_family([borderline, *equivalent], delta))
    assert adjusted[0]["p_adjusted"]["worse"] == pytest.approx(0.09, rel=1e-6)
    assert [c["outcome"] for c in adjusted] == ["inconclusive"] + ["equivalent"] * 3
    assert reproduce.claim_verdict(c["outcome"] for c in adjusted) == "inconclusive"
    # A clear one survives the adjustment: p = 0.001 -> 0.009.
    clear = _sample(_one_sided_mean(0.001, delta), 1.0, n)
    adjusted = reproduce.decide(_family([clear, *equivalent], delta))
    assert adjusted[0]["outcome"] == "worse"
    assert reproduce.claim_verdict(c["outcome"] for c in adjusted) == "does not hold"


def test_degenerate_comparisons_are_inconclusive_or_exact():
    delta = 0.05
    family = reproduce.decide(
        _family([np.full(10, np.nan), np.zeros(10), np.full(10, 2.0), np.full(10, -2.0)], delta)
    )
    assert [c["outcome"] for c in family] == ["inconclusive", "equivalent", "better", "worse"]


VERDICTS = set(reproduce.claims.VERDICTS)


@pytest.mark.slow
def test_reproduce_end_to_end_tiny(tmp_path):
    out = tmp_path / "run"
    argv = ["reproduce", "--out", str(out), "--draws", "3", "--device-batch", "2", "--keep", "2"]
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
        for comparison in claim.get("comparisons", []):
            assert comparison["outcome"] in reproduce.claims.OUTCOMES
            assert comparison["margin"] > 0
            assert set(comparison["p_adjusted"]) == {"better", "worse", "equivalent"}
    assert report["settings"]["reaching_band"] == pytest.approx(reproduce.reaching_band(1e-3))
    finite_time = report["claims"][-1]
    assert len(finite_time["rows"]) == 3 * 6
    assert {row["band"] for row in finite_time["rows"]} == set(reproduce.reaching_band(1e-3))
    assert "### The verdict rule" in text and "Holm" in text
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
        got = tables["paired_differences"]["fl"]["position_rmse"]["difference"]["mean"]
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


@dataclasses.dataclass(frozen=True)
class _AfonftsmcAgain(AFONFTSMC):
    """The AFONFTSMC under another name: compared with itself, every per-draw
    difference is exactly 0."""

    name = "afonftsmc-again"


def test_a_controller_compared_with_itself_is_equivalent_end_to_end(tmp_path, monkeypatch):
    # A verdict known by construction, through the whole command: the same law on the same
    # draws (common random numbers) differs by exactly 0 in every metric, so every
    # comparison is equivalent and every scenario claim is "equivalent within the margin".
    # A broken pairing of draws, a comparison against the wrong data or a changed rule
    # for an exact tie fails it. The settings of test_reproduce_end_to_end_tiny (the
    # AFONFTSMC's program is the same).
    monkeypatch.setattr(registry, "_LAWS", dict(registry._LAWS))  # registered for this test
    registry.register(_AfonftsmcAgain)
    out = tmp_path / "run"
    argv = ["reproduce", "--out", str(out), "--draws", "3", "--device-batch", "2", "--keep", "2"]
    argv += ["--horizon", "0.2", "--seed", "4", "--quiet", "--no-figures"]
    assert cli.main([*argv, "--compare", "afonftsmc-again"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["settings"]["controllers"] == ["afonftsmc", "afonftsmc-again"]
    scenario_claims = {c["id"]: c for c in report["claims"] if c["scenario"] is not None}
    assert list(scenario_claims) == [c["id"] for c in reproduce.CLAIMS]
    for claim_id, claim in scenario_claims.items():
        assert claim["verdict"] == "equivalent within the margin", claim_id
        assert len(claim["comparisons"]) == len(claim["metrics"]), claim_id
        for comparison in claim["comparisons"]:
            assert comparison["controller"] == "afonftsmc-again"
            assert comparison["difference"]["mean"] == 0.0, (claim_id, comparison["metric"])
            assert comparison["difference"]["n"] == 3
            assert comparison["outcome"] == "equivalent", (claim_id, comparison["metric"])


def test_regeneration_replaces_only_what_follows_the_marker(tmp_path):
    from experiments import regenerate_reproduction as regenerate

    document = tmp_path / "reproduction.md"
    document.write_text(f"# Title\n\nReading, by hand.\n\n{regenerate.MARKER}\n\nold report\n")
    report = tmp_path / "report.md"
    report.write_text("# Report title\n\nnew report\n\n![fig05](figures/fig05.png)\n")
    regenerate.splice(document, report, "reproduction")
    text = document.read_text()
    assert text.startswith("# Title\n\nReading, by hand.\n\n" + regenerate.MARKER)
    assert "old report" not in text and "![fig05](reproduction/fig05.png)" in text
    below = text.split(regenerate.MARKER + "\n\n", 1)[1]  # the label, then the report
    label, report_text = below.split("\n\n", 1)
    assert label.startswith(output.LABEL_PREFIX) and "Generated by `" in label
    assert report_text == "new report\n\n![fig05](reproduction/fig05.png)\n"
    with pytest.raises(SystemExit):
        regenerate.splice(report, report, "reproduction")
