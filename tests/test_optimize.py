"""optimize/: parameter maps, the tuning cost and its gradient, the tuner, resume,
derivative-free baselines, bad input."""

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax.controllers import registry
from fojax.controllers.afonftsmc import AFONFTSMC, GAINS, paper_gains
from fojax.optimize import cost as cost_lib
from fojax.optimize import params as params_lib
from fojax.optimize import problem as problem_lib
from fojax.optimize import tuner as tuner_lib

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


def test_mean_and_cvar_weights():
    costs = jnp.asarray([1.0, 5.0, 2.0, 4.0, 3.0, 0.5, 7.0, 6.0])
    mean, w = cost_lib.combine(cost_lib.CostConfig(), costs)
    assert float(mean) == pytest.approx(3.5625) and np.allclose(w, 1 / 8)
    cvar_config = cost_lib.CostConfig(objective="cvar", cvar_fraction=0.25)
    cvar, w = cost_lib.combine(cvar_config, costs)
    assert float(cvar) == pytest.approx(6.5)  # mean of the two worst, 7 and 6
    np.testing.assert_allclose(w, [0, 0, 0, 0, 0, 0, 0.5, 0.5])
    assert cost_lib.CostConfig(objective="cvar", cvar_fraction=0.3).tail_count(10) == 3
    guarded, diverged = cost_lib.guard(
        cost_lib.CostConfig(divergence_cost=99.0),
        jnp.asarray([1.0, jnp.nan, 2.0]),
        jnp.asarray([0, 0, 2], jnp.int32),
    )
    np.testing.assert_array_equal(guarded, [1.0, 99.0, 99.0])
    np.testing.assert_array_equal(diverged, [False, True, True])


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
SPEC = problem_lib.ProblemSpec(
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
def small_problem():
    return problem_lib.TuningProblem(SPEC, NAIVE)


def test_cost_gradient_matches_finite_differences():
    problem = small_problem()
    params = problem.initial_params()
    rng = np.random.default_rng(0)
    direction = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in params.items()}
    keys = problem.minibatch_keys(0)
    scale = 2.0
    step = problem.value_and_grad(params, scale, keys)
    assert int(step.bad_gradients) == 0 and not np.any(step.costs.diverged)
    terms = np.asarray(step.costs.terms)
    assert np.all(terms > 0)  # every term (tracking, effort, chattering) is exercised
    analytic = sum(float(jnp.vdot(step.gradient[k], direction[k])) for k in params)

    def objective(eps):
        shifted = {k: params[k] + eps * direction[k] for k in params}
        return float(problem.value(shifted, scale, keys).objective)

    eps = 1e-5
    numeric = (objective(eps) - objective(-eps)) / (2 * eps)
    assert abs(analytic) > 1e-3
    assert analytic == pytest.approx(numeric, rel=1e-5)
    # The value-only path gives the same objective as the gradient path.
    assert float(problem.value(params, scale, keys).objective) == pytest.approx(
        float(step.objective), rel=1e-13
    )


def test_the_gradient_program_is_open_to_memory_analysis():
    """experiments.tune_memory reads the compiled gradient's working set."""
    problem = small_problem()
    keys = problem.minibatch_keys(0)
    compiled = problem.lower_gradient(problem.initial_params(), 2.0, keys).compile()
    assert compiled.memory_analysis().temp_size_in_bytes > 0
    leading = {leaf.shape[0] for leaf in jax.tree.leaves(compiled.out_info)}
    assert leading == {keys.shape[0]}  # per-draw values, reduced by the caller


def _run(tmp, steps, stop_after=None, resume=False, config_overrides=None):
    settings = {"method": "adam", "learning_rate": 0.1, **(config_overrides or {})}
    config = tuner_lib.TunerConfig(steps=steps, checkpoint_every=1, **settings)
    run = tuner_lib.prepare(SPEC, config, NAIVE, "naive", tmp, resume=resume)
    return tuner_lib.tune(run, progress=False, stop_after=stop_after, problem=small_problem())


