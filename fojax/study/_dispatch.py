"""How :func:`fojax.study.run` runs its plan: the blocks to compute, ``devices`` per
call of the compiled runner (:class:`Dispatch`), each call's blocks saved to the
store, the draws assembled in order from the store and the calls, and, in a
multi-process run, process 0's plan and result sent to the others."""

from __future__ import annotations

import io
import itertools
import sys
import time

import jax
import numpy as np

from fojax import blocks, observers, scenarios, sharding
from fojax.study._store import ChunkStore, flatten_snapshot, plan

DIVERGED = observers.NONFINITE | observers.TILT_LIMIT
"""Status bits that make a draw count as diverged (excluded from the metrics)."""

MAX_DRAWS = 2**32
"""Most draws of one run: draw indices are folded into the key as 32-bit integers, so
index ``2**32`` would repeat draw 0."""


def _multiprocess(mesh) -> bool:
    return mesh is not None and any(
        d.process_index != jax.process_index() for d in mesh.devices.flat
    )


def _broadcast_arrays(arrays: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """``arrays`` of process 0, on every process."""
    from jax.experimental import multihost_utils

    lead, buffer = jax.process_index() == 0, io.BytesIO()
    if lead:
        np.savez(buffer, **arrays)
    payload = buffer.getvalue()
    sharding.barrier("broadcast")
    size = np.array([len(payload) if lead else 0], np.int64)
    size = int(np.asarray(multihost_utils.broadcast_one_to_all(size))[0])
    data = np.frombuffer(payload, np.uint8) if lead else np.zeros(size, np.uint8)
    data = np.asarray(multihost_utils.broadcast_one_to_all(data)).tobytes()
    with np.load(io.BytesIO(data)) as loaded:
        return {k: loaded[k] for k in loaded.files}


def to_compute(segments) -> int:
    """How many draws of the plan are computed (not read from the store)."""
    return sum(b - a for kind, a, b, _ in segments if kind == "compute")


def plan_calls(chunk_store, draws: int, keep: int, batch: int, devices: int, mesh):
    """The plan: ``segments`` (:func:`fojax.study._store.plan`: what is read from the
    store, what is computed) and ``calls``, the blocks to compute, ``devices`` per call
    (process 0's plan in a multi-process run: it alone reads the store)."""
    segments = [("compute", 0, draws, None)]
    if chunk_store is not None:
        segments = plan(chunk_store.ranges(), draws, keep)
    computing = [(a, b) for kind, a, b, _ in segments if kind == "compute"]
    blocks = sorted({k for a, b in computing for k in range(a // batch, (b - 1) // batch + 1)})
    if _multiprocess(mesh):
        lead = jax.process_index() == 0
        message = {"blocks": np.asarray(blocks, np.int64)} if lead else None
        blocks = [int(k) for k in _broadcast_arrays(message)["blocks"]]
    return segments, [blocks[i : i + devices] for i in range(0, len(blocks), devices)]


class Dispatch:
    """Runs calls of the compiled runner, one block per device, and keeps each block's
    ``(status, per_draw, snapshots or None)`` in ``computed``."""

    def __init__(self, runner, gains, scenario, config, seed, batch, keep, mesh, member):
        self.runner, self.gains, self.scenario = runner, gains, scenario
        self.seed, self.batch, self.keep, self.mesh, self.member = seed, batch, keep, mesh, member
        self.member_blocks = None  # a union member's snapshots stop at its own horizon
        if scenario.members:
            own_steps = int(round(scenario.members[member].horizon / config.dt))
            self.member_blocks = own_steps // config.save_every
        self.computed: dict[int, tuple] = {}
        self.start_time = time.perf_counter()
        self.per_call = batch

    def _runner(self, shared, keys):
        """The compiled runner as :func:`fojax.blocks.evaluate_in_blocks` calls it."""
        gains, *member = shared
        return self.runner(gains, keys, *member)

    def __call__(self, call: list[int], devices: int) -> None:
        batch = self.batch
        self.per_call = batch * devices
        indices = np.concatenate([np.arange(k * batch, (k + 1) * batch) for k in call])
        keys = np.asarray(scenarios.draw_keys(self.seed, np.minimum(indices, MAX_DRAWS - 1)))
        shared = (self.gains,)
        if self.scenario.members:  # a union's member index, shared by every draw
            shared = (self.gains, np.asarray(self.member, np.int32))
        evaluate = blocks.evaluate_in_blocks
        status, values, snapshots = evaluate(self._runner, shared, keys, self.mesh, batch)
        flat = flatten_snapshot(snapshots)
        if self.member_blocks is not None:
            flat = {name: v[:, : self.member_blocks] for name, v in flat.items()}
        for j, k in enumerate(call):
            part = slice(j * batch, (j + 1) * batch)
            kept = min(batch, max(self.keep - k * batch, 0))
            snaps = {name: v[part][:kept] for name, v in flat.items()} if kept else None
            self.computed[k] = (
                np.asarray(status)[part],
                {name: np.asarray(v)[part] for name, v in values.items()},
                snaps,
            )

    def report(self, name: str, done: int, draws: int, steps: int, call_times) -> None:
        batch = self.batch
        diverged = sum(
            int(np.sum((c[0][: max(0, draws - k * batch)] & DIVERGED) > 0))
            for k, c in self.computed.items()
        )
        elapsed = time.perf_counter() - self.start_time
        steady = np.median(call_times[1:]) if len(call_times) > 1 else None
        eta = f", about {(draws - done) / self.per_call * steady:.0f} s left" if steady else ""
        rate = len(self.computed) * batch * steps / max(sum(call_times), 1e-9)
        print(
            f"\r  {name}: {done}/{draws} draws, {elapsed:.0f} s{eta}, {rate:.3g} draw-steps/s, "
            f"diverged {diverged}   ",
            end="",
            file=sys.stderr,
            flush=True,
        )


def run_result(segments, chunk_store, computed, batch, keep, mesh, call_times):
    """The run's draws in order, read and computed (the same on every process):
    ``(status, per_draw, kept snapshots, computed draws, compile time)``."""
    multi, flat = _multiprocess(mesh), None
    if jax.process_index() == 0 or not multi:
        flat = _assemble(segments, chunk_store, computed, batch, keep)
        flat["computed"] = np.asarray([to_compute(segments)], np.int64)
    if multi:  # the others hold only the computed blocks: process 0 sends the result
        flat = _broadcast_arrays(flat)
    computed_draws = int(flat.pop("computed")[0])
    per_draw = {k[2:]: v for k, v in flat.items() if k.startswith("m.")}
    kept = {k[2:]: v for k, v in flat.items() if k.startswith("s.")}
    compile_time = 0.0
    if len(call_times) > 1:
        compile_time = max(0.0, call_times[0] - float(np.median(call_times[1:])))
    elif call_times:
        compile_time = float("nan")  # one call: cannot separate compile from run
    return flat["status"], per_draw, kept, computed_draws, compile_time


def save_blocks(chunk_store: ChunkStore, call: list[int], computed: dict, batch: int) -> None:
    """Store the call's blocks, consecutive ones in one file (indices below 2**32)."""
    consecutive = itertools.groupby(enumerate(sorted(set(call))), lambda p: p[1] - p[0])
    for run_blocks in ([k for _, k in group] for _, group in consecutive):
        first = run_blocks[0] * batch
        n = min(len(run_blocks) * batch, MAX_DRAWS - first)
        if n <= 0:
            continue
        status = np.concatenate([computed[k][0] for k in run_blocks])[:n]
        values = {
            name: np.concatenate([computed[k][1][name] for k in run_blocks])[:n]
            for name in computed[run_blocks[0]][1]
        }
        snaps = None
        if computed[run_blocks[0]][2] is not None:
            parts = [computed[k][2] for k in run_blocks if computed[k][2] is not None]
            snaps = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
        chunk_store.save(first, status, values, snaps)


def _assemble(segments, chunk_store, computed: dict, batch: int, keep: int) -> dict:
    """Draws ``[0, draws)`` from the store and the computed blocks, as flat arrays:
    ``status``, ``m.<metric>``, ``s.<snapshot leaf>`` (the first ``keep`` draws)."""
    pieces = []  # (first, status, per_draw, snapshots or None)
    for kind, start, stop, item in segments:
        if kind == "load":
            pieces.append((start, *chunk_store.load(item, start, stop)))
            continue
        for k in range(start // batch, (stop - 1) // batch + 1):
            a, b = max(start, k * batch), min(stop, (k + 1) * batch)
            lo, hi = a - k * batch, b - k * batch
            status, values, snaps = computed[k]
            snaps = {n: v[lo:hi] for n, v in snaps.items()} if snaps and a < keep else None
            pieces.append((a, status[lo:hi], {n: v[lo:hi] for n, v in values.items()}, snaps))
    out = {"status": np.concatenate([p[1] for p in pieces])}
    for name in pieces[0][2]:
        out[f"m.{name}"] = np.concatenate([p[2][name] for p in pieces])
    kept = []
    for first, status, _, snaps in pieces:
        if first >= keep:
            break
        n = min(len(status), keep - first)
        kept.append({k: v[:n] for k, v in snaps.items()})
    if kept:
        for name in kept[0]:
            out[f"s.{name}"] = np.concatenate([k[name] for k in kept])
    return out
