"""Many draws evaluated in blocks, one block per device and call: the one way fojax
runs a per-draw function over a long list of draws (the Monte Carlo study's calls,
:func:`fojax.requirements.measure`, the tuning engine's objective).

* :func:`evaluate_in_blocks`: the keys completed to whole calls by repeating the last
  one, split into calls of one block per device of a mesh, each call's results
  gathered to the host (to every process of a ``jax.distributed`` run), the padding
  dropped.
* :class:`EvaluatorCache`: compiled evaluators kept by their settings, at most a given
  number (the least recently used is dropped), so that a long session compiling many
  settings does not keep every program alive.

Why blocks: XLA compiles a batch into code that depends on its size, and on a CPU
rounds a draw according to where it sits in the batch (:mod:`fojax.study`). With a
fixed ``block``, draw ``i`` is always computed at position ``i % block`` of block
``i // block`` by the same per-device program, so its numbers do not depend on the
draw count, the padding, the devices or the processes.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Hashable
from typing import Any

import jax
import numpy as np

from fojax import sharding

__all__ = ["EvaluatorCache", "abstract", "evaluate_in_blocks", "gather"]


def gather(tree: Any, mesh=None) -> Any:
    """A call's outputs as host NumPy arrays, every draw on every process (across the
    processes of ``mesh``, :func:`jax.experimental.multihost_utils.process_allgather`)."""
    if mesh is not None and any(d.process_index != jax.process_index() for d in mesh.devices.flat):
        from jax.experimental import multihost_utils

        sharding.barrier("gather")  # processes may finish compiling far apart
        return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))
    return jax.tree.map(np.asarray, tree)


def evaluate_in_blocks(fn: Callable, shared: Any, keys, mesh=None, block: int | None = None) -> Any:
    """``fn`` over every key of ``keys``, in blocks of ``block`` keys, one block per
    device of ``mesh`` and call.

    Args:
        fn: ``fn(shared, keys)``, a compiled (``jax.jit``) function of a call's keys
            ``(devices * block, ...)`` returning a pytree of arrays whose leading axis
            is those keys' draws, each computed from its own key only. With a ``mesh``
            it is made for that mesh (:func:`fojax.sharding.sharded_batch` with
            ``batched=(False, True)``: each device runs its own block).
        shared: a pytree given whole to every call (gains, parameters, ...); placed
            on every device of ``mesh`` (:func:`fojax.sharding.replicate`).
        keys: ``(n, ...)``, e.g. ``(n, 2)`` keys of :func:`fojax.scenarios.draw_keys`,
            or a pytree of such arrays (every leaf with the leading axis ``n``: a
            draw's inputs), ``n >= 1``; the same values on every process.
        mesh: None: ``fn`` as it is, one block per call; else a
            :func:`fojax.sharding.draw_mesh`, the keys of each call split over its
            devices (:func:`fojax.sharding.shard_draws`; placed only for more than one
            device).
        block: keys per block (default ``n``: one block).

    Returns ``fn``'s pytree of NumPy arrays with leading axis ``n``, the draws in the
    order of ``keys``, on every process. The keys are completed to a whole number of
    calls (``devices * block`` keys each) by repeating the last one; the results of
    the repeats are dropped. Draw ``i``'s numbers are those of a direct call of ``fn``
    on its block, whatever ``n``, the mesh and the processes.
    """
    keys = jax.tree.map(np.asarray, keys)
    shapes = [np.shape(leaf) for leaf in jax.tree.leaves(keys)]
    count = shapes[0][0] if shapes and shapes[0] else 0
    block = count if block is None else block
    if count < 1 or any(not shape or shape[0] != count for shape in shapes):
        raise ValueError(f"evaluate_in_blocks needs at least one key, got shapes {shapes}")
    if isinstance(block, bool) or not isinstance(block, int | np.integer) or block < 1:
        raise ValueError(f"block must be a positive integer, got {block!r}")
    devices = 1 if mesh is None else int(mesh.devices.size)
    per_call = int(block) * devices
    keys, _ = sharding.pad_draws(keys, per_call)
    placed = devices > 1
    if placed:
        shared = sharding.replicate(shared, mesh)
    parts = []
    for first in range(0, count + (-count % per_call), per_call):
        chunk = jax.tree.map(lambda leaf, first=first: leaf[first : first + per_call], keys)
        chunk = sharding.shard_draws(chunk, mesh) if placed else chunk
        parts.append(gather(fn(shared, chunk), mesh))
    return jax.tree.map(lambda *xs: np.concatenate(xs)[:count], *parts)


def abstract(shared: Any, keys: Any, mesh=None) -> tuple:
    """``(shared, keys)`` of one call of :func:`evaluate_in_blocks` as its program
    receives them, from ``jax.ShapeDtypeStruct`` trees (``keys`` those of one whole
    call): with more than one device, ``shared`` replicated and ``keys`` split over
    ``mesh``, as the call places them; for compiling the program ahead
    (``jit(fn).lower(*abstract(...)).compile()``) without running it."""
    if mesh is None or int(mesh.devices.size) == 1:
        return shared, keys

    def placed(tree, where):
        return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=where), tree)

    return placed(shared, sharding.replicated_sharding(mesh)), placed(
        keys, sharding.draw_sharding(mesh)
    )


class EvaluatorCache:
    """Compiled evaluators by key, at most ``size`` of them (the least recently used
    is dropped, and with it its compiled program once nothing else holds it).

    ``get(key, build)``: the evaluator kept under ``key``, else ``build()``, kept. A key
    that cannot be hashed (e.g. a controller holding arrays) is built every time.
    Safe to share between threads (two threads asking for one new key may both build).
    """

    def __init__(self, size: int = 16):
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ValueError(f"size must be a positive integer, got {size!r}")
        self.size = size
        self._items: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: Hashable, build: Callable[[], Any]) -> Any:
        try:
            hash(key)
        except TypeError:
            return build()
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = build()
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value