def test_resumed_run_equals_uninterrupted_run(tmp_path):
    full = _run(tmp_path / "full", 4)
    part = _run(tmp_path / "part", 4, stop_after=2)
    assert part.completed == 2 and not (tmp_path / "part" / "gains.json").exists()
    resumed = _run(tmp_path / "part", 4, resume=True)
    assert resumed.completed == 4
    for name in full.params:
        np.testing.assert_array_equal(
            np.asarray(resumed.params[name]), np.asarray(full.params[name])
        )
    strip = [{k: v for k, v in row.items() if k != "wall_time_s"} for row in full.history]
    again = [{k: v for k, v in row.items() if k != "wall_time_s"} for row in resumed.history]
    assert again == strip
    assert (tmp_path / "part" / "gains.json").read_text().split('"metadata"')[0] == (
        tmp_path / "full" / "gains.json"
    ).read_text().split('"metadata"')[0]
    rows = (tmp_path / "part" / "history.csv").read_text().strip().splitlines()
    assert rows[0].split(",") == list(tuner_lib.HISTORY_COLUMNS) and len(rows) == 5


def test_short_tuning_lowers_cost_on_heldout_draws():
    result = tuner_lib.tune(
        tuner_lib.prepare(
            SPEC,
            tuner_lib.TunerConfig(steps=12, method="adam", learning_rate=0.1),
            NAIVE,
            "naive",
            None,
        ),
        progress=False,
        problem=small_problem(),
    )
    keys = small_problem().heldout_keys(8)
    # Held-out draws are not in any minibatch.
    train = np.asarray(small_problem().minibatch_keys(0, draws=12 * SPEC.draws))
    assert not set(map(tuple, np.asarray(keys).tolist())) & set(map(tuple, train.tolist()))
    before = problem_lib.evaluate(SPEC, NAIVE, keys, switching="sat")
    after = problem_lib.evaluate(SPEC, result.gains, keys, switching="sat")
    AFONFTSMC.check_gains(result.gains)
    assert not before.diverged.any() and not after.diverged.any()
    assert after.cost.mean() < 0.8 * before.cost.mean()
    assert np.mean(after.cost < before.cost) >= 0.75  # better on most draws, not on average only


# ---------------------------------------------------------------------- bad input


def test_bad_tuner_settings_are_rejected():
    with pytest.raises(ValueError, match="steps must be a positive integer"):
        tuner_lib.TunerConfig(steps=0)
    with pytest.raises(ValueError, match="learning_rate must be a finite number > 0"):
        tuner_lib.TunerConfig(learning_rate=float("nan"))
    with pytest.raises(ValueError, match="draws must be a positive integer"):
        problem_lib.ProblemSpec(draws=0)
    with pytest.raises(ValueError, match="whole, positive number of steps"):
        problem_lib.ProblemSpec(horizon=0.0105, dt=0.001 * 2)
    with pytest.raises(ValueError, match="unknown controller 'pid'"):
        problem_lib.ProblemSpec(controller="pid")


def test_settings_that_would_change_nothing_are_rejected():
    """The FL has no fractional operator (only the default 'soe' is accepted), and a
    device_batch without a mesh to split the draws over changes nothing."""
    with pytest.raises(ValueError, match="fractional='gl' does not apply to fl"):
        problem_lib.ProblemSpec(controller="fl", fractional="gl")
    spec = problem_lib.ProblemSpec(controller="fl", horizon=0.01)
    assert spec.fractional == "soe"
    law = spec.make_controller("sat", 0.01).law  # switching and fractional: none for the FL
    assert type(law).__name__ == "FL" and law.horizon == 0.01
    assert (
        spec.make_controller.__doc__
        and "where the controller has one" in spec.make_controller.__doc__
    )
    bsmc = problem_lib.ProblemSpec(controller="bsmc", horizon=0.01)
    assert bsmc.make_controller("tanh", 0.01).law.switching == "tanh"
    with pytest.raises(ValueError, match="device_batch=4 applies to draws split over a mesh"):
        problem_lib.TuningProblem(SPEC, NAIVE, device_batch=4)


