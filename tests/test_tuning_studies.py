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
    import jax.numpy as jnp

    from experiments import tuning_study
    from fojax import optimize
    from fojax.controllers.afonftsmc import paper_gains
    from fojax.optimize import strategies

    out = tmp_path / "study"
    argv = ["--tiny", "--quiet", "--shares", "paper", "--out", str(out)]
    assert tuning_study.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    runs = {(r["start"], r["method"]): r for r in results["runs"]}
    assert set(runs) == {(s, m) for s in ("paper", "naive") for m in tuning_study.METHODS}
    # The held-out cost at the start is the paper's gains' cost on the held-out draws,
    # on an objective of their own.
    cost = optimize.CostConfig(effort_weight=1e-3, chattering_weight=1e-3, attitude_weight=2.0)
    spec = optimize.ProblemSpec(horizon=0.3, draws=3, cost=cost, dtype="float64")
    objective = optimize.Objective(spec, paper_gains(jnp.float64))
    keys = optimize.draw_keys(0, "heldout", 4)
    paper = objective.evaluate(objective.x0, keys)[1]["cost"]
    for method in tuning_study.METHODS:
        run = runs[("paper", method)]
        assert run["initial_heldout"] == pytest.approx(paper, rel=1e-12)
        curve = np.asarray(run["curve"])
        assert run["curve"][0] == [0, 0.0, 0, run["initial_heldout"]]
        assert list(curve[:, 0]) == list(range(len(curve)))  # every step, in order
        assert np.all(np.diff(curve[:, 1:3], axis=0) >= 0)  # wall time, draw-steps
        assert curve[-1, 2] == run["draw_steps"] and curve[-1, 1] <= run["wall_time_s"]
        # The final held-out cost is the returned (best validated) answer's: one of the
        # curve's answers, or the start.
        assert run["final_heldout"] in curve[:, 3]
    assert runs[("paper", "cma-es")]["draw_steps"] == 2 * 14 * 3 * 300  # 2 generations of 14
    assert runs[("paper", "lbfgs")]["draw_steps"] == 4 * 3 * 300
    # auto: 4 generations of 14 candidates on its own 8 fresh draws (not --draws)
    assert runs[("paper", "default")]["draw_steps"] == 4 * 14 * strategies.AUTO_DRAWS * 300
    assert runs[("paper", "nelder-mead")]["draw_steps"] <= (34 + 14) * 3 * 300
    targets = results["summary"]["paper/naive"]["target"]
    assert len(targets) == 1 and {"default", "lbfgs"} <= set(targets[0])
    table = (out / "table.md").read_text()
    assert "| 33 (`--share paper`) | paper | CMA-ES (batched) |" in table
    assert "reaches it in half of CMA-ES's wall time in" in table
    assert (out / "tuning_wall.png").stat().st_size > 10_000
    # The report regenerates from the stored runs without running anything.
    doc = tmp_path / "doc.md"
    doc.write_text("head\n<!-- tuning-study:begin -->\nold\n<!-- tuning-study:end -->\ntail\n")
    assert tuning_study.main(argv + ["--report-only", "--update-doc", str(doc)]) == 0
    text = doc.read_text()
    assert text.startswith("head\n") and text.endswith("tail\n") and "old" not in text
    assert table.strip() in text
    assert (tmp_path / "tuning_wall.png").exists()
    # Runs are kept under their fingerprints: another L-BFGS setting finds the CMA-ES
    # runs but not the L-BFGS ones.
    other = tuning_study.parse_args(argv + ["--max-step", "0.5"])
    assert tuning_study._stored_run(other, "paper", "paper", 0, "cma-es") is not None
    assert tuning_study._stored_run(other, "paper", "paper", 0, "lbfgs") is None


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


@pytest.mark.slow
def test_tuning_study_user_view_tiny(tmp_path):
    """The user view end to end: each command of USER_MODES run by ``fojax tune`` in a
    fresh process (``--tiny``'s small problem), recorded and tabulated."""
    from experiments import tuning_study
    from experiments.tuning_study_report import USER_MODES

    out = tmp_path / "study"
    argv = ["--tiny", "--quiet", "--shares", "paper", "--methods", "default"]
    assert tuning_study.main(argv + ["--user-view", "1", "--out", str(out)]) == 0
    users = json.loads((out / "results.json").read_text())["user_view"]
    assert [u["mode"] for u in users] == list(USER_MODES)
    by_mode = {u["mode"]: u for u in users}
    for user in users:
        assert user["command"].startswith("fojax tune --scenario 2 --controller afonftsmc")
        assert 0 <= user["returned_step"] <= 2 and user["total_s"] >= user["tuning_s"] > 0
        assert user["heldout_draws"] == 4
    # The same start on the same held-out draws: the same initial cost, whatever the method.
    naive = [by_mode[m]["heldout_initial"] for m in USER_MODES if m.startswith("naive")]
    assert len(naive) == 2 and naive[0] == pytest.approx(naive[1], rel=1e-12)
    assert "The user's view" in (out / "table.md").read_text()


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


def test_user_view_read_back_run_by_run_and_only_of_this_code(tmp_path, monkeypatch):
    import types

    from experiments import _common, tuning_study_user
    from experiments.tuning_study_report import USER_MODES

    args = types.SimpleNamespace(scenario=2, tiny=True, horizon=0.3)
    folder = tmp_path / "user_view"

    def keep(mode, index):
        fingerprint = tuning_study_user.user_fingerprint(args, mode, index)
        _common.cached(folder, f"{mode}_{index}", fingerprint, lambda: {"mode": mode, "run": index})

    for index in (1, 0):
        for mode in USER_MODES:
            keep(mode, index)
    keep(USER_MODES[0], 3)  # after a gap: not one of the runs 0, 1, ...
    found = tuning_study_user.records(args, tmp_path, run=False)
    assert [(r["mode"], r["run"]) for r in found] == [(m, i) for i in (0, 1) for m in USER_MODES]
    assert all(set(r) == {"mode", "run"} for r in found)
    monkeypatch.setattr(_common, "code", lambda: "other code")
    assert tuning_study_user.records(args, tmp_path, run=False) == []


def test_tuning_study_report_without_runs_says_so(tmp_path):
    from experiments import tuning_study

    with pytest.raises(SystemExit, match="no run made with these settings"):
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
