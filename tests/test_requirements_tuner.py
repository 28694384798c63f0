"""The constrained tuner: a toy with a known constrained optimum (pure JAX), then one
short simulator run whose held-out yield must fall in the interval it states."""

import jax.numpy as jnp
import numpy as np
import pytest

from fojax import requirements as rq
from fojax.optimize import constrained as co


def _toy(x, data):
    """Draw i: minimise |x|^2 subject to x_1 >= 1 + 0.1 xi_i and x_2 >= 0.5 + 0.1 eta_i.
    With every draw required the optimum is x* = (1 + 0.1 max xi, 0.5 + 0.1 max eta)."""
    xi, eta = data
    objective = x[0] ** 2 + x[1] ** 2
    violations = jnp.stack([1.0 + 0.1 * xi - x[0], 0.5 + 0.1 * eta - x[1]])
    return (objective, violations), jnp.zeros(xi.shape, jnp.int32)


@pytest.fixture(scope="module")
def toy():
    rng = np.random.default_rng(0)
    n = 64
    data = tuple(jnp.asarray(rng.standard_normal(n)) for _ in range(2))
    star = np.array([1 + 0.1 * float(jnp.max(data[0])), 0.5 + 0.1 * float(jnp.max(data[1]))])
    return data, n, star


def _run(toy, **kw):
    data, n, _ = toy
    config = co.ConstrainedConfig(
        outer_steps=20,
        inner_steps=50,
        margin=0.01,
        validation_draws=0,
        penalty_growth=4.0,
        penalty_max=1e4,
        **kw,
    )
    result = co.minimize(co.make_alm_step(_toy, config), jnp.zeros(2), data, n, config, 2)
    return np.asarray(result.params), result


def _train_yield(toy, x):
    (xi, eta), _, _ = toy
    return np.mean((1 + 0.1 * np.asarray(xi) <= x[0]) & (0.5 + 0.1 * np.asarray(eta) <= x[1]))


def test_mean_formulation_reaches_the_constrained_optimum(toy):
    x, result = _run(toy, formulation="mean")
    star = toy[2]
    assert np.max(np.abs(x - star)) < 0.03, (x, star)
    assert x @ x == pytest.approx(star @ star, rel=0.05)
    assert result.multipliers.shape == (2,) and np.all(result.multipliers > 0)


def test_chance_surrogate_is_feasible_and_conservative(toy):
    x, _ = _run(toy, formulation="chance", allowed_share=0.05, temperature=0.1)
    star = toy[2]
    assert _train_yield(toy, x) == 1.0
    assert np.all(x >= star - 1e-3)
    assert x @ x < 1.5 * (star @ star)


def test_config_is_checked():
    with pytest.raises(ValueError, match="formulation"):
        co.ConstrainedConfig(formulation="barrier")
    with pytest.raises(ValueError, match="allowed_share"):
        co.ConstrainedConfig(allowed_share=1.0)
    with pytest.raises(ValueError, match="allowed_share > 0"):
        co.ConstrainedConfig(formulation="chance")
    with pytest.raises(ValueError, match="inner_steps"):
        co.ConstrainedConfig(inner_steps=0)


@pytest.fixture(scope="module")
def simulator_run():
    """FL on scenario 2 (0.4 s, rotor-limited actuators at thrust-to-weight 2), tuned for
    tracking under a torque-effort and a tilt requirement its default gains miss."""
    from fojax.controllers import registry
    from fojax.optimize.problem import ProblemSpec

    reqs = rq.parse(
        {
            "settings": {"thrust_to_weight": 2.0},
            "requirements": [
                {"name": "tilt", "metric": "max_tilt", "max": 3, "unit": "deg"},
                {"name": "torque", "metric": "torque_effort", "max": 0.7, "unit": "N m"},
            ],
        }
    )
    spec = ProblemSpec(controller="fl", scenario=2, horizon=0.4, draws=8, dtype="float32")
    base = registry.get_controller_class("fl").default_gains()
    problem = co.RequirementProblem(spec, base, reqs, objective="tracking")
    config = co.ConstrainedConfig(
        formulation="mean", outer_steps=3, inner_steps=4, validation_draws=32, learning_rate=0.1
    )
    result = co.tune_to_requirements(problem, config)
    heldout = problem.evaluate(result.params, problem.heldout_keys(64))
    return problem, result, heldout


def test_simulator_run_is_rotor_limited_and_validated(simulator_run):
    problem, result, _ = simulator_run
    assert problem.sim_config.rotor_speed_limit == pytest.approx(rq.rotor_speed_limit(2.0))
    assert len(result.history) == 3
    start = result.initial
    assert "interval" in result.selected
    for row in [{"validation": start}, *result.history]:  # the best validated one
        assert co._rank(row["validation"]) <= co._rank(result.selected)
    assert start["draws"] == 32


