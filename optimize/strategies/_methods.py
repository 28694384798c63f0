"""The named methods of ``fojax tune --method`` and the studies, with their defaults.

``auto`` (the default): CMA-ES on fresh draws for ``switch`` generations (the gradient
program compiling beside them, :func:`fojax.optimize.run`), its mean then handed to
L-BFGS on the fixed sample. ``adam``, ``lbfgs``, ``cma-es``, ``nelder-mead``: one
strategy each (:mod:`fojax.optimize.strategies`).
"""

from __future__ import annotations

from fojax.optimize.strategies._compose import Chain
from fojax.optimize.strategies._gradient import LBFGS, adam
from fojax.optimize.strategies._population import CMAES, NelderMead

__all__ = ["DEFAULT_STEPS", "METHODS", "make"]

METHODS = ("auto", "adam", "lbfgs", "cma-es", "nelder-mead")
DEFAULT_STEPS = {"auto": 30, "adam": 6, "lbfgs": 6, "cma-es": 20, "nelder-mead": 300}
"""Steps of a run by method: gradient steps, generations (CMA-ES), simplex steps."""


def make(
    method: str,
    steps: int | None = None,
    *,
    seed: int = 0,
    switch: int = 8,
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
    switch: ``auto``'s CMA-ES generations. sigma, popsize: CMA-ES's. max_step: L-BFGS's.
    width: the gradient's (last) width scale. learning_rate, final_learning_rate,
    clip_norm, anneal_start, sample: Adam's."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    steps = DEFAULT_STEPS[method] if steps is None else steps
    cma = CMAES(sigma0=sigma, popsize=popsize, seed=seed)
    lbfgs = LBFGS(max_step=max_step, width=width)
    if method == "adam":
        anneal = (anneal_start, width)
        return adam(steps, learning_rate, final_learning_rate, clip_norm, anneal, sample)
    if method == "auto":
        return Chain(cma, lbfgs, switch)
    return {"lbfgs": lbfgs, "cma-es": cma, "nelder-mead": NelderMead()}[method]
