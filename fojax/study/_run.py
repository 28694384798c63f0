"""Monte Carlo over random draws: chunked, vmapped rollouts with online metrics.

Draw ``i`` of a run with seed ``s`` always uses the key ``fold_in(PRNGKey(s), i)``
(:func:`fojax.scenarios.draw_keys`), so its trajectory does not depend on how many
draws run or how they are chunked, and every controller given the same seed sees the
same draws (common random numbers): comparisons between controllers are paired.

Draws run in chunks of a fixed size (the last chunk is padded, so one compiled
function serves the whole run); each chunk is one ``jit(vmap(rollout))`` call. With a
``store`` directory every finished chunk is written to disk at once, and a run
started again with the same settings picks up where it stopped.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fojax import metrics, observers, plant, scenarios, sharding, simulator
from fojax.controllers.cascade import as_controller
from fojax.study._store import ChunkStore, flatten_snapshot, unflatten_snapshot

Array = jax.Array

DIVERGED = observers.NONFINITE | observers.TILT_LIMIT
"""Status bits that make a draw count as diverged (excluded from the metrics)."""


class MonteCarloResult(NamedTuple):
    """Per-draw results on the host.

    controller: the controller's name.
    status: ``(draws,)`` int32 bit flags (:data:`fojax.observers.STATUS_NAMES`).
    per_draw: metric name -> ``(draws,)`` or ``(draws, k)`` array (:mod:`fojax.metrics`).
    trajectories: :class:`fojax.simulator.Snapshot` of the first ``keep`` draws, leaves
        ``(keep, blocks, ...)``.
    wall_time: seconds spent, compilation included. compile_time: seconds of the first
        chunk beyond the steady per-chunk time (an estimate; 0 when every chunk came
        from the store).
    """

    controller: str
    status: np.ndarray
    per_draw: dict
    trajectories: Any
    wall_time: float
    compile_time: float

    @property
    def draws(self) -> int:
        return int(self.status.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """``(draws,)`` bool, draws that neither diverged nor left Assumption 1."""
        return (self.status & DIVERGED) == 0


def make_chunk_runner(
    controller,
    scenario: scenarios.Scenario,
    config: simulator.SimulationConfig,
    metrics_config: metrics.MetricsConfig | None = None,
    dtype=None,
    mesh=None,
) -> Callable:
    """A jitted ``(gains, keys (n, 2)) -> (status (n,), metrics, snapshots)``.

    ``gains`` is shared by every draw of the chunk; the compiled function is reused for
    any gains and keys of the same shapes. With ``mesh`` (a :func:`fojax.sharding.draw_mesh`
    of more than one device) the draws of each call are split over its devices; ``n``
    must then be a multiple of the mesh's size (:func:`run` rounds its chunk up to one).
    """
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    metrics_config = metrics_config or metrics.MetricsConfig(dt=config.dt, steps=config.steps)
    model = plant.nominal_params(dtype)
    controller = as_controller(controller)
    observer = metrics.Metrics(metrics_config)

    def one(gains, key):
        draw = scenarios.sample_draw(scenario, key, config.dt, dtype)
        result = simulator.rollout(controller, gains, model, scenario, draw, config, observer)
        return result.status, result.outputs, result.trajectory

    if mesh is not None and mesh.devices.size > 1:
        return sharding.sharded_vmap(one, mesh, in_axes=(None, 0))
    return jax.jit(jax.vmap(one, in_axes=(None, 0)))


def fingerprint(controller, gains, scenario, config, seed, chunk, keep, dtype, mcfg) -> dict:
    """Every setting a run's per-draw results depend on, as a JSON-ready dict (nested
    dataclasses as dicts, functions by name): what the chunk store keys its chunks by."""

    def plain(obj):
        if dataclasses.is_dataclass(obj):
            return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        return obj.__name__ if callable(obj) else obj

    return {
        "controller": controller.name,
        "controller_config": plain(controller),
        "gains": {k: np.asarray(v).tolist() for k, v in gains._asdict().items()},
        "scenario": plain(scenario),
        "simulation": plain(config),
        "metrics": plain(mcfg),
        "seed": int(seed),
        "chunk": int(chunk),
        "keep": int(keep),
        "dtype": str(dtype),
    }


def run(
    controller,
    gains,
    scenario: scenarios.Scenario,
    config: simulator.SimulationConfig,
    draws: int,
    seed: int = 0,
    chunk: int = 1024,
    keep: int = 64,
    progress: bool = True,
    dtype=None,
    metrics_config: metrics.MetricsConfig | None = None,
    store: str | os.PathLike | None = None,
    runner: Callable | None = None,
    mesh=None,
) -> MonteCarloResult:
    """Roll out draws ``0 ... draws - 1`` of ``scenario`` with seed ``seed``.

    Args:
        controller, gains: the controller (:func:`fojax.make_controller`) and its gains
            (checked against the controller's declared gains before anything runs).
        scenario: the scenario; its ``horizon`` should cover ``config.horizon`` (the
            random tables are laid out for it).
        config: simulation settings.
        draws: number of draws, >= 1. seed: the run's seed, >= 0.
        chunk: draws per compiled call (memory grows with it).
        keep: decimated trajectories are kept for the first ``keep`` draws.
        progress: print a progress line per chunk to stderr.
        dtype: floating dtype (default float32, float64 with x64 enabled).
        metrics_config: settling bands etc.; default :class:`fojax.metrics.MetricsConfig`.
        store: a directory: each finished chunk is saved there, and chunks already
            there (from an interrupted run with the same settings) are loaded, not rerun.
        runner: a function from :func:`make_chunk_runner` for these settings, to share
            one compiled function between calls (made with the same ``mesh``).
        mesh: a :func:`fojax.sharding.draw_mesh`: each chunk's draws are split over its
            devices (one per core on a CPU with
            ``XLA_FLAGS=--xla_force_host_platform_device_count=N``, or the GPUs), the
            chunk rounded up to a multiple of its size. Each draw's result is the same
            as on one device up to floating-point rounding (XLA may vectorise batches
            of other sizes differently), as it is between chunk sizes; a chattering
            closed loop (``sign`` switching) amplifies that rounding in single draws.

    Returns a :class:`MonteCarloResult`.
    """
    controller = as_controller(controller)
    if hasattr(controller, "check_gains"):
        controller.check_gains(gains)
    if not isinstance(draws, int | np.integer) or draws < 1:
        raise ValueError(f"draws must be a positive integer, got {draws!r}")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if not isinstance(chunk, int | np.integer) or chunk < 1:
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    metrics_config = metrics_config or metrics.MetricsConfig(dt=config.dt, steps=config.steps)
    devices = 1 if mesh is None else int(mesh.devices.size)
    chunk = int(min(chunk, draws))
    chunk = -(-chunk // devices) * devices  # whole draws per device
    keep = int(min(max(keep, 0), draws))
    chunk_store = None
    if store is not None:
        settings = fingerprint(
            controller, gains, scenario, config, seed, chunk, keep, dtype, metrics_config
        )
        chunk_store = ChunkStore(Path(store), settings)
    if runner is None:
        runner = make_chunk_runner(controller, scenario, config, metrics_config, dtype, mesh)

    statuses, per_draw, kept = [], [], []
    start = time.perf_counter()
    chunk_times = []
    computed = 0
    for first in range(0, draws, chunk):
        n = min(chunk, draws - first)
        loaded = chunk_store.load(first) if chunk_store is not None else None
        if loaded is not None:
            status, values, snaps = loaded
        else:
            t0 = time.perf_counter()
            indices = np.arange(first, first + chunk)
            indices = np.minimum(indices, draws - 1)  # pad the last chunk
            keys = scenarios.draw_keys(seed, indices)
            status, values, snapshots = runner(gains, keys)
            status = np.asarray(status)[:n]
            values = {k: np.asarray(v)[:n] for k, v in values.items()}
            snaps = None
            if first < keep:
                snaps = {k: v[:n] for k, v in flatten_snapshot(snapshots).items()}
            chunk_times.append(time.perf_counter() - t0)
            computed += n
            if chunk_store is not None:
                chunk_store.save(first, status, values, snaps)
        statuses.append(status)
        per_draw.append(values)
        if first < keep and snaps is not None:
            kept.append(snaps)
        if progress:
            done = first + n
            elapsed = time.perf_counter() - start
            diverged = int(np.sum((np.concatenate(statuses) & DIVERGED) > 0))
            steady = np.median(chunk_times[1:]) if len(chunk_times) > 1 else None
            remaining = (draws - done) / chunk
            eta = f", about {remaining * steady:.0f} s left" if steady else ""
            rate = computed * config.steps / max(sum(chunk_times), 1e-9) if computed else 0.0
            print(
                f"\r  {controller.name}: {done}/{draws} draws, {elapsed:.0f} s"
                f"{eta}, {rate:.3g} draw-steps/s, diverged {diverged}   ",
                end="",
                file=sys.stderr,
                flush=True,
            )
    if progress:
        print(file=sys.stderr)
    wall = time.perf_counter() - start
    compile_time = 0.0
    if len(chunk_times) > 1:
        compile_time = max(0.0, chunk_times[0] - float(np.median(chunk_times[1:])))
    elif chunk_times:
        compile_time = float("nan")  # one chunk: cannot separate compile from run
    trajectories = None
    if kept:
        merged = {k: np.concatenate([c[k] for c in kept])[:keep] for k in kept[0]}
        trajectories = unflatten_snapshot(merged)
    return MonteCarloResult(
        controller=controller.name,
        status=np.concatenate(statuses).astype(np.int32),
        per_draw={k: np.concatenate([p[k] for p in per_draw]) for k in per_draw[0]},
        trajectories=trajectories,
        wall_time=wall,
        compile_time=compile_time,
    )