def test_failed_starts_never_write_or_overwrite(tmp_path):
    config = tuner_lib.TunerConfig(steps=2)
    out = tmp_path / "run"
    bad = NAIVE._replace(gamma1=jnp.full(6, 1.5))
    with pytest.raises(ValueError, match="0 < gamma1 < 1"):
        tuner_lib.prepare(SPEC, config, bad, "file", out)
    with pytest.raises(ValueError, match="nothing to resume"):
        tuner_lib.prepare(SPEC, config, NAIVE, "naive", out, resume=True)
    assert not out.exists()
    # A checkpoint exists: a fresh start is refused, a resume with other settings too.
    out.mkdir()
    checkpoint = out / tuner_lib.CHECKPOINT
    meta = {
        "fingerprint": tuner_lib._canonical(tuner_lib.fingerprint(SPEC, config, "naive", NAIVE)),
        "step": 1,
        "history": [],
        "wall_time_s": 0.0,
    }
    tuner_lib._save_checkpoint(checkpoint, ({"a": jnp.zeros(2)},), meta)
    before = checkpoint.read_bytes()
    stamp = os.stat(checkpoint).st_mtime_ns
    with pytest.raises(ValueError, match="pass --resume to continue it"):
        tuner_lib.prepare(SPEC, config, NAIVE, "naive", out)
    other = dataclasses.replace(SPEC, draws=4)
    with pytest.raises(
        ValueError, match=r"another configuration.*\n  problem.draws: checkpoint 3, now 4"
    ):
        tuner_lib.prepare(other, config, NAIVE, "naive", out, resume=True)
    with pytest.raises(ValueError, match=r"tuner.learning_rate: checkpoint 0.05, now 0.2"):
        tuner_lib.prepare(
            SPEC,
            tuner_lib.TunerConfig(steps=2, learning_rate=0.2),
            NAIVE,
            "naive",
            out,
            resume=True,
        )
    with pytest.raises(ValueError, match=r'init: checkpoint "naive", now "paper"'):
        tuner_lib.prepare(SPEC, config, paper_gains(jnp.float64), "paper", out, resume=True)
    assert checkpoint.read_bytes() == before and os.stat(checkpoint).st_mtime_ns == stamp
    assert sorted(p.name for p in out.iterdir()) == [tuner_lib.CHECKPOINT]


# ------------------------------------------------------------- derivative-free tuners


def test_derivative_free_tuners_respect_the_budget():
    from fojax.optimize import derivative_free

    problem = small_problem()
    per_eval = SPEC.draws * SPEC.steps
    es = derivative_free.cma_es(problem, 3 * 4 * per_eval + per_eval - 1, popsize=4, seed=1)
    assert es.evaluations == 12 and es.draw_steps == 12 * per_eval and len(es.history) == 3
    AFONFTSMC.check_gains(es.gains)
    again = derivative_free.cma_es(problem, 12 * per_eval, popsize=4, seed=1)
    for name in es.params:
        np.testing.assert_array_equal(np.asarray(again.params[name]), np.asarray(es.params[name]))
    size = problem.param_map.size
    nm = derivative_free.nelder_mead(problem, (size + 12) * per_eval, callback_every=1)
    assert nm.evaluations <= size + 12 and nm.draw_steps == nm.evaluations * per_eval
    start = float(problem.value(problem.initial_params(), 1.0, problem.minibatch_keys(0)).objective)
    assert nm.history[-1]["best_objective"] <= start
    AFONFTSMC.check_gains(nm.gains)
    with pytest.raises(ValueError, match="positive number of draw-steps"):
        derivative_free.cma_es(problem, 0)
    with pytest.raises(ValueError, match="does not cover one CMA-ES generation"):
        derivative_free.cma_es(problem, per_eval, popsize=4)
    with pytest.raises(ValueError, match="does not cover the initial simplex"):
        derivative_free.nelder_mead(problem, 3 * per_eval)


