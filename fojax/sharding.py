"""Monte Carlo draws spread over every device: one mesh axis, ``"draws"``.

Draws are independent, so a batch of draws splits over devices with no
communication inside the time loop: the leading (draw) axis of every batched input
and output is sharded over a one-dimensional :class:`jax.sharding.Mesh`, everything
shared (gains, the nominal model) is replicated, and each device runs the batched
rollout on its own block (:func:`sharded_batch`). Each device runs the same program as
a single-device run of its block, so the results are the same.

On one host the mesh holds its local devices: GPUs, or CPU "devices" made with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (one per core; set before JAX
starts). On several hosts, call :func:`initialize` first in every process
(``jax.distributed``); the mesh then spans the devices of all processes, and
:func:`shard_draws` builds global arrays from the values every process computes for
the shards it owns.

Typical use::

    mesh = sharding.draw_mesh()
    keys = sharding.shard_draws(scenarios.draw_keys(seed, range(n)), mesh)
    run = sharding.sharded_batch(run_draws, mesh, batched=(False, True))
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
    "barrier",
    "draw_mesh",
    "draw_sharding",
    "detect_cluster",
    "one_device_mesh",
    "initialize",
    "pad_draws",
    "replicate",
    "replicated_sharding",
    "shard_draws",
    "sharded_batch",
]

DRAW_AXIS = "draws"


JAX_VARIABLES = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
"""The environment variables of a :func:`jax.distributed.initialize` run."""


def detect_cluster() -> tuple[str, int] | None:
    """``(name, process count)`` of the cluster this process runs in, as
    :func:`jax.distributed.initialize` detects it (SLURM, Open MPI, Kubernetes, Cloud
    TPU; not the opt-in mpi4py), or None. A cluster job of one process is not a
    distributed run, so callers join only when the count is above 1."""
    try:
        from jax._src import clusters  # JAX's own detection; private, hence guarded

        types = list(clusters.ClusterEnv._cluster_types)
    except (ImportError, AttributeError):  # another JAX: SLURM's variables by hand
        if all(os.environ.get(v) for v in ("SLURM_JOB_ID", "SLURM_NTASKS", "SLURM_PROCID")):
            return "slurm", int(os.environ["SLURM_NTASKS"])
        return None
    for env in types:
        if getattr(env, "opt_in_only_method", False):
            continue
        try:
            if env.is_env_present():
                return str(getattr(env, "name", env.__name__)), int(env.get_process_count())
        except Exception:  # a detector that cannot answer here (e.g. no API access)
            continue
    return None


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    detect: bool = True,
) -> dict[str, int]:
    """Join a multi-process run through :func:`jax.distributed.initialize`, if there is one.

    Joins when any argument is given, when any of ``JAX_COORDINATOR_ADDRESS``,
    ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID`` is set (arguments override them), or,
    with ``detect``, when :func:`detect_cluster` finds a cluster job of more than one
    process (e.g. ``srun`` with several tasks); otherwise this is a single-process run
    and nothing is done. Call it before any other JAX call that touches devices; a
    second call after joining does nothing. On CPUs the processes exchange results
    through JAX's CPU collectives (gloo).

    Returns ``{"process_index", "process_count", "device_count", "local_device_count",
    "joined"}`` (``joined``: how the run was joined: ``"arguments"``, ``"environment"``,
    the cluster's name, or ``None``).
    """
    if num_processes is not None and (
        isinstance(num_processes, bool) or not isinstance(num_processes, int) or num_processes < 1
    ):
        raise ValueError(f"num_processes must be a positive integer, got {num_processes!r}")
    if process_id is not None and (
        isinstance(process_id, bool)
        or not isinstance(process_id, int)
        or process_id < 0
        or (num_processes is not None and process_id >= num_processes)
    ):
        raise ValueError(f"process_id must be an integer in [0, num_processes), got {process_id!r}")
    joined = None
    if jax.distributed.is_initialized():
        joined = "earlier"
    elif any(v is not None for v in (coordinator_address, num_processes, process_id)):
        joined = "arguments"
    elif any(os.environ.get(name) for name in JAX_VARIABLES):
        joined = "environment"
    elif detect:
        cluster = detect_cluster()
        if cluster is not None and cluster[1] > 1:
            joined = cluster[0]
    if joined is not None and joined != "earlier":
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
        "joined": joined,
    }


_BARRIERS = {"count": 0}


def barrier(name: str, timeout_s: float = 3600.0) -> None:
    """Wait until every process of a ``jax.distributed`` run gets here (nothing to do
    in a single-process run).

    Collectives on CPUs (gloo) give up when the processes reach their first one more
    than 30 s apart, which a compilation of the gradient on a loaded machine exceeds;
    this waits through the coordination service instead, up to ``timeout_s``.
    """
    if jax.process_count() == 1:
        return
    _BARRIERS["count"] += 1
    label = f"fojax:{name}:{_BARRIERS['count']}"
    try:
        from jax._src import distributed  # the coordination client; private, hence guarded

        client = distributed.global_state.client
    except (ImportError, AttributeError):
        client = None
    if client is None or not hasattr(client, "wait_at_barrier"):
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(label)
        return
    client.wait_at_barrier(label, int(timeout_s * 1000))


def draw_mesh(devices: Sequence[Any] | None = None) -> Mesh:
    """A one-dimensional mesh with axis :data:`DRAW_AXIS` over ``devices``.

    devices: default every device of every process (``jax.devices()``).
    """
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("draw_mesh needs at least one device")
    return Mesh(np.array(devices), (DRAW_AXIS,))


def one_device_mesh() -> Mesh:
    """The mesh of this process's first device: where a batch runs when no mesh is given.

    Every batch runs as the per-device program of a mesh (:func:`sharded_batch`), one
    device included: XLA compiles a program partitioned over a mesh differently from a
    plain one (it fuses, and so rounds, some steps differently), and a draw's numbers
    must not depend on how many devices there are."""
    return draw_mesh(jax.local_devices()[:1])


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


def sharded_batch(
    fn: Callable, mesh: Mesh, batched: Sequence[bool], compiler_options: dict | None = None
) -> Callable:
    """``jax.jit(fn)`` with the draws split over ``mesh``: each device runs ``fn`` on its
    own block of draws.

    ``fn`` maps a batch of draws to results per draw (every output's leading axis the
    draws, computed for each draw from its own inputs only). batched: one entry per
    positional argument of ``fn``, ``True`` for arguments whose leading axis holds the
    draws (split over the devices), ``False`` for shared ones (replicated). Each device
    runs exactly the program ``fn`` compiles to for its block (``jax.shard_map``), so a
    draw's numbers are those of a one-device run of the same block. Inputs may be given
    already placed (:func:`shard_draws`, :func:`replicate`) or as host arrays; the
    compiled program is reused for inputs of the same shapes. ``compiler_options``: XLA's
    options for the program (``jax.jit``'s).
    """
    batched = tuple(batched)
    if not all(isinstance(b, bool) for b in batched):
        raise ValueError(
            f"batched entries must be True (batched) or False (shared), got {batched}"
        )
    specs = tuple(PartitionSpec(DRAW_AXIS) if b else PartitionSpec() for b in batched)
    mapped = jax.shard_map(
        fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(DRAW_AXIS), check_vma=False
    )
    shardings = tuple(draw_sharding(mesh) if b else replicated_sharding(mesh) for b in batched)
    return jax.jit(
        mapped,
        in_shardings=shardings,
        out_shardings=draw_sharding(mesh),
        compiler_options=compiler_options,
    )
