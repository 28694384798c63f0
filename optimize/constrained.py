"""Tuning to requirements: minimise an objective subject to per-draw requirements on the
Monte Carlo draws, by gradient (an augmented Lagrangian, inner steps by optax), with
batched CMA-ES on a penalty as the derivative-free baseline.

Formulation. Draw ``i`` of a fixed sample of ``n`` tuning draws (a sample-average
problem, as the L-BFGS tuner's) has an objective ``o_i`` and normalised violations
``v_ij`` (:func:`fojax.requirements.violations`: ``<= 0`` when draw ``i`` meets
requirement ``j``). With ``f = mean_i o_i / f_0`` (``f_0`` the start's value) and one
constraint ``c_j <= 0`` per requirement, the augmented Lagrangian of the inequality
constraints (Nocedal & Wright, Sec. 17.4, the Rockafellar form) is::

    L(x; lam, rho) = f + sum_j (max(0, lam_j + rho c_j)^2 - lam_j^2) / (2 rho)

minimised over ``x`` by ``inner_steps`` optax steps, then ``lam_j <- max(0, lam_j + rho
c_j)`` and ``rho <- growth rho`` (capped) when the largest violation did not fall below a
quarter of the previous one. (Growth 4 up to 1e4 was measured to throw the AFONFTSMC's
gains into divergence once ``rho`` passed about 2.5e3; growth 2 capped at 1e3 is the
default.) Two choices of ``c_j``:

* ``formulation="mean"``: the mean violation, ``c_j = mean_i max(v_ij + m, 0)`` (``m``
  the margin): zero exactly when every draw meets requirement ``j`` with margin ``m``; a
  constraint on the mean of per-draw hinge penalties (exact: a finite multiplier makes
  the minimiser feasible; a squared hinge needs ``lam -> inf`` and was measured to stop
  short of the constraint);
* ``formulation="chance"``: a chance-constraint surrogate, ``c_j = mean_i sigmoid((v_ij +
  m) / T) - alpha``: the smooth share of draws violating requirement ``j`` at most
  ``alpha``.

A diverged draw (non-finite metrics, status ``nonfinite`` or ``tilt_limit``) counts as a
full violation (``c_j`` term 1 in both forms) and contributes no gradient: gradients are
per draw (one copy of the parameters per draw, one reverse pass, ``jax.vjp``) and the
non-finite ones are dropped, as in :mod:`optimize.cost`.

Selection: the start and the iterate after every outer iteration are validated on
``validation_draws`` draws disjoint from the tuning sample (the exact, non-smooth
metrics; the simulator's evaluation switching ``sat``); the result is the best by
yield, then by the total of failed (draw, requirement) pairs (so that among iterates no
draw of which passes, the one nearer to passing wins), then objective (the start wins
ties), with the validation yield's Clopper-Pearson interval.

Measured (docs/requirements.md has the tables): on a toy with a known constrained
optimum (minimise ``|x|^2`` under per-draw linear bounds) the mean hinge ends within
0.012 of ``x*`` (objective 1.896 vs 1.921) where the chance surrogate (``alpha`` 0.05,
``T`` 0.1) stays feasible but pays 31 % in objective, and a sharp sigmoid (``T`` 0.02)
has no gradient far from feasibility and did not move; on the FL (scenario 2, 0.4 s,
rotor-limited) the mean hinge reached 35.5 % held-out yield from 0 %, the chance
surrogate 15.2 %, CMA-ES on the penalty 27.0 % with 6.5x the forward draw-steps; the
AFONFTSMC from the paper's gains (scenario 2, 10 s, rotor-limited, the example
requirement set, objective effort) went from 0/64 to 63/64 held-out draws. Hence
``formulation="mean"`` is the default.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fojax import observers, plant, scenarios, simulator
from fojax import requirements as rq
from fojax.optimize import cost as cost_lib
from fojax.optimize import problem as problem_lib
from fojax.optimize.checkpoint import _load_state, _read_meta, _save_checkpoint, check_checkpoint
from fojax.optimize.derivative_free import cma_es_requirements

Array = jax.Array

__all__ = [
    "FORMULATIONS",
    "OBJECTIVES",
    "ConstrainedConfig",
    "ConstrainedResult",
    "RequirementProblem",
    "alm_loss",
    "cma_es_requirements",
    "make_alm_step",
    "minimize",
    "tune_to_requirements",
]

FORMULATIONS = ("mean", "chance")
OBJECTIVES = ("effort", "tracking", "cost")
"""``effort``: the cost's ``E`` (commanded accelerations squared, :mod:`optimize.cost`);
``tracking``: ``P + A``; ``cost``: the weighted sum ``J`` of ``ProblemSpec.cost``."""


@dataclasses.dataclass(frozen=True)
class ConstrainedConfig:
    """Settings of the augmented-Lagrangian tuner (module docstring).

    formulation: ``"mean"`` or ``"chance"``. outer_steps: multiplier updates.
    inner_steps: optax steps per outer iteration. method: ``"adam"`` (clipped to
    ``clip_norm``) or ``"lbfgs"`` (optax's L-BFGS with its zoom line search).
    learning_rate: Adam's step (unconstrained parameters). penalty, penalty_growth,
    penalty_max: ``rho`` at the start, its growth factor, its cap. margin: ``m`` in
    normalised units (a draw must beat each bound by ``m`` of its scale). temperature:
    ``T`` of the chance surrogate. allowed_share: ``alpha``. validation_draws: draws
    scoring the start and each outer iterate (0: no validation, the last iterate).
    """

    formulation: str = "mean"
    outer_steps: int = 6
    inner_steps: int = 10
    method: str = "adam"
    learning_rate: float = 0.05
    clip_norm: float = 1.0
    penalty: float = 10.0
    penalty_growth: float = 2.0
    penalty_max: float = 1e3
    margin: float = 0.05
    temperature: float = 0.1
    allowed_share: float = 0.0
    validation_draws: int = 32

    def __post_init__(self) -> None:
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}, got {self.formulation!r}")
        if self.method not in ("adam", "lbfgs"):
            raise ValueError(f"method must be 'adam' or 'lbfgs', got {self.method!r}")
        for label in ("outer_steps", "inner_steps"):
            value = getattr(self, label)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{label} must be a positive integer, got {value!r}")
        for label in ("learning_rate", "clip_norm", "penalty", "penalty_max", "temperature"):
            value = getattr(self, label)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        if not self.penalty_growth >= 1:
            raise ValueError(f"penalty_growth must be >= 1, got {self.penalty_growth!r}")
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"margin must be a finite number >= 0, got {self.margin!r}")
        if not 0 <= self.allowed_share < 1:
            raise ValueError(f"allowed_share must be in [0, 1), got {self.allowed_share!r}")
        if self.formulation == "chance" and self.allowed_share == 0:
            raise ValueError(
                "the chance surrogate needs allowed_share > 0 (its sigmoid is > 0 on every "
                "draw, so a zero share can never be met); e.g. allowed_share=0.05, or use "
                "formulation='mean' to require every draw"
            )
        if not isinstance(self.validation_draws, int) or self.validation_draws < 0:
            raise ValueError(
                f"validation_draws must be an integer >= 0, got {self.validation_draws!r}"
            )

    def optimizer(self) -> optax.GradientTransformation:
        if self.method == "lbfgs":
            return optax.lbfgs()
        return optax.chain(
            optax.clip_by_global_norm(self.clip_norm), optax.adam(self.learning_rate)
        )


def constraint_values(config: ConstrainedConfig, violations: Array, valid: Array) -> Array:
    """``(requirements,)`` the ALM constraints ``c_j`` (module docstring) from normalised
    violations ``(requirements, n)`` and ``valid`` ``(n,)`` (an invalid draw counts 1)."""
    if config.formulation == "mean":
        per_draw = jnp.maximum(violations + config.margin, 0.0)
    else:
        per_draw = rq.smooth_share(violations, config.temperature, config.margin)
    per_draw = jnp.where(valid[None, :], per_draw, 1.0)
    c = jnp.mean(per_draw, axis=1)
    return c - config.allowed_share if config.formulation == "chance" else c


def alm_loss(config, objective, violations, valid, scale, lam, rho):
    """``(L, (f, c))``: the augmented Lagrangian of per-draw ``objective`` ``(n,)`` and
    ``violations`` ``(requirements, n)`` (module docstring); ``scale`` is ``f_0``."""
    count = jnp.maximum(jnp.sum(valid), 1)
    f = jnp.sum(jnp.where(valid, objective, 0.0)) / count / scale
    c = constraint_values(config, violations, valid)
    shifted = jnp.maximum(0.0, lam + rho * c)
    return f + jnp.sum(shifted**2 - lam**2) / (2.0 * rho), (f, c)


def make_alm_step(per_draw: Callable, config: ConstrainedConfig):
    """``step(params, data, scale, lam, rho) -> (L, gradient, f, c, valid)``, jitted.

    ``per_draw(copies, data) -> ((objective (n,), violations (R, n)), status (n,))`` is
    called with one copy of the parameters per draw (every leaf's last axis ``n``, the
    batch-last layout); each draw must depend on its own copy only. The gradient is the
    sum of the per-draw gradients of ``L``, non-finite draws left out."""

    def step(params, data, n, scale, lam, rho):
        copies = jax.tree.map(lambda p: jnp.broadcast_to(p[..., None], p.shape + (n,)), params)
        (objective, violations), pullback, status = jax.vjp(
            lambda c: per_draw(c, data), copies, has_aux=True
        )
        valid = (
            jnp.isfinite(objective)
            & jnp.all(jnp.isfinite(violations), 0)
            & ((status & rq.DIVERGED) == 0)
        )
        objective_safe = jnp.where(valid, objective, 0.0)
        violations_safe = jnp.where(valid[None, :], violations, 0.0)
        (loss, (f, c)), cotangents = jax.value_and_grad(
            lambda o, v: alm_loss(config, o, v, valid, scale, lam, rho),
            argnums=(0, 1),
            has_aux=True,
        )(objective_safe, violations_safe)
        ct_o = jnp.where(valid, cotangents[0], 0.0)
        ct_v = jnp.where(valid[None, :], cotangents[1], 0.0)
        (grads,) = pullback((ct_o, ct_v))
        finite = jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(g.reshape(-1, n)), 0) for g in jax.tree.leaves(grads)]),
            0,
        )
        gradient = jax.tree.map(lambda g: jnp.sum(jnp.where(finite, g, 0.0), -1), grads)
        return loss, gradient, f, c, valid

    return jax.jit(step, static_argnums=2)


class ConstrainedResult(NamedTuple):
    """params: the selected parameters. history: one dict per outer iteration.
    selected: the selected iterate's outer step (0: the start) and its validation
    (``yield``, ``interval``, ``objective``, ...). initial: the start's validation
    (``None`` without validation). multipliers, penalty: the final
    ``lam`` and ``rho``. wall_time_s: the run's time, validation included."""

    params: Any
    history: list
    selected: dict
    multipliers: np.ndarray
    penalty: float
    wall_time_s: float
    final_params: Any
    initial: dict | None = None


@dataclasses.dataclass
class _Loop:
    """:func:`minimize`'s state between outer iterations (what a checkpoint holds)."""

    params: Any
    best_params: Any
    lam: Any
    rho: float
    scale: float
    previous: float
    best: dict | None
    initial: dict | None
    history: list
    start: float

    def record(self) -> dict:
        keep = ("rho", "scale", "previous", "best", "initial", "history")
        return {k: getattr(self, k) for k in keep} | {"elapsed_s": time.perf_counter() - self.start}


def _begin(step, params, data, n, config, requirements, score, checkpoint, fingerprint) -> _Loop:
    """The loop's state: continued from ``checkpoint`` when it exists, else the start
    (its objective ``f_0`` sets the scale, its validation the first best)."""
    lam = jnp.zeros(requirements)
    if checkpoint is not None and Path(checkpoint).is_file():
        check_checkpoint(checkpoint, fingerprint)
        state = _read_meta(checkpoint)["loop"]
        params, best_params, lam = _load_state(checkpoint, (params, params, lam))
        state["start"] = time.perf_counter() - state.pop("elapsed_s")
        return _Loop(params, best_params, lam, **state)
    start = time.perf_counter()
    rho = float(config.penalty)
    # Every number passed as an array of the default float: one compilation of ``step``.
    _, _, f0, _, _ = step(params, data, n, jnp.asarray(1.0), lam, jnp.asarray(rho))
    scale = float(f0) if float(f0) > 1e-12 else 1.0
    best = score(params)
    if best is not None:
        best = {**best, "outer_step": 0}
    return _Loop(params, params, lam, rho, scale, math.inf, best, best, [], start)


def minimize(
    step: Callable,
    params: Any,
    data: Any,
    n: int,
    config: ConstrainedConfig,
    requirements: int,
    validate: Callable | None = None,
    progress: bool = False,
    checkpoint: Path | None = None,
    fingerprint: dict | None = None,
) -> ConstrainedResult:
    """The augmented-Lagrangian loop around ``step`` (:func:`make_alm_step`) on the fixed
    sample ``data`` of ``n`` draws. ``validate(params) -> dict`` with ``passed``,
    ``failures`` (name -> count) and ``objective`` (lower is better) scores the start and
    each outer iterate; the best by ``passed``, then fewer failures, then ``objective``,
    is returned (without ``validate``: the last).

    checkpoint: a file written (atomically) after every outer iteration; when it exists
    the loop continues from it, with the result an uninterrupted run gives (each outer
    iteration starts a fresh inner optimiser, so its state is the iterate, ``lam``,
    ``rho`` and the selection). fingerprint: JSON-ready settings the checkpoint must
    have been written with (a ``ValueError`` names the ones that differ)."""

    def score(p):
        return validate(p) if validate is not None else None

    loop = _begin(step, params, data, n, config, requirements, score, checkpoint, fingerprint)
    inner = _inner_loop(step, data, n, loop.scale, config)
    for outer in range(len(loop.history) + 1, config.outer_steps + 1):
        loop.params, (loss, f, c, valid) = inner(loop.params, loop.lam, jnp.asarray(loop.rho))
        c = np.asarray(c, np.float64)
        loop.lam = jnp.maximum(0.0, loop.lam + loop.rho * jnp.asarray(c, loop.lam.dtype))
        worst = float(np.max(np.maximum(c, 0.0)))
        if worst > 0.25 * loop.previous:
            loop.rho = min(loop.rho * config.penalty_growth, config.penalty_max)
        loop.previous = worst
        row = {
            "outer_step": outer,
            "loss": float(loss),
            "objective": float(f) * loop.scale,
            "constraints": c.tolist(),
            "multipliers": np.asarray(loop.lam).tolist(),
            "penalty": loop.rho,
            "valid_draws": int(np.sum(np.asarray(valid))),
            "wall_time_s": round(time.perf_counter() - loop.start, 3),
        }
        scored = score(loop.params)
        if scored is not None:
            row["validation"] = scored
            if _rank(scored) > _rank(loop.best):
                loop.best, loop.best_params = {**scored, "outer_step": outer}, loop.params
        else:
            loop.best_params = loop.params
        loop.history.append(row)
        if checkpoint is not None:
            meta = {"loop": loop.record(), "fingerprint": fingerprint}
            _save_checkpoint(checkpoint, (loop.params, loop.best_params, loop.lam), meta)
        if progress:
            _print_outer(row, config.outer_steps, worst, scored)
    return ConstrainedResult(
        loop.best_params,
        loop.history,
        loop.best if loop.best is not None else {"outer_step": config.outer_steps},
        np.asarray(loop.lam),
        loop.rho,
        time.perf_counter() - loop.start,
        loop.params,
        loop.initial,
    )


def _inner_loop(step: Callable, data: Any, n: int, scale: float, config: ConstrainedConfig):
    """``run(params, lam, rho) -> (params, (L, f, c, valid))``: :func:`minimize`'s inner
    loop, ``config.inner_steps`` steps of ``config``'s optimizer on ``L(.; lam, rho)``
    from ``params`` (a fresh optimizer state), and ``step``'s values at the last
    iterate."""
    optimizer = config.optimizer()

    def inner_value(p, lam, rho):
        return step(p, data, n, jnp.asarray(scale), lam, rho)

    @jax.jit
    def lbfgs_update(p, state, lam, rho):
        loss, gradient, *_ = step(p, data, n, scale, lam, rho)
        updates, state = optimizer.update(
            gradient,
            state,
            p,
            value=loss,
            grad=gradient,
            value_fn=lambda q: step(q, data, n, scale, lam, rho)[0],
        )
        return optax.apply_updates(p, updates), state

    def run(params, lam, rho):
        state = optimizer.init(params)
        for _ in range(config.inner_steps):
            if config.method == "lbfgs":
                params, state = lbfgs_update(params, state, lam, rho)
            else:
                _, gradient, *_ = inner_value(params, lam, rho)
                updates, state = optimizer.update(gradient, state, params)
                params = optax.apply_updates(params, updates)
        loss, _, f, c, valid = inner_value(params, lam, rho)
        return params, (loss, f, c, valid)

    return run


def _print_outer(row: dict, outer_steps: int, worst: float, scored: dict | None) -> None:
    """:func:`minimize`'s progress line of one outer iteration (stderr)."""
    text = f"  outer {row['outer_step']}/{outer_steps}  objective {row['objective']:.4e}  "
    text += f"max c {worst:.3g}  rho {row['penalty']:g}"
    if scored is not None:
        text += f"  validation yield {scored['yield']:.1%}"
    print(text, file=sys.stderr, flush=True)


# -------------------------------------------------------------- the simulator problem


class RequirementProblem:
    """A tuning problem of :class:`optimize.problem.ProblemSpec` (controller, scenario,
    horizon, draws, seed, tuned fields) against a requirement set, with ``objective`` one
    of :data:`OBJECTIVES`. Actuators are rotor-limited when the requirements' settings
    give a limit (``rotor_limited`` overrides: ``True`` needs a limit in the settings,
    ``False`` simulates ideal actuators while still measuring against it).

    Tuning runs the controller with ``tanh`` switching at the base boundary layer (the
    gradient needs a smooth law); validation and :meth:`evaluate` use ``switching``
    (default ``sat``, the evaluation law). ``scenario``: a
    :class:`fojax.scenarios.Scenario` simulated instead of ``spec.scenario``'s (e.g. with
    its random drag switched off), or a union (:func:`fojax.scenarios.union`: draw ``i``
    of a batch is of member ``i % members``); the draws' keys still come from ``spec``."""

    def __init__(
        self,
        spec: problem_lib.ProblemSpec,
        base_gains: Any,
        requirements: rq.RequirementSet,
        objective: str = "effort",
        rotor_limited: bool | None = None,
        switching: str = "sat",
        scenario: scenarios.Scenario | None = None,
    ):
        if objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
        limit = requirements.settings.speed_limit()
        if rotor_limited is None:
            rotor_limited = requirements.settings.rotor_limited and limit is not None
        if rotor_limited and limit is None:
            raise ValueError(
                "rotor-limited actuators need a limit: set thrust_to_weight or "
                "rotor_speed_limit in the requirements' [settings]"
            )
        self.base = problem_lib.TuningProblem(spec, base_gains)
        self.spec, self.requirements, self.objective = spec, requirements, objective
        self.param_map = self.base.param_map
        self.base_gains = self.base.base_gains
        self.switching = switching
        self.sim_config = dataclasses.replace(
            self.base.sim_config, rotor_speed_limit=limit if rotor_limited else None
        )
        self.scenario = self.base.scenario if scenario is None else scenario
        self.dtype = spec.jnp_dtype
        self.observer = observers.Chain(
            requirements=rq.RequirementMetrics.for_requirements(requirements, self.sim_config),
            cost=cost_lib.CostObserver(spec.cost, spec.dt),
        )
        self._tuning = self._simulate_fn(self.base.controller)
        self._evaluation = jax.jit(self._simulate_fn(spec.make_controller(switching, spec.horizon)))
        param_map, base = self.param_map, self.base_gains
        simulate = self._tuning

        def per_draw(copies, keys):
            gains = jax.vmap(lambda p: param_map.to_gains(p, base), in_axes=-1, out_axes=-1)(copies)
            objective, metrics, status = simulate(gains, keys)
            return (objective, rq.violations(requirements, metrics)), status

        self.per_draw = per_draw

        def batch_value(vector_list, keys, unravel):
            def one(vector):
                objective, metrics, status = simulate(
                    param_map.to_gains(unravel(vector), base), keys
                )
                return objective, rq.violations(requirements, metrics), status

            return jax.vmap(one)(vector_list)

        self._batch_value = batch_value

    def outputs(self, controller, gains, keys):
        """``(terms (4, n): P, A, E, C; metrics: name -> (n,); status (n,))`` of
        ``controller`` with ``gains`` on the draws ``keys`` (a union's draw ``i`` of
        member ``i % members``), on the problem's actuators."""
        scenario, config, dtype = self.scenario, self.sim_config, self.dtype
        member = jnp.arange(keys.shape[0]) % len(scenario.members) if scenario.members else 0
        draws = scenarios.sample_draws(scenario, keys, config.dt, dtype, member)
        model = plant.nominal_params(dtype)
        result = simulator.rollout(controller, gains, model, scenario, draws, config, self.observer)
        return result.outputs["cost"], result.outputs["requirements"], result.status

    def _simulate_fn(self, controller):
        weights = jnp.asarray(self.spec.cost.weights, self.dtype)

        def simulate(gains, keys):
            terms, metrics, status = self.outputs(controller, gains, keys)
            if self.objective == "effort":
                value = terms[2]
            elif self.objective == "tracking":
                value = terms[0] + terms[1]
            else:
                value = jnp.sum(weights[:, None] * terms, 0)
            return value, metrics, status

        return simulate

    # -- keys, parameters -------------------------------------------------------------
    def tuning_keys(self) -> Array:
        return self.base.minibatch_keys(0)

    def validation_keys(self, draws: int) -> Array:
        return self.base.validation_keys(draws)

    def heldout_keys(self, draws: int) -> Array:
        return self.base.heldout_keys(draws)

    def initial_params(self) -> dict:
        return self.base.initial_params()

    def gains(self, params) -> Any:
        return self.base.gains(params)

    # -- evaluation -------------------------------------------------------------------
    def evaluate(self, params_or_gains, keys, chunk: int = 64) -> dict:
        """Per-draw metrics, objective and status of ``params`` (a dict) or gains on
        ``keys`` with the evaluation switching, and the yield: ``{"yield":
        YieldResult, "objective": mean over valid draws, "metrics", "status"}``."""
        gains = params_or_gains
        if isinstance(params_or_gains, dict):
            gains = self.gains(params_or_gains)
        gains = type(gains)(*(jnp.asarray(g, self.dtype) for g in gains))
        keys = np.asarray(keys)
        n = keys.shape[0]
        chunk = max(1, min(chunk, n))
        objective, metrics, status = [], [], []
        for first in range(0, n, chunk):
            index = np.minimum(np.arange(first, first + chunk), n - 1)
            o, m, s = self._evaluation(gains, jnp.asarray(keys[index]))
            size = min(chunk, n - first)
            objective.append(np.asarray(o)[:size])
            metrics.append({k: np.asarray(v)[:size] for k, v in m.items()})
            status.append(np.asarray(s)[:size])
        status = np.concatenate(status)
        values = rq.draw_metrics(
            {k: np.concatenate([m[k] for m in metrics]) for k in metrics[0]}, status
        )
        objective = np.concatenate(objective).astype(np.float64)
        valid = ((status & rq.DIVERGED) == 0) & np.isfinite(objective)
        result = rq.evaluate(self.requirements, values, valid=valid)
        mean = float(np.mean(objective[valid])) if np.any(valid) else math.inf
        return {"yield": result, "objective": mean, "metrics": values, "status": status}


def _rank(scored: dict) -> tuple:
    """Selection key of a validation (larger is better): yield, then fewer failed
    (draw, requirement) pairs, then a lower objective."""
    return (scored["passed"], -sum(scored["failures"].values()), -scored["objective"])


def _validation_summary(evaluated: dict) -> dict:
    result = evaluated["yield"]
    return {
        "passed": int(result.passed),
        "draws": int(result.draws),
        "yield": float(result.yield_),
        "interval": [float(x) for x in result.interval],
        "most_failed": result.most_failed,
        "failures": {n: int(f) for n, f in zip(result.names, result.failures, strict=True)},
        "objective": float(evaluated["objective"]),
    }


def tune_to_requirements(
    problem: RequirementProblem,
    config: ConstrainedConfig = ConstrainedConfig(),
    init_params: Any = None,
    progress: bool = False,
    checkpoint: Path | None = None,
    fingerprint: dict | None = None,
) -> ConstrainedResult:
    """Minimise ``problem``'s objective subject to its requirements (module docstring)
    from ``init_params`` (default the base gains), on the problem's tuning draws
    (minibatch 0, ``spec.draws`` draws), validated on ``config.validation_draws``
    validation draws. The result's ``params`` are the best validated by yield, then
    objective; ``problem.gains(result.params)`` are the gains. ``checkpoint``,
    ``fingerprint``: as :func:`minimize`'s (continue an interrupted run)."""
    params = problem.initial_params() if init_params is None else init_params
    step = make_alm_step(problem.per_draw, config)
    keys = problem.tuning_keys()
    validation = (
        problem.validation_keys(config.validation_draws) if config.validation_draws else None
    )

    def validate(p):
        return _validation_summary(problem.evaluate(p, validation))

    return minimize(
        step,
        params,
        keys,
        int(keys.shape[0]),
        config,
        len(problem.requirements),
        validate if validation is not None else None,
        progress,
        checkpoint,
        fingerprint,
    )
