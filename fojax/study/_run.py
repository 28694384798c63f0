"""Monte Carlo over random draws: vmapped rollouts in fixed blocks, with online metrics.

Draw ``i`` of a run with seed ``s`` always uses the key ``fold_in(PRNGKey(s), i)``
(:func:`fojax.scenarios.draw_keys`), and every controller given the same seed sees the
same draws (common random numbers): comparisons between controllers are paired.

**Draw i's numbers do not depend on the layout.** The draws are computed in blocks of
``device_batch`` consecutive draws, ``[k B, (k + 1) B)``: each device of each call runs
exactly one block, so every draw is computed by the same compiled per-device program
at the same position in its block, whatever the draw count, the number of calls, the
devices and the processes; its numbers are the same bit for bit. (XLA compiles a batch
into code that depends on its size, and on the CPU some of it, e.g. the library
kernels it hands dots and large reductions to, also rounds a draw according to where it
sits in the batch: measured, per-device batches of 8, 16, 20, 50 and 2048 draws give
up to four different roundings of the same draw.) The
block size is therefore a setting of the run, part of its fingerprint like the seed:
runs with another ``device_batch`` round differently. The last block of a run is
completed with the draws that follow (real draws, kept in the store).

With a ``store`` directory every finished call is written to disk at once
(:class:`fojax.study.ChunkStore`), and a run started again with the same settings,
with more draws or on other devices reads what is there and computes the rest.

Across processes (``jax.distributed``; :func:`fojax.sharding.initialize`): the mesh
spans every process's devices, every process computes the same keys and takes part
in every call, the results are gathered to every process, and process 0 alone reads
and writes the store (it sends what it read to the others), so the run needs no
shared file system.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fojax import metrics, scenarios, sharding, simulator
from fojax import settings as process_settings
from fojax.controllers.cascade import as_controller
from fojax.records import code_digest as code_version
from fojax.study._dispatch import (
    DIVERGED,
    MAX_DRAWS,
    Dispatch,
    plan_calls,
    run_result,
    save_blocks,
    to_compute,
)
from fojax.study._store import ChunkStore, unflatten_snapshot

DEVICE_BATCH = {"cpu": 50}
"""Default draws per block (per device and call), by platform. On a CPU, 50: the
default ``fojax reproduce`` (100 draws per scenario and controller) is then two blocks,
one call on two cores with no padded draws, and a call's per-step kernel overhead
stays below half its arithmetic; larger blocks are faster for large runs (measured:
``docs/performance.md``). Other platforms: :data:`OTHER_DEVICE_BATCH`."""

OTHER_DEVICE_BATCH = 1024
"""Default block on GPUs and other accelerators (not measured here: no GPU)."""


def default_device_batch(platform: str | None = None) -> int:
    """:data:`DEVICE_BATCH` of ``platform`` (default JAX's backend)."""
    platform = platform or jax.default_backend()
    return DEVICE_BATCH.get(platform, OTHER_DEVICE_BATCH)


MAX_SEED = 2**63 - 1
"""Largest seed :func:`jax.random.PRNGKey` takes."""


class MonteCarloResult(NamedTuple):
    """Per-draw results on the host.

    controller: the controller's name.
    status: ``(draws,)`` int32 bit flags (:data:`fojax.observers.STATUS_NAMES`).
    per_draw: metric name -> ``(draws,)`` or ``(draws, k)`` array (:mod:`fojax.metrics`).
    trajectories: :class:`fojax.simulator.Snapshot` of the first ``keep`` draws, leaves
        ``(keep, blocks, ...)``.
    wall_time: seconds spent, compilation included. compile_time: seconds of the first
        call beyond the steady per-call time (an estimate; 0 when every draw came
        from the store).
    layout: how the draws were computed (:func:`batch_layout` plus ``computed`` and
        ``loaded``: draws computed in this run and read from the store).
    """

    controller: str
    status: np.ndarray
    per_draw: dict
    trajectories: Any
    wall_time: float
    compile_time: float
    layout: dict | None = None

    @property
    def draws(self) -> int:
        return int(self.status.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """``(draws,)`` bool, draws that neither diverged nor left Assumption 1."""
        return (self.status & DIVERGED) == 0


def batch_layout(draws: int, device_batch: int | None = None, mesh=None) -> dict:
    """``{"processes", "devices", "device_batch", "draws_per_call", "blocks", "calls"}``
    of a run of ``draws`` draws in blocks of ``device_batch`` (default
    :func:`default_device_batch`) over ``mesh`` (None: one device), all computed."""
    batch = device_batch or default_device_batch()
    devices = 1 if mesh is None else int(mesh.devices.size)
    processes = 1 if mesh is None else len({d.process_index for d in mesh.devices.flat})
    blocks = -(-draws // batch)
    return {
        "processes": processes,
        "devices": devices,
        "device_batch": batch,
        "draws_per_call": batch * devices,
        "blocks": blocks,
        "calls": -(-blocks // devices),
    }


def check_run_arguments(draws, seed, device_batch=None) -> None:
    """``ValueError`` saying what to change for a bad draw count, seed or block size."""
    limits = (
        ("draws", draws, 1, "a positive", MAX_DRAWS, "2**32", "draw indices are 32-bit; more "
         "would repeat draws", "; split the study over several seeds"),
        ("seed", seed, 0, "a non-negative", MAX_SEED, "2**63 - 1",
         "the range of jax.random.PRNGKey", ""),
    )  # fmt: skip
    for label, value, lowest, kind, top, top_text, why, advice in limits:
        if _not_integer(value, lowest):
            raise ValueError(f"{label} must be {kind} integer, got {value!r}")
        if value > top:
            raise ValueError(
                f"{label} must be at most {top_text} = {top} ({why}), got {value}{advice}"
            )
    if device_batch is not None and _not_integer(device_batch, 1):
        raise ValueError(f"device_batch must be a positive integer, got {device_batch!r}")


def _not_integer(value, lowest: int) -> bool:
    """Whether ``value`` is not an integer (``bool`` is not one) ``>= lowest``."""
    return isinstance(value, bool) or not isinstance(value, int | np.integer) or value < lowest


def check_settings(controller, scenario, config, metrics_config=None) -> None:
    """``ValueError`` saying what to change when the settings of a run disagree, which
    the rollout would otherwise follow silently: a controller made for another step
    than ``config.dt`` (its filter and fractional weights are discretised for its own
    ``dt``), a ``config.horizon`` that is not a whole number of steps (the rollout
    takes ``round(horizon / dt)`` of them), a scenario shorter than the simulation (its
    random tables end at its own horizon; past it the last row would be held), and
    ``metrics_config`` made for another step or step count."""
    dt = getattr(controller, "dt", None)
    if isinstance(dt, int | float) and not math.isclose(dt, config.dt, rel_tol=1e-9):
        raise ValueError(
            f"the controller is made for dt={dt} but the simulation steps at "
            f"dt={config.dt}; make it with fojax.make_controller(..., dt={config.dt})"
        )
    steps = config.horizon / config.dt
    if abs(steps - round(steps)) > 1e-6 * steps:
        raise ValueError(
            f"the simulation's horizon ({config.horizon} s) is not a whole number of steps "
            f"of {config.dt} s (it would run {config.steps} steps, "
            f"{config.steps * config.dt:g} s); e.g. horizon={config.steps * config.dt:g}"
        )
    if config.steps > math.ceil(scenario.horizon / config.dt - 1e-9):
        raise ValueError(
            f"the scenario's horizon ({scenario.horizon} s) is shorter than the simulation's "
            f"({config.horizon} s): its random tables end there; use "
            f"dataclasses.replace(scenario, horizon={config.horizon})"
        )
    if metrics_config is not None and (
        not math.isclose(metrics_config.dt, config.dt, rel_tol=1e-9)
        or metrics_config.steps != config.steps
    ):
        raise ValueError(
            f"metrics_config is made for dt={metrics_config.dt}, {metrics_config.steps} steps, "
            f"the simulation runs dt={config.dt}, {config.steps} steps; make it with "
            "fojax.metrics.MetricsConfig(dt=config.dt, steps=config.steps, ...)"
        )


def make_chunk_runner(
    controller,
    scenario: scenarios.Scenario,
    config: simulator.SimulationConfig,
    metrics_config: metrics.MetricsConfig | None = None,
    dtype=None,
    mesh=None,
) -> Callable:
    """A jitted ``(gains, keys (n, 2)) -> (status (n,), metrics, snapshots)``.

    ``gains`` is shared by every draw of the call; the compiled function is reused for
    any gains and keys of the same shapes. With ``mesh`` (a :func:`fojax.sharding.draw_mesh`
    of more than one device) the draws of each call are split over its devices; ``n``
    must then be a multiple of the mesh's size (:func:`run` makes it one).

    For a union scenario (:func:`fojax.scenarios.union`) the function takes a third
    argument, ``member``: the ``()`` int32 index of the member every draw of the call
    belongs to, traced, so that one compiled program serves every member (``config``
    then has the union's horizon; the snapshots cover it: :func:`run` trims them to the
    member's own).
    """
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    metrics_config = metrics_config or metrics.MetricsConfig(dt=config.dt, steps=config.steps)
    model = scenario.plant_params(dtype)
    controller = as_controller(controller)
    check_settings(controller, scenario, config, metrics_config)
    observer = metrics.Metrics(metrics_config)

    def batch(gains, keys, member=0):
        result = simulator.rollout_from_keys(
            controller, gains, model, scenario, keys, config, observer, dtype, member
        )
        return scenarios.batch_first((result.status, result.outputs, result.trajectory))

    batched = (False, True, False) if scenario.members else (False, True)
    return sharding.sharded_batch(batch, mesh or sharding.one_device_mesh(), batched)


def compile_chunk_runner(
    controller,
    gains,
    scenario: scenarios.Scenario,
    config: simulator.SimulationConfig,
    draws_per_call: int,
    metrics_config: metrics.MetricsConfig | None = None,
    dtype=None,
    mesh=None,
) -> Callable:
    """:func:`make_chunk_runner` compiled ahead of time for calls of ``draws_per_call``
    draws (``device_batch`` times the mesh's devices: :func:`batch_layout`) with gains
    shaped like ``gains``.

    Lowering holds Python's lock, XLA's compilation does not: called in a worker thread
    it compiles while other runs go on (``fojax.cli.study`` does so). Pass the result
    to :func:`run` as ``runner``. For a union scenario it takes the member index as a
    third argument (:func:`make_chunk_runner`): one program for every member. With the
    persistent compilation cache on (``jax_compilation_cache_dir``) a compiled program
    is read from there.
    """
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    mesh = mesh or sharding.one_device_mesh()
    jitted = make_chunk_runner(controller, scenario, config, metrics_config, dtype, mesh)
    gains = jax.tree.map(lambda g: jnp.asarray(g, dtype), gains)
    replicated = sharding.replicated_sharding(mesh)
    gains_spec = jax.tree.map(
        lambda g: jax.ShapeDtypeStruct(g.shape, g.dtype, sharding=replicated), gains
    )
    keys_spec = jax.ShapeDtypeStruct(
        (draws_per_call, 2), jnp.uint32, sharding=sharding.draw_sharding(mesh)
    )
    member_spec = jax.ShapeDtypeStruct((), jnp.int32, sharding=replicated)
    specs = (gains_spec, keys_spec, member_spec) if scenario.members else (gains_spec, keys_spec)
    return jitted.lower(*specs).compile()


def numeric_xla_flags(flags: str | None = None) -> list[str]:
    """The ``XLA_FLAGS`` (default: the process's, :func:`fojax.settings.read`) that can
    change a program's arithmetic: all but the host device count and dump options."""
    flags = process_settings.read().xla_flags if flags is None else flags
    kept = []
    for flag in flags.split():
        name = flag.lstrip("-").split("=")[0]
        if name != "xla_force_host_platform_device_count" and not name.startswith("xla_dump"):
            kept.append(flag)
    return sorted(kept)


def fingerprint(
    controller,
    gains,
    scenario,
    config,
    seed,
    dtype,
    mcfg,
    device_batch: int | None = None,
    backend: str | None = None,
    member: int | None = None,
) -> dict:
    """Every setting draw ``i``'s numbers depend on, as a JSON-ready dict (nested
    dataclasses as dicts, functions by name): what the chunk store keys its draws by.

    With the settings of the rollout: the block size ``device_batch`` (default
    :func:`default_device_batch`), the platform ``backend`` (``cpu``, ``gpu``, ...;
    default JAX's) and the ``XLA_FLAGS`` that change arithmetic
    (:func:`numeric_xla_flags`), and the library's code (``code_version``:
    :func:`fojax.records.code_digest`, so draws stored by other code are not reused). Not in
    it, since they do not change a draw's numbers: the draw count, ``keep``, the
    devices and processes.

    For a union scenario (:func:`fojax.scenarios.union`; its members are spelled out
    under ``scenario.members``) it also holds ``member``, the index of the member whose
    draws these are; a plain scenario's fingerprint has no ``member``.
    """

    def plain(obj):
        if dataclasses.is_dataclass(obj):
            return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        if isinstance(obj, tuple | list):  # e.g. a union's members
            items = [plain(item) for item in obj]
            same = all(a is b for a, b in zip(items, obj, strict=True))
            return obj if same else items
        return obj.__name__ if callable(obj) else obj

    controller = as_controller(controller)
    extra = {"member": int(member if member is not None else 0)} if scenario.members else {}
    return {
        "controller": controller.name,
        "controller_config": plain(controller),
        "gains": {k: np.asarray(v).tolist() for k, v in gains._asdict().items()},
        "scenario": plain(scenario),
        "simulation": plain(config),
        "metrics": plain(mcfg),
        "seed": int(seed),
        "dtype": str(jnp.dtype(dtype)),
        "device_batch": int(device_batch or default_device_batch(backend)),
        "backend": backend or jax.default_backend(),
        "xla_flags": numeric_xla_flags(),
        "fojax_code": code_version(),
        **extra,
    }


def check_member(scenario: scenarios.Scenario, member) -> int | None:
    """The member index :func:`run` uses (None for a plain scenario), or a ``ValueError``
    saying what to pass: a union (``scenario.members``) needs ``0 <= member <
    len(members)``; a plain scenario takes none (or 0)."""
    if member is not None and _not_integer(member, -math.inf):
        raise ValueError(f"member must be an integer index, got {member!r}")
    if not scenario.members:
        if member not in (None, 0):
            raise ValueError(
                f"member={member} given for {scenario.name!r}, which is not a union of "
                "scenarios (fojax.scenarios.union)"
            )
        return None
    count = len(scenario.members)
    if member is None:
        raise ValueError(
            f"{scenario.name!r} is a union of {count} scenarios: pass member= (0 to "
            f"{count - 1}), the one whose draws to run"
        )
    if not 0 <= member < count:
        raise ValueError(
            f"member must be 0 to {count - 1} for this union of {count} scenarios, got {member}"
        )
    return int(member)


def run(
    controller,
    gains,
    scenario: scenarios.Scenario,
    config: simulator.SimulationConfig,
    draws: int,
    seed: int = 0,
    device_batch: int | None = None,
    keep: int = 64,
    progress: bool = True,
    dtype=None,
    metrics_config: metrics.MetricsConfig | None = None,
    store: str | os.PathLike | None = None,
    runner: Callable | None = None,
    mesh=None,
    member: int | None = None,
) -> MonteCarloResult:
    """Roll out draws ``0 ... draws - 1`` of ``scenario`` with seed ``seed``.

    Args:
        controller, gains: the controller (:func:`fojax.make_controller`) and its gains
            (checked against the controller's declared gains before anything runs).
        scenario: the scenario; its ``horizon`` must cover ``config.horizon`` (the
            random tables are laid out for it).
        config: simulation settings: ``dt`` the controller's, ``horizon`` a whole
            number of steps (:func:`check_settings`).
        draws: number of draws, 1 to 2**32. seed: the run's seed, 0 to 2**63 - 1.
        device_batch: draws per block, the draws each device computes in one call
            (default :func:`default_device_batch`: 50 on a CPU). Memory grows with it;
            draw ``i``'s numbers depend on it (rounding), and on nothing else of the
            layout.
        keep: decimated trajectories are kept for the first ``keep`` draws (an
            integer >= 0; more than ``draws`` keeps them all).
        progress: print a progress line per call to stderr (process 0 only).
        dtype: floating dtype (default float32, float64 with x64 enabled).
        metrics_config: settling bands etc.; default :class:`fojax.metrics.MetricsConfig`.
        store: a directory: each finished call's draws are saved there, and draws already
            there (from an interrupted or shorter run, or one on other devices, with the
            same :func:`fingerprint`) are read, not rerun. Other settings raise
            :class:`fojax.study.StoreMismatch` naming the fields that differ.
        runner: a function from :func:`make_chunk_runner` or :func:`compile_chunk_runner`
            for these settings, made with the same ``mesh`` (compiled: for
            ``device_batch`` draws per device), to share one compiled function.
        mesh: a :func:`fojax.sharding.draw_mesh`: each call runs one block per device
            (one per core on a CPU with
            ``XLA_FLAGS=--xla_force_host_platform_device_count=N``, the GPUs, or every
            process's devices after :func:`fojax.sharding.initialize`).
        member: for a union scenario (:func:`fojax.scenarios.union`, with ``config``
            of the union's horizon), the index of the member whose draws to run
            (required; None or 0 for a plain scenario). Its draws are that scenario's
            run alone (bit for bit in float64); the snapshots are trimmed to its own
            horizon, and the store's :func:`fingerprint` holds the union and the
            member. One runner (compiled program) serves every member.

    Returns a :class:`MonteCarloResult`, the same on every process.
    """
    controller = as_controller(controller)
    member = _check_run(controller, gains, scenario, draws, seed, device_batch, keep, member)
    draws, seed = int(draws), int(seed)
    batch = int(device_batch or default_device_batch())
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    metrics_config = metrics_config or metrics.MetricsConfig(dt=config.dt, steps=config.steps)
    check_settings(controller, scenario, config, metrics_config)
    layout = batch_layout(draws, batch, mesh)
    keep = int(min(max(keep, 0), draws))
    lead = jax.process_index() == 0
    fields = (controller, gains, scenario, config, seed, dtype, metrics_config, batch)
    chunk_store = _open_store(store, lead, fields, member)
    segments, calls = plan_calls(chunk_store, draws, keep, batch, layout["devices"], mesh)
    if runner is None and calls:
        runner = make_chunk_runner(controller, scenario, config, metrics_config, dtype, mesh)
    dispatch = Dispatch(runner, gains, scenario, config, seed, batch, keep, mesh, member)
    start_time = time.perf_counter()
    report = progress and lead and (lambda *a: dispatch.report(controller.name, *a))
    done = draws - to_compute(segments)  # loaded from the store
    call_times = _run_calls(dispatch, calls, chunk_store, done, draws, layout, config, report)
    wall = time.perf_counter() - start_time
    result = run_result(segments, chunk_store, dispatch.computed, batch, keep, mesh, call_times)
    return _monte_carlo_result(controller.name, result, wall, layout, len(calls), draws)


def _open_store(store, lead: bool, fields: tuple, member) -> ChunkStore | None:
    """:func:`run`'s chunk store in folder ``store``, under the :func:`fingerprint` of
    ``fields`` and ``member``; process 0 (``lead``) keeps it, the others have None."""
    if store is None or not lead:
        return None
    return ChunkStore(Path(store), fingerprint(*fields, member=member))


def _check_run(controller, gains, scenario, draws, seed, device_batch, keep, member):
    """:func:`run`'s checks of its arguments, before anything runs; returns the member
    (:func:`check_member`)."""
    if hasattr(controller, "check_gains"):
        controller.check_gains(gains)
    check_run_arguments(draws, seed, device_batch)
    if _not_integer(keep, 0):
        raise ValueError(f"keep must be an integer >= 0 (0: no trajectories), got {keep!r}")
    return check_member(scenario, member)


def _monte_carlo_result(name, result, wall, layout, calls, draws) -> MonteCarloResult:
    """The :class:`MonteCarloResult` of :func:`run_result`'s ``result`` for ``calls`` calls."""
    status, per_draw, kept, computed, compile_time = result
    return MonteCarloResult(
        controller=name,
        status=status.astype(np.int32),
        per_draw=per_draw,
        trajectories=unflatten_snapshot(kept) if kept else None,
        wall_time=wall,
        compile_time=compile_time,
        layout={**layout, "calls": calls, "computed": computed, "loaded": draws - computed},
    )


def _run_calls(dispatch, calls, chunk_store, done, draws, layout, config, report) -> list:
    """Each call's blocks run, stored (with a store) and reported (``report``: a
    function of (done, draws, steps, call times), or False); returns the calls' times."""
    batch = dispatch.batch
    call_times: list[float] = []
    for call in calls:
        t0 = time.perf_counter()
        dispatch(call, layout["devices"])
        if chunk_store is not None:
            save_blocks(chunk_store, call, dispatch.computed, batch)
        call_times.append(time.perf_counter() - t0)
        done += sum(max(0, min(batch, draws - k * batch)) for k in call)
        if report:
            report(min(done, draws), draws, config.steps, call_times)
    if report and calls:
        print(file=sys.stderr)
    return call_times