def test_heldout_yield_within_the_stated_interval(simulator_run):
    _, result, heldout = simulator_run
    low, high = result.selected["interval"]
    assert low <= heldout["yield"].yield_ <= high, (result.selected, heldout["yield"].describe())


def test_cma_es_baseline_on_the_same_constraints(simulator_run):
    problem, result, _ = simulator_run
    out = co.cma_es_requirements(
        problem, budget_draw_steps=2 * 4 * 4 * 400, popsize=4, draws=4, validation_draws=32
    )
    assert len(out["history"]) == 2 and out["draw_steps"] == 2 * 4 * 4 * 400
    start = result.initial  # the start's validation, on the same validation draws
    # The selection never hands back worse than the start (by yield, then objective).
    assert co._rank(out["selected"]) >= co._rank(start)
    assert out["selected"]["draws"] == start["draws"]
    problem.gains(out["params"])  # maps onto feasible gains


def test_an_interrupted_run_resumes_to_the_uninterrupted_result(toy, tmp_path):
    data, n, _ = toy

    def run(outer_steps, checkpoint=None, fingerprint=None):
        config = co.ConstrainedConfig(outer_steps=outer_steps, inner_steps=10, validation_draws=0)

        def validate(x):  # counts by hand on the tuning draws: passed and failures
            ok = np.stack(
                [1 + 0.1 * np.asarray(data[0]) <= x[0], 0.5 + 0.1 * np.asarray(data[1]) <= x[1]]
            )
            failures = {"a": int(np.sum(~ok[0])), "b": int(np.sum(~ok[1]))}
            return {
                "passed": int(np.sum(ok.all(0))),
                "failures": failures,
                "objective": float(x @ x),
            }

        step = co.make_alm_step(_toy, config)
        return co.minimize(
            step, jnp.zeros(2), data, n, config, 2, validate,
            checkpoint=checkpoint, fingerprint=fingerprint,
        )  # fmt: skip

    whole = run(4)
    path = tmp_path / "checkpoint.npz"
    first = run(2, path, {"run": 1})
    assert len(first.history) == 2 and path.is_file()
    resumed = run(4, path, {"run": 1})
    np.testing.assert_array_equal(resumed.params, whole.params)
    np.testing.assert_array_equal(resumed.final_params, whole.final_params)
    np.testing.assert_array_equal(resumed.multipliers, whole.multipliers)
    assert resumed.penalty == whole.penalty
    assert resumed.selected == whole.selected and resumed.initial == whole.initial
    strip = [{k: v for k, v in row.items() if k != "wall_time_s"} for row in whole.history]
    again = [{k: v for k, v in row.items() if k != "wall_time_s"} for row in resumed.history]
    assert again == strip
    with pytest.raises(ValueError, match="differs in:\n  run: checkpoint 1, now 2"):
        run(4, path, {"run": 2})


def test_union_problem_alternates_members():
    """A requirement problem on a union of scenarios: draw i is draw i of member
    i % members run alone (the same metrics, float32 within the union's rounding)."""
    from fojax import scenarios
    from fojax.controllers import registry
    from fojax.optimize.problem import ProblemSpec

    reqs = rq.parse(
        {"requirements": [{"name": "t", "metric": "max_tilt", "max": 30, "unit": "deg"}]}
    )
    spec = ProblemSpec(controller="fl", scenario=2, horizon=0.05, draws=4, dtype="float32")
    base = registry.get_controller_class("fl").default_gains()
    union = scenarios.union(scenarios.get_scenario(2), scenarios.get_scenario(3))
    keys = scenarios.draw_keys(0, np.arange(4))
    together = co.RequirementProblem(spec, base, reqs, scenario=union).evaluate(base, keys)
    for member, scenario_id in enumerate((2, 3)):
        alone = co.RequirementProblem(
            spec, base, reqs, scenario=scenarios.get_scenario(scenario_id)
        ).evaluate(base, keys)
        for name in ("max_tilt", "position_rmse", "torque_effort"):
            np.testing.assert_allclose(
                together["metrics"][name][member::2],
                alone["metrics"][name][member::2],
                rtol=1e-4, atol=1e-6, err_msg=name,
            )  # fmt: skip
    # The members differ (scenario 3's reference and disturbances are other ones).
    assert not np.allclose(together["metrics"]["position_rmse"], alone["metrics"]["position_rmse"])
