"""Monte Carlo draws spread over every device: one mesh axis, ``"draws"``.

Draws are independent, so a batch of draws splits over devices with no
communication inside the time loop: the leading (draw) axis of every batched array is
sharded over a one-dimensional :class:`jax.sharding.Mesh`, everything shared (gains,
the nominal model) is replicated, and ``jax.jit`` partitions the vmapped rollout. Each
device runs the same per-draw arithmetic as a single-device run, so the results are
the same.

On one host the mesh holds its local devices: GPUs, or CPU "devices" made with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (one per core; set before JAX
starts). On several hosts, call :func:`initialize` first in every process
(``jax.distributed``); the mesh then spans the devices of all processes, and
:func:`shard_draws` builds global arrays from the values every process computes for
the shards it owns.

Typical use::

    mesh = sharding.draw_mesh()
    keys = sharding.shard_draws(scenarios.draw_keys(seed, range(n)), mesh)
    run = sharding.sharded_vmap(one_draw, mesh, in_axes=(None, 0))
    results = run(gains, keys)        # results sharded along the draws
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = [
    "DRAW_AXIS",
    "draw_mesh",
    "draw_sharding",
    "initialize",
    "pad_draws",
    "replicate",
    "replicated_sharding",
    "shard_draws",
    "sharded_vmap",
]

DRAW_AXIS = "draws"


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> dict[str, int]:
    """Join a multi-host run through :func:`jax.distributed.initialize`, if there is one.

    With all three arguments ``None`` and none of ``JAX_COORDINATOR_ADDRESS``,
    ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID`` set (and no cluster detected by JAX), this
    is a single-process run and nothing is done. Call it before any other JAX call.

    Returns ``{"process_index", "process_count", "device_count", "local_device_count"}``.
    """
    given = (coordinator_address, num_processes, process_id)
    from_env = any(
        os.environ.get(name)
        for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
    )
    if any(v is not None for v in given) or from_env:
        if num_processes is not None and (not isinstance(num_processes, int) or num_processes < 1):
            raise ValueError(f"num_processes must be a positive integer, got {num_processes!r}")
        if process_id is not None and (
            not isinstance(process_id, int)
            or process_id < 0
            or (num_processes is not None and process_id >= num_processes)
        ):
            raise ValueError(
                f"process_id must be an integer in [0, num_processes), got {process_id!r}"
            )
        jax.distributed.initialize(
            coordinator_address=coordinator_address,
            num_processes=num_processes,
            process_id=process_id,
        )
    return {
        "process_index": jax.process_index(),
        "process_count": jax.process_count(),
        "device_count": jax.device_count(),
        "local_device_count": jax.local_device_count(),
    }


def draw_mesh(devices: Sequence[Any] | None = None) -> Mesh:
    """A one-dimensional mesh with axis :data:`DRAW_AXIS` over ``devices``.

    devices: default every device of every process (``jax.devices()``).
    """
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("draw_mesh needs at least one device")
    return Mesh(np.array(devices), (DRAW_AXIS,))


def draw_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (draw) axis split over the mesh, other axes whole."""
    return NamedSharding(mesh, PartitionSpec(DRAW_AXIS))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    """A full copy on every device (gains, nominal model)."""
    return NamedSharding(mesh, PartitionSpec())


def _mesh_size(mesh: Mesh) -> int:
    return int(math.prod(mesh.devices.shape))


def _draw_count(tree: Any) -> int:
    leaves = jax.tree.leaves(tree)
    if not leaves:
        raise ValueError("shard_draws needs at least one array")
    counts = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in leaves}
    if None in counts or len(counts) != 1:
        shapes = [np.shape(leaf) for leaf in leaves]
        raise ValueError(f"every array must have the same leading (draw) axis; got shapes {shapes}")
    return counts.pop()


def pad_draws(tree: Any, multiple: int) -> tuple[Any, int]:
    """Repeat the last draw so that the draw count is a multiple of ``multiple``.

    Returns ``(padded tree, original count)``; drop the extra results with
    ``result[:count]``.
    """
    if not isinstance(multiple, int) or multiple < 1:
        raise ValueError(f"multiple must be a positive integer, got {multiple!r}")
    count = _draw_count(tree)
    extra = -count % multiple
    if extra == 0:
        return tree, count

    def pad(leaf):
        leaf = np.asarray(leaf)
        return np.concatenate([leaf, np.repeat(leaf[-1:], extra, axis=0)])

    return jax.tree.map(pad, tree), count


def shard_draws(tree: Any, mesh: Mesh) -> Any:
    """Place every array of ``tree`` with its leading (draw) axis split over ``mesh``.

    All leaves must share the leading axis ``n``, a multiple of the number of devices
    (see :func:`pad_draws`). Every process passes the same full values (draws are cheap
    and deterministic, :func:`fojax.scenarios.draw_keys`); each keeps the shards of its
    own devices, so this works unchanged on several hosts.
    """
    count = _draw_count(tree)
    size = _mesh_size(mesh)
    if count % size:
        raise ValueError(
            f"{count} draws do not split evenly over {size} devices; use a multiple of "
            f"{size} draws or pad them with fojax.sharding.pad_draws"
        )
    sharding = draw_sharding(mesh)

    def place(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(place, tree)


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Place every array of ``tree`` whole on every device of ``mesh``."""
    sharding = replicated_sharding(mesh)

    def place(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(place, tree)


def sharded_vmap(fn: Callable, mesh: Mesh, in_axes: Sequence[int | None]) -> Callable:
    """``jax.jit(jax.vmap(fn, in_axes))`` with the mapped arguments split over ``mesh``.

    in_axes: one entry per positional argument of ``fn``, ``0`` for arguments batched
        along their leading (draw) axis, ``None`` for shared ones (replicated).
    The outputs are batched along their leading axis and sharded the same way. Inputs
    may be given already placed (:func:`shard_draws`, :func:`replicate`) or as host
    arrays; the compiled program is reused for inputs of the same shapes.
    """
    in_axes = tuple(in_axes)
    for axis in in_axes:
        if axis not in (0, None):
            raise ValueError(f"in_axes entries must be 0 (batched) or None (shared), got {axis}")
    shardings = tuple(
        draw_sharding(mesh) if axis == 0 else replicated_sharding(mesh) for axis in in_axes
    )
    return jax.jit(
        jax.vmap(fn, in_axes=in_axes),
        in_shardings=shardings,
        out_shardings=draw_sharding(mesh),
    )
