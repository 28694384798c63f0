"""fojax: differentiable, vectorised quadrotor simulation with fractional-order control.

Read top to bottom, each layer uses only those below it:

* :mod:`fojax.study`: Monte Carlo studies (chunked, vmapped rollouts, a resumable
  store, summaries); :mod:`fojax.statistics` their intervals; :mod:`fojax.sharding`
  draws over devices; :mod:`fojax.requirements` bounds per draw on metrics, their
  yield and its interval;
* :mod:`fojax.simulator`: one closed-loop rollout (plant + controller + scenario,
  ``lax.scan``), whose records are folded by :mod:`fojax.observers` (status flags,
  :mod:`fojax.metrics`, tuning costs);
* :mod:`fojax.controllers`: the cascade every controller shares and the control laws
  it runs (the paper's AFONFTSMC; FL, BSMC, FOBSMC, ANFTSMC), their declared gains,
  the registry and gains files;
* :mod:`fojax.scenarios` (Section V as data), :mod:`fojax.plant` (eqs. (8)-(11)),
  :mod:`fojax.vehicle` (other quadrotors, from files), :mod:`fojax.rotors` (rotor
  layouts, their allocation and authority, rotor lag), :mod:`fojax.reference`
  (references from waypoint files),
  :mod:`fojax.fractional` (fractional operators).
"""

from fojax import (
    controllers,
    fractional,
    metrics,
    observers,
    plant,
    reference,
    requirements,
    rotors,
    scenarios,
    sharding,
    simulator,
    statistics,
    study,
    vehicle,
)
from fojax.controllers import (
    Cascade,
    ControlLaw,
    GainField,
    GainSpec,
    controller_names,
    load_gains,
    make_controller,
    paper_gains,
    register,
    save_gains,
)
from fojax.fractional import differintegrate
from fojax.plant import PlantParams, nominal_params
from fojax.scenarios import Scenario, get_scenario
from fojax.simulator import Rollout, SimulationConfig, rollout
from fojax.study import MonteCarloResult
from fojax.study import run as run_monte_carlo
from fojax.vehicle import Vehicle

__all__ = [
    "Cascade",
    "ControlLaw",
    "GainField",
    "GainSpec",
    "MonteCarloResult",
    "PlantParams",
    "Rollout",
    "Scenario",
    "SimulationConfig",
    "Vehicle",
    "controller_names",
    "controllers",
    "differintegrate",
    "fractional",
    "get_scenario",
    "load_gains",
    "make_controller",
    "metrics",
    "nominal_params",
    "observers",
    "paper_gains",
    "plant",
    "reference",
    "register",
    "rotors",
    "requirements",
    "rollout",
    "run_monte_carlo",
    "save_gains",
    "scenarios",
    "sharding",
    "simulator",
    "statistics",
    "study",
    "vehicle",
]
__version__ = "0.1.0"
