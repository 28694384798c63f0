"""fojax: differentiable, vectorised quadrotor simulation with fractional-order control.

Modules: :mod:`fojax.fractional` (fractional operators), :mod:`fojax.plant` (the
quadrotor, eqs. (8)-(11)), :mod:`fojax.scenarios` (Section V's scenarios as data),
:mod:`fojax.controller` (the controller interface), :mod:`fojax.afonftsmc` (the paper's
controller), :mod:`fojax.anftsmc`, :mod:`fojax.backstepping` (BSMC, FOBSMC) and
:mod:`fojax.fl` (the compared controllers, on :mod:`fojax.cascade`),
:mod:`fojax.registry` (controllers by name), :mod:`fojax.simulator` (one
closed-loop rollout), :mod:`fojax.metrics`, :mod:`fojax.montecarlo` (batched draws),
:mod:`fojax.statistics`, :mod:`fojax.gains_io` (gains files).
"""

from fojax import (
    afonftsmc,
    anftsmc,
    backstepping,
    cascade,
    controller,
    fl,
    fractional,
    gains_io,
    metrics,
    montecarlo,
    plant,
    registry,
    scenarios,
    simulator,
    statistics,
)
from fojax.afonftsmc import AFONFTSMC, AFONFTSMCGains, paper_gains
from fojax.anftsmc import ANFTSMC, ANFTSMCGains
from fojax.backstepping import BSMC, FOBSMC, BSMCGains, FOBSMCGains
from fojax.fl import FL, FLGains
from fojax.fractional import differintegrate
from fojax.gains_io import load_gains, save_gains
from fojax.montecarlo import MonteCarloResult
from fojax.montecarlo import run as run_monte_carlo
from fojax.plant import PlantParams, nominal_params
from fojax.registry import controller_names, make_controller
from fojax.scenarios import Scenario, get_scenario
from fojax.simulator import Rollout, SimulationConfig, rollout

__all__ = [
    "AFONFTSMC",
    "AFONFTSMCGains",
    "ANFTSMC",
    "ANFTSMCGains",
    "BSMC",
    "BSMCGains",
    "FL",
    "FLGains",
    "FOBSMC",
    "FOBSMCGains",
    "MonteCarloResult",
    "PlantParams",
    "Rollout",
    "Scenario",
    "SimulationConfig",
    "afonftsmc",
    "anftsmc",
    "backstepping",
    "cascade",
    "controller",
    "controller_names",
    "differintegrate",
    "fl",
    "fractional",
    "gains_io",
    "get_scenario",
    "load_gains",
    "make_controller",
    "metrics",
    "montecarlo",
    "nominal_params",
    "paper_gains",
    "plant",
    "registry",
    "rollout",
    "run_monte_carlo",
    "save_gains",
    "scenarios",
    "simulator",
    "statistics",
]
__version__ = "0.1.0"
