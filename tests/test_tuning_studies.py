"""experiments.tuning_study and experiments.remark3: seconds-long versions, end to end,
checked against independent evaluations; the tuning study's report regenerates from
its stored runs."""

import json

import numpy as np
import pytest


def _tiny_results(module, out) -> dict:
    """results.json of ``module``'s seconds-long version, run into ``out``."""
    assert module.main(["--tiny", "--quiet", "--out", str(out)]) == 0
    return json.loads((out / "results.json").read_text())


@pytest.mark.slow
def test_tuning_study_tiny(tmp_path):
    """Each run is fojax tune in a fresh process; its returned gains scored on held-out
    draws by an evaluation of the study's own, against the gains file's validation."""
    from experiments import tuning_study
    from fojax import optimize
    from fojax.controllers import gains_io

    out, doc = tmp_path / "study", tmp_path / "doc.md"
    argv = ["--tiny", "--quiet", "--shares", "paper", "--starts", "naive",
            "--methods", "auto,lbfgs", "--out", str(out)]  # fmt: skip
    # --carry with no stored run to carry (a fresh clone): every run is run.
    assert tuning_study.main(argv + ["--carry", "lbfgs"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["carried"] is None
    runs = {r["method"]: r for r in results["runs"]}
    assert set(runs) == {"auto", "lbfgs"}
    for method, run in runs.items():
        assert run["command"].startswith("fojax tune --scenario 2 --controller afonftsmc")
        assert ("--method lbfgs" in run["command"]) == (method == "lbfgs")
        assert run["wall_s"] >= run["tuning_s"] > 0 and 0 <= run["returned_step"] <= run["steps"]
        # The held-out cost, recomputed here on the same draws, from the gains file.
        gains = gains_io.gains_from_dict("afonftsmc", run["gains"])
        objective = optimize.Objective(optimize.ProblemSpec(horizon=0.3), gains)
        keys = optimize.draw_keys(0, "heldout", 4)
        again = objective.evaluate(objective.vector(gains), keys)[1]["cost"]
        assert run["heldout"] == pytest.approx(again, rel=1e-9)
        assert set(run["full_horizon"]) == {"2", "3"}
    best = results["summary"]["best_known"]["paper"]["cost"]
    assert best == min(r["heldout"] for r in results["runs"])
    (target,) = results["summary"]["targets"]
    assert target["above_best"] == pytest.approx(runs["auto"]["heldout"] / best - 1)
    # The report again from the stored runs, into a document's block.
    doc.write_text("<!-- tuning-study:begin -->\n<!-- tuning-study:end -->\n")
    assert tuning_study.main(argv + ["--report-only", "--update-doc", str(doc)]) == 0
    assert "above the best-known" in doc.read_text() and (tmp_path / "tuning_methods.png").is_file()
    # --carry: a stored run made by other code is kept once a rerun returns its gains ...
    path = next((out / "runs").glob("paper_naive_lbfgs_0-*.json"))

    def made_elsewhere(change=None):
        document = json.loads(path.read_text())
        document["code"] = "other"
        if change is not None:
            document["gains"]["surface_c1"][0] += change
        path.write_text(json.dumps(document))

    made_elsewhere()
    assert tuning_study.main(argv + ["--carry", "lbfgs"]) == 0
    carried = json.loads((out / "results.json").read_text())["carried"]
    assert carried["rerun"] == "paper_naive_lbfgs_0" and carried["methods"] == ["lbfgs"]
    # ... and refused where the rerun returns other gains.
    made_elsewhere(1.0)
    with pytest.raises(SystemExit, match="returned other gains than its stored run"):
        tuning_study.main(argv + ["--carry", "lbfgs"])


@pytest.mark.slow
def test_remark3_tiny(tmp_path):
    from experiments import remark3

    out = tmp_path / "remark3"
    results = _tiny_results(remark3, out)
    point = results["paper_point"]
    # The reverse-mode gradient agrees with a central finite difference along it.
    assert point["finite_difference"] == pytest.approx(point["directional_derivative"], rel=1e-4)
    costs = results["costs"]
    assert costs["tuned from paper"]["sat"]["J"] <= costs["paper"]["sat"]["J"]
    assert costs["tuned from naive"]["sat"]["J"] < costs["naive"]["sat"]["J"]
    table = (out / "table.md").read_text()
    assert "| hbar1 | phi = theta = psi | 1 | 156.4 |" in table


def test_cached_runs(tmp_path):
    """fojax.records.cached (the studies' runs): computed once per fingerprint, kept
    atomically as ``<stem>-<digest10>.json``, never reused for other settings."""
    from fojax import records

    calls = []

    def compute(value):
        calls.append(value)
        return {"value": value}

    assert records.cached(tmp_path, "run", {"a": 1}, lambda: compute(1)) == {"value": 1}
    assert records.cached(tmp_path, "run", {"a": 1}, lambda: compute(9)) == {"value": 1}
    assert records.cached(tmp_path, "run", {"a": 2}, lambda: compute(2)) == {"value": 2}
    assert calls == [1, 2] and len(list(tmp_path.glob("run-*.json"))) == 2
    assert records.stored(tmp_path, "run", {"a": 3}) is None
    # A file whose stored fingerprint is not the one asked for is computed again.
    path = tmp_path / f"run-{records.digest({'a': 1}, 10)}.json"
    path.write_text(json.dumps({"value": 1, "fingerprint": {"a": 5}}))
    assert records.cached(tmp_path, "run", {"a": 1}, lambda: compute(3)) == {"value": 3}
    assert json.loads(path.read_text())["fingerprint"] == {"a": 1}
    assert not list(tmp_path.glob(".*tmp"))


def test_tuning_study_report_without_runs_says_so(tmp_path):
    from experiments import tuning_study

    with pytest.raises(SystemExit, match="holds no run of these settings"):
        tuning_study.main(["--tiny", "--quiet", "--report-only", "--out", str(tmp_path)])
    assert not (tmp_path / "results.json").exists()


def test_cone_residual_constructed():
    """The KKT residual of experiments.remark3_inverted on vectors with a known answer."""
    from experiments.remark3_inverted import best_subsets, cone_residual

    rng = np.random.default_rng(1)
    a, b, c = np.linalg.qr(rng.standard_normal((8, 3)))[0].T  # orthonormal
    # -g in the cone of {a, b}: stationary with multipliers (2, 3).
    r, lam = cone_residual(-(2 * a + 3 * b), np.stack([a, 5 * b]))
    assert r == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(lam, [2.0, 0.6], rtol=1e-10)
    # A bound along the objective's own gradient never helps: r = 1, lam = 0.
    r, lam = cone_residual(a, np.stack([a]))
    assert r == pytest.approx(1.0) and lam[0] == 0.0
    # Part of the gradient orthogonal to every bound remains: r = |c| / |g|.
    g = -a + 2 * c
    r, lam = cone_residual(g, np.stack([a, b]))
    assert r == pytest.approx(2 / np.sqrt(5), rel=1e-12)
    np.testing.assert_allclose(lam, [1.0, 0.0], atol=1e-12)
    # No candidate, or only zero gradients: nothing helps.
    assert cone_residual(g, np.zeros((0, 8)))[0] == 1.0
    assert cone_residual(g, np.zeros((2, 8)))[0] == 1.0
    with pytest.raises(ValueError, match="finite"):
        cone_residual(g, np.stack([a * np.nan]))
    # The best single bound and the best pair are found among four.
    rows = best_subsets(-(a + b), np.stack([c, a, -b, b]), ["c", "a", "-b", "b"], max_size=2)
    assert rows[0]["residual"] == pytest.approx(1 / np.sqrt(2))
    assert rows[1]["residual"] == pytest.approx(0.0, abs=1e-12)
    assert {n for n, w in rows[1]["set"].items() if w > 0} == {"a", "b"}
    assert rows[-1]["size"] == "all" and set(rows[-1]["set"]) == {"a", "b"}


def test_nnls_matches_scipy():
    """experiments.remark3_inverted.nnls (Lawson-Hanson in NumPy) against SciPy's on
    random problems: tall, wide, with active bounds and without."""
    from scipy import optimize as scipy_optimize

    from experiments.remark3_inverted import nnls

    rng = np.random.default_rng(3)
    for m, n in [(8, 3), (33, 17), (33, 5), (5, 9), (40, 40), (1, 1)] * 5:
        A = rng.standard_normal((m, n)) * rng.uniform(0.1, 10, n)
        b = rng.standard_normal(m)
        x, residual = nnls(A, b)
        expected, expected_residual = scipy_optimize.nnls(A, b)
        assert np.all(x >= 0)
        assert residual == pytest.approx(expected_residual, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(x, expected, rtol=1e-7, atol=1e-9)
    # b in the cone of A's columns: an exact, non-negative solution.
    A = rng.standard_normal((10, 4))
    x, residual = nnls(A, A @ np.array([1.0, 0.0, 2.0, 0.5]))
    np.testing.assert_allclose(x, [1.0, 0.0, 2.0, 0.5], atol=1e-12)
    assert residual == pytest.approx(0.0, abs=1e-12)


@pytest.mark.slow
def test_remark3_inverted_tiny(tmp_path):
    from experiments import remark3_inverted

    out = tmp_path / "inverted"
    results = _tiny_results(remark3_inverted, out)
    # Every Jacobian row agrees with a central finite difference (surrogates excepted).
    check = results["finite_difference_check"]
    assert max(e["relative_error"] for e in check.values()) < 1e-4
    # The requirement set found holds at the paper's gains (bounds at its own values).
    assert results["requirement_tuning"]["naive"]["paper"]["passed"] == 1
    for point in results["analysis"].values():
        for objective in ("tracking", "effort"):
            residuals = [e["residual"] for e in point[objective]["subsets"]]
            assert all(0.0 <= r <= 1.0 + 1e-12 for r in residuals)
            # More bounds can only lower the residual.
            assert all(b <= a + 1e-9 for a, b in zip(residuals, residuals[1:], strict=False))
    assert (out / "remark3_inverted.png").stat().st_size > 10_000
