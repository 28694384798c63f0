"""fojax.optimize: parameter maps, the cost, the objective (outputs, batching, gradients
against independent evaluations and finite differences), the strategies against
reference implementations, the driver (validation, budgets, resume), bad input."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import drive

from fojax import optimize, records, scenarios, simulator
from fojax.controllers import registry
from fojax.controllers.afonftsmc import AFONFTSMC, GAINS, paper_gains
from fojax.optimize import Evaluation, Objective, Outputs, Request, driver
from fojax.optimize import cost as cost_lib
from fojax.optimize import params as params_lib
from fojax.optimize import spec as spec_lib
from fojax.optimize import strategies as st

# ------------------------------------------------------------------ parameter maps


@pytest.mark.parametrize("share", ["paper", "none"])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_maps_give_only_feasible_gains(share, dtype):
    pmap = params_lib.make_parameter_map("afonftsmc", GAINS.names, share)
    base = paper_gains(dtype)
    template = pmap.to_params(base, dtype)
    rng = np.random.default_rng(1)
    for scale in (1.0, 10.0, 100.0, 1e4):
        params = {k: jnp.asarray(rng.normal(0, scale, v.shape), dtype) for k, v in template.items()}
        gains = pmap.to_gains(params, base)
        AFONFTSMC.check_gains(gains)  # raises on any infeasible entry
        for f in pmap.fields:
            value = np.asarray(getattr(gains, f.name))
            assert value.dtype == dtype
            assert np.all(f.bounds.contains(value)), f.name
    # The extremes, where sigmoid and exp saturate in float32.
    for extreme in (-1e30, 1e30):
        params = {k: jnp.full(v.shape, extreme, dtype) for k, v in template.items()}
        AFONFTSMC.check_gains(pmap.to_gains(params, base))


@pytest.mark.parametrize("share", ["paper", "none"])
def test_maps_invert_exactly(share):
    pmap = params_lib.make_parameter_map("afonftsmc", GAINS.names, share)
    base = paper_gains(jnp.float64)
    # gains -> params -> gains
    params = pmap.to_params(base, jnp.float64)
    back = pmap.to_gains(params, base)
    for name in base._fields:
        np.testing.assert_allclose(getattr(back, name), getattr(base, name), rtol=1e-14, atol=0)
    # params -> gains -> params, over the range a tuner visits
    rng = np.random.default_rng(2)
    params = {k: jnp.asarray(rng.uniform(-8, 8, v.shape)) for k, v in params.items()}
    again = pmap.to_params(pmap.to_gains(params, base), jnp.float64)
    for name in params:
        np.testing.assert_allclose(again[name], params[name], rtol=0, atol=1e-12)
    assert len(pmap.labels()) == pmap.size == pmap.ravel(params)[0].shape[0]


def test_sharing_ties_axes_and_untuned_fields_are_kept():
    pmap = params_lib.make_parameter_map("afonftsmc", None, "paper")
    assert "mu" not in pmap.names and "boundary_layer" not in pmap.names
    assert {"gamma1", "gamma2", "ratio", "power"} <= set(pmap.names)  # orders are tuned
    base = paper_gains(jnp.float64)
    params = pmap.to_params(base)
    assert params["surface_c1"].shape == (3,) and params["adaptation"].shape == (3, 3)
    params = {k: v + 0.3 for k, v in params.items()}
    gains = pmap.to_gains(params, base)
    c1 = np.asarray(gains.surface_c1)
    assert c1[0] == c1[1] and c1[3] == c1[4] == c1[5] and c1[2] != c1[0]
    np.testing.assert_array_equal(gains.mu, base.mu)
    np.testing.assert_array_equal(gains.boundary_layer, base.boundary_layer)
    np.testing.assert_allclose(c1, np.asarray(base.surface_c1) * np.exp(0.3), rtol=1e-14)


def test_maps_reject_unrepresentable_starts():
    pmap = params_lib.make_parameter_map("afonftsmc", None, "paper")
    gains = paper_gains(jnp.float64)
    with pytest.raises(ValueError, match=r"differs between the axes \(x, y\)"):
        pmap.to_params(gains._replace(surface_c1=gains.surface_c1.at[0].set(0.3)))
    with pytest.raises(ValueError, match="adaptation .* on or too close to a bound"):
        pmap.to_params(gains._replace(adaptation=jnp.zeros((6, 3))))
    with pytest.raises(ValueError, match="1 < p/q < 2"):
        pmap.to_params(gains._replace(ratio=jnp.full(6, 2.0)))
    with pytest.raises(ValueError, match="unknown gain fields for afonftsmc: kp"):
        params_lib.make_parameter_map("afonftsmc", ("kp",))
    with pytest.raises(ValueError, match="unknown sharing mode"):
        params_lib.make_parameter_map("afonftsmc", None, "pairs")


@pytest.mark.parametrize("name", registry.controller_names())
def test_every_registered_controller_has_a_parameter_map(name):
    cls = registry.get_controller_class(name)
    pmap = params_lib.make_parameter_map(name)
    assert pmap.size > 0
    naive = params_lib.naive_gains(name, jnp.float64)
    cls.check_gains(naive)
    params = pmap.to_params(naive)
    back = pmap.to_gains(params, naive)
    for field in naive._fields:
        np.testing.assert_allclose(getattr(back, field), getattr(naive, field), rtol=1e-14)


# -------------------------------------------------------------------------- cost


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"objective": "median"}, "unknown objective 'median'"),
        ({"error": "iae"}, "unknown error measure"),
        ({"effort_weight": -1.0}, "effort_weight must be a finite number >= 0"),
        (
            {
                "position_weight": 0,
                "attitude_weight": 0,
                "effort_weight": 0,
                "chattering_weight": 0,
            },
            "at least one cost weight",
        ),
        ({"cvar_fraction": 0.0}, "cvar_fraction must be in"),
    ],
)
def test_bad_cost_settings_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        cost_lib.CostConfig(**kwargs)


# ------------------------------------------------- one small problem shared by the tests

HORIZON = 0.3
COST = cost_lib.CostConfig(
    error="ise", effort_weight=1e-3, chattering_weight=1e-3, attitude_weight=2.0
)
SPEC = spec_lib.ProblemSpec(
    controller="afonftsmc",
    scenario=2,
    horizon=HORIZON,
    draws=3,
    seed=5,
    cost=COST,
    dtype="float64",
)
NAIVE = params_lib.naive_gains("afonftsmc", jnp.float64)


@functools.cache
def small() -> Objective:
    return Objective(SPEC, NAIVE)


@functools.cache
def reference_cost():
    """``cost(gains, keys)`` of :data:`SPEC`'s problem at the tuning law, composed from
    the simulator's functions without the engine, compiled once."""
    config = simulator.SimulationConfig(dt=SPEC.dt, horizon=HORIZON, save_every=10)
    controller = SPEC.make_controller("tanh", HORIZON)
    return jax.jit(
        cost_lib.make_batch_cost(controller, scenarios.get_scenario(2), config, COST, jnp.float64)
    )


