"""experiments.fair_comparison: input checks, and one tiny study, interrupted and resumed."""

import json

import numpy as np
import pytest
from conftest import usage_error

from experiments import fair_comparison
from fojax.controllers import registry
from fojax.optimize.strategies import METHODS


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--controllers", "pid"], "--controllers must be among"),
        (["--controllers", "bsmc,fl"], "must include afonftsmc"),
        (["--horizon", "0.0005"], "whole number of 1 ms steps"),
        (["--steps", "0"], "positive integer"),
        (["--eval-scenarios", "4"], "scenarios must be among"),
        (["--method", "lbfgs", "--switch", "3"], "--switch applies to --method cma-lbfgs only"),
    ],
)
def test_bad_arguments_fail_before_compiling(capsys, argv, message):
    assert message in usage_error(capsys, fair_comparison.parse_args, argv)


def test_default_study_tunes_every_controller_from_its_defaults():
    args = fair_comparison.parse_args([])
    assert args.controllers == registry.controller_names()
    assert (args.steps, args.draws, args.horizon, args.eval_draws) == (None, 16, 10.0, 64)
    budget = fair_comparison.budget_of(args)  # the method's own, as fojax tune runs it
    assert (budget.steps, budget.patience) == (METHODS["auto"].steps, METHODS["auto"].patience)
    assert args.eval_scenarios == (1, 2, 3)
    # fojax tune's default method, its options at the method table's defaults
    assert (args.method, args.switch, args.learning_rate) == ("auto", None, None)


@pytest.mark.slow
def test_tiny_study_end_to_end_and_resume(tmp_path):
    out = tmp_path / "fair"
    # L-BFGS: one point per step on the same draws, so every controller's budget is the
    # same number of draw-steps (the default's CMA-ES population grows with the gains).
    argv = ["--tiny", "--quiet", "--controllers", "fl,afonftsmc", "--method", "lbfgs"]
    argv += ["--out", str(out)]
    assert fair_comparison.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    assert list(results["tuning"]) == ["afonftsmc", "fl"]  # the baseline first
    for name, tuning in results["tuning"].items():
        assert tuning["draw_steps"] == 2 * 3 * 300, name  # same budget for every controller
        cls = registry.get_controller_class(name)
        gains = {k: np.asarray(v) for k, v in results["gains"][name]["tuned"].items()}
        cls.check_gains(cls.GAINS.type(**gains))  # tuned gains stay feasible
        # The tuned gains are the best validated: the defaults exactly when no answer
        # validated better than them.
        default = results["gains"][name]["default"]
        changed = any(not np.allclose(gains[k], default[k]) for k in gains)
        v = tuning["validation"]
        assert changed == (tuning["returned_step"] > 0), name
        assert v["best"]["cost"] <= min(v["initial"]["cost"], v["final"]["cost"]), name
    assert set(results["evaluation"]) == {"scenario 2"}  # --tiny: the tuning scenario
    for setting in results["evaluation"].values():
        fl = setting["controllers"]["fl"]
        assert fl["tuned_minus_baseline"]["n"] == 3
        base = setting["controllers"]["afonftsmc"]["tuned"]["cost"]["mean"]
        assert fl["tuned_minus_baseline"]["mean"] == pytest.approx(
            fl["tuned"]["cost"]["mean"] - base, rel=1e-9, abs=1e-12
        )
    text = (out / "table.md").read_text()
    assert "| fl | tuned |" in text and "| afonftsmc | default |" in text

    # Started again, every tuning run resumes from its finished checkpoint: same gains,
    # same held-out costs, no tuning step repeated.
    assert fair_comparison.main(argv) == 0
    again = json.loads((out / "results.json").read_text())
    assert again["gains"] == results["gains"]
    assert again["evaluation"] == results["evaluation"]
    assert again["tuning"]["fl"]["draw_steps"] == results["tuning"]["fl"]["draw_steps"]
