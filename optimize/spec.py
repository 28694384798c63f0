"""A tuning problem's static description: the controller, the scenario, the draws, the
cost, the tuned fields, the precision (:class:`ProblemSpec`, validated in Python before
anything is traced), and the three disjoint ranges of draws (:func:`draw_keys`).

Draws (``scenarios.draw_keys(seed, i)``): tuning sample ``k`` of ``n`` draws is indices
``k n ... (k + 1) n - 1`` (sample 0 is the fixed sample of the sample-average methods,
``k`` the generation or step of those that take fresh draws); validation draws, which a
run uses to choose among its own iterates, are ``2^30 + j``; held-out draws, which no
tuner sees, are ``2^31 + j``. No run reaches the validation range.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from fojax import scenarios, simulator
from fojax.controllers import registry
from fojax.optimize import checks
from fojax.optimize import cost as cost_lib
from fojax.optimize import params as params_lib

__all__ = [
    "COMPILE_MODES", "DTYPES", "HELDOUT_OFFSET", "TARGETS", "VALIDATION_OFFSET", "ProblemSpec",
    "checkpoint_interval", "draw_keys",
]  # fmt: skip

VALIDATION_OFFSET = 2**30
HELDOUT_OFFSET = 2**31
OFFSETS = {"tuning": 0, "validation": VALIDATION_OFFSET, "heldout": HELDOUT_OFFSET}
DTYPES = ("float32", "float64")
TARGETS = ("cost", "effort", "tracking")
"""What ``f`` is: ``cost`` the weighted sum ``J``; ``effort`` ``E``; ``tracking`` ``P + A``."""
COMPILE_MODES = {"optimized": None, "fast": {"xla_backend_optimization_level": 0}}
"""``ProblemSpec.compile`` -> XLA options of the gradient program (``fast``: without
LLVM's optimisation passes: several times faster to compile, slower to run)."""


def draw_keys(seed: int, kind: str, count: int, first: int = 0) -> np.ndarray:
    """Keys ``(count, 2)`` of draws ``first ... first + count - 1`` of range ``kind``
    (``"tuning"``, ``"validation"`` or ``"heldout"``) of ``seed``."""
    indices = OFFSETS[kind] + first + np.arange(count)
    return np.asarray(scenarios.draw_keys(seed, indices))


def checkpoint_interval(steps: int, target: float | None = None) -> int:
    """Steps per checkpointed block of the reverse pass: the divisor of ``steps`` nearest
    ``target`` (default ``0.75 sqrt(steps)``: memory ``(steps / L) c + L r`` for blocks
    of ``L`` steps is least at ``L = sqrt(steps c / r)``; for the AFONFTSMC the carry
    ``c`` is about 0.55 of one step's residuals ``r``, measured with
    ``experiments/tune_memory.py``), so memory grows like the square root of the horizon."""
    target = 0.75 * math.sqrt(steps) if target is None else target
    return simulator.divisor_near(steps, target)


@dataclasses.dataclass(frozen=True)
class ProblemSpec:
    """Everything that fixes an objective's draws and cost (validated on construction).

    controller: registry name. scenario: 1, 2 or 3, or a tuple of them (their union).
    horizon, dt: s. draws: draws per sample. seed: the draws' seed. cost:
    :class:`fojax.optimize.cost.CostConfig`. fields: tuned gain fields (``None``:
    :func:`fojax.optimize.params.default_fields`). share: axis sharing
    (:data:`fojax.optimize.params.SHARING`). fractional: fractional method (controllers
    with fractional operators; the others take only ``"soe"``). dtype: ``"float32"`` or
    ``"float64"``. save_every: steps per checkpointed block of the reverse pass (``None``:
    :func:`checkpoint_interval`). compile: ``"optimized"`` or ``"fast"``
    (:data:`COMPILE_MODES`, the gradient program). vehicle: the
    :class:`fojax.vehicle.Vehicle` flown (``None``: the paper's). reference: the
    :mod:`fojax.reference` waypoints or built-in flown in place of every scenario's
    reference (``None``: the scenarios' own). envelope: a :class:`fojax.envelope.Envelope`
    whose cases are flown in place of ``scenario`` (which must then be ``None``).
    case_scales: ``None``, or per case of the union flown a divisor (> 0) of its draws'
    cost (:func:`fojax.optimize.cost.case_scales`): every case's cost in units of a
    reference's on that case. case_chattering: ``None``, or per case a bound (N m) on a
    draw's torques' total variation ``V`` (:class:`fojax.optimize.cost.TorqueVariation`).
    case_tracking: ``None``, or per case a bound (m^2 s) on a draw's position term ``P``
    (the integral of the squared position error). bound_excess: ``w``; a draw pays ``w
    (V / V_c - 1)`` past its chattering bound and ``w (sqrt(P / P_c) - 1)`` (its position
    RMSE over the bound's) past its tracking bound, on top of its (scaled) cost.
    """

    controller: str = "afonftsmc"
    scenario: int | tuple[int, ...] = 2
    horizon: float = 10.0
    dt: float = 1e-3
    draws: int = 16
    seed: int = 0
    cost: cost_lib.CostConfig = cost_lib.CostConfig()
    fields: tuple[str, ...] | None = None
    share: str = "paper"
    fractional: str = "soe"
    dtype: str = "float32"
    save_every: int | None = None
    compile: str = "optimized"
    vehicle: Any = None
    reference: Any = None
    envelope: Any = None
    case_scales: tuple[float, ...] | None = None
    case_chattering: tuple[float, ...] | None = None
    case_tracking: tuple[float, ...] | None = None
    bound_excess: float = 10.0

    def __post_init__(self) -> None:
        registry.get_controller_class(self.controller)
        from fojax.reference import Builtin, Waypoints
        from fojax.vehicle import Vehicle

        if self.reference is not None and not isinstance(self.reference, Waypoints | Builtin):
            raise ValueError(
                "reference must be fojax.reference.Waypoints, a fojax.reference.Builtin or "
                f"None, got {self.reference!r}"
            )
        if self.vehicle is not None and not isinstance(self.vehicle, Vehicle):
            raise ValueError(
                f"vehicle must be a fojax.vehicle.Vehicle or None, got {self.vehicle!r}"
            )
        from fojax.envelope import Envelope

        if self.envelope is not None:
            if not isinstance(self.envelope, Envelope):
                raise ValueError(f"envelope must be a fojax.envelope.Envelope or None, got "
                                 f"{self.envelope!r}")  # fmt: skip
            if self.scenario is not None or self.reference is not None:
                raise ValueError(
                    "an envelope holds the cases flown: give no scenario and no reference "
                    "with it (add reference files to the envelope)"
                )
        ids = self.scenario if isinstance(self.scenario, tuple | list) else (self.scenario,)
        if self.envelope is not None:
            ids = ()
        elif not ids:
            raise ValueError("scenario must name at least one scenario")
        for i in ids:
            scenarios.get_scenario(i)
        if isinstance(self.scenario, list):
            object.__setattr__(self, "scenario", tuple(self.scenario))
        for name in ("case_scales", "case_chattering", "case_tracking"):
            given = getattr(self, name)
            if given is None:
                continue
            values = tuple(float(v) for v in given)
            cases = len(self.scenario_object().members) or 1
            if len(values) != cases or not all(math.isfinite(v) and v > 0 for v in values):
                raise ValueError(f"{name} must be {cases} numbers > 0 (one per case "
                                 f"flown), got {given!r}")  # fmt: skip
            object.__setattr__(self, name, values)
        checks.number("bound_excess", self.bound_excess, allow_low=True)
        checks.choice("compile", self.compile, COMPILE_MODES)
        for label in ("horizon", "dt"):
            checks.number(label, getattr(self, label))
        steps = self.horizon / self.dt
        if abs(steps - round(steps)) > 1e-6 * steps or round(steps) < 1:
            raise ValueError(
                f"the horizon ({self.horizon} s) must be a whole, positive number of steps "
                f"of {self.dt} s"
            )
        checks.integer("draws", self.draws)
        checks.integer("seed", self.seed, 0)
        checks.choice("dtype", self.dtype, DTYPES)
        every = self.save_every
        if every is not None and (not isinstance(every, int) or every < 1 or self.steps % every):
            raise ValueError(
                f"save_every must be a positive divisor of the {self.steps} steps, got "
                f"{self.save_every!r}"
            )
        if self.fields is not None:
            object.__setattr__(self, "fields", tuple(self.fields))
        self.parameter_map()  # validates the fields
        options = registry.controller_options(self.controller)
        if "fractional_method" not in options and self.fractional != "soe":
            raise ValueError(
                f"fractional={self.fractional!r} does not apply to {self.controller}, "
                "which has no fractional operator; leave fractional at its default 'soe'"
            )
        self.make_controller("tanh", self.horizon)  # validates the fractional method

    def parameter_map(self, share: str | None = None) -> params_lib.ParameterMap:
        """The tuned fields' :class:`fojax.optimize.params.ParameterMap` (with ``share``,
        default the spec's), within the search bounds over a flight envelope."""
        return params_lib.make_parameter_map(self.controller, self.fields, share or self.share,
                                             capped=self.envelope is not None)  # fmt: skip

    @property
    def steps(self) -> int:
        return int(round(self.horizon / self.dt))

    def steps_at(self, dt: float | None) -> int:
        """Steps of the horizon at the step ``dt`` (``None``: the spec's)."""
        return self.steps if dt is None else int(round(self.horizon / dt))

    def check_step(self, dt: float) -> None:
        """``ValueError`` unless ``dt`` is a whole multiple of the spec's step that
        divides the horizon (a coarser step of the same draws)."""
        factor = dt / self.dt
        steps = self.horizon / dt
        if (
            abs(factor - round(factor)) > 1e-9 * factor
            or round(factor) < 1
            or abs(steps - round(steps)) > 1e-6 * steps
        ):
            raise ValueError(
                f"a step of {dt} s must be a whole multiple of dt = {self.dt} s that divides "
                f"the horizon ({self.horizon} s)"
            )

    @property
    def block(self) -> int:
        return self.save_every or checkpoint_interval(self.steps)

    def scenario_object(self) -> scenarios.Scenario:
        """The scenario (a union for several) on the spec's vehicle and reference, or the
        union of the envelope's cases."""
        if self.envelope is not None:
            return self.envelope.scenario(self.vehicle)
        ids = self.scenario if isinstance(self.scenario, tuple) else (self.scenario,)
        found = [scenarios.get_scenario(i).on(self.vehicle) for i in ids]
        if self.reference is not None:
            flown = self.reference.reference()
            found = [dataclasses.replace(s, reference=flown) for s in found]
        return found[0] if len(found) == 1 else scenarios.union(*found)

    def make_controller(self, switching: str, horizon: float, dt: float | None = None):
        """The controller over ``horizon`` at the step ``dt`` (default the spec's) with
        ``switching`` and the fractional method, each where the controller has one (the
        FL has neither)."""
        options = dict(dt=self.dt if dt is None else dt, horizon=horizon,
                       fractional_method=self.fractional, switching=switching)  # fmt: skip
        return registry.make_controller(
            self.controller, **registry.options_for(self.controller, options)
        )

    def as_dict(self) -> dict:
        """JSON-ready description (part of every run's fingerprint)."""
        out = {  # the envelope in the description only where one is flown
            f.name: dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
            for f in dataclasses.fields(self)
            if f.name not in ("envelope", "case_scales", "case_chattering", "case_tracking",
                              "bound_excess")
            for value in [getattr(self, f.name)]
        }
        pmap = self.parameter_map()
        out["fields"], out["save_every"] = list(pmap.names), self.block
        if self.envelope is not None:
            out["envelope"] = self.envelope.to_dict()
        if self.case_scales is not None:
            out["case_scales"] = list(self.case_scales)
        if self.case_chattering is not None:
            out["case_chattering"] = list(self.case_chattering)
        if self.case_tracking is not None:
            out["case_tracking"] = list(self.case_tracking)
        if self.case_chattering is not None or self.case_tracking is not None:
            out["bound_excess"] = self.bound_excess
        return out

    def describe_cases(self) -> str:
        """What is flown: ``scenario 2``, ``scenarios (1, 2)`` or the envelope's cases."""
        if self.envelope is not None:
            return "the envelope's " + ", ".join(n for n, _ in self.envelope.cases(self.vehicle))
        return f"scenario {self.scenario}"
