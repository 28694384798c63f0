"""experiments.tuning_study and experiments.remark3: seconds-long versions, end to end,
checked against independent evaluations; the tuning study's report regenerates from
its stored runs."""

import json

import numpy as np
import pytest


@pytest.mark.slow
def test_tuning_study_tiny(tmp_path):
    import jax.numpy as jnp

    from experiments import tuning_study
    from fojax.controllers.afonftsmc import paper_gains
    from fojax.optimize import cost as cost_lib
    from fojax.optimize import problem as problem_lib

    out = tmp_path / "study"
    argv = ["--tiny", "--quiet", "--shares", "paper", "--out", str(out)]
    assert tuning_study.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    runs = {(r["start"], r["method"]): r for r in results["runs"]}
    assert set(runs) == {(s, m) for s in ("paper", "naive") for m in tuning_study.METHODS}
    # The held-out cost at the start is the paper's gains' cost on the held-out draws.
    spec = problem_lib.ProblemSpec(
        horizon=0.3,
        draws=3,
        cost=cost_lib.CostConfig(effort_weight=1e-3, chattering_weight=1e-3, attitude_weight=2.0),
        dtype="float64",
    )
    keys = problem_lib.TuningProblem(spec, paper_gains(jnp.float64)).heldout_keys(4)
    paper = float(np.mean(problem_lib.evaluate(spec, paper_gains(jnp.float64), keys).cost))
    for method in tuning_study.METHODS:
        run = runs[("paper", method)]
        assert run["initial_heldout"] == pytest.approx(paper, rel=1e-12)
        assert run["curve"][0] == [0, 0.0, run["initial_heldout"]]
        assert run["curve"][-1][2] == run["final_heldout"]
        assert np.all(np.diff([point[0] for point in run["curve"]]) >= 0)
    cma = runs[("paper", "cma-es")]
    assert cma["draw_steps"] == 2 * 14 * 3 * 300  # two generations of 14 candidates x 3 draws
    gradient = runs[("paper", "gradient")]
    assert gradient["draw_steps"] == 4 * 3 * 300 and gradient["validation"]["best_step"] >= 0
    table = (out / "table.md").read_text()
    assert "| 33 (`--share paper`) | paper | CMA-ES (batched) |" in table
    assert (out / "tuning_wall.png").stat().st_size > 10_000
    # The report regenerates from the stored runs without running anything.
    doc = tmp_path / "doc.md"
    doc.write_text("head\n<!-- tuning-study:begin -->\nold\n<!-- tuning-study:end -->\ntail\n")
    assert tuning_study.main(argv + ["--report-only", "--update-doc", str(doc)]) == 0
    text = doc.read_text()
    assert text.startswith("head\n") and text.endswith("tail\n") and "old" not in text
    assert table.strip() in text
    assert (tmp_path / "tuning_wall.png").exists()


@pytest.mark.slow
def test_remark3_tiny(tmp_path):
    from experiments import remark3

    out = tmp_path / "remark3"
    assert remark3.main(["--tiny", "--quiet", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    point = results["paper_point"]
    # The reverse-mode gradient agrees with a central finite difference along it.
    assert point["finite_difference"] == pytest.approx(point["directional_derivative"], rel=1e-4)
    costs = results["costs"]
    assert costs["tuned from paper"]["sat"]["J"] <= costs["paper"]["sat"]["J"]
    assert costs["tuned from naive"]["sat"]["J"] < costs["naive"]["sat"]["J"]
    table = (out / "table.md").read_text()
    assert "| hbar1 | phi = theta = psi | 1 | 156.4 |" in table