def test_outputs_equal_the_rollout_and_do_not_depend_on_the_request():
    objective = small()
    rng = np.random.default_rng(3)
    points = objective.x0 + 0.3 * rng.normal(size=(4, objective.size))
    keys = objective.sample(1)
    together = objective.forward(points, keys, width=2.0)
    assert together.values.shape == (4, 3, 1) and together.terms.shape == (4, 3, 4)
    assert np.ptp(together.values[:, :, 0].mean(1)) > 1e-3  # the points differ
    batch = reference_cost()
    for i, x in enumerate(points):
        gains = objective.gains(x)
        gains = gains._replace(boundary_layer=gains.boundary_layer * 2.0)
        j, terms, status = batch(gains, keys)
        np.testing.assert_allclose(together.values[i, :, 0], j, rtol=1e-12)
        np.testing.assert_allclose(together.terms[i], terms, rtol=1e-12)
        np.testing.assert_array_equal(together.status[i], status)
        alone = objective.forward(x[None], keys, width=2.0)  # another request, same lanes
        np.testing.assert_array_equal(alone.values[0], together.values[i])
    # The evaluation law (sat) and the loss of the request path.
    evaluation = objective(Request(points, sample=1))
    sat = objective.forward(points, keys)
    np.testing.assert_allclose(evaluation.values, sat.values[:, :, 0].mean(1), rtol=1e-14)
    assert evaluation.draw_steps == 4 * 3 * SPEC.steps


def test_gradient_is_the_mean_of_the_per_draw_gradients_and_finite_differences():
    objective = small()
    x = objective.x0 + 0.1
    keys = objective.sample(0)
    evaluation = objective(Request(x[None], gradient=True, width=2.0))
    assert evaluation.bad_gradients == 0 and evaluation.gradient.shape == (objective.size,)
    batch = reference_cost()
    _, unravel = objective.param_map.ravel(objective.param_map.to_params(NAIVE, jnp.float64))

    def mean_cost(vector):  # an independent composition of the same functions
        gains = objective.param_map.to_gains(unravel(vector), NAIVE)
        gains = gains._replace(boundary_layer=NAIVE.boundary_layer * 2.0)
        return jnp.mean(batch(gains, keys)[0])

    value, gradient = jax.jit(jax.value_and_grad(mean_cost))(jnp.asarray(x))
    assert float(evaluation.values[0]) == pytest.approx(float(value), rel=1e-13)
    np.testing.assert_allclose(evaluation.gradient, gradient, rtol=1e-9, atol=1e-12)
    direction = np.random.default_rng(0).normal(size=x.size)
    eps = 1e-5
    ends = objective(Request(np.stack([x + eps * direction, x - eps * direction]), width=2.0))
    numeric = (ends.values[0] - ends.values[1]) / (2 * eps)
    assert abs(numeric) > 1e-3
    assert float(evaluation.gradient @ direction) == pytest.approx(numeric, rel=1e-5)


def test_cvar_loss_weights_the_worst_draws():
    costs = np.asarray([[1.0, 5.0, 2.0, 4.0, 3.0, 0.5, 7.0, 6.0]])
    outputs = Outputs(costs[..., None], np.zeros(costs.shape + (4,)), np.zeros(costs.shape, int))
    loss = optimize.MeanLoss(cost_lib.CostConfig(objective="cvar", cvar_fraction=0.25))
    value, weights = loss.weights(outputs)
    assert value[0] == pytest.approx(6.5)
    np.testing.assert_allclose(weights[0], [0, 0, 0, 0, 0, 0, 0.5, 0.5])
    diverged = Outputs(costs[..., None], outputs.terms, np.asarray([[0, 2, 0, 0, 0, 0, 0, 0]]))
    mean = optimize.MeanLoss(cost_lib.CostConfig(divergence_cost=99.0))
    assert mean.values(diverged)[0] == pytest.approx((costs.sum() - 5 + 99) / 8)


