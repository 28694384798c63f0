"""The settings and the plan of :mod:`experiments.sensitivity`: what each setting
changes (actuator limits, disturbance scale, step, precision, fractional operators),
the scenario variants, the jobs (one compiled program each) and their runs, and the
lanes that share the jobs among workers."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from fojax import make_controller, metrics, records, requirements, scenarios, simulator, study
from fojax.cli.reproduce import claims as claims_module
from fojax.controllers import gains_io, registry

SCENARIO_IDS = (1, 2, 3)

THRUST_TO_WEIGHT = 2.0
"""The rotor-limited actuators' largest speed gives this multiple of the nominal weight
with all four rotors at full speed: ``w_max = sqrt(THRUST_TO_WEIGHT m g / (4 rho_b))``.
A thrust-to-weight ratio of 2 is the low end of what multirotors are built with (it
leaves the hover at half throttle); scenario 3's 30 % heavier draws keep 1.5."""

SIGMA_FACTOR = 5.0
"""Scenario 2's Gaussian disturbances scaled by this (0.1 -> 0.5 m/s^2 and rad/s^2)."""


def rotor_speed_limit(thrust_to_weight: float = THRUST_TO_WEIGHT) -> float:
    """``w_max`` (rad/s) at which four rotors give ``thrust_to_weight`` times the nominal
    weight (:func:`fojax.requirements.rotor_speed_limit`)."""
    return requirements.rotor_speed_limit(thrust_to_weight)


# ------------------------------------------------------------------------- settings


@dataclasses.dataclass(frozen=True)
class Setting:
    """One column of the verdict matrix: the default with one choice moved.

    key: short name (``--settings``). choice: the modelling choice. value: its value here.
    controller: options of :func:`fojax.make_controller` (``(name, value)`` pairs).
    simulation: fields of :class:`fojax.SimulationConfig` (``dt``, ``rotor_speed_limit``).
    scenarios: ``(scenario id, variant)`` pairs, variants of :func:`scenario_variant`.
    gains: ``"ours"`` (each controller's documented defaults, as ``fojax reproduce``) or
    ``"tuned"`` (``experiments/fair_comparison.py``). dtype: ``"float32"`` or
    ``"float64"``. reduced: run the first ``--dt-draws`` draws only. reference: the
    setting whose verdicts this one is compared with.
    """

    key: str
    choice: str
    value: str
    controller: tuple = ()
    simulation: tuple = ()
    scenarios: tuple = ()
    gains: str = "ours"
    dtype: str = "float32"
    reduced: bool = False
    reference: str = "default"


SETTINGS = (
    Setting("default", "default", "as fojax reproduce", reference=""),
    Setting("default-reduced", "default", "first --dt-draws draws", reduced=True, reference=""),
    Setting(
        "dt-0.1ms",
        "step dt",
        "0.1 ms (default 1 ms)",
        controller=(("dt", 1e-4),),
        simulation=(("dt", 1e-4),),
        reduced=True,
        reference="default-reduced",
    ),
    Setting("guard-0.5g", "thrust guard", "0.5 g (default 0.1 g)", (("thrust_floor", 0.5),)),
    Setting("filter-25", "command filter", "25 rad/s (default 50)", (("filter_frequency", 25.0),)),
    Setting(
        "filter-100", "command filter", "100 rad/s (default 50)", (("filter_frequency", 100.0),)
    ),
    Setting(
        "oustaloup",
        "fractional method",
        "Oustaloup/CRONE (default sum of exponentials)",
        (("fractional_method", "oustaloup"),),
    ),
    Setting("sat", "switching", "sat (default sgn)", (("switching", "sat"),)),
    Setting(
        "rotor-limited",
        "actuators",
        "rotor-limited, w_max for thrust/weight 2 (default ideal)",
        simulation=(("rotor_speed_limit", "thrust/weight 2"),),
    ),
    Setting(
        "s3-smoothed",
        "scenario-3 reference",
        "smoothed start (default as printed)",
        scenarios=((3, "smoothed"),),
    ),
    Setting("sigma-x5", "Gaussian sigma", "x5: 0.5 (default 0.1)", scenarios=((2, "sigma-x5"),)),
    Setting("tuned", "baseline gains", "all tuned, same budget (default ours)", gains="tuned"),
    Setting("float64", "precision", "float64 (default float32)", dtype="float64"),
)
"""The default, and each choice moved one at a time."""

