"""The study layer shared by the commands: a validated Monte Carlo study, running it,
writing its outputs, and what every output records to be rerun exactly.

* :class:`Study`, :func:`run_study`: one scenario under one or several controllers on
  the same draws (``fojax simulate``; ``fojax reproduce`` runs one per scenario); its
  files: :func:`fojax.cli.study_files.write_outputs`.
* :func:`provenance` (:mod:`fojax.cli.output`): the command line, versions (fojax and
  its git commit, Python, JAX, jaxlib, NumPy), backend and device and process counts;
  :func:`gains_record`: the gains' values and where they came from. ``fojax
  simulate``, ``tune`` and ``bench`` store both with their results.
* :func:`store_differences`: the settings in which a run differs from the one whose
  chunks are already in the output folder, field by field, before anything runs.
* :func:`write_json` (:mod:`fojax.cli.output`): atomic JSON files.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Any, NamedTuple

from fojax.cli.output import provenance, write_json
from fojax.settings import Settings
from fojax.settings import read as read_settings
from fojax.study import StoreMismatch

__all__ = [
    "Study",
    "StoreMismatch",
    "UnionMember",
    "check_stores",
    "compile_threads",
    "gains_record",
    "options_applied_to",
    "plan_unions",
    "prepare_runs",
    "provenance",
    "run_studies",
    "run_study",
    "snapshot_interval",
    "store_differences",
    "union_enabled",
    "write_json",
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

    def metrics_config(self, steps: int):
        from fojax import metrics

        return metrics.MetricsConfig(dt=self.dt, steps=steps, reaching_band=self.reaching_band)


def snapshot_interval(steps: int, dt: float, target: float = 0.1) -> int:
    """Steps between snapshots: the divisor of ``steps`` closest to ``target / dt``."""
    want = max(1, round(target / dt))
    divisors = [d for d in range(1, min(steps, 10 * want) + 1) if steps % d == 0]
    return min(divisors, key=lambda d: (abs(d - want), d))


# ------------------------------------------------------------------------- provenance


def gains_record(gains, source: str | os.PathLike | None) -> dict:
    """``{"source": absolute file path or "defaults", "values": {field: value}}``: the
    values as the run used them (after the cast to its dtype)."""
    from fojax.controllers import gains_io

    return {
        "source": str(Path(source).resolve()) if source is not None else "defaults",
        "values": gains_io.gains_to_dict(gains),
    }


# ---------------------------------------------------------------------- the chunk store


_FLAGS = {
    "seed": "--seed",
    "dtype": "--dtype",
    "device_batch": "--device-batch",
    "xla_flags": "XLA_FLAGS",
    "backend": "the platform: cpu or gpu draws round differently",
    "store_format": "stored by an earlier fojax",
    "gains": "--gains",
    "controller_config.law.switching": "--switching",
    "controller_config.law.fractional_method": "--fractional",
    "controller_config.law.dt": "--dt",
    "controller_config.law.horizon": "--horizon",
    "scenario.horizon": "--horizon",
    "simulation.horizon": "--horizon",
    "simulation.dt": "--dt",
    "simulation.rotor_speed_limit": "--rotor-limit or the requirement file's rotor limit",
    "simulation.save_every": "snapshot interval (follows --horizon and --dt)",
    "metrics": "metric settings (follow --horizon and --dt)",
}


def _flag(field: str) -> str:
    for prefix in sorted(_FLAGS, key=len, reverse=True):
        if field == prefix or field.startswith(prefix + "."):
            return _FLAGS[prefix]
    return ""


def _fingerprint(controller, gains, scenario, config, study: Study, dtype, member=None) -> dict:
    """The store's fingerprint of this run, as :func:`fojax.study.run` makes it
    (``member``: the study's index in a union ``scenario``)."""
    from fojax import study as monte_carlo

    settings = (study.seed, dtype, study.metrics_config(config.steps), study.device_batch)
    return monte_carlo.fingerprint(controller, gains, scenario, config, *settings, member=member)


def store_differences(store: Path, fingerprint: dict | None) -> list[str] | None:
    """How ``fingerprint`` differs from the one of the draws in ``store``: one line per
    field, naming the option that sets it (``[]``: the same settings; None: nothing
    stored there to compare)."""
    from fojax import records
    from fojax.study import manifest_differences

    if fingerprint is None:
        return None
    differences = manifest_differences(store, fingerprint)
    return None if differences is None else records.describe(differences, _flag)


def _scenario(study: Study):
    """The study's scenario, with the study's horizon."""
    from fojax import scenarios

    return dataclasses.replace(scenarios.get_scenario(study.scenario_id), horizon=study.horizon)


def _law_options(study: Study) -> dict:
    """The study's options shared by its controllers, each given to the controllers
    that take it (:func:`fojax.controllers.registry.options_for`)."""
    return {"fractional_method": study.fractional, "switching": study.switching}


def options_applied_to(study: Study) -> dict[str, list[str]]:
    """For each of the study's shared options (``switching``, ``fractional_method``),
    the controllers that take it: the others (the FL has no switching function, only
    the AFONFTSMC and the FOBSMC have fractional operators) ran without it."""
    from fojax.controllers import registry

    return registry.applied_options(study.controllers, _law_options(study))


def prepare_runs(study: Study, union: UnionMember | None = None):
    """What the study runs: ``(mesh, scenario, config, dtype, {name: (controller,
    gains)})``, the mesh over every device (:func:`fojax.sharding.default_mesh`); with
    ``union`` (:func:`plan_unions`) the union's scenario, and its horizon for the
    simulation and the controllers."""
    import jax.numpy as jnp

    from fojax import sharding, simulator
    from fojax.controllers import registry

    mesh = sharding.default_mesh()
    scenario = _scenario(study) if union is None else union.scenario
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


def check_stores(study: Study, out: Path, union: UnionMember | None = None) -> None:
    """Raise :class:`StoreMismatch` naming the fields that differ when ``out/chunks``
    holds draws of a run with other settings (before anything is compiled). The draw
    count, ``--keep``, the devices and the processes may differ: a longer run extends
    the stored one. ``union``: the study runs as a member of it (:func:`plan_unions`)."""
    from fojax.study import manifest_differences

    _, scenario, config, dtype, runs = prepare_runs(study, union)
    member = None if union is None else union.member
    problems = []
    for name, (controller, gains) in runs.items():
        store = Path(out) / "chunks" / name
        fingerprint = _fingerprint(controller, gains, scenario, config, study, dtype, member)
        differences = manifest_differences(store, fingerprint)
        if differences:
            problems.append((store, differences))
    if problems:
        raise StoreMismatch(
            *problems[0],
            stores=problems,
            hint=_flag,
            advice="to start afresh, add --overwrite (discards those draws), or choose "
            "another --out",
        )


# ---------------------------------------------------------------------- scenario unions


class UnionMember(NamedTuple):
    """A study run as member ``member`` of the union ``scenario``
    (:func:`fojax.scenarios.union`), over the union's horizon."""

    scenario: Any
    member: int


def union_enabled(settings: Settings | None = None) -> bool:
    """Whether :func:`run_studies` runs studies that differ only in their scenario and
    horizon as members of one union of scenarios (``FOJAX_UNION``, default 1; 0: each
    study on its own scenario, one compiled program per study and controller);
    ``settings``: default read now (:func:`fojax.settings.read`)."""
    return (settings or read_settings()).union


def _union_key(study: Study):
    """What studies must share (all but the scenario, horizon, draws, seed and keep)
    to run as members of one union with one program per controller."""
    from fojax.controllers import gains_io

    gains = {name: gains_io.gains_to_dict(g) for name, g in study.gains.items()}
    band = study.reaching_band
    return (
        tuple(study.controllers),
        study.dt,
        study.save_every,
        study.fractional,
        study.switching,
        study.device_batch,
        study.dtype,
        tuple(band) if isinstance(band, list | tuple) else band,
        study.rotor_speed_limit,
        json.dumps(gains, sort_keys=True, default=str),
    )


def plan_unions(studies: list[Study], settings: Settings | None = None) -> list[UnionMember | None]:
    """For each study, the union it runs in, or None (alone).

    Studies with the same settings but their scenario and horizon (:func:`_union_key`)
    and at least two different scenarios run as members of the union of their
    scenarios (each with its own horizon), so that a controller's runs share one
    compiled program: the simulation runs the union's (longest) horizon and the
    controllers are made for it (their fractional memory spans it), each draw is
    recorded up to its own scenario's horizon, so its metrics and snapshots are those
    of its scenario alone (bit for bit in float64 when the controller does not depend
    on the horizon). Off with ``FOJAX_UNION=0`` (:func:`union_enabled`).
    """
    from fojax import scenarios, simulator

    plans: list[UnionMember | None] = [None] * len(studies)
    if not union_enabled(settings):
        return plans
    groups: dict = {}
    for index, study in enumerate(studies):
        try:
            key = _union_key(study)
            hash(key)
        except (TypeError, ValueError):
            continue
        groups.setdefault(key, []).append(index)
    for indices in groups.values():
        members = [_scenario(studies[i]) for i in indices]
        distinct = list(dict.fromkeys(members))
        if len(distinct) < 2:
            continue
        try:
            bank = scenarios.union(*distinct)
            study = studies[indices[0]]
            simulator.SimulationConfig(
                dt=study.dt, horizon=bank.horizon, save_every=study.save_every
            )
        except ValueError:  # scenarios that cannot share a program
            continue
        for index, member in zip(indices, members, strict=True):
            plans[index] = UnionMember(bank, distinct.index(member))
    return plans


def _stored_alone(study: Study, out: Path) -> bool:
    """Whether ``out/chunks`` holds draws of this study run alone (an earlier run
    without the union, which it then continues)."""
    chunks = Path(out) / "chunks"
    if not chunks.is_dir():
        return False
    _, scenario, config, dtype, runs = prepare_runs(study)
    for name, (controller, gains) in runs.items():
        fingerprint = _fingerprint(controller, gains, scenario, config, study, dtype)
        if store_differences(chunks / name, fingerprint) == []:
            return True
    return False


def _agreed(unions: list[UnionMember | None]) -> list[UnionMember | None]:
    """Process 0's choice of which studies run alone (it alone may see the stores)."""
    import jax

    if jax.process_count() == 1:
        return unions
    import numpy as np
    from jax.experimental import multihost_utils

    from fojax import sharding

    sharding.barrier("unions")
    alone = np.asarray([u is None for u in unions], np.int32)
    alone = np.asarray(multihost_utils.broadcast_one_to_all(alone))
    return [None if alone[i] else u for i, u in enumerate(unions)]


# --------------------------------------------------------------------- running studies


def compile_threads(settings: Settings | None = None) -> int:
    """Threads compiling the runs' programs while earlier runs compute
    (``FOJAX_COMPILE_THREADS``, default one per core, at most 4; 0: each compiled when
    its run starts): :attr:`fojax.settings.Settings.threads`."""
    return (settings or read_settings()).threads


class _Job:
    """One (study, controller) run: what it needs compiled and where it stores draws."""

    def __init__(self, study: Study, out: Path, name: str, prepared, member: int | None = None):
        mesh, scenario, config, dtype, runs = prepared
        self.study, self.out, self.name, self.member = study, Path(out), name, member
        self.mesh, self.scenario, self.config, self.dtype = mesh, scenario, config, dtype
        self.controller, self.gains = runs[name]
        self.metrics_config = study.metrics_config(config.steps)
        self.store = self.out / "chunks" / name

    def compile_key(self):
        """Runs with equal keys share one compiled program. The rollout compiles the
        scenario in (:mod:`fojax.simulator`): runs of several scenarios share one when
        they run as members of one union (:func:`plan_unions`), whose member index is
        an argument of the program."""
        from fojax import study as monte_carlo

        batch = self.study.device_batch or monte_carlo.default_device_batch()
        per_call = batch * (1 if self.mesh is None else int(self.mesh.devices.size))
        shapes = tuple((tuple(g.shape), str(g.dtype)) for g in self.gains)
        settings = (self.controller, self.scenario, self.config, self.metrics_config)
        return (*settings, str(self.dtype), per_call, shapes)

    def compile(self):
        from fojax import study as monte_carlo

        run = (self.controller, self.gains, self.scenario, self.config)
        per_call = self.compile_key()[5]
        return monte_carlo.compile_chunk_runner(
            *run, per_call, self.metrics_config, self.dtype, self.mesh
        )

    def pending(self) -> bool:
        """Whether some draws are not in the store yet (process 0 reads the store; its
        answer is every process's)."""
        import jax
        import numpy as np

        from fojax import study as monte_carlo
        from fojax.study import _store

        keep = min(max(self.study.keep, 0), self.study.draws)
        answer = True
        if jax.process_index() == 0 and (self.store / "manifest.json").is_file():
            run = (self.controller, self.gains, self.scenario, self.config, self.study)
            fingerprint = _fingerprint(*run, self.dtype, self.member)
            try:
                store = monte_carlo.ChunkStore(self.store, fingerprint, writable=False)
                segments = _store.plan(store.ranges(), self.study.draws, keep)
                answer = any(kind == "compute" for kind, *_ in segments)
            except ValueError:
                answer = True  # the run itself reports the mismatch
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            from fojax import sharding

            sharding.barrier("pending")
            answer = bool(multihost_utils.broadcast_one_to_all(np.asarray(answer)))
        return answer

    def run(self, runner, progress: bool):
        from fojax import study as monte_carlo

        return monte_carlo.run(
            self.controller,
            self.gains,
            self.scenario,
            self.config,
            self.study.draws,
            seed=self.study.seed,
            device_batch=self.study.device_batch,
            keep=self.study.keep,
            progress=progress,
            dtype=self.dtype,
            metrics_config=self.metrics_config,
            store=self.store,
            runner=runner,
            mesh=self.mesh,
            member=self.member,
        )


def _jobs(studies: list[tuple[Study, Path]], overwrite: bool, settings=None) -> list[_Job]:
    """Every (study, controller) run, in order, each study alone or in its union
    (:func:`plan_unions`), after checking (or, with ``overwrite``, discarding) the stores."""
    unions = plan_unions([study for study, _ in studies], settings)
    for index, (study, out) in enumerate(studies):
        chunks = Path(out) / "chunks"
        if overwrite and chunks.exists():
            import jax

            if jax.process_index() == 0:
                shutil.rmtree(chunks)
        elif chunks.exists() and unions[index] is not None and _stored_alone(study, out):
            unions[index] = None
    unions = _agreed(unions)
    for index, (study, out) in enumerate(studies):
        if not overwrite and (Path(out) / "chunks").exists():
            check_stores(study, out, unions[index])
    jobs = []
    for (study, out), union in zip(studies, unions, strict=True):
        prepared = prepare_runs(study, union)
        member = None if union is None else union.member
        jobs.extend(_Job(study, out, name, prepared, member) for name in study.controllers)
    return jobs


def run_studies(
    studies: list[tuple[Study, Path]],
    progress: bool = True,
    overwrite: bool = False,
    threads: int | None = None,
    announce=None,
    settings: Settings | None = None,
):
    """Run several studies, each (study, output folder), controller after controller;
    yields ``(study, {name: result})`` as each study finishes.

    Every store is checked before anything is compiled (:func:`check_stores`; with
    ``overwrite`` the stored draws are discarded instead). ``threads`` worker threads
    (default :func:`compile_threads`) compile the programs of every run that has draws
    left, in run order, while the runs whose programs are ready compute; runs with the
    same program share one. Studies that differ only in their scenario and horizon run
    as members of one union of scenarios (:func:`plan_unions`; ``FOJAX_UNION=0``: not),
    so that each controller's runs share one program; a study whose folder holds draws
    of an earlier run alone continues that run alone. Each study's results are those
    of its scenario (its metrics, its horizon's snapshots).
    ``announce(study)`` is called before a study's first run. ``settings``: the
    process's (:func:`fojax.settings.read`; default read now).
    """
    import concurrent.futures

    settings = settings or read_settings()
    threads = compile_threads(settings) if threads is None else threads
    jobs = _jobs(studies, overwrite, settings)
    pending = [job.pending() for job in jobs]
    compiled: dict = {}
    executor = concurrent.futures.ThreadPoolExecutor(threads) if threads > 0 else None

    def request(index: int):
        key = jobs[index].compile_key()
        try:
            hash(key)
        except TypeError:  # an unhashable setting: this run's own program
            key = ("job", index)
        if key not in compiled:
            if executor is not None:
                compiled[key] = executor.submit(jobs[index].compile)
            else:
                compiled[key] = jobs[index].compile()
        return compiled[key]

    results: dict = {}
    try:
        if executor is not None:  # every program that will be needed, in run order
            for index in range(len(jobs)):
                if pending[index]:
                    request(index)
        for index, job in enumerate(jobs):
            if job.name == job.study.controllers[0] and announce is not None:
                announce(job.study)
            runner = None
            if pending[index]:
                runner = request(index)
                if isinstance(runner, concurrent.futures.Future):
                    runner = runner.result()
            results.setdefault(id(job.study), {})[job.name] = job.run(runner, progress)
            if job.name == job.study.controllers[-1]:
                yield job.study, results.pop(id(job.study))
    finally:
        if executor is not None:
            executor.shutdown(wait=False, cancel_futures=True)


def run_study(
    study: Study, out: Path, progress: bool = True, overwrite: bool = False, settings=None
) -> dict:
    """Run every controller of ``study`` on the same draws; returns the results by name.

    Draws go to ``out/chunks/<controller>``; a run started again with the same
    settings continues from them, one with more draws extends them. Raises
    :class:`StoreMismatch` (a ValueError) naming the fields that differ when they hold
    a run with other settings (unless ``overwrite``: then they are discarded).
    ``settings``: :func:`run_studies`'.
    """
    runs = run_studies([(study, out)], progress, overwrite, settings=settings)
    try:
        return next(runs)[1]
    finally:
        runs.close()
