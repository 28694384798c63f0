"""The named methods of ``fojax tune --method`` and of every study, each declared once
(:data:`METHODS`) with its whole plan: the strategy it builds, its default budget, the
options that apply to it and their defaults, the settings of its plan that no option
changes (``auto``'s stages, coarse step, draws per phase, population rule, ...), the
values of either that differ with a requirement set (the inner strategy of the
augmented Lagrangian), whether it takes gradients and whether the objective's sample
size (``--draws``) is what it samples. ``fojax tune`` derives its method options, their
defaults, its help and its "does not apply" errors from this table, the studies build
their tuners from it, and a test holds docs/tuning.md's method table and its account of
the default method to it, so none can drift.
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

__all__ = ["METHODS", "NONE", "Method", "Problem", "lanes", "make", "starts", "table", "words"]


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
    """One named method and its whole plan. summary: what it does, in words (a template
    filled from its options' and settings' defaults: ``{draws}``). steps: its default
    budget (requests: generations, gradient steps, simplex steps). options: its options
    (each a ``fojax tune`` option of that name) and their defaults. settings: the rest of
    its plan, which no option of the command changes (:meth:`make` takes them, for tests
    and studies). constrained: the options' and settings' values that differ with a
    requirement set. build: ``build(problem, steps, **options, **settings) ->
    strategy``. gradient: it takes gradients (the gradient program's options apply).
    draws: it samples the objective's sample size (``--draws``) without a requirement
    set; with one every method does (a setting ``draws`` is ``None`` there). own: where
    it does not, ``own(settings)``: the draws per point of the fresh samples it takes
    instead, phase by phase. patience, tolerance: it stops once its validated score
    improved by less than ``tolerance`` over ``patience`` steps
    (:class:`fojax.optimize.Budget`)."""

    name: str
    summary: str
    steps: int
    options: Mapping[str, Any]
    build: Callable
    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    constrained: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    gradient: bool = False
    draws: bool = True
    own: Callable | None = None
    patience: int | None = None
    tolerance: float = 1e-3

    def __post_init__(self) -> None:
        both = sorted(set(self.options) & set(self.settings))
        if both:
            raise ValueError(f"method {self.name}: {', '.join(both)} both option and setting")
        unknown = sorted(set(self.constrained) - set(self.options) - set(self.settings))
        if unknown:
            raise ValueError(f"method {self.name}: no option or setting {', '.join(unknown)}")
        if self.draws == (self.own is not None):
            raise ValueError(f"method {self.name}: own draws exactly where it has no --draws")
        if self.plan(constrained=True).get("draws") is not None:
            raise ValueError(f"method {self.name}: with a requirement set it samples --draws")
        summary = self.summary.format(**self.options, **self.settings)
        object.__setattr__(self, "summary", summary)

    def defaults(self, constrained: bool = False) -> dict:
        """The options' defaults (with a requirement set where ``constrained``)."""
        return self._with(self.options, constrained)

    def plan(self, constrained: bool = False) -> dict:
        """The settings (with a requirement set where ``constrained``)."""
        return self._with(self.settings, constrained)

    def _with(self, values: Mapping, constrained: bool) -> dict:
        changed = self.constrained if constrained else {}
        return {name: changed.get(name, value) for name, value in values.items()}

    def own_draws(self) -> tuple[int, ...]:
        """The draws per point of the fresh samples it takes without a requirement set
        where it does not sample ``--draws`` (``()`` where it does), phase by phase."""
        return () if self.own is None else tuple(self.own(self.settings))

    def make(self, problem: Problem, steps: int | None = None, **options):
        """The strategy for ``problem`` over ``steps`` (default :attr:`steps`) with
        ``options`` (options or settings; the others at their defaults); ``ValueError``
        for one the method does not have or a budget the method cannot use."""
        unknown = sorted(set(options) - set(self.options) - set(self.settings))
        if unknown:
            raise ValueError(
                f"method {self.name} takes no option {', '.join(unknown)} (its options: "
                f"{', '.join(self.options) or 'none'}; its settings: "
                f"{', '.join(self.settings) or 'none'})"
            )
        steps = self.steps if steps is None else steps
        checks.integer("steps", steps)
        constrained = problem.constrained
        values = {**self.defaults(constrained), **self.plan(constrained), **options}
        return self.build(problem, steps, **values)


def _auto(problem: Problem, steps: int, sigma: float, stages, coarse, draws, popsize,
          diagonal, window, lift):  # fmt: skip
    objective = problem.objective
    if problem.constrained:  # inside the augmented Lagrangian: one CMA-ES
        return CMAES(sigma0=sigma, seed=problem.seed, draws=draws, name="auto")

    tie, d = None, objective.size
    if objective.param_map.share != "paper":
        coarse_map = objective.spec.parameter_map("paper")
        tie = tuple(objective.param_map.tie(coarse_map).tolist())
    searches = stages[0][1] if stages else 1  # the first stage's: every start's search
    found = starts(objective, problem.x0)
    free = found[-1] if found else np.asarray(problem.x0)  # the knowledge-free start
    found += [free] * (searches - 1 - len(found))
    k = d if tie is None else max(tie) + 1
    first = max(s * (CMAES().constants(k)["lam"] + 1) * n for _, s, n in stages)
    # every point's sample holds each case of a union equally often; the second phase
    # keeps the lanes of the first at its declared draws (a call of them on two devices)
    stages = tuple((g, s, objective.stratified(n)) for g, s, n in stages)
    draws = objective.stratified(draws)
    if popsize == "fill":  # as many candidates as fill the first phase's declared lanes
        popsize = max(first // draws - 1, CMAES().constants(d)["lam"])
    coarse_dt = None if coarse is None else coarse * objective.spec.dt
    try:
        if coarse_dt is not None:
            objective.spec.check_step(coarse_dt)
    except ValueError:  # a horizon of an odd number of steps: no coarse phase
        coarse_dt = None
    return MultiStart(
        starts=tuple(tuple(s) for s in found), tie=tie, sigma0=sigma, seed=problem.seed,
        stages=stages, coarse_dt=coarse_dt, draws=draws, popsize=popsize,
        window=window, lift=lift, diagonal=diagonal, name="auto",
    )  # fmt: skip


def _cma_lbfgs(problem: Problem, steps: int, sigma: float, popsize, switch: int, max_step: float,
               draws: int, width):  # fmt: skip
    if switch >= steps * problem.outer_steps:
        raise ValueError(
            f"cma-lbfgs: {steps * problem.outer_steps} steps leave no L-BFGS step after "
            f"{switch} CMA-ES generations (--switch): give more steps than --switch, or use "
            f"--method cma-es"
        )
    first = CMAES(sigma0=sigma, popsize=popsize, seed=problem.seed, draws=draws,
                  name="cma-lbfgs")  # fmt: skip
    return Chain(first, LBFGS(max_step=max_step, width=width), switch)


def _adam(problem, steps, learning_rate, final_learning_rate, clip_norm, anneal_start, anneal_end,
          sample):  # fmt: skip
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
            240, {"sigma": 0.5}, _auto,
            # stages: the first phase, (generations, searches, draws per point) each, its
            # first stage's searches every start's (MultiStart); coarse: its step, times
            # the objective's (None: the objective's); draws, popsize: the second phase's
            # draws per point and candidates ("fill": as many as fill the first phase's
            # largest request's lanes at its declared draws); over a union (an
            # envelope's cases) every draws per point rounded up to a multiple of the
            # cases (6 and 12 for six: 19 candidates on 12 draws); diagonal: the second
            # phase separable; window: the generations whose means rank the searches;
            # lift: the variance the second phase adds on its diagonal. With
            # requirements: one CMA-ES on --draws draws (every method samples --draws
            # there).
            settings={"stages": ((100, 4, 4),), "coarse": 2, "draws": 8, "popsize": "fill",
                      "diagonal": True, "window": 20, "lift": 0.5},
            constrained={"draws": None}, draws=False,
            own=lambda s: tuple(dict.fromkeys([n for _, _, n in s["stages"]] + [s["draws"]])),
            patience=60, tolerance=2e-3,
        ),  # fmt: skip
        Method(
            "cma-lbfgs", "CMA-ES on {draws}-draw fresh samples, then L-BFGS on the fixed sample",
            60, {**_CMA, "switch": 30, "max_step": 1.0}, _cma_lbfgs,
            # draws: the CMA-ES's draws per point (with requirements --draws, as every
            # method's); width: L-BFGS's law (None: the evaluation law)
            settings={"draws": 8, "width": None}, constrained={"draws": None}, gradient=True,
        ),  # fmt: skip
        Method(
            "adam", "Adam on {sample} samples, the tuning law's width annealed",
            100,
            {"learning_rate": 0.05, "clip_norm": 1.0, "anneal_start": 4.0, "anneal_end": 1.0},
            _adam, {"final_learning_rate": 0.1, "sample": "fresh"},
            {"learning_rate": 0.1, "final_learning_rate": 1.0, "anneal_start": 1.0,
             "sample": "fixed"},
            gradient=True,
        ),  # fmt: skip
        Method(
            "lbfgs", "L-BFGS on the fixed sample", 60, {"max_step": 1.0, "anneal_end": 1.0},
            lambda p, steps, max_step, anneal_end: LBFGS(max_step=max_step, width=anneal_end),
            gradient=True,
        ),  # fmt: skip
        Method(
            "cma-es", "CMA-ES, every generation on a fresh sample of --draws draws", 500, _CMA,
            lambda p, steps, sigma, popsize: CMAES(sigma0=sigma, popsize=popsize, seed=p.seed),
        ),  # fmt: skip
        Method(
            "nelder-mead", "Nelder-Mead on the fixed sample", 2000, {},
            lambda p, steps: NelderMead(),
        ),  # fmt: skip
    )
}
"""The methods by name, ``auto`` (the default) first."""


