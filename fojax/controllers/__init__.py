"""Controllers: the cascade every controller shares, the control laws it runs, their
declared gains, the registry and gains files.

* :mod:`~fojax.controllers.base`: the controller interface the simulator calls
  (:class:`Observation`, :class:`ControlInfo`), :class:`ControlLaw` (the base of every
  law), :class:`FractionalMemory` (a law's fractional memory) and :class:`LawOutput`;
* :mod:`~fojax.controllers.gains`: :class:`GainField`, :class:`GainSpec`,
  :class:`Bounds`: gains declared once;
* :mod:`~fojax.controllers.cascade`: :class:`Cascade`, the position/attitude cascade
  (eq. (13), command filter, model cancellation) around a law;
* the laws: :class:`AFONFTSMC` (the paper's), and the four it is compared with,
  :class:`ANFTSMC`, :class:`FOBSMC`, :class:`BSMC`, :class:`FL`;
* :mod:`~fojax.controllers.registry`: controllers by name (:func:`make_controller`);
* :mod:`~fojax.controllers.gains_io`: gains files;
* :func:`unstack`: the entries of a per-axis array, read the way the reverse pass
  handles best.
"""

from fojax._arrays import unstack
from fojax.controllers import gains_io, registry
from fojax.controllers.afonftsmc import AFONFTSMC, AFONFTSMCGains, paper_gains
from fojax.controllers.anftsmc import ANFTSMC, ANFTSMCGains
from fojax.controllers.backstepping import BSMC, FOBSMC, BSMCGains, FOBSMCGains
from fojax.controllers.base import (
    SWITCHING_FUNCTIONS,
    ControlInfo,
    ControlLaw,
    Controller,
    FractionalMemory,
    LawOutput,
    Observation,
    abs_power,
    signed_power,
    switching,
)
from fojax.controllers.cascade import Cascade, as_controller
from fojax.controllers.fl import FL, FLGains
from fojax.controllers.gains import Bounds, GainField, GainSpec, per_axis
from fojax.controllers.gains_io import load_gains, save_gains
from fojax.controllers.registry import (
    controller_names,
    controller_options,
    get_controller_class,
    make_controller,
    register,
)

__all__ = [
    "AFONFTSMC",
    "AFONFTSMCGains",
    "ANFTSMC",
    "ANFTSMCGains",
    "BSMC",
    "BSMCGains",
    "Bounds",
    "Cascade",
    "ControlInfo",
    "ControlLaw",
    "Controller",
    "FL",
    "FLGains",
    "FOBSMC",
    "FOBSMCGains",
    "FractionalMemory",
    "GainField",
    "GainSpec",
    "LawOutput",
    "Observation",
    "SWITCHING_FUNCTIONS",
    "abs_power",
    "as_controller",
    "controller_names",
    "controller_options",
    "gains_io",
    "get_controller_class",
    "load_gains",
    "make_controller",
    "paper_gains",
    "per_axis",
    "register",
    "registry",
    "save_gains",
    "signed_power",
    "switching",
    "unstack",
]