def test_validation_and_heldout_draws_are_disjoint_from_tuning_draws():
    objective = small()
    validation = set(map(tuple, objective.keys("validation", 64).tolist()))
    heldout = set(map(tuple, objective.keys("heldout", 64).tolist()))
    tuning = set(map(tuple, objective.sample(0, 4096).tolist()))
    assert len(validation) == 64 and not validation & heldout and not validation & tuning
    assert not heldout & tuning


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="draws must be an integer >= 1"):
        spec_lib.ProblemSpec(draws=0)
    with pytest.raises(ValueError, match="whole, positive number of steps"):
        spec_lib.ProblemSpec(horizon=0.0105, dt=0.001 * 2)
    with pytest.raises(ValueError, match="unknown controller 'pid'"):
        spec_lib.ProblemSpec(controller="pid")
    with pytest.raises(ValueError, match="fractional='gl' does not apply to fl"):
        spec_lib.ProblemSpec(controller="fl", fractional="gl")
    with pytest.raises(ValueError, match="device_batch=4 applies to draws split over a mesh"):
        Objective(SPEC, NAIVE, device_batch=4)
    with pytest.raises(ValueError, match="target must be one of"):
        Objective(SPEC, NAIVE, target="effort")  # a target needs a requirement set
    with pytest.raises(ValueError, match="untuned fields differ"):
        small().vector(NAIVE._replace(mu=NAIVE.mu * 2))
    with pytest.raises(ValueError, match="a gradient is taken at one point"):
        small()(Request(np.zeros((2, small().size)), gradient=True, width=1.0))
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        st.adam(0)
    with pytest.raises(ValueError, match="a budget needs a limit"):
        driver.Budget()
    with pytest.raises(ValueError, match="method must be one of"):
        st.make("bfgs", None)


# --------------------------------------------------- strategies against references


class _Function:
    """A strategy driven on an analytic function (no simulator): ``f(x)`` and its
    gradient per point."""

    def __init__(self, f, grad=None):
        self.f, self.grad, self.evaluations = f, grad, 0

    def __call__(self, request: Request) -> Evaluation:
        points = np.atleast_2d(request.points)
        self.evaluations += len(points)
        values = np.asarray([self.f(x) for x in points])
        gradient = self.grad(points[0]) if request.gradient else None
        outputs = Outputs(
            values[:, None, None], np.zeros((len(points), 1, 4)), np.zeros((len(points), 1), int)
        )
        return Evaluation(values, gradient, outputs, 0, 0)


def test_lbfgs_minimises_rosenbrock_like_scipy():
    from scipy import optimize as scipy_optimize

    function = _Function(scipy_optimize.rosen, scipy_optimize.rosen_der)
    strategy = st.LBFGS(memory=5, max_step=0.5)
    x0 = np.asarray([-1.2, 1.0, -0.5, 0.8])
    state, values = strategy.init(x0), []
    for _ in range(400):
        request = strategy.ask(state)
        state = strategy.tell(state, request, function(request))
        if bool(state["moved"]):
            values.append(float(state["f"]))
    assert np.all(np.diff(values) <= 0)  # sufficient decrease at every move
    reference = scipy_optimize.minimize(function.f, x0, jac=function.grad, method="L-BFGS-B")
    np.testing.assert_allclose(reference.x, np.ones(4), atol=1e-4)
    np.testing.assert_allclose(strategy.answer(state), reference.x, atol=1e-4)


def test_nelder_mead_takes_scipys_steps():
    from scipy import optimize as scipy_optimize

    x0 = np.asarray([-1.2, 1.0, -0.5])
    simplex = x0[None] + np.vstack([np.zeros(3), 0.5 * np.eye(3)])
    budget = 120
    reference = scipy_optimize.minimize(
        scipy_optimize.rosen,
        x0,
        method="Nelder-Mead",
        options={"maxfev": budget, "initial_simplex": simplex, "xatol": 0, "fatol": 0},
    )
    function = _Function(scipy_optimize.rosen)
    strategy, state = st.NelderMead(step=0.5), None
    state = strategy.init(x0)
    while True:  # as SciPy: stop before an evaluation past the budget
        request = strategy.ask(state)
        if function.evaluations + len(request.points) > budget:
            break
        state = strategy.tell(state, request, function(request))
    # SciPy stops inside the iteration that passes maxfev; both hold the same best vertex.
    np.testing.assert_array_equal(strategy.answer(state), reference.x)
    assert float(state["values"][0]) == reference.fun