NONE = {"popsize": "4 + 3 ln d", "draws": "--draws", "width": "evaluation law",
        "coarse": "the objective's step"}  # fmt: skip
"""What ``None`` means for an option or setting of that name (:func:`words`)."""


def words(name: str, value) -> str:
    """An option's or setting's value as the help and the docs write it: ``None`` as
    :data:`NONE` says, a number as ``%g``, stages as ``(generations, searches, draws)``
    each, a flag as yes or no."""
    if value is None:
        return NONE.get(name, "none")
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, tuple):
        return ", ".join(words(name, v) for v in value) if isinstance(value[0], tuple) else (
            "(" + ", ".join(words(name, v) for v in value) + ")")  # fmt: skip
    return f"{value:g}" if isinstance(value, float) else str(value)


def _values(values: Mapping) -> str:
    return ", ".join(f"`{name}` {words(name, value)}" for name, value in values.items()) or "-"


def table() -> str:
    """The method table in Markdown (docs/tuning.md holds it verbatim; a test compares):
    each method's summary, default steps, convergence test, options and settings with
    their defaults, and what differs with a requirement set."""
    lines = [
        "| `--method` | what it does | `--steps` | stops once converged | options "
        "(defaults) | settings (its fixed plan) | with `--requirements` |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in METHODS.items():
        stop = "no"
        if m.patience:
            stop = f"below {m.tolerance:.1%} over {m.patience} steps".replace("%", " %")
        label = f"`{name}` (the default)" if name == next(iter(METHODS)) else f"`{name}`"
        lines.append(
            f"| {label} | {m.summary} | {m.steps} | {stop} | {_values(m.options)} | "
            f"{_values(m.settings)} | {_values(m.constrained)} |"
        )
    return "\n".join(lines)


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

    capped = objective.spec.envelope is not None
    naive = tuned_of(params.naive_gains(objective.spec.controller, objective.dtype, capped))
    found: list[np.ndarray] = []
    for gains in (objective.gains(x0), naive):
        x = objective.vector(tuned_of(params.integer_order_gains(gains)))
        if not any(np.allclose(x, y, rtol=0, atol=1e-6) for y in [x0, *found]):
            found.append(x)
    return found


def lanes(strategy, size: int, draws: int, devices: int) -> int:
    """Lanes per device and call that fit the strategy's requests: the lanes it asks for
    (``lanes(d)``, where it has one: ``auto``'s, its longest phase's) or its first
    request's points (or its
    ``typical_points``) x draws over ``devices`` (the inner strategy's, for a wrapper),
    in ``[8, 128]``: a population in one call where that fits, else in the fewest calls of
    equal lanes (360 lanes on two devices: two calls of 90 each, not a call of 128 and
    one of 52 padded to 128), with no lane padded where the division allows."""
    inner = getattr(strategy, "inner", strategy)
    if hasattr(inner, "lanes"):
        per_device = -(-inner.lanes(size) // devices)
    else:
        request = inner.ask(inner.init(np.zeros(size)))
        points = getattr(inner, "typical_points", len(request.points))
        per_device = -(-points * (request.draws or draws) // devices)
    calls = -(-per_device // 128)
    return int(max(8, -(-per_device // calls)))
