"""Compiled rollouts of an objective in blocks over devices: the lanes of a forward
evaluation, and the per-draw gradient.

:func:`in_blocks` runs a lanes program ``lanes`` per device and call, the last call
padded by repeating its last lane; :func:`over_mesh` runs the per-draw gradient in
blocks of ``device_batch`` draws per device, so that every mesh gives the same
per-draw values, bit for bit; :func:`gather` brings a sharded result to every process's
host; :class:`FirstCall` keeps two threads from compiling one program twice.
"""

from __future__ import annotations

import threading

import jax
import numpy as np

from fojax import export_cache, sharding

__all__ = ["FirstCall", "gather", "in_blocks", "over_mesh"]


class FirstCall:
    """A program whose first call holds a lock: two threads never compile it twice."""

    def __init__(self, program):
        self.program, self.lock, self.ready = program, threading.Lock(), False

    def __call__(self, *args):
        if not self.ready:
            with self.lock:
                out = self.program(*args)
                self.ready = True
                return out
        return self.program(*args)


def gather(tree, mesh):
    """Host copies of a result sharded over ``mesh`` (every process's part)."""
    if any(d.process_index != jax.process_index() for d in mesh.devices.flat):
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree.map(
        lambda a: np.asarray(a, np.float64) if a.dtype.kind == "f" else np.asarray(a), tree
    )


def in_blocks(program, mesh, lanes: int, batched: tuple, shared, dtype):
    """``program(xs, shared, keys, member)`` over every lane of ``batched`` = ``(xs (L,
    d), keys (L, 2), member (L,))``, ``lanes`` per device and call, the last call padded
    by repeating the last lane; results ``(L, ...)`` on the host."""
    total = batched[0].shape[0]
    per_call = lanes * int(mesh.devices.size)
    parts = []
    for first in range(0, total, per_call):
        index = np.minimum(np.arange(first, first + per_call), total - 1)
        xs, keys, member = (np.asarray(a)[index] for a in batched)
        out = program(
            sharding.shard_draws(xs.astype(dtype), mesh),
            sharding.replicate(shared, mesh),
            sharding.shard_draws(keys, mesh),
            sharding.shard_draws(member.astype(np.int32), mesh),
        )
        size = min(per_call, total - first)
        parts.append(jax.tree.map(lambda a, size=size: a[:size], gather(out, mesh)))
    return jax.tree.map(lambda *a: np.concatenate(a), *parts)


def over_mesh(per_draw, mesh, device_batch=None, compiler_options=None, key=None):
    """``gradient(x, width, keys, member, cotangent)`` with the draws over ``mesh``: the
    sample in blocks of ``device_batch`` draws (default: the whole sample, one block),
    one block per device and call (the last block completed by repeating the last draw,
    a short last call by repeating its last block), ``per_draw`` compiled for one block
    per device, the per-draw results gathered to every process, the padding dropped.

    Each draw is computed by the same per-device program at the same place in its block
    whatever the mesh, so every mesh, one device or the devices of several processes,
    gives the same per-draw values, bit for bit, for a given ``device_batch``. key: what
    ``per_draw`` closes over; given, its program is kept across processes
    (:func:`fojax.export_cache.reusable`)."""
    devices = int(mesh.devices.size)
    program = sharding.sharded_batch(
        per_draw, mesh, batched=(False, False, True, True, True), compiler_options=compiler_options
    )
    if key is not None:
        program = export_cache.reusable(program, "gradient", key, compiler_options)
    program = FirstCall(program)

    several = any(d.process_index != jax.process_index() for d in mesh.devices.flat)

    def gradient(x, width, keys, member, cotangent):
        keys, n = np.asarray(keys), len(keys)
        batch = int(device_batch or n)
        blocks = -(-n // batch)
        x, width = sharding.replicate(x, mesh), sharding.replicate(width, mesh)
        parts = []
        for first_block in range(0, blocks, devices):
            chosen = [min(b, blocks - 1) for b in range(first_block, first_block + devices)]
            index = np.minimum(
                np.concatenate([np.arange(b * batch, (b + 1) * batch) for b in chosen]), n - 1
            )
            if several:
                sharding.barrier("gradients")  # compilations may end far apart
            out = program(
                x,
                width,
                *(
                    sharding.shard_draws(np.asarray(a)[index], mesh)
                    for a in (keys, np.asarray(member, np.int32), cotangent)
                ),
            )
            real = min(devices, blocks - first_block) * batch
            parts.append(jax.tree.map(lambda a, real=real: a[:real], gather(out, mesh)))
        return jax.tree.map(lambda *a: np.concatenate(a)[:n], *parts)

    gradient.program = program
    return gradient