def test_cma_es_converges_like_the_cma_package():
    """On a sphere and an ill-conditioned ellipsoid in 10-D the engine's CMA-ES needs
    about the evaluations the ``cma`` package needs (medians over five seeds)."""
    cma = pytest.importorskip("cma")
    d = 10
    scales = 10.0 ** (3 * np.arange(d) / (d - 1))
    for f in (lambda x: float(x @ x), lambda x: float(np.sum((scales * x) ** 2))):
        ours, theirs = [], []
        for seed in range(5):
            function, strategy = _Function(f), st.CMAES(sigma0=0.5, seed=seed)
            state = strategy.init(np.ones(d))
            while f(strategy.answer(state)) > 1e-8 and function.evaluations < 40_000:
                request = strategy.ask(state)
                state = strategy.tell(state, request, function(request))
            ours.append(function.evaluations)
            es = cma.CMAEvolutionStrategy(np.ones(d), 0.5, {"seed": seed + 1, "verbose": -9})
            count = 0
            while f(es.mean) > 1e-8 and count < 40_000:
                candidates = es.ask()
                es.tell(candidates, [f(np.asarray(c)) for c in candidates])
                count += len(candidates)
            theirs.append(count)
        assert np.median(ours) <= 1.3 * np.median(theirs), (ours, theirs)


def test_separable_cma_es_converges_like_the_cma_package_and_stays_diagonal():
    """On a separable ellipsoid in 30-D (scales over three decades) the diagonal CMA-ES
    needs about the evaluations the ``cma`` package's separable CMA-ES
    (``CMA_diagonal``) needs, a third of the full one's, and its covariance stays
    diagonal (medians over five seeds)."""
    cma = pytest.importorskip("cma")
    d = 30
    scales = 10.0 ** (3 * np.arange(d) / (d - 1))

    def f(x):
        return float(np.sum((scales * x) ** 2))

    def evaluations(strategy):
        function, state = _Function(f), strategy.init(np.ones(d))
        while f(strategy.answer(state)) > 1e-8 and function.evaluations < 100_000:
            request = strategy.ask(state)
            state = strategy.tell(state, request, function(request))
            C = state["C"]
            assert not diagonal or np.array_equal(C, np.diag(np.diag(C)))
        return function.evaluations

    found = {}
    for diagonal in (True, False):
        found[diagonal] = [evaluations(st.CMAES(0.5, seed=s, diagonal=diagonal)) for s in range(5)]
    theirs = []
    for seed in range(5):
        options = {"seed": seed + 1, "verbose": -9, "CMA_diagonal": True}
        es, count = cma.CMAEvolutionStrategy(np.ones(d), 0.5, options), 0
        while f(es.mean) > 1e-8 and count < 100_000:
            candidates = es.ask()
            es.tell(candidates, [f(np.asarray(c)) for c in candidates])
            count += len(candidates)
        theirs.append(count)
    assert np.median(found[True]) <= 1.3 * np.median(theirs), (found[True], theirs)
    assert np.median(found[True]) <= 0.5 * np.median(found[False]), found


def test_optax_strategy_is_the_optax_transformation():
    import optax

    strategy = st.adam(5, learning_rate=0.1, sample="fixed")
    function = _Function(lambda x: float(x @ x), lambda x: 2 * x)
    state = drive(function, strategy, np.ones(3), 5)
    tx = optax.chain(
        optax.clip_by_global_norm(1.0), optax.adam(optax.cosine_decay_schedule(0.1, 4, alpha=0.1))
    )
    x, opt = jnp.ones(3), tx.init(jnp.ones(3))
    for _ in range(5):
        updates, opt = tx.update(2 * x, opt, x)
        x = optax.apply_updates(x, updates)
    np.testing.assert_allclose(strategy.answer(state), x, rtol=1e-6)


# ------------------------------------------------------------------ the driver


def _run(tmp, strategy, steps, stop_after=None, resume=False, **kw):
    kw = {"validation_draws": 2, "validate_every": 2, "checkpoint_every": 1, **kw}
    return driver.run(
        small(),
        strategy,
        driver.Budget(steps=steps),
        out=tmp,
        resume=resume,
        stop_after=stop_after,
        progress=False,
        **kw,
    )


def _rows(result):
    return [{k: v for k, v in row.items() if k != "wall_time_s"} for row in result.history]


@pytest.mark.parametrize(
    "strategy",
    [
        st.LBFGS(max_step=0.5),
        st.adam(4, learning_rate=0.1),
        st.Chain(st.CMAES(popsize=4, seed=1), st.LBFGS(max_step=0.5), 2),
        st.MultiStart(starts=((0.1,) * 33,), stages=((2, 2, 2),), draws=2, popsize=4,
                      coarse_dt=2e-3, window=20, lift=0.5, diagonal=False),  # fmt: skip
    ],
    ids=["lbfgs", "adam", "chain", "multistart"],
)
def test_resumed_run_equals_uninterrupted_run(tmp_path, strategy):
    full = _run(tmp_path / "full", strategy, 4)
    part = _run(tmp_path / "part", strategy, 4, stop_after=2)
    assert part.steps == 2
    resumed = _run(tmp_path / "part", strategy, 4, resume=True)
    assert resumed.steps == 4 and _rows(resumed) == _rows(full)
    np.testing.assert_array_equal(resumed.x, full.x)
    np.testing.assert_array_equal(resumed.final_x, full.final_x)
    assert resumed.validation == full.validation  # the true start's validation kept
    header = (tmp_path / "part" / "history.csv").read_text().splitlines()
    assert header[0].startswith(",".join(driver.COLUMNS)) and len(header) == 5