SETTING_KEYS = tuple(s.key for s in SETTINGS)


def scenario_variant(scenario_id: int, variant: str | None, horizon: float):
    """Scenario ``scenario_id`` (``variant``: ``None``, ``"smoothed"`` for scenario 3's
    reference with its start smoothed, ``"sigma-x5"`` for scenario 2's Gaussian
    disturbances x :data:`SIGMA_FACTOR`) over ``horizon`` s."""
    scenario = scenarios.get_scenario(scenario_id)
    if variant == "smoothed":
        scenario = dataclasses.replace(scenario, reference=scenarios.reference_57_smoothed)
    elif variant == "sigma-x5":
        scenario = dataclasses.replace(
            scenario,
            noise_std_position=SIGMA_FACTOR * scenario.noise_std_position,
            noise_std_attitude=SIGMA_FACTOR * scenario.noise_std_attitude,
        )
    elif variant is not None:
        raise ValueError(f"unknown scenario variant {variant!r}")
    return dataclasses.replace(scenario, horizon=float(horizon))


# ----------------------------------------------------------------------------- plan


@dataclasses.dataclass(eq=False)
class Job:
    """One compiled program: a controller, simulation settings and dtype, for a union
    of the scenarios its runs need, with a batch of ``draws`` draws."""

    index: int
    controller: object
    config: object
    dtype: str
    members: list = dataclasses.field(default_factory=list)
    runs: list = dataclasses.field(default_factory=list)
    draws: int = 0

    def union(self):
        return scenarios.union(*self.members)

    def cost(self) -> float:
        """A rough cost in units of one compilation: compile plus run."""
        compile_units = 1.0 + 0.25 * (len(self.members) - 1)
        steps = self.config.steps * self.draws * len(self.runs)
        scale = 2.0 if self.dtype == "float64" else 1.0
        return compile_units + scale * steps / 7e6


@dataclasses.dataclass(eq=False)
class Run:
    """One batch of draws: a job's program with one set of gains for one member."""

    job: Job
    gains: str
    scenario: object

    @property
    def member(self) -> int:
        return self.job.members.index(self.scenario)


@dataclasses.dataclass
class Plan:
    settings: tuple
    jobs: list
    runs: list
    cells: dict  # (setting key, scenario id, controller) -> (Run, draws)
    horizon: float
    seed: int
    controllers: tuple


def simulation_config(setting: Setting, horizon: float):
    fields = dict(setting.simulation)
    dt = float(fields.get("dt", 1e-3))
    limit = None if fields.get("rotor_speed_limit") is None else rotor_speed_limit()
    return simulator.SimulationConfig(
        dt=dt,
        horizon=float(horizon),
        save_every=simulator.divisor_near(round(horizon / dt), 100),
        rotor_speed_limit=limit,
    )


def make_plan(
    settings, horizon: float, draws: int, dt_draws: int, seed: int, controllers=None
) -> Plan:
    """The jobs (programs) and runs (batches) that ``settings`` need, shared where the
    numbers are the same: one job per distinct (controller, simulation settings,
    dtype), one run per distinct (job, gains, scenario). ``controllers``: default the
    paper's five (the AFONFTSMC first)."""
    controllers = tuple(controllers or registry.PAPER_CONTROLLERS)

    jobs, runs, cells = {}, {}, {}
    for setting in settings:
        config = simulation_config(setting, horizon)
        n = dt_draws if setting.reduced else draws
        variants = dict(setting.scenarios)
        for scenario_id in SCENARIO_IDS:
            scenario = scenario_variant(scenario_id, variants.get(scenario_id), horizon)
            for name in controllers:
                options = {"dt": config.dt, "horizon": config.horizon, **dict(setting.controller)}
                # A setting moves an option of the laws that have it (sat: all but the
                # FL; oustaloup: the AFONFTSMC and the FOBSMC); the others run as they are.
                controller = make_controller(name, **registry.options_for(name, options))
                job_key = (controller, config, setting.dtype)
                job = jobs.setdefault(job_key, Job(len(jobs), controller, config, setting.dtype))
                if scenario not in job.members:
                    job.members.append(scenario)
                identity = (job_key, setting.gains, scenario)
                if identity not in runs:
                    runs[identity] = Run(job, setting.gains, scenario)
                    job.runs.append(runs[identity])
                job.draws = max(job.draws, n)
                cells[(setting.key, scenario_id, name)] = (runs[identity], n)
    jobs, runs = list(jobs.values()), list(runs.values())
    return Plan(tuple(settings), jobs, runs, cells, horizon, seed, controllers)


