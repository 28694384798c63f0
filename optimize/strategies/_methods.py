"""The named methods of ``fojax tune --method`` and of every study, each declared once
(:data:`METHODS`): the strategy it builds, its default budget, the options that apply
to it and their defaults (with the weighted-sum cost and, where they differ, with a
requirement set: the inner strategy of the augmented Lagrangian), whether it takes
gradients and whether the objective's sample size (``--draws``) is what it samples.
``fojax tune`` derives its method options, their defaults and its "does not apply"
errors from this table; the studies build their tuners from it, so none can drift.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import numpy as np

from fojax.optimize import checks
from fojax.optimize.strategies._compose import Chain
from fojax.optimize.strategies._gradient import LBFGS, adam
from fojax.optimize.strategies._multistart import MultiStart
from fojax.optimize.strategies._population import CMAES, NelderMead

__all__ = ["AUTO_DRAWS", "METHODS", "Method", "Problem", "lanes", "make", "starts"]

AUTO_DRAWS = 8
"""Draws per point of ``auto``'s second phase and of ``cma-lbfgs``'s CMA-ES (with a
requirement set, every method samples ``--draws``)."""


class Problem(NamedTuple):
    """What a method's strategy is built for: the objective (its parameter map, base
    gains and problem spec), the start ``x0`` ``(d,)``, the sampling seed, and whether a
    requirement set is tuned (the strategy is the augmented Lagrangian's inner one). With
    one, ``outer_steps`` is the augmented Lagrangian's: it restarts its inner strategy
    after every multiplier update, so a method's ``steps`` are one outer step's (an
    optimiser's schedule), and a chain's switch counts inner requests over all of them."""

    objective: Any
    x0: np.ndarray
    seed: int = 0
    constrained: bool = False
    outer_steps: int = 1


@dataclasses.dataclass(frozen=True)
class Method:
    """One named method. steps: its default budget (requests: generations, gradient
    steps, simplex steps). options: its options and their defaults. constrained: the
    defaults that differ with a requirement set. build: ``build(problem, steps,
    **options) -> strategy``. gradient: it takes gradients (the gradient program's
    options apply). draws: it samples the objective's sample size (``--draws``).
    patience, tolerance: it stops once its validated score improved by less than
    ``tolerance`` over ``patience`` steps (:class:`fojax.optimize.Budget`)."""

    name: str
    summary: str
    steps: int
    options: Mapping[str, Any]
    build: Callable
    constrained: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    gradient: bool = False
    draws: bool = True
    patience: int | None = None
    tolerance: float = 1e-3

    def defaults(self, constrained: bool = False) -> dict:
        """The options' defaults (with a requirement set where ``constrained``)."""
        return {**self.options, **(self.constrained if constrained else {})}

    def make(self, problem: Problem, steps: int | None = None, **options):
        """The strategy for ``problem`` over ``steps`` (default :attr:`steps`) with
        ``options`` (the others at their defaults); ``ValueError`` for an option that
        does not apply or a budget the method cannot use."""
        unknown = sorted(set(options) - set(self.options))
        if unknown:
            raise ValueError(
                f"method {self.name} takes no option {', '.join(unknown)} (its options: "
                f"{', '.join(self.options) or 'none'})"
            )
        steps = self.steps if steps is None else steps
        checks.integer("steps", steps)
        settings = {**self.defaults(problem.constrained), **options}
        return self.build(problem, steps, **settings)


def _auto(problem: Problem, steps: int, sigma: float):
    objective = problem.objective
    if problem.constrained:  # inside the augmented Lagrangian: one CMA-ES on --draws draws
        return CMAES(sigma0=sigma, seed=problem.seed, name="auto")
    from fojax.optimize import params

    tie, d = None, objective.size
    if objective.param_map.share != "paper":
        coarse = params.make_parameter_map(objective.spec.controller, objective.spec.fields,
                                           "paper")  # fmt: skip
        tie = tuple(objective.param_map.tie(coarse).tolist())
    found = starts(objective, problem.x0)
    free = found[-1] if found else np.asarray(problem.x0)  # the knowledge-free start
    found += [free] * (AUTO_SEARCHES - 1 - len(found))
    k = d if tie is None else max(tie) + 1
    first = max(s * (CMAES().constants(k)["lam"] + 1) * n for _, s, n in AUTO_STAGES)
    popsize = max(first // AUTO_DRAWS - 1, CMAES().constants(d)["lam"])
    coarse_dt = AUTO_COARSE * objective.spec.dt
    try:
        objective.spec.check_step(coarse_dt)
    except ValueError:  # a horizon of an odd number of steps: no coarse phase
        coarse_dt = None
    return MultiStart(
        starts=tuple(tuple(s) for s in found), tie=tie, sigma0=sigma, seed=problem.seed,
        stages=AUTO_STAGES, coarse_dt=coarse_dt, draws=AUTO_DRAWS, popsize=popsize,
        diagonal=True, name="auto",
    )  # fmt: skip


AUTO_SEARCHES = 4
"""Searches of ``auto``'s first phase: the start, the start at integer orders and the
knowledge-free start at integer orders, and copies of the latter up to this count."""
AUTO_STAGES = ((100, 4, 4),)
"""``auto``'s first phase: 100 generations of its four searches on 4 draws each
(:class:`MultiStart`'s ``stages``)."""
AUTO_COARSE = 2
"""``auto``'s first phase runs at this many times the objective's step."""


def _cma_lbfgs(problem: Problem, steps: int, sigma: float, popsize, switch: int, max_step: float):
    if switch >= steps * problem.outer_steps:
        raise ValueError(
            f"cma-lbfgs: {steps * problem.outer_steps} steps leave no L-BFGS step after "
            f"{switch} CMA-ES generations (--switch): give more steps than --switch, or use "
            f"--method cma-es"
        )
    draws = None if problem.constrained else AUTO_DRAWS  # with requirements: --draws
    first = CMAES(sigma0=sigma, popsize=popsize, seed=problem.seed, draws=draws,
                  name="cma-lbfgs")  # fmt: skip
    return Chain(first, LBFGS(max_step=max_step, width=None), switch)


def _adam(problem, steps, learning_rate, final_learning_rate, clip_norm, anneal_start, anneal_end):
    sample = "fixed" if problem.constrained else "fresh"
    anneal = (anneal_start, anneal_end)
    return adam(steps, learning_rate, final_learning_rate, clip_norm, anneal, sample)


_CMA = {"sigma": 0.5, "popsize": None}
METHODS = {
    m.name: m
    for m in (
        Method(
            "auto",
            "CMA-ES from the start, from it at integer fractional orders and from a "
            "knowledge-free start side by side, the best continued until it converges",
            240, {"sigma": 0.5}, _auto, draws=False, patience=60, tolerance=2e-3,
        ),
        Method(
            "cma-lbfgs", "CMA-ES on 8-draw fresh samples, then L-BFGS on the fixed sample",
            60, {**_CMA, "switch": 30, "max_step": 1.0}, _cma_lbfgs, gradient=True,
        ),
        Method(
            "adam", "Adam on fresh samples, the tuning law's width annealed",
            100,
            {"learning_rate": 0.05, "final_learning_rate": 0.1, "clip_norm": 1.0,
             "anneal_start": 4.0, "anneal_end": 1.0},
            _adam, {"learning_rate": 0.1, "final_learning_rate": 1.0, "anneal_start": 1.0},
            gradient=True,
        ),  # fmt: skip
        Method(
            "lbfgs", "L-BFGS on the fixed sample", 60, {"max_step": 1.0, "anneal_end": 1.0},
            lambda p, steps, max_step, anneal_end: LBFGS(max_step=max_step, width=anneal_end),
            gradient=True,
        ),
        Method(
            "cma-es", "CMA-ES, every generation on a fresh sample of --draws draws", 500, _CMA,
            lambda p, steps, sigma, popsize: CMAES(sigma0=sigma, popsize=popsize, seed=p.seed),
        ),
        Method(
            "nelder-mead", "Nelder-Mead on the fixed sample", 2000, {},
            lambda p, steps: NelderMead(),
        ),
    )
}
"""The methods by name, ``auto`` (the default) first."""


def make(method: str, problem: Problem, steps: int | None = None, **options):
    """``METHODS[method].make(problem, steps, **options)``."""
    checks.choice("method", method, tuple(METHODS))
    return METHODS[method].make(problem, steps, **options)


def starts(objective, x0) -> list[np.ndarray]:
    """Other starts than ``x0`` for ``auto``: ``x0`` with its tuned fractional orders at
    their integer-order bounds (:func:`fojax.optimize.params.integer_order_gains`; an
    order field the objective does not tune keeps the base gains' value), and the
    knowledge-free start (:func:`fojax.optimize.params.naive_gains`: positive gains 1)
    at integer orders; those equal to ``x0`` or to each other left out."""
    from fojax.optimize import params

    x0 = np.asarray(x0, np.float64)
    base, tuned = objective.base_gains, objective.param_map.names

    def tuned_of(gains):  # base gains with the tuned fields of ``gains``
        return base._replace(**{name: getattr(gains, name) for name in tuned})

    naive = tuned_of(params.naive_gains(objective.spec.controller, objective.dtype))
    found: list[np.ndarray] = []
    for gains in (objective.gains(x0), naive):
        x = objective.vector(tuned_of(params.integer_order_gains(gains)))
        if not any(np.allclose(x, y, rtol=0, atol=1e-6) for y in [x0, *found]):
            found.append(x)
    return found


def lanes(strategy, size: int, draws: int, devices: int) -> int:
    """Lanes per device and call that fit the strategy's requests: its largest request
    (``lanes(d)``, where it has one) or its first request's points (or its
    ``typical_points``) x draws over ``devices`` (the inner strategy's, for a wrapper),
    in ``[8, 128]``: a population in one call where that fits, with no lane padded."""
    inner = getattr(strategy, "inner", strategy)
    if hasattr(inner, "lanes"):
        per_device = -(-inner.lanes(size) // devices)
    else:
        request = inner.ask(inner.init(np.zeros(size)))
        points = getattr(inner, "typical_points", len(request.points))
        per_device = -(-points * (request.draws or draws) // devices)
    return int(min(128, max(8, per_device)))