def test_ctrl_c_during_a_validation_resumes_to_the_uninterrupted_run(tmp_path, monkeypatch):
    """Ctrl-C while a step's validation runs (the step's evaluation already counted, its
    row not yet written): the checkpoint holds the run before that step, which the
    resumed run takes again, to the uninterrupted run's rows and gains."""
    strategy = st.CMAES(popsize=4, seed=1)
    full = _run(tmp_path / "full", strategy, 4)
    score = driver._Run.score

    def interrupted(self, x):
        if self.used["steps"] == 2:  # the second step's validation (every 2 steps)
            raise KeyboardInterrupt
        return score(self, x)

    monkeypatch.setattr(driver._Run, "score", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path / "part", strategy, 4)
    monkeypatch.setattr(driver._Run, "score", score)
    header = records.read_arrays(tmp_path / "part" / driver.CHECKPOINT)[1]
    assert header["used"]["steps"] == 1 and len(header["history"]) == 1
    resumed = _run(tmp_path / "part", strategy, 4, resume=True)
    assert resumed.steps == 4 and _rows(resumed) == _rows(full)
    np.testing.assert_array_equal(resumed.x, full.x)
    assert resumed.validation == full.validation


def test_host_linear_algebra_runs_on_one_thread_during_a_run_only():
    import threadpoolctl

    def blas_threads():
        found = threadpoolctl.threadpool_info()
        return {i["num_threads"] for i in found if i["user_api"] == "blas"}

    assert blas_threads(), "no BLAS library found: nothing to check"
    seen = []
    with threadpoolctl.threadpool_limits(2, user_api="blas"):
        before = blas_threads()
        if before == {1}:
            pytest.skip("BLAS runs on one thread on this machine: nothing to limit")
        driver.run(small(), st.CMAES(popsize=4, seed=1), driver.Budget(steps=2),
                   validation_draws=0, progress=False,
                   callback=lambda step, x, row: seen.append(blas_threads()))  # fmt: skip
        after = blas_threads()
    assert seen == [{1}, {1}] and after == before


@pytest.mark.parametrize("learning_rate", [0.1, 30.0])
def test_the_best_validated_answer_is_returned(learning_rate):
    # 0.1: tuning helps; 30: every step throws the gains by e^30, the start must come back.
    answers = {}
    objective = small()
    result = driver.run(
        objective,
        st.adam(4, learning_rate=learning_rate),
        driver.Budget(steps=4),
        validation_draws=4,
        validate_every=2,
        progress=False,
        callback=lambda step, x, row: answers.__setitem__(step, x),
    )
    answers[0] = objective.x0
    keys = objective.keys("validation", 4)

    def cost(x):  # a diverged draw costs divergence_cost
        out = objective.forward(x[None], keys)
        return float(np.mean(np.where(out.valid[0], out.values[0, :, 0], COST.divergence_cost)))

    cost = {step: cost(x) for step, x in answers.items()}
    for row in result.history:
        if row["step"] in (2, 4):
            assert row["validation"] == pytest.approx(cost[row["step"]], rel=1e-12)
        else:
            assert row["validation"] is None
    best = min((0, 2, 4), key=lambda s: (cost[s], s))
    assert result.returned_step == best
    np.testing.assert_array_equal(result.x, answers[best])
    assert result.validation["initial"]["cost"] == pytest.approx(cost[0], rel=1e-12)
    if learning_rate == 30.0:
        assert best == 0 and cost[4] > cost[0]
    else:
        assert best > 0 and cost[best] < 0.9 * cost[0]


def test_budgets_are_respected():
    objective = small()
    per_point = SPEC.draws * SPEC.steps
    cma = driver.run(
        objective,
        st.CMAES(popsize=4),
        driver.Budget(draw_steps=3 * 4 * per_point + 5),
        validation_draws=0,
        progress=False,
    )
    assert cma.steps == 3 and cma.draw_steps == 12 * per_point
    nm = driver.run(
        objective,
        st.NelderMead(),
        driver.Budget(evaluations=objective.size + 12),
        validation_draws=0,
        progress=False,
    )
    assert sum(row["points"] for row in nm.history) <= objective.size + 12
    start = objective(Request(objective.x0[None])).values[0]
    assert min(row["loss"] for row in nm.history) <= start
    AFONFTSMC.check_gains(objective.gains(nm.x))


def test_failed_starts_never_write_or_overwrite(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="nothing to resume"):
        driver.check_resume(out, {"a": 1}, resume=True)
    assert not out.exists()
    _run(out, st.LBFGS(), 1)
    checkpoint = out / driver.CHECKPOINT
    before = checkpoint.read_bytes()
    with pytest.raises(ValueError, match="pass --resume to continue it"):
        _run(out, st.LBFGS(), 1)
    with pytest.raises(
        ValueError, match=r"another configuration.*\n  strategy.max_step: checkpoint 1.0, now 0.5"
    ):
        _run(out, st.LBFGS(max_step=0.5), 1, resume=True)
    assert checkpoint.read_bytes() == before


def test_a_study_goes_on_from_a_checkpoint_of_its_own_settings_and_code(tmp_path, monkeypatch):
    def steps_run(out, **kw):
        seen = []
        result = _run(out, st.LBFGS(max_step=0.5), 4, callback=lambda s, x, r: seen.append(s), **kw)
        return result, seen

    full, _ = steps_run(tmp_path / "full")
    steps_run(tmp_path / "same", stop_after=2)
    went_on, seen = steps_run(tmp_path / "same", resume="if-same")
    assert seen == [3, 4] and _rows(went_on) == _rows(full)
    with monkeypatch.context() as m:  # a checkpoint written by other code
        m.setattr(driver.records, "code_digest", lambda: "0123456789abcdef")
        steps_run(tmp_path / "other", stop_after=2)
    with pytest.raises(ValueError, match=r"(?s)code: checkpoint \"0123456789abcdef\".*source"):
        steps_run(tmp_path / "other", resume=True)
    again, seen = steps_run(tmp_path / "other", resume="if-same")
    assert seen == [1, 2, 3, 4] and _rows(again) == _rows(full)
    with pytest.raises(ValueError, match="resume must be True, False or 'if-same'"):
        steps_run(tmp_path / "other", resume="yes")


