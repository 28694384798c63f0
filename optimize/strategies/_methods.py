"""The named methods of ``fojax tune --method`` and the studies, with their defaults.

``auto`` (the default): CMA-ES on small fresh samples, :data:`AUTO_DRAWS` draws per
generation (a new sample every generation, common to its candidates: a population of
``4 + 3 ln d`` candidates is then about one efficient call of 112-128 lanes), 40
generations (docs/tuning.md, "the default method", has the measurements). ``adam``,
``lbfgs``, ``cma-es``, ``nelder-mead``: one strategy each
(:mod:`fojax.optimize.strategies`); ``cma-es`` takes the objective's sample size.
``cma-lbfgs``: ``auto``'s CMA-ES for ``switch`` generations, its mean then handed to
L-BFGS at the evaluation law on the fixed sample (the gradient compiled beside the
generations): a composition, measured beside the default.
"""

from __future__ import annotations

from fojax.optimize import checks
from fojax.optimize.strategies._compose import Chain
from fojax.optimize.strategies._gradient import LBFGS, adam
from fojax.optimize.strategies._population import CMAES, NelderMead

__all__ = ["AUTO_DRAWS", "DEFAULT_STEPS", "METHODS", "lanes", "make"]

METHODS = ("auto", "cma-lbfgs", "adam", "lbfgs", "cma-es", "nelder-mead")
AUTO_DRAWS = 8
"""Draws per candidate and generation of ``auto``."""
DEFAULT_STEPS = {
    "auto": 40,
    "cma-lbfgs": 40,
    "adam": 6,
    "lbfgs": 6,
    "cma-es": 20,
    "nelder-mead": 300,
}
"""Steps of a run by method: gradient steps, generations (CMA-ES), simplex steps."""


def make(
    method: str,
    steps: int | None = None,
    *,
    seed: int = 0,
    switch: int = 30,
    sigma: float = 0.5,
    popsize: int | None = None,
    max_step: float = 1.0,
    width: float = 1.0,
    learning_rate: float = 0.05,
    final_learning_rate: float = 0.1,
    clip_norm: float = 1.0,
    anneal_start: float = 4.0,
    sample: str = "fresh",
):
    """The strategy of ``method`` (:data:`METHODS`) for a run of ``steps`` steps (default
    :data:`DEFAULT_STEPS`; Adam's schedule spans them). seed: CMA-ES's sampling seed.
    switch: ``cma-lbfgs``'s CMA-ES generations. sigma, popsize: CMA-ES's. max_step:
    L-BFGS's. width: the gradient's (last) width scale. learning_rate, final_learning_rate,
    clip_norm, anneal_start, sample: Adam's."""
    checks.choice("method", method, METHODS)
    steps = DEFAULT_STEPS[method] if steps is None else steps
    cma = CMAES(sigma0=sigma, popsize=popsize, seed=seed)
    lbfgs = LBFGS(max_step=max_step, width=width)
    if method == "adam":
        anneal = (anneal_start, width)
        return adam(steps, learning_rate, final_learning_rate, clip_norm, anneal, sample)
    if method in ("auto", "cma-lbfgs"):
        small = CMAES(sigma0=sigma, popsize=popsize, seed=seed, draws=AUTO_DRAWS, name=method)
        return (
            small
            if method == "auto"
            else Chain(small, LBFGS(max_step=max_step, width=None), switch)
        )
    return {"lbfgs": lbfgs, "cma-es": cma, "nelder-mead": NelderMead()}[method]


def lanes(strategy, size: int, draws: int, devices: int) -> int:
    """Lanes per device and call that fit the strategy's requests: its first request's
    points (or its ``typical_points``) x draws over ``devices`` (the inner strategy's,
    for a wrapper), in ``[8, 128]`` (a population in one call where that fits, with no
    lane padded: a call's time grows far slower than its lanes, docs/tuning.md)."""
    import numpy as np

    inner = getattr(strategy, "inner", strategy)
    request = inner.ask(inner.init(np.zeros(size)))
    points = getattr(inner, "typical_points", len(request.points))
    per_device = -(-points * (request.draws or draws) // devices)
    return int(min(128, max(8, per_device)))
