"""Derivative-free baselines at a fixed budget of simulated draw-steps.

Stand-ins for the MATLAB optimisation toolbox of the paper's Remark 3, on exactly the
gradient tuner's problem: the same unconstrained parameters (so every candidate is
feasible), the same cost and objective (:class:`fojax.optimize.problem.TuningProblem`) with
the switching at a fixed width (``width_scale``, by default the gradient tuner's final
one), draws from the same tuning stream (never the held-out ones).

* :func:`cma_es`: CMA-ES (the ``cma`` package's ask/tell). Every generation evaluates
  all its candidates on one fresh minibatch (common random numbers within a
  generation) in one compiled, batched call (:meth:`TuningProblem.batch_value`:
  candidates x draws, compiled once); ``batched=False`` evaluates them one at a time
  (the same costs to rounding, slower). The answer is the distribution mean
  (``xfavorite``), the robust choice for a noisy objective.
* :func:`nelder_mead`: SciPy's Nelder-Mead on one fixed minibatch (a sample-average
  approximation: a deterministic objective, as the simplex method needs), initial
  simplex ``x0 + step e_i``.

The budget counts forward-simulated draw-steps (draws x steps per evaluation); an
evaluation that would exceed it is not started. ``callback(draw_steps, params, row)``
is called after each generation (CMA-ES) or every ``callback_every`` evaluations
(Nelder-Mead); its time is not counted in ``wall_time_s``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from fojax.optimize.problem import TuningProblem

__all__ = ["Budget", "DFResult", "cma_es", "cma_es_requirements", "nelder_mead"]


class Budget:
    """A counter of simulated draw-steps with a limit."""

    def __init__(self, draw_steps: int):
        if not isinstance(draw_steps, int | np.integer) or draw_steps < 1:
            raise ValueError(
                f"the budget must be a positive number of draw-steps, got {draw_steps!r}"
            )
        self.limit = int(draw_steps)
        self.used = 0

    def affords(self, draw_steps: int) -> bool:
        return self.used + draw_steps <= self.limit

    def charge(self, draw_steps: int) -> None:
        if not self.affords(draw_steps):
            raise RuntimeError("budget exceeded")
        self.used += draw_steps


class DFResult(NamedTuple):
    """method: name. params: final unconstrained parameters. gains: evaluation gains.
    history: one dict per generation / callback point (``evaluations``,
    ``draw_steps``, ``wall_time_s``, ``objective``, ``best_objective``).
    evaluations, draw_steps: totals. wall_time_s: tuning time (callbacks excluded)."""

    method: str
    params: dict
    gains: Any
    history: list
    evaluations: int
    draw_steps: int
    wall_time_s: float


class _Objective:
    """Candidate vector -> objective on ``keys``, with counters and timing."""

    def __init__(self, problem: TuningProblem, width_scale: float, budget: Budget, x0=None):
        self.problem = problem
        self.width_scale = width_scale
        self.budget = budget
        params = problem.initial_params() if x0 is None else x0
        self.x0, self.unravel = problem.param_map.ravel(params)
        self.x0 = np.asarray(self.x0, np.float64)
        self.dtype = problem.spec.jnp_dtype
        self.evaluations = 0
        self.start = time.perf_counter()
        self.excluded = 0.0

    def params(self, x) -> dict:
        return self.unravel(jnp.asarray(x, self.dtype))

    def __call__(self, x, keys) -> float:
        self.budget.charge(int(keys.shape[0]) * self.problem.spec.steps)
        self.evaluations += 1
        return float(self.problem.value(self.params(x), self.width_scale, keys).objective)

    def batch(self, candidates, keys) -> np.ndarray:
        """Objectives ``(P,)`` of ``P`` candidates on the same ``keys``, in one call."""
        count = len(candidates)
        self.budget.charge(count * int(keys.shape[0]) * self.problem.spec.steps)
        self.evaluations += count
        objectives, _ = self.problem.batch_value(np.asarray(candidates), self.width_scale, keys)
        return np.asarray(objectives, np.float64)

    @property
    def wall(self) -> float:
        return time.perf_counter() - self.start - self.excluded

    def record(self, history: list, callback, x, objective: float, best: float) -> None:
        """Append a row to ``history`` (:class:`DFResult`) and pass it to ``callback``
        with the parameters of ``x`` (the callback's time excluded)."""
        row = {
            "evaluations": self.evaluations,
            "draw_steps": self.budget.used,
            "wall_time_s": round(self.wall, 3),
            "objective": objective,
            "best_objective": float(best),
        }
        history.append(row)
        if callback is None:
            return
        t0 = time.perf_counter()
        callback(self.budget.used, self.params(x), row)
        self.excluded += time.perf_counter() - t0


def cma_es(
    problem: TuningProblem,
    budget_draw_steps: int,
    draws_per_candidate: int | None = None,
    sigma0: float = 0.5,
    popsize: int | None = None,
    seed: int = 0,
    width_scale: float = 1.0,
    callback: Callable | None = None,
    batched: bool = True,
    x0: Any = None,
) -> DFResult:
    """CMA-ES from ``x0`` (parameters dict; default the problem's initial parameters)
    with step ``sigma0`` (in the unconstrained parameters), ``popsize`` candidates per
    generation (default the ``cma`` package's ``4 + 3 ln n``), each on
    ``draws_per_candidate`` draws (default the problem's minibatch size), the whole
    generation in one batched call (``batched=False``: one call per candidate)."""

    budget = Budget(budget_draw_steps)
    objective = _Objective(problem, width_scale, budget, x0)
    n = problem.spec.draws if draws_per_candidate is None else int(draws_per_candidate)
    if n < 1:
        raise ValueError(f"draws_per_candidate must be >= 1, got {draws_per_candidate!r}")
    es, per_generation = cma_strategy(
        objective.x0, sigma0, seed, popsize, n * problem.spec.steps, budget
    )
    history = []
    best = np.inf
    generation = 0
    while budget.affords(per_generation):
        candidates = es.ask()
        keys = problem.minibatch_keys(generation, draws=n)
        if batched:
            values = objective.batch(candidates, keys).tolist()
        else:
            values = [objective(x, keys) for x in candidates]
        es.tell(candidates, values)
        generation += 1
        best = min(best, min(values))
        objective.record(history, callback, es.result.xfavorite, float(np.min(values)), best)
    return _result("cma-es", objective, np.asarray(es.result.xfavorite), history, budget)


def nelder_mead(
    problem: TuningProblem,
    budget_draw_steps: int,
    draws: int | None = None,
    step: float = 0.5,
    width_scale: float = 1.0,
    callback: Callable | None = None,
    callback_every: int = 20,
    minibatch: int = 0,
    x0: Any = None,
) -> DFResult:
    """SciPy Nelder-Mead on minibatch ``minibatch`` of ``draws`` draws (default the
    problem's size), initial simplex ``x0 + step e_i`` (``x0`` a parameters dict;
    default the problem's initial parameters), until the budget is spent."""
    from scipy import optimize as scipy_optimize

    budget = Budget(budget_draw_steps)
    objective = _Objective(problem, width_scale, budget, x0)
    n = problem.spec.draws if draws is None else int(draws)
    per_evaluation = n * problem.spec.steps
    max_evaluations = budget.limit // per_evaluation
    size = objective.x0.shape[0]
    if max_evaluations < size + 1:
        raise ValueError(
            f"the budget ({budget.limit} draw-steps) does not cover the initial simplex "
            f"({size + 1} evaluations of {per_evaluation} draw-steps)"
        )
    keys = problem.minibatch_keys(minibatch, draws=n)
    history = []
    state = {"best": np.inf, "x": objective.x0}

    def fun(x):
        value = objective(x, keys)
        if value < state["best"]:
            state["best"], state["x"] = value, np.array(x)
        if objective.evaluations % callback_every == 0:
            objective.record(history, callback, state["x"], value, state["best"])
        return value

    simplex = objective.x0[None, :] + np.vstack([np.zeros(size), step * np.eye(size)])
    scipy_optimize.minimize(
        fun,
        objective.x0,
        method="Nelder-Mead",
        options={
            "maxfev": max_evaluations,
            "maxiter": 10**9,
            "initial_simplex": simplex,
            "xatol": 0.0,
            "fatol": 0.0,
        },
    )
    return _result("nelder-mead", objective, state["x"], history, budget)


def _result(method: str, objective: _Objective, x, history: list, budget: Budget) -> DFResult:
    """The :class:`DFResult` of ``method``'s answer ``x`` (unconstrained vector)."""
    params = objective.params(x)
    gains = objective.problem.gains(params)
    return DFResult(
        method, params, gains, history, objective.evaluations, budget.used, objective.wall
    )


def cma_strategy(x0, sigma0: float, seed: int, popsize, candidate_steps: int, budget):
    """A CMA-ES strategy at ``x0`` (seed ``seed + 1``, no stopping rule but the budget)
    and the draw-steps of one generation (``popsize * candidate_steps``); raises when
    ``budget`` does not cover one generation."""
    import cma

    options = {"seed": int(seed) + 1, "verbose": -9, "tolx": 0, "tolfun": 0}
    options["tolflatfitness"] = 10**9
    if popsize is not None:
        options["popsize"] = int(popsize)
    es = cma.CMAEvolutionStrategy(np.asarray(x0, np.float64).tolist(), float(sigma0), options)
    per_generation = es.popsize * candidate_steps
    if not budget.affords(per_generation):
        raise ValueError(
            f"the budget ({budget.limit} draw-steps) does not cover one CMA-ES generation "
            f"({per_generation} draw-steps)"
        )
    return es, per_generation


def cma_es_requirements(
    problem,
    budget_draw_steps: int,
    penalty: float = 100.0,
    margin: float = 0.05,
    sigma0: float = 0.5,
    popsize: int | None = None,
    draws: int | None = None,
    seed: int = 0,
    validation_draws: int = 32,
    init_params: Any = None,
) -> dict:
    """Batched CMA-ES (the ``cma`` package) on the penalty ``f / f_0 + penalty sum_j
    mean_i max(v_ij + margin, 0)^2`` (a diverged draw costs ``penalty`` per requirement),
    the derivative-free baseline with the same constraints: every generation's
    candidates on one fresh minibatch of ``draws`` draws (default ``spec.draws``), one
    vmapped call, until ``budget_draw_steps`` simulated draw-steps are spent. The start
    and the final distribution mean are validated; the better by yield, then objective,
    is returned: ``{"params", "selected", "history", "wall_time_s", "draw_steps"}``."""
    import cma  # noqa: F401  (without the extra, fail before compiling)

    start = time.perf_counter()
    budget = Budget(budget_draw_steps)
    params0 = problem.initial_params() if init_params is None else init_params
    x0, unravel = problem.param_map.ravel(params0)
    n = problem.spec.draws if draws is None else int(draws)

    penalised = _penalised(problem, unravel, margin)
    f0, _ = penalised(jnp.asarray(x0)[None], problem.base.minibatch_keys(0, n))
    scale = max(float(f0[0]), 1e-12)
    es, per_generation = cma_strategy(x0, sigma0, seed, popsize, n * problem.spec.steps, budget)
    history = []
    generation = 0
    while budget.affords(per_generation):
        candidates = es.ask()
        keys = problem.base.minibatch_keys(generation, draws=n)
        budget.charge(per_generation)
        f, h = penalised(jnp.asarray(np.asarray(candidates), problem.dtype), keys)
        values = (np.asarray(f, np.float64) / scale + penalty * np.asarray(h, np.float64)).tolist()
        es.tell(candidates, values)
        generation += 1
        history.append(
            {
                "generation": generation,
                "draw_steps": budget.used,
                "best_penalised": float(min(values)),
                "wall_time_s": round(time.perf_counter() - start, 3),
            }
        )
    final = unravel(jnp.asarray(es.result.xfavorite, problem.dtype))
    chosen, selected = _select(problem, params0, final, validation_draws)
    return {
        "params": chosen,
        "selected": selected,
        "history": history,
        "wall_time_s": time.perf_counter() - start,
        "draw_steps": budget.used,
    }


def _penalised(problem, unravel: Callable, margin: float) -> Callable:
    """:func:`cma_es_requirements`' jitted ``(vectors, keys) -> (f (candidates,), sum_j
    mean_i max(v_ij + margin, 0)^2 (candidates,))``, ``f`` the mean objective over the
    valid draws; a diverged draw's hinge is 1."""
    import jax

    from fojax import requirements as rq

    def penalised(vectors, keys):
        objective, violations, status = problem._batch_value(vectors, keys, unravel)
        valid = (
            jnp.isfinite(objective)
            & jnp.all(jnp.isfinite(violations), 1)
            & ((status & rq.DIVERGED) == 0)
        )
        count = jnp.maximum(jnp.sum(valid, -1), 1)
        f = jnp.sum(jnp.where(valid, objective, 0.0), -1) / count
        hinge = jnp.where(valid[:, None, :], rq.squared_hinge(violations, margin), 1.0)
        return f, jnp.sum(jnp.mean(hinge, -1), -1)

    return jax.jit(penalised)


def _select(problem, params0: Any, final: Any, validation_draws: int) -> tuple:
    """``(params, selected)``: the start or CMA-ES's final mean, the better on
    ``validation_draws`` validation draws (without validation: the final mean, ``None``)."""
    from fojax.optimize.constrained import _rank, _validation_summary

    if not validation_draws:
        return final, None
    keys = problem.validation_keys(validation_draws)
    selected = {**_validation_summary(problem.evaluate(params0, keys)), "candidate": "start"}
    scored = _validation_summary(problem.evaluate(final, keys))
    if _rank(scored) > _rank(selected):
        return final, {**scored, "candidate": "cma-es mean"}
    return params0, selected
