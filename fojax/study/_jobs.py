"""Studies run: every (study, controller) run a :class:`Job`, its program compiled in a
worker thread while earlier runs compute, runs with one program sharing it
(:func:`run_studies`, :func:`run_study`)."""

from __future__ import annotations

import concurrent.futures
import itertools
import os
import shutil
from pathlib import Path

import jax
import numpy as np

from fojax import sharding
from fojax.settings import Settings
from fojax.settings import read as read_settings
from fojax.study import _run
from fojax.study._declaration import Study, check_stores, prepare_runs, store_fingerprint
from fojax.study._store import ChunkStore, plan
from fojax.study._unions import agreed, plan_unions, stored_alone

__all__ = ["Job", "compile_threads", "run_studies", "run_study", "study_jobs"]


def compile_threads(settings: Settings | None = None) -> int:
    """Threads compiling the runs' programs while earlier runs compute
    (``FOJAX_COMPILE_THREADS``, default one per core, at most 4; 0: each compiled when
    its run starts): :attr:`fojax.settings.Settings.threads`."""
    return (settings or read_settings()).threads


class Job:
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
        they run as members of one union (:func:`fojax.study.plan_unions`), whose
        member index is an argument of the program."""
        per_call = _run.batch_layout(1, self.study.device_batch, self.mesh)["draws_per_call"]
        shapes = tuple((tuple(g.shape), str(g.dtype)) for g in self.gains)
        settings = (self.controller, self.scenario, self.config, self.metrics_config)
        return (*settings, str(self.dtype), per_call, shapes)

    def compile(self):
        run = (self.controller, self.gains, self.scenario, self.config)
        per_call = self.compile_key()[5]
        return _run.compile_chunk_runner(*run, per_call, self.metrics_config, self.dtype, self.mesh)

    def pending(self) -> bool:
        """Whether some draws are not in the store yet (process 0 reads the store; its
        answer is every process's)."""
        keep = min(max(self.study.keep, 0), self.study.draws)
        answer = True
        if jax.process_index() == 0 and (self.store / "manifest.json").is_file():
            run = (self.controller, self.gains, self.scenario, self.config, self.study)
            fingerprint = store_fingerprint(*run, self.dtype, self.member)
            try:
                store = ChunkStore(self.store, fingerprint, writable=False)
                segments = plan(store.ranges(), self.study.draws, keep)
                answer = any(kind == "compute" for kind, *_ in segments)
            except ValueError:
                answer = True  # the run itself reports the mismatch
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            sharding.barrier("pending")
            answer = bool(multihost_utils.broadcast_one_to_all(np.asarray(answer)))
        return answer

    def run(self, runner, progress: bool):
        study = self.study
        return _run.run(
            self.controller, self.gains, self.scenario, self.config, study.draws,
            seed=study.seed, device_batch=study.device_batch, keep=study.keep,
            progress=progress, dtype=self.dtype, metrics_config=self.metrics_config,
            store=self.store, runner=runner, mesh=self.mesh, member=self.member,
        )  # fmt: skip


def study_jobs(
    studies: list[tuple[Study, Path]], overwrite: bool, settings=None, **mismatch
) -> list[Job]:
    """Every (study, controller) run, in order, each study alone or in its union
    (:func:`fojax.study.plan_unions`), after checking (or, with ``overwrite``,
    discarding) the stores; ``mismatch``: ``hint`` and ``advice`` of
    :func:`fojax.study.check_stores`."""
    unions = plan_unions([study for study, _ in studies], settings)
    for index, (study, out) in enumerate(studies):
        chunks = Path(out) / "chunks"
        if overwrite and chunks.exists():
            if jax.process_index() == 0:
                shutil.rmtree(chunks)
        elif chunks.exists() and unions[index] is not None and stored_alone(study, out):
            unions[index] = None
    unions = agreed(unions)
    for index, (study, out) in enumerate(studies):
        if not overwrite and (Path(out) / "chunks").exists():
            check_stores(study, out, unions[index], **mismatch)
    jobs = []
    for (study, out), union in zip(studies, unions, strict=True):
        prepared = prepare_runs(study, union)
        member = None if union is None else union.member
        jobs.extend(Job(study, out, name, prepared, member) for name in study.controllers)
    return jobs


class _Programs:
    """The runs' compiled programs, one per compile key, compiled by ``threads``
    worker threads (0: each when asked for)."""

    def __init__(self, jobs: list[Job], threads: int):
        self.jobs, self.compiled = jobs, {}
        self.executor = concurrent.futures.ThreadPoolExecutor(threads) if threads > 0 else None

    def request(self, index: int):
        key = self.jobs[index].compile_key()
        try:
            hash(key)
        except TypeError:  # an unhashable setting: this run's own program
            key = ("job", index)
        if key not in self.compiled:
            compile_job = self.jobs[index].compile
            self.compiled[key] = (
                self.executor.submit(compile_job) if self.executor else compile_job()
            )
        return self.compiled[key]

    def get(self, index: int):
        runner = self.request(index)
        return runner.result() if isinstance(runner, concurrent.futures.Future) else runner

    def close(self) -> None:
        if self.executor is not None:
            self.executor.shutdown(wait=False, cancel_futures=True)


def run_studies(
    studies: list[tuple[Study, str | os.PathLike]],
    progress: bool = True,
    overwrite: bool = False,
    threads: int | None = None,
    announce=None,
    settings: Settings | None = None,
    **mismatch,
):
    """Run several studies, each (study, output folder), controller after controller;
    yields ``(study, {name: result})`` as each study finishes.

    Every store is checked before anything is compiled (:func:`fojax.study.check_stores`,
    given ``mismatch``: its ``hint`` and ``advice``; with ``overwrite`` the stored draws
    are discarded instead). ``threads`` worker threads (default :func:`compile_threads`)
    compile the programs of every run that has draws left, in run order, while the runs
    whose programs are ready compute; runs with the same program share one. Studies
    that differ only in their scenario and horizon run as members of one union of
    scenarios (:func:`fojax.study.plan_unions`; ``FOJAX_UNION=0``: not), so that each
    controller's runs share one program; a study whose folder holds draws of an earlier
    run alone continues that run alone. Each study's results are those of its scenario
    (its metrics, its horizon's snapshots). ``announce(study)`` is called before a
    study's first run. ``settings``: the process's (:func:`fojax.settings.read`;
    default read now).
    """
    settings = settings or read_settings()
    threads = compile_threads(settings) if threads is None else threads
    jobs = study_jobs([(s, Path(o)) for s, o in studies], overwrite, settings, **mismatch)
    pending = [job.pending() for job in jobs]
    programs = _Programs(jobs, threads)
    results: dict = {}
    try:
        if programs.executor is not None:  # every program that will be needed, in run order
            for index in itertools.compress(range(len(jobs)), pending):
                programs.request(index)
        for index, job in enumerate(jobs):
            if job.name == job.study.controllers[0] and announce is not None:
                announce(job.study)
            runner = programs.get(index) if pending[index] else None
            results.setdefault(id(job.study), {})[job.name] = job.run(runner, progress)
            if job.name == job.study.controllers[-1]:
                yield job.study, results.pop(id(job.study))
    finally:
        programs.close()


def run_study(
    study: Study,
    out: str | os.PathLike,
    progress: bool = True,
    overwrite: bool = False,
    settings: Settings | None = None,
    **mismatch,
) -> dict:
    """Run every controller of ``study`` on the same draws; returns the results by name.

    Draws go to ``out/chunks/<controller>``; a run started again with the same
    settings continues from them, one with more draws extends them. Raises
    :class:`fojax.study.StoreMismatch` (a ValueError) naming the fields that differ
    when they hold a run with other settings (unless ``overwrite``: then they are
    discarded). ``settings``, ``mismatch``: :func:`run_studies`'.
    """
    runs = run_studies([(study, out)], progress, overwrite, settings=settings, **mismatch)
    try:
        return next(runs)[1]
    finally:
        runs.close()
