"""Tuning strategies: one interface for every optimiser of the engine.

A strategy is a static object (settled before anything runs) with pure functions on a
state that is a dict of NumPy arrays of fixed shapes (checkpointed as it is, so a
resumed run continues exactly), in the style of optax's transformations:

* ``init(x0 (d,)) -> state``: the state before the first request;
* ``ask(state) -> Request``: what to evaluate next (:class:`fojax.optimize.Request`:
  points, whether a gradient is needed, which tuning sample, which law, which loss);
* ``tell(state, request, evaluation) -> state``: consume the evaluation of that request;
* ``answer(state) -> (d,)``: the current best guess (what the driver validates);
* ``restart(state) -> state``: the loss changed (an outer iteration of
  :class:`AugmentedLagrangian`): forget what depended on it;
* ``settings() -> dict``: JSON-ready description (part of a run's fingerprint);
* ``row(state) -> dict``: what the strategy adds to the run's history after a request;
* ``settling(state) -> int | None`` (optional): the step from which the budget's
  convergence test judges the run, on the validations from there on (``None``: not
  yet, e.g. while several searches are still being ranked; without it, step 0);
* ``needs() -> tuple``: the programs it will ask for, in order: ``(kind, width[, dt])``,
  ``kind`` ``"forward"`` or ``"gradient"``, ``width`` the law's (``None``: evaluation),
  ``dt`` the step (``None``: the objective's).

Gradient strategies (:mod:`._gradient`): :class:`Optax` (any optax transformation;
:func:`adam` is fojax's setting) and :class:`LBFGS`. Population strategies
(:mod:`._population`): :class:`CMAES` and :class:`NelderMead`. Compositions
(:mod:`._compose`): :class:`Chain` (one strategy hands its answer to the next) and
:class:`AugmentedLagrangian` (requirements as constraints around any strategy).
:class:`MultiStart` (:mod:`._multistart`) runs CMA-ES searches from several starts
side by side and continues the best: the default method. :data:`METHODS` declares the
named methods of ``fojax tune --method`` and the studies (:mod:`._methods`).
"""

from fojax.optimize.strategies._compose import AugmentedLagrangian, Chain
from fojax.optimize.strategies._gradient import LBFGS, Optax, adam
from fojax.optimize.strategies._methods import (
    METHODS,
    Method,
    Problem,
    lanes,
    make,
    starts,
    table,
    words,
)
from fojax.optimize.strategies._multistart import MultiStart
from fojax.optimize.strategies._population import CMAES, NelderMead

__all__ = [
    "CMAES", "LBFGS", "METHODS", "AugmentedLagrangian", "Chain", "Method",
    "MultiStart", "NelderMead", "Optax", "Problem", "adam", "lanes", "make", "starts", "table",
    "words",
]  # fmt: skip
