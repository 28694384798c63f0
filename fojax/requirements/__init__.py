"""Requirements: bounds per Monte Carlo draw on metrics an engineer signs off, and the
yield (the share of draws meeting every one), with its exact 95 % interval.

Typical use (what ``fojax simulate --requirements FILE`` does)::

    from fojax import requirements as rq
    reqs = rq.load("examples/requirements/small_quadrotor.toml")   # checked here
    config = rq.simulation_config(reqs, horizon=10.0)               # rotor limits
    keys = fojax.scenarios.draw_keys(seed, range(draws))
    metrics, status = rq.measure(controller, gains, scenario, reqs, keys, config)
    result = rq.evaluate(reqs, metrics)                             # YieldResult
    summary["requirements"] = {**reqs.to_dict(), **result.to_dict()}

* :mod:`._spec`: the metric catalogue (:data:`METRICS`), units (:data:`UNITS`),
  :class:`Requirement`, :class:`RequirementSet`, :func:`parse`, :func:`load`;
* :mod:`._observer`: :class:`RequirementMetrics` (the observer computing every metric
  in a rollout), :func:`measure`, smooth :func:`violations` for gradient tuners
  (:class:`fojax.optimize.strategies.AugmentedLagrangian`), :func:`rotor_speed_limit`;
* :mod:`._yield`: :func:`pass_matrix`, :func:`evaluate` -> :class:`YieldResult`,
  :func:`clopper_pearson`.

docs/requirements.md describes the file format, the metrics and the tuner.
"""

from fojax.requirements._observer import (
    DIVERGED,
    RequirementMetrics,
    draw_metrics,
    measure,
    rotor_speed_limit,
    simulation_config,
    smooth_share,
    squared_hinge,
    violations,
)
from fojax.requirements._spec import (
    BOUNDS,
    METRICS,
    UNITS,
    MetricInfo,
    Requirement,
    RequirementError,
    RequirementSet,
    Settings,
    load,
    parse,
)
from fojax.requirements._yield import YieldResult, clopper_pearson, evaluate, pass_matrix

__all__ = [
    "BOUNDS",
    "DIVERGED",
    "METRICS",
    "UNITS",
    "MetricInfo",
    "Requirement",
    "RequirementError",
    "RequirementMetrics",
    "RequirementSet",
    "Settings",
    "YieldResult",
    "clopper_pearson",
    "draw_metrics",
    "evaluate",
    "load",
    "measure",
    "parse",
    "pass_matrix",
    "rotor_speed_limit",
    "simulation_config",
    "smooth_share",
    "squared_hinge",
    "violations",
]
