"""Tuning to requirements: the augmented Lagrangian on a toy with a known constrained
optimum (any inner strategy), its gradient against finite differences on the
simulator, a short simulator run that must raise the held-out yield from a start that
fails the set, resume, and a union of scenarios."""

import functools

import numpy as np
import pytest
from conftest import drive

from fojax import requirements as rq
from fojax.controllers import registry
from fojax.optimize import Evaluation, Objective, Outputs, Request, driver
from fojax.optimize import strategies as st
from fojax.optimize.spec import ProblemSpec


class _Toy:
    """Draw i: minimise ``|x|^2`` subject to ``x_1 >= 1 + 0.1 xi_i`` and ``x_2 >= 0.5 +
    0.1 eta_i``; with every draw required the optimum is ``x* = (1 + 0.1 max xi, 0.5 +
    0.1 max eta)``. The outputs and their per-draw Jacobians are exact (by hand), so the
    loss's gradient is ``sum_i cot_i . J_i`` as the objective forms it."""

    def __init__(self, n=64):
        rng = np.random.default_rng(0)
        self.xi, self.eta = rng.standard_normal(n), rng.standard_normal(n)
        self.star = np.array([1 + 0.1 * self.xi.max(), 0.5 + 0.1 * self.eta.max()])

    def outputs(self, points) -> Outputs:
        points = np.atleast_2d(points)
        f = np.sum(points**2, 1)[:, None] + 0 * self.xi
        v1 = 1.0 + 0.1 * self.xi - points[:, :1]
        v2 = 0.5 + 0.1 * self.eta - points[:, 1:]
        values = np.stack([f, v1, v2], -1)
        return Outputs(values, np.zeros(values.shape[:2] + (4,)), np.zeros(values.shape[:2], int))

    def __call__(self, request: Request) -> Evaluation:
        outputs = self.outputs(request.points)
        values = request.loss.values(outputs)
        gradient = None
        if request.gradient:
            x = np.asarray(request.points)[0]
            cot = request.loss.cotangents(Outputs(*(a[0] for a in outputs[:3])))
            jacobian = np.array([2 * x, [-1.0, 0.0], [0.0, -1.0]])  # (outputs, parameters)
            gradient = cot.sum(0) @ jacobian
        return Evaluation(values, gradient, outputs, 0, 0)

    def drive(self, strategy, x0, requests):
        state = drive(self, strategy, x0, requests)
        return strategy.answer(state), state


@pytest.fixture(scope="module")
def toy():
    return _Toy()


def _alm(inner, **kw):
    settings = dict(outer_steps=20, inner_steps=50, margin=0.01, penalty_growth=4.0,
                    penalty_max=1e4)  # fmt: skip
    return st.AugmentedLagrangian(inner, 2, **{**settings, **kw})


@pytest.mark.parametrize(
    "inner", [st.adam(1000, 0.05, 1.0, 1.0, sample="fixed"), st.LBFGS(max_step=0.5)],
    ids=["adam", "lbfgs"],
)  # fmt: skip
def test_mean_formulation_reaches_the_constrained_optimum(toy, inner):
    strategy = _alm(inner)
    x, state = toy.drive(strategy, np.zeros(2), strategy.requests)
    assert np.max(np.abs(x - toy.star)) < 0.03, (x, toy.star)
    assert x @ x == pytest.approx(toy.star @ toy.star, rel=0.05)
    assert np.all(state["lam"] > 0)


def test_cma_es_inside_the_lagrangian_reaches_it_too(toy):
    strategy = _alm(st.CMAES(sigma0=0.3, popsize=8, sample="fixed"), inner_steps=30)
    x, _ = toy.drive(strategy, np.zeros(2), strategy.requests)
    assert np.max(np.abs(x - toy.star)) < 0.05, (x, toy.star)


def test_chance_surrogate_is_feasible_and_conservative(toy):
    inner = st.adam(1000, 0.05, 1.0, 1.0, sample="fixed")
    strategy = _alm(inner, formulation="chance", allowed_share=0.05, temperature=0.1)
    x, _ = toy.drive(strategy, np.zeros(2), strategy.requests)
    meets = (1 + 0.1 * toy.xi <= x[0]) & (0.5 + 0.1 * toy.eta <= x[1])
    assert np.mean(meets) == 1.0
    assert np.all(x >= toy.star - 1e-3) and x @ x < 1.5 * (toy.star @ toy.star)


