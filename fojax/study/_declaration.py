"""A study as a declaration: the scenario, the controllers run on the same draws, their
gains, the draws, the seed and the settings, settled before anything compiles; and
what it runs and stores.

* :class:`Study`: the declaration (``fojax simulate`` runs one, ``fojax reproduce`` one
  per scenario); :func:`snapshot_interval`, the steps between its snapshots.
* :func:`prepare_runs`: what it runs, each controller with its gains, alone or as a
  member of a union of scenarios (:class:`UnionMember`, :func:`fojax.study.plan_unions`);
  :func:`options_applied_to`: which controllers took each shared option.
* :func:`store_fingerprint`, :func:`check_stores`: the fingerprint of each
  controller's draws (:func:`fojax.study.fingerprint`) and the stores under the
  study's folder that hold draws of other settings, named before anything compiles.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp

from fojax import metrics, scenarios, sharding, simulator
from fojax.controllers import registry
from fojax.study._run import fingerprint
from fojax.study._store import StoreMismatch, manifest_differences

__all__ = [
    "Study",
    "UnionMember",
    "check_stores",
    "options_applied_to",
    "prepare_runs",
    "scenario_of",
    "snapshot_interval",
    "store_fingerprint",
    "stored_differences",
]


@dataclasses.dataclass(frozen=True)
class Study:
    """A validated study: everything settled before anything is compiled.

    gains: controller name -> gains NamedTuple, for those not run with their defaults;
    gains_sources: controller name -> the file each of those came from.
    """

    scenario_id: int
    controllers: tuple[str, ...]
    draws: int
    seed: int
    horizon: float
    dt: float
    save_every: int
    gains: dict
    fractional: str
    switching: str
    device_batch: int | None
    """Draws per block, each device's share of a call (None: the platform's default,
    :func:`fojax.study.default_device_batch`); draw ``i``'s numbers depend on it."""
    keep: int
    dtype: str
    gains_sources: dict = dataclasses.field(default_factory=dict)
    reaching_band: float | tuple[float, ...] = 0.01
    """``fojax.metrics.MetricsConfig.reaching_band``: one band, or six (one per axis)."""
    rotor_speed_limit: float | None = None
    """``w_max`` (rad/s) of rotor-limited actuators (None: ideal; ``--rotor-limit``)."""
    vehicle: Any = None
    """The :class:`fojax.vehicle.Vehicle` flown (None: the paper's; ``--vehicle``)."""
    reference: Any = None
    """The :class:`fojax.reference.Waypoints` flown (None: the scenario's; ``--reference``)."""

    def metrics_config(self, steps: int) -> metrics.MetricsConfig:
        return metrics.MetricsConfig(dt=self.dt, steps=steps, reaching_band=self.reaching_band)


class UnionMember(NamedTuple):
    """A study run as member ``member`` of the union ``scenario``
    (:func:`fojax.scenarios.union`), over the union's horizon."""

    scenario: Any
    member: int


def snapshot_interval(steps: int, dt: float, target: float = 0.1) -> int:
    """Steps between snapshots: the divisor of ``steps`` closest to ``target / dt``."""
    want = max(1, round(target / dt))
    divisors = [d for d in range(1, min(steps, 10 * want) + 1) if steps % d == 0]
    return min(divisors, key=lambda d: (abs(d - want), d))


def scenario_of(study: Study) -> scenarios.Scenario:
    """The study's scenario, on the study's vehicle and reference, with the study's
    horizon."""
    scenario = scenarios.get_scenario(study.scenario_id).on(study.vehicle)
    if study.reference is not None:
        scenario = dataclasses.replace(scenario, reference=study.reference.reference())
    return dataclasses.replace(scenario, horizon=study.horizon)


def _law_options(study: Study) -> dict:
    """The study's options shared by its controllers, each given to the controllers
    that take it (:func:`fojax.controllers.registry.options_for`)."""
    return {"fractional_method": study.fractional, "switching": study.switching}


def options_applied_to(study: Study) -> dict[str, list[str]]:
    """For each of the study's shared options (``switching``, ``fractional_method``),
    the controllers that take it: the others (the FL has no switching function, only
    the AFONFTSMC and the FOBSMC have fractional operators) ran without it."""
    return registry.applied_options(study.controllers, _law_options(study))


def prepare_runs(study: Study, union: UnionMember | None = None):
    """What the study runs: ``(mesh, scenario, config, dtype, {name: (controller,
    gains)})``, the mesh over every device (:func:`fojax.sharding.default_mesh`); with
    ``union`` (:func:`fojax.study.plan_unions`) the union's scenario, and its horizon
    for the simulation and the controllers."""
    mesh = sharding.default_mesh()
    scenario = scenario_of(study) if union is None else union.scenario
    horizon = study.horizon if union is None else union.scenario.horizon
    config = simulator.SimulationConfig(
        dt=study.dt,
        horizon=horizon,
        save_every=study.save_every,
        rotor_speed_limit=study.rotor_speed_limit,
    )
    dtype = jnp.dtype(study.dtype)
    runs = {}
    for name in study.controllers:
        options = dict(dt=study.dt, horizon=horizon, **_law_options(study))
        controller = registry.make_controller(name, **registry.options_for(name, options))
        gains = study.gains.get(name)
        if gains is None:
            gains = controller.default_gains(dtype)
        gains = type(gains)(*(jnp.asarray(g, dtype) for g in gains))
        runs[name] = (controller, gains)
    return mesh, scenario, config, dtype, runs


def store_fingerprint(controller, gains, scenario, config, study: Study, dtype, member=None):
    """The store's fingerprint of one controller's run of ``study``, as
    :func:`fojax.study.run` makes it (``member``: the study's index in a union
    ``scenario``)."""
    settings = (study.seed, dtype, study.metrics_config(config.steps), study.device_batch)
    return fingerprint(controller, gains, scenario, config, *settings, member=member)


def check_stores(
    study: Study,
    out: str | os.PathLike,
    union: UnionMember | None = None,
    hint=lambda field: "",
    advice: str | None = None,
) -> None:
    """Raise :class:`fojax.study.StoreMismatch` naming the fields that differ when
    ``out/chunks`` holds draws of a run with other settings (before anything is
    compiled). The draw count, ``keep``, the devices and the processes may differ: a
    longer run extends the stored one. ``union``: the study runs as a member of it.
    ``hint(field)``, ``advice``: the message's, as :class:`fojax.study.StoreMismatch`
    takes them (e.g. the command's option that sets a field)."""
    problems = [(store, found) for store, found in stored_differences(study, out, union) if found]
    if problems:
        raise StoreMismatch(*problems[0], stores=problems, hint=hint, advice=advice)


def stored_differences(study: Study, out: str | os.PathLike, union: UnionMember | None = None):
    """``[(out/chunks/<controller>, differences), ...]``: each controller's
    :func:`fojax.study.manifest_differences` (None: nothing stored) of the study's
    fingerprint (``union``: run as a member of it)."""
    _, scenario, config, dtype, runs = prepare_runs(study, union)
    member = None if union is None else union.member
    found = []
    for name, (controller, gains) in runs.items():
        store = Path(out) / "chunks" / name
        fingerprint = store_fingerprint(controller, gains, scenario, config, study, dtype, member)
        found.append((store, manifest_differences(store, fingerprint)))
    return found