def test_batched_costs_equal_one_at_a_time_costs():
    """One compiled call over candidates x draws gives each candidate the costs that
    evaluating it alone gives (float64, to rounding), also through the evaluation path
    (``evaluate``, another compiled program of the same rollout)."""
    problem = small_problem()
    rng = np.random.default_rng(3)
    start = problem.vector(problem.initial_params())
    candidates = start + 0.5 * rng.normal(size=(5, start.size))
    keys = problem.minibatch_keys(1)
    objectives, costs = problem.batch_value(candidates, 1.0, keys)
    assert np.asarray(costs.cost).shape == (5, SPEC.draws)
    assert np.ptp(np.asarray(objectives)) > 1e-3  # the candidates differ in cost
    for i, x in enumerate(candidates):
        params = problem.unravel(x)
        alone = problem.value(params, 1.0, keys)
        np.testing.assert_allclose(costs.cost[i], alone.costs.cost, rtol=1e-12, atol=0)
        np.testing.assert_allclose(costs.terms[i], alone.costs.terms, rtol=1e-12, atol=0)
        np.testing.assert_allclose(objectives[i], alone.objective, rtol=1e-12, atol=0)
        reference = problem_lib.evaluate(SPEC, problem.gains(params), keys, switching="tanh")
        np.testing.assert_allclose(costs.cost[i], reference.cost, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match=r"candidates must be an array \(P, 33\)"):
        problem.batch_value(candidates[:, :-1], 1.0, keys)


def test_batched_cma_es_equals_one_at_a_time_cma_es():
    from fojax.optimize import derivative_free

    problem = small_problem()
    budget = 3 * 4 * SPEC.draws * SPEC.steps
    batched = derivative_free.cma_es(problem, budget, popsize=4, seed=2, batched=True)
    alone = derivative_free.cma_es(problem, budget, popsize=4, seed=2, batched=False)
    assert batched.evaluations == alone.evaluations == 12
    for a, b in zip(batched.history, alone.history, strict=True):
        assert a["draw_steps"] == b["draw_steps"]
        assert a["objective"] == pytest.approx(b["objective"], rel=1e-12)
    for name in batched.params:
        np.testing.assert_allclose(batched.params[name], alone.params[name], rtol=1e-10)


def test_validation_draws_are_disjoint_from_tuning_and_heldout_draws():
    problem = small_problem()
    validation = set(map(tuple, np.asarray(problem.validation_keys(64)).tolist()))
    heldout = set(map(tuple, np.asarray(problem.heldout_keys(64)).tolist()))
    tuning = set(map(tuple, np.asarray(problem.minibatch_keys(0, draws=4096)).tolist()))
    assert len(validation) == 64 and not validation & heldout and not validation & tuning


def _validated_run(config):
    """A run recording every iterate, and the independent validation of each."""
    iterates = {}
    problem = small_problem()
    run = tuner_lib.prepare(SPEC, config, NAIVE, "naive", None)
    result = tuner_lib.tune(
        run,
        progress=False,
        problem=problem,
        callback=lambda step, params, row: iterates.__setitem__(step, params),
    )
    iterates[0] = problem.initial_params()
    keys = problem.validation_keys(config.validation_draws)
    validation = {
        step: float(np.mean(problem_lib.evaluate(SPEC, problem.gains(p), keys).cost))
        for step, p in iterates.items()
    }
    return result, iterates, validation