@pytest.mark.parametrize("formulation", ["mean", "chance"])
def test_lagrangian_cotangents_match_finite_differences_on_the_toy(toy, formulation):
    """The loss's per-draw cotangents composed with the toy's exact Jacobians against a
    central difference of the loss's values (the simulator's case is in the slow tier)."""
    share = 0.05 if formulation == "chance" else 0.0
    strategy = st.AugmentedLagrangian(st.LBFGS(), 2, formulation=formulation, allowed_share=share)
    loss = strategy.loss(
        {"lam": np.array([0.3, 1.5]), "rho": 10.0, "scale": 2.0}
    )
    x = np.array([0.9, 0.45])  # some draws violate, some do not
    gradient = toy(Request(x[None], gradient=True, loss=loss)).gradient
    eps = 1e-6
    for direction in np.eye(2):
        ends = toy(Request(np.stack([x + eps * direction, x - eps * direction]), loss=loss))
        numeric = (ends.values[0] - ends.values[1]) / (2 * eps)
        assert gradient @ direction == pytest.approx(numeric, rel=1e-6, abs=1e-9)


def test_a_point_with_diverged_draws_ranks_after_every_point_without():
    """A diverged draw's violation is capped at 1 in the constraints, a real one is not:
    a candidate diverging on every draw must not beat one that violates by much."""
    from fojax.optimize.losses import AlmLoss

    loss = AlmLoss(lam=np.zeros(1), rho=10.0, scale=1.0)
    values = np.array(
        [
            [[1.0, 50.0], [1.0, 40.0]],  # violates by far, never diverges
            [[np.nan, np.nan], [np.nan, np.nan]],  # diverges on both draws
            [[1.0, 0.0], [np.nan, np.nan]],  # diverges on one draw
            [[2.0, 60.0], [2.0, 60.0]],  # violates by more
        ]
    )
    outputs = Outputs(values, np.zeros((4, 2, 4)), np.zeros((4, 2), np.int32))
    capped = AlmLoss.parts(loss, outputs)
    assert np.all(capped[1][1] == 1.0) and capped[1][0, 0] > 1.0  # the cap, and a real one
    ranked = np.argsort(loss.values(outputs), kind="stable")
    np.testing.assert_array_equal(ranked, [0, 3, 2, 1])  # by divergences, then by L
    single = loss.values(Outputs(values[2:3], np.zeros((1, 2, 4)), np.zeros((1, 2), np.int32)))
    assert np.isfinite(single[0])


def test_config_is_checked():
    inner = st.LBFGS()
    with pytest.raises(ValueError, match="formulation"):
        st.AugmentedLagrangian(inner, 2, formulation="barrier")
    with pytest.raises(ValueError, match="allowed_share"):
        st.AugmentedLagrangian(inner, 2, allowed_share=1.0)
    with pytest.raises(ValueError, match="allowed_share > 0"):
        st.AugmentedLagrangian(inner, 2, formulation="chance")
    with pytest.raises(ValueError, match="inner_steps"):
        st.AugmentedLagrangian(inner, 2, inner_steps=0)


# ---------------------------------------------------------------- the simulator

REQUIREMENTS = rq.parse(
    {
        "settings": {"thrust_to_weight": 2.0},
        "requirements": [
            {"name": "tilt", "metric": "max_tilt", "max": 3, "unit": "deg"},
            {"name": "torque", "metric": "torque_effort", "max": 0.7, "unit": "N m"},
        ],
    }
)


@functools.cache
def fl_objective(dtype="float32"):
    """The FL on scenario 2 (0.4 s, rotor-limited at thrust-to-weight 2), tracking under a
    tilt and a torque-effort requirement its default gains miss."""
    spec = ProblemSpec(controller="fl", scenario=2, horizon=0.4, draws=8, dtype=dtype)
    base = registry.get_controller_class("fl").default_gains()
    limit = REQUIREMENTS.settings.speed_limit()
    return Objective(spec, base, REQUIREMENTS, target="tracking", rotor_speed_limit=limit)


