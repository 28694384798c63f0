"""Gain tuning on one engine: an objective, strategies, one driver.

* :class:`Objective` (:mod:`.objective`): a tuning problem (:class:`ProblemSpec`,
  :mod:`.spec`: controller, scenario or union, cost or requirement set, draws,
  actuators, precision) compiled once: a population's outputs in one batched call, the
  loss's gradient by per-draw reverse mode, held-out evaluation, in blocks over devices;
* strategies (:mod:`.strategies`): ``init``/``ask``/``tell`` on array states: optax
  transformations (Adam), L-BFGS, CMA-ES, Nelder-Mead, a chain of two, the augmented
  Lagrangian around any of them;
* :func:`run` (:mod:`.driver`): the loop, within a :class:`Budget`, validated
  (the best validated answer returned), checkpointed (resume equals the uninterrupted
  run), with a history; one :class:`Result`.

:mod:`.params` maps unconstrained parameters onto feasible gains; :mod:`.cost` is the
weighted-sum cost.
"""

from fojax.optimize import strategies
from fojax.optimize.cost import CostConfig
from fojax.optimize.driver import CHECKPOINT, Budget, Result, check_resume, describe, run
from fojax.optimize.losses import AlmLoss, MeanLoss
from fojax.optimize.objective import Objective
from fojax.optimize.params import make_parameter_map, naive_gains
from fojax.optimize.requests import Evaluation, Outputs, Request
from fojax.optimize.spec import (
    HELDOUT_OFFSET,
    VALIDATION_OFFSET,
    ProblemSpec,
    checkpoint_interval,
    draw_keys,
)

__all__ = [
    "CHECKPOINT", "HELDOUT_OFFSET", "VALIDATION_OFFSET", "AlmLoss", "Budget", "CostConfig",
    "Evaluation", "MeanLoss", "Objective", "Outputs", "ProblemSpec", "Request", "Result",
    "check_resume", "checkpoint_interval", "describe", "draw_keys", "make_parameter_map",
    "naive_gains", "run", "strategies",
]  # fmt: skip