def test_a_run_resumed_after_it_converged_takes_no_step_and_returns_the_same(tmp_path):
    budget = driver.Budget(steps=40, patience=2, tolerance=0.5)  # converges early

    def run(budget=budget, **kw):
        return driver.run(small(), st.LBFGS(max_step=0.5), budget, out=tmp_path / "run",
                          validation_draws=2, validate_every=1, progress=False, **kw)  # fmt: skip

    first = run()
    assert first.steps < budget.steps  # stopped by its convergence test
    again = run(resume=True)
    assert again.steps == first.steps and again.returned_step == first.returned_step
    np.testing.assert_array_equal(again.x, first.x)
    assert _rows(again) == _rows(first)
    # resumed without the convergence stop, it goes on
    assert run(driver.Budget(steps=first.steps + 2), resume=True).steps == first.steps + 2


def test_short_tuning_lowers_the_heldout_cost():
    objective = small()
    result = driver.run(
        objective,
        st.make("cma-lbfgs", st.Problem(objective, objective.x0), 8, switch=3, popsize=6),
        driver.Budget(steps=8),
        validation_draws=4,
        progress=False,
    )
    keys = objective.keys("heldout", 8)
    before = objective.forward(objective.x0[None], keys).values[0, :, 0]
    after = objective.forward(result.x[None], keys).values[0, :, 0]
    AFONFTSMC.check_gains(objective.gains(result.x))
    assert after.mean() < 0.8 * before.mean()
    assert np.mean(after < before) >= 0.75  # better on most draws, not on average only


# ------------------------------------------------------------------ the default method


def test_a_tie_maps_full_parameters_onto_the_shared_ones():
    """``x = z[tie]``: every axis of a shared group takes its group's parameter, the
    fields keep their order (checked through the parameters' names)."""
    fine = params_lib.make_parameter_map("afonftsmc", None, "none")
    coarse = params_lib.make_parameter_map("afonftsmc", None, "paper")
    tie = fine.tie(coarse)
    assert tie.shape == (fine.size,) and sorted(set(tie)) == list(range(coarse.size))
    groups = {"x": "x=y", "y": "x=y", "z": "z", "phi": "phi=theta=psi", "theta": "phi=theta=psi",
              "psi": "phi=theta=psi"}  # fmt: skip
    for label, index in zip(fine.labels(), tie, strict=True):
        name, axis, *rest = label.replace("]", "").split("[")
        assert coarse.labels()[index] == name + "".join(f"[{p}]" for p in (groups[axis], *rest))
    with pytest.raises(ValueError, match="same fields"):
        fine.tie(params_lib.make_parameter_map("afonftsmc", ("surface_c1",), "paper"))


def test_integer_order_gains_move_only_the_declared_orders():
    gains = params_lib.integer_order_gains(NAIVE)
    np.testing.assert_allclose(gains.gamma1, 0.99)  # D^(gamma1 - 1): the identity at 1
    np.testing.assert_allclose(gains.gamma2, 0.01)  # I^gamma2: the identity at 0
    for name in set(GAINS.names) - {"gamma1", "gamma2"}:
        np.testing.assert_array_equal(getattr(gains, name), getattr(NAIVE, name))
    fobsmc = registry.get_controller_class("fobsmc")
    np.testing.assert_allclose(params_lib.integer_order_gains(fobsmc.default_gains()).order, 0.99)
    fl = registry.get_controller_class("fl").default_gains()
    assert params_lib.integer_order_gains(fl) == fl  # no fractional order


def test_auto_searches_from_the_start_its_integer_orders_and_the_knowledge_free_start():
    objective = small()
    x0 = objective.vector(paper_gains(jnp.float64))
    found = st.starts(objective, x0)
    naive = objective.vector(params_lib.integer_order_gains(NAIVE))
    # The paper's orders are already 0.99 and 0.01: one other start, the naive gains'.
    assert len(found) == 1 and np.allclose(found[0], naive)
    from_naive = st.starts(objective, objective.vector(NAIVE))
    assert len(from_naive) == 1 and np.allclose(from_naive[0], naive)
    strategy = st.make("auto", st.Problem(objective, x0))
    assert isinstance(strategy, st.MultiStart) and len(strategy.starts) == 3
    assert strategy.tie is None and strategy.coarse_dt == 2 * objective.spec.dt
    constrained = st.make("auto", st.Problem(objective, x0, constrained=True))
    assert isinstance(constrained, st.CMAES) and constrained.draws is None  # --draws