def test_lagrangian_gradient_matches_finite_differences():
    objective = fl_objective("float64")
    x = objective.x0 + 0.05
    loss = st.AugmentedLagrangian(st.LBFGS(), 2).loss(
        {"lam": np.array([0.5, 2.0]), "rho": 10.0, "scale": 0.3}
    )
    evaluation = objective(Request(x[None], gradient=True, width=1.0, loss=loss))
    assert evaluation.draw_steps == 2 * 8 * 400  # the outputs first, then the reverse pass
    direction = np.random.default_rng(1).normal(size=x.size)
    eps = 1e-6
    ends = objective(Request(np.stack([x + eps * direction, x - eps * direction]), width=1.0,
                             loss=loss))  # fmt: skip
    numeric = (ends.values[0] - ends.values[1]) / (2 * eps)
    assert abs(numeric) > 1e-3
    assert float(evaluation.gradient @ direction) == pytest.approx(numeric, rel=1e-4)


@pytest.fixture(scope="module")
def simulator_run():
    objective = fl_objective()
    strategy = st.AugmentedLagrangian(
        st.adam(12, 0.1, 1.0, 1.0, sample="fixed"), 2, outer_steps=3, inner_steps=4
    )
    result = driver.run(objective, strategy, driver.Budget(steps=strategy.requests),
                        validation_draws=32, validate_every=5, progress=False)  # fmt: skip
    keys = objective.keys("heldout", 64)
    before = objective.evaluate(objective.x0, keys)[1]
    after = objective.evaluate(result.x, keys)[1]
    return objective, result, before, after


def test_tuning_raises_the_heldout_yield_from_a_failing_start(simulator_run):
    objective, result, before, after = simulator_run
    assert objective.rotor_speed_limit == pytest.approx(rq.rotor_speed_limit(2.0))
    assert before["yield"] <= 0.1  # the default gains fail the set
    assert after["yield"] >= before["yield"] + 0.25, (before, after)
    low, high = result.validation["best"]["interval"]
    assert low <= after["yield"] <= high or after["yield"] >= high  # the interval is honest


def test_the_run_returns_its_best_validated_iterate(simulator_run):
    objective, result, _, _ = simulator_run
    assert result.steps == 1 + 3 * 5
    best = result.validation["best"]
    for row in result.history:
        if row["validation"] is not None:
            assert row["validation"] <= best["yield"] + 1e-12
    assert result.validation["initial"]["draws"] == 32


def test_an_interrupted_lagrangian_run_resumes_to_the_uninterrupted_result(tmp_path):
    objective = fl_objective()

    def run(out, stop_after=None, resume=False):
        strategy = st.AugmentedLagrangian(st.LBFGS(), 2, outer_steps=2, inner_steps=2)
        return driver.run(
            objective, strategy, driver.Budget(steps=strategy.requests), validation_draws=4,
            validate_every=3, checkpoint_every=1, out=out, stop_after=stop_after,
            resume=resume, progress=False,
        )  # fmt: skip

    whole = run(tmp_path / "whole")
    run(tmp_path / "part", stop_after=4)
    resumed = run(tmp_path / "part", resume=True)
    np.testing.assert_array_equal(resumed.x, whole.x)
    np.testing.assert_array_equal(resumed.state["lam"], whole.state["lam"])
    assert resumed.validation == whole.validation
    strip = [{k: v for k, v in row.items() if k != "wall_time_s"} for row in whole.history]
    assert [{k: v for k, v in r.items() if k != "wall_time_s"} for r in resumed.history] == strip


def test_a_union_objective_alternates_members():
    """Draw i of a union of scenarios is draw i of member i % members run alone (the same
    metrics, float32 within the union's rounding)."""
    reqs = rq.parse(
        {"requirements": [{"name": "t", "metric": "max_tilt", "max": 30, "unit": "deg"}]}
    )
    base = registry.get_controller_class("fl").default_gains()

    def metrics(scenario):
        spec = ProblemSpec(controller="fl", scenario=scenario, horizon=0.05, draws=4)
        objective = Objective(spec, base, reqs, target="tracking")
        return objective.evaluate(objective.x0, objective.sample(0))[2].metrics

    together = metrics((2, 3))
    for member, scenario_id in enumerate((2, 3)):
        alone = metrics(scenario_id)
        for name in ("max_tilt", "position_rmse", "torque_effort"):
            np.testing.assert_allclose(together[name][member::2], alone[name][member::2],
                                       rtol=1e-4, atol=1e-6, err_msg=name)  # fmt: skip
    assert not np.allclose(together["position_rmse"], alone["position_rmse"])