@pytest.mark.parametrize("learning_rate", [0.1, 30.0])
def test_tuner_returns_the_best_validated_gains(learning_rate):
    # 0.1: tuning helps; 30: every step throws the gains by e^30, and the start must come back.
    config = tuner_lib.TunerConfig(
        steps=4, method="adam", learning_rate=learning_rate, validation_draws=4, validate_every=2
    )
    result, iterates, validation = _validated_run(config)
    validated = [0, 2, 4]
    for row in result.history:
        expected = validation[row["step"]] if row["step"] in validated else None
        if expected is None:
            assert row["validation_cost"] is None
        else:
            assert row["validation_cost"] == pytest.approx(expected, rel=1e-12)
    best = min(validated, key=lambda step: (validation[step], step))
    assert result.best_step == best
    assert result.validation["initial"] == pytest.approx(validation[0], rel=1e-12)
    assert result.validation["best"] == pytest.approx(validation[best], rel=1e-12)
    assert result.validation["final"] == pytest.approx(validation[4], rel=1e-12)
    for name in result.params:
        np.testing.assert_array_equal(result.params[name], iterates[best][name])
        np.testing.assert_array_equal(result.final_params[name], iterates[4][name])
    if learning_rate == 30.0:
        assert best == 0 and validation[4] > validation[0]
        for name in NAIVE._fields:
            np.testing.assert_array_equal(getattr(result.gains, name), getattr(NAIVE, name))
    else:
        assert best > 0 and validation[best] < 0.9 * validation[0]


# ------------------------------------------------------------------------- L-BFGS


def test_lbfgs_minimises_rosenbrock_like_scipy():
    from scipy import optimize as scipy_optimize

    from fojax.optimize import lbfgs as lbfgs_lib

    def rosenbrock(x):
        return scipy_optimize.rosen(x), scipy_optimize.rosen_der(x)

    x0 = np.asarray([-1.2, 1.0, -0.5, 0.8])
    method = lbfgs_lib.LBFGS(memory=5, max_step=0.5)
    state = method.start(x0)
    accepted_values = []
    for _ in range(400):
        f, g = rosenbrock(state["trial"])
        state, accepted = method.tell(state, f, g)
        if accepted:
            accepted_values.append(state["f"])
    assert np.all(np.diff(accepted_values) <= 0)  # sufficient decrease at every move
    reference = scipy_optimize.minimize(rosenbrock, x0, jac=True, method="L-BFGS-B")
    np.testing.assert_allclose(reference.x, np.ones(4), atol=1e-4)
    np.testing.assert_allclose(state["x"], reference.x, atol=1e-4)
    # The state survives a JSON round trip exactly (checkpoints).
    import json

    again = lbfgs_lib.state_from_json(json.loads(json.dumps(lbfgs_lib.state_to_json(state))))
    for key, value in state.items():
        if isinstance(value, list):
            for a, b in zip(value, again[key], strict=True):
                np.testing.assert_array_equal(a, b)
        elif isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, again[key])
        else:
            assert value == again[key]


def test_lbfgs_tuner_resumes_exactly_and_only_accepts_decreases(tmp_path):
    overrides = {"method": "lbfgs", "max_step": 0.5, "validation_draws": 2}
    full = _run(tmp_path / "full", 5, config_overrides=overrides)
    part = _run(tmp_path / "part", 5, stop_after=3, config_overrides=overrides)
    resumed = _run(tmp_path / "part", 5, resume=True, config_overrides=overrides)
    assert part.completed == 3 and resumed.completed == 5
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name])
        np.testing.assert_array_equal(resumed.final_params[name], full.final_params[name])
    strip = [{k: v for k, v in row.items() if k != "wall_time_s"} for row in full.history]
    assert [{k: v for k, v in r.items() if k != "wall_time_s"} for r in resumed.history] == strip
    # Every accepted trial lowered the fixed-sample objective (re-evaluated independently).
    problem = small_problem()
    keys = problem.minibatch_keys(0)
    objectives = [row["objective"] for row in full.history if row["accepted"]]
    assert len(objectives) >= 2 and np.all(np.diff(objectives) < 0)
    final = float(problem.value(full.final_params, 1.0, keys).objective)
    assert final == pytest.approx(objectives[-1], rel=1e-12)