def test_auto_moves_only_the_tuned_orders_to_integer_order():
    """With an order field left untuned (``--fields``), auto's integer-order starts keep
    it at the base gains' value (the objective takes no other: :meth:`Objective.vector`)."""
    objective = Objective(dataclasses.replace(SPEC, fields=("surface_c1", "gamma1")), NAIVE)
    found = st.starts(objective, objective.x0)
    assert len(found) == 1  # the naive gains are the base: one start, at integer gamma1
    gains = objective.gains(found[0])
    np.testing.assert_allclose(gains.gamma1, 0.99)
    np.testing.assert_array_equal(gains.gamma2, NAIVE.gamma2)  # untuned: as it was
    strategy = st.make("auto", st.Problem(objective, objective.x0))
    assert len(strategy.starts) == 3


def test_auto_over_an_envelope_flies_every_case_in_every_sample():
    """Over a union of K cases every draws per point of ``auto`` is a multiple of K
    (each case equally often in every sample), the second phase's candidates fill the
    first phase's declared lanes, and a tuning sample's draws fly the cases in turn."""
    from fojax import envelope as envelope_lib

    loaded = envelope_lib.load("examples/envelopes/paper_and_manoeuvres.toml")
    spec = optimize.ProblemSpec(scenario=None, envelope=loaded, horizon=0.1)
    gains = spec.make_controller("sat", 0.1).default_gains("float32")
    objective = optimize.Objective(spec, gains)
    cases, method = objective.members, st.METHODS["auto"]
    assert cases == 6 and objective.stratified(4) == 6 and objective.stratified(12) == 12
    strategy = method.make(st.Problem(objective, objective.x0))
    (generations, searches, draws), = method.plan()["stages"]
    assert strategy.stages == ((generations, searches, 6),) and strategy.draws == 12
    lam = st.CMAES().constants(objective.size)["lam"]
    assert strategy.popsize == searches * (lam + 1) * draws // 12 - 1
    assert strategy.lanes(objective.size) == (strategy.popsize + 1) * 12
    members = [objective._members(4, 4 * k) for k in range(3)]  # 4-draw samples 0, 1, 2
    assert np.array_equal(np.sort(np.concatenate(members)), np.repeat(np.arange(6), 2))


def test_the_auto_plan_is_its_table_entry_and_says_when_steps_cut_it():
    """``auto``'s strategy is built from its table entry's settings alone (a setting given
    to ``make`` replaces it), and its plan in words says when ``steps`` end within the
    first phase."""
    objective, method = small(), st.METHODS["auto"]
    plan, d = method.plan(), small().size
    strategy = method.make(st.Problem(objective, objective.x0))
    (generations, searches, draws), = plan["stages"]
    assert strategy.stages == plan["stages"] and len(strategy.starts) == searches - 1
    assert strategy.coarse_dt == plan["coarse"] * objective.spec.dt
    assert (strategy.draws, strategy.diagonal) == (plan["draws"], plan["diagonal"])
    assert (strategy.window, strategy.lift) == (plan["window"], plan["lift"])
    lam = st.CMAES().constants(d)["lam"]  # "fill": the first phase's lanes on 8 draws
    assert strategy.popsize == searches * (lam + 1) * draws // plan["draws"] - 1
    assert strategy.lanes(d) == (strategy.popsize + 1) * plan["draws"]
    assert strategy.lanes(d) == searches * (lam + 1) * draws  # one scenario: the same lanes
    full = strategy.plan(method.steps, d)
    assert full.startswith(f"{searches} CMA-ES searches ({lam} candidates and the mean each) "
                           f"for {generations} generations on {draws} draws at a 2 ms step")
    assert full.endswith(f"then the best continued alone (separable CMA-ES, {strategy.popsize} "
                         f"candidates on {plan['draws']} draws) for up to "
                         f"{method.steps - generations} generations")  # fmt: skip
    cut = strategy.plan(30, d)
    assert cut.startswith("the first phase alone: ") and f"for 30 of its {generations} " in cut
    assert cut.endswith(f"continued only with more than {generations} steps")
    small_plan = method.make(st.Problem(objective, objective.x0), stages=((3, 2, 2),))
    assert small_plan.search == 3 and len(small_plan.starts) == 1
    with pytest.raises(ValueError, match="its settings: stages, coarse"):
        method.make(st.Problem(objective, objective.x0), searches=3)


class _Bowls:
    """A two-basin function of ``d`` parameters for strategies: a shallow bowl at
    ``+1`` (the start's side) and a deeper one at ``-2`` (``min`` of two quadratics)."""

    spec = spec_lib.ProblemSpec(horizon=0.01, dt=1e-3)

    def __init__(self, d):
        self.size, self.calls = d, []

    @staticmethod
    def value(points):
        a = np.sum((points - 1.0) ** 2, -1) + 1.0
        b = np.sum((points + 2.0) ** 2, -1)
        return np.minimum(a, b)

    def __call__(self, request):
        self.calls.append(request)
        values = self.value(np.atleast_2d(request.points))
        outputs = Outputs(values[:, None, None], np.zeros((len(values), 1, 4)),
                          np.zeros((len(values), 1), np.int32))  # fmt: skip
        return Evaluation(values, None, outputs, 0, len(values), len(values))