def assign_lanes(plan: Plan, workers: int) -> dict:
    """Lane name -> job indices: ``"f64"`` for the float64 jobs, ``"0" ... "workers-1"``
    for the others (longest first to the least loaded lane; the jobs whose runs wait
    for the tuned gains first in lane 0, so that their other runs finish early)."""
    lanes = {str(i): [] for i in range(workers)}
    load = {str(i): 0.0 for i in range(workers)}
    float32 = [j for j in plan.jobs if j.dtype != "float64"]
    waiting = [j for j in float32 if any(r.gains == "tuned" for r in j.runs)]
    rest = sorted((j for j in float32 if j not in waiting), key=lambda j: -j.cost())
    for job in waiting + rest:
        lane = "0" if job in waiting else min(load, key=lambda k: (load[k], k))
        lanes[lane].append(job.index)
        load[lane] += job.cost()
    lanes["f64"] = [j.index for j in plan.jobs if j.dtype == "float64"]
    return {k: v for k, v in lanes.items() if v}


# ------------------------------------------------------------------- gains and keys


def gains_for(run: Run, tuned: dict | None, dtype: str | None = None):
    """The run's gains in ``dtype`` (default the run's): the controller's defaults or
    the tuned ones."""
    dtype = jnp.dtype(dtype or run.job.dtype)
    name = run.job.controller.name
    if run.gains == "ours":
        return run.job.controller.default_gains(dtype)
    if tuned is None:
        raise ValueError("the tuned gains are not available")
    return gains_io.gains_from_dict(name, tuned[name], source="tuned gains", dtype=dtype)


def load_tuned(path: Path) -> dict:
    """``{controller: {field: value}}``: the tuned gains of a fair-comparison
    ``results.json`` (``"gains"`` -> controller -> ``"tuned"``), or a mapping of that
    shape."""
    data = json.loads(Path(path).read_text())
    gains = data.get("gains", data)
    return {name: entry["tuned"] if "tuned" in entry else entry for name, entry in gains.items()}


# ---------------------------------------------------------------------------- runs


def reaching_band(dt: float) -> tuple:
    """:func:`fojax.cli.reproduce.claims.reaching_band` from the AFONFTSMC's default
    gains in float64 (NumPy), the same band in every process, float32 or float64."""
    spec = registry.get_controller_class(claims_module.BASELINE).GAINS
    gains = spec.type(*(np.asarray(f.default, np.float64) for f in spec.fields))
    return claims_module.reaching_band(dt, gains)


def metrics_config(config):
    return metrics.MetricsConfig(
        dt=config.dt, steps=config.steps, reaching_band=reaching_band(config.dt)
    )


def _plain(obj):
    """JSON-ready: dataclasses as dicts, functions by module and name, recursively."""
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [_plain(v) for v in obj]
    if callable(obj):
        return f"{getattr(obj, '__module__', '')}.{getattr(obj, '__qualname__', repr(obj))}"
    return obj


def run_key(run: Run, tuned: dict | None, seed: int) -> str:
    """Everything the run's per-draw numbers depend on, hashed: the fingerprint of
    :func:`fojax.study.fingerprint` with the union's members spelled out, the member and
    the batch. The gains enter as float32 values, so that every process, with or
    without ``jax_enable_x64``, finds the same key (the dtype is a field of its own)."""
    job = run.job
    gains, metrics = gains_for(run, tuned, "float32"), metrics_config(job.config)
    fields = (job.controller, gains, run.scenario, job.config, seed, job.dtype, metrics)
    settings = study.fingerprint(*fields, device_batch=job.draws)
    settings.update(union=_plain(job.members), member=run.member, draws=job.draws)
    text = json.dumps(records.canonical(settings), sort_keys=True)
    if " at 0x" in text:  # an object spelled by its address: not the same in another process
        raise ValueError(f"run key depends on an address: {text}")
    return records.digest(settings, 20)