def test_multistart_keeps_the_best_search_and_continues_it_lifted():
    """Two searches, one from the start near the shallow bowl, one from a start near
    the deep one: the second is kept and continued in the full space (``tie`` pairs the
    coordinates), at the coarse step first and the full step after."""
    d, objective = 4, _Bowls(4)
    strategy = st.MultiStart(starts=((-1.5,) * d,), tie=(0, 0, 1, 1), sigma0=0.3,
                             stages=((30, 2, 1),), draws=1, coarse_dt=2e-3, window=20,
                             lift=0.5, diagonal=False)  # fmt: skip
    state = strategy.init(np.full(d, 1.2))
    for _ in range(80):
        request = strategy.ask(state)
        state = strategy.tell(state, request, objective(request))
    first, later = objective.calls[0], objective.calls[-1]
    assert first.dt == 2e-3 and later.dt is None
    # Phase 1: each search's candidates and its mean, tied coordinates equal.
    lam = st.CMAES().constants(2)["lam"]
    assert first.points.shape == (2 * (lam + 1), d)
    np.testing.assert_array_equal(first.points[:, 0], first.points[:, 1])
    assert int(state["chosen"]) == 1  # the search from the deep bowl's side
    assert later.points.shape[0] == st.CMAES().constants(d)["lam"]
    assert not np.array_equal(later.points[:, 0], later.points[:, 1])  # lifted: untied
    np.testing.assert_allclose(strategy.answer(state), -2.0, atol=0.05)


def test_multistart_continues_separable_when_diagonal():
    """With ``diagonal`` the continued search starts from the lifted covariance's
    diagonal and keeps its covariance diagonal, and still ends in the deep bowl."""
    d, objective = 4, _Bowls(4)
    strategy = st.MultiStart(starts=((-1.5,) * d,), tie=(0, 0, 1, 1), sigma0=0.3,
                             stages=((30, 2, 1),), draws=1, window=20, lift=0.5,
                             diagonal=True)  # fmt: skip
    state = strategy.init(np.full(d, 1.2))
    for generation in range(80):
        request = strategy.ask(state)
        state = strategy.tell(state, request, objective(request))
        C = state["final"]["C"]
        if generation >= 29:  # lifted at the end of the first phase
            assert np.array_equal(C, np.diag(np.diag(C)))
            assert np.all(np.diag(C) > 0)
    assert strategy._search(-1).diagonal and not strategy._search(0).diagonal
    np.testing.assert_allclose(strategy.answer(state), -2.0, atol=0.05)


def test_convergence_ends_a_run_whose_validation_stopped_improving():
    budget = driver.Budget(steps=100, patience=4, tolerance=0.01)
    scores = [(0, 10.0), (2, 5.0), (4, 4.99), (6, 4.98)]
    assert not budget.converged(scores[:2], 3)  # fewer steps than the patience
    assert not budget.converged(scores[:3], 4)  # 10 -> 4.99 since step 0
    assert budget.converged(scores, 6)  # 5.0 -> 4.98 over the last 4 steps: < 1 %
    assert not driver.Budget(steps=100).converged(scores, 6)  # no patience: never
    assert not budget.converged(scores, 6, since=4)  # from step 4: fewer steps than 4
    late = scores + [(8, 4.97), (10, 4.97)]
    assert budget.converged(late, 10, since=4)  # 4.99 -> 4.97 since step 6
    # the first phase's 3.0 does not count: 4.99 -> 4.0 since step 4
    assert not budget.converged([(2, 3.0), (4, 4.99), (8, 4.0)], 8, since=4)


def test_auto_is_not_judged_converged_while_its_searches_are_ranked():
    """A plateau in the first phase (the leading search's mean validated alike for many
    generations) does not end the run; the second phase is judged from its first step,
    on its own validations."""
    strategy = st.MultiStart(starts=((0.0,) * 4,), stages=((30, 2, 1),), draws=1, window=20,
                             lift=0.5, diagonal=False)  # fmt: skip
    objective, state = _Bowls(4), strategy.init(np.ones(4))
    seen = []
    for _ in range(40):
        seen.append(strategy.settling(state))
        request = strategy.ask(state)
        state = strategy.tell(state, request, objective(request))
    assert seen == [None] * 30 + [30] * 10


def test_every_method_declares_its_options_and_refuses_others():
    problem = st.Problem(small(), small().x0)
    for name, method in st.METHODS.items():
        strategy = method.make(problem)  # every default builds
        assert strategy is not None, name
        with pytest.raises(ValueError, match=f"method {name} takes no option bogus"):
            method.make(problem, bogus=1)
    with pytest.raises(ValueError, match="leave no L-BFGS step after 30"):
        st.make("cma-lbfgs", problem, 30)


def test_compiling_ahead_runs_nothing_and_leaves_nothing_to_compile(monkeypatch):
    """The programs are compiled from their arguments' shapes (no call on blank
    inputs), and the first call compiles no program of its own again."""
    from jax._src import dispatch

    compiled = []

    def listen(event, duration, fun_name=None, **_):
        if event == dispatch.BACKEND_COMPILE_EVENT:
            compiled.append(fun_name)

    objective = Objective(SPEC, NAIVE, lanes=6)  # a fresh one: nothing compiled yet
    calls = []
    objective.compile("sampler")
    objective.compile("forward", None, 2e-3)
    program = objective._forward(objective.switching, HORIZON, objective.scenario, True, 2e-3)
    real = program.program
    monkeypatch.setattr(program, "program", lambda *a: calls.append(a) or real(*a))
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        objective.forward(objective.x0[None], objective.sample(0), dt=2e-3)
    finally:
        jax._src.monitoring.unregister_event_duration_listener(listen)
    assert len(calls) == 1  # compile() ran nothing; the call ran the program once
    assert not [name for name in compiled if "lanes" in str(name)], compiled
