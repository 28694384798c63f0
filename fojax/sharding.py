"""Monte Carlo draws spread over every device: one mesh axis, ``"draws"``.

Draws are independent, so a batch of draws splits over devices with no
communication inside the time loop: the leading (draw) axis of every batched input
and output is sharded over a one-dimensional :class:`jax.sharding.Mesh`, everything
shared (gains, the nominal model) is replicated, and each device runs the batched
rollout on its own block (:func:`sharded_batch`). Each device runs the same program as
a single-device run of its block, so the results are the same.

On one host the mesh holds its local devices: GPUs, or CPU "devices", one per core
(:func:`fojax.settings.use_host_devices`, or
``XLA_FLAGS=--xla_force_host_platform_device_count=N``; set before JAX starts). On
several hosts, call :func:`initialize` first in every process (``jax.distributed``);
the mesh then spans the devices of all processes, and
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
import re
import socket
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from fojax import settings as process_settings

__all__ = [
    "DRAW_AXIS",
    "barrier",
    "draw_mesh",
    "draw_sharding",
    "check_coordinator_address",
    "default_mesh",
    "detect_cluster",
    "distributed_settings",
    "free_port",
    "one_device_mesh",
    "initialize",
    "pad_draws",
    "replicate",
    "replicated_sharding",
    "shard_draws",
    "sharded_batch",
]

DRAW_AXIS = "draws"


JAX_VARIABLES = process_settings.DISTRIBUTED_VARIABLES
"""The environment variables of a :func:`jax.distributed.initialize` run
(:data:`fojax.settings.DISTRIBUTED_VARIABLES`)."""

_SETTINGS = ("coordinator_address", "num_processes", "process_id")
_VARIABLE = dict(zip(_SETTINGS, JAX_VARIABLES, strict=True))


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now: the coordinator's of processes on one machine
    (``--coordinator 127.0.0.1:PORT``)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def detect_cluster(settings: process_settings.Settings | None = None) -> tuple[str, int] | None:
    """``(name, process count)`` of the cluster this process runs in, as
    :func:`jax.distributed.initialize` detects it (SLURM, Open MPI, Kubernetes, Cloud
    TPU; not the opt-in mpi4py), or None. A cluster job of one process is not a
    distributed run, so callers join only when the count is above 1. ``settings``
    (default read now, :func:`fojax.settings.read`): where JAX's own detection is
    missing, SLURM's variables from there."""
    try:
        from jax._src import clusters  # JAX's own detection; private, hence guarded

        types = list(clusters.ClusterEnv._cluster_types)
    except (ImportError, AttributeError):  # another JAX: SLURM's variables by hand
        slurm = (settings or process_settings.read()).slurm
        return ("slurm", int(slurm[1])) if all(slurm) else None
    for env in types:
        if getattr(env, "opt_in_only_method", False):
            continue
        try:
            if env.is_env_present():
                return str(getattr(env, "name", env.__name__)), int(env.get_process_count())
        except Exception:  # a detector that cannot answer here (e.g. no API access)
            continue
    return None


def check_coordinator_address(text: str, label: str = "coordinator_address") -> str:
    """``text`` if it is ``HOST:PORT`` with a port in 1-65535, else ``ValueError``
    naming ``label`` (the argument, flag or variable it came from)."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(
            f"{label} must be HOST:PORT with a port in 1-65535 (e.g. 127.0.0.1:12355 or "
            f"node01:12355), got {text!r}"
        )
    return str(text).strip()


def _count(value: Any, label: str, minimum: int) -> int:
    """An integer >= ``minimum`` from an argument or an environment variable's text."""
    what = "an integer >= 1" if minimum == 1 else "an integer >= 0"
    if isinstance(value, str):
        text = value.strip()
        if not re.fullmatch(r"[+-]?\d+", text):
            raise ValueError(f"{label} must be {what}, got {value!r}")
        value = int(text)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{label} must be {what}, got {value!r}")
    return value


def distributed_settings(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    detect: bool = True,
    names: dict[str, str] | None = None,
    settings: process_settings.Settings | None = None,
) -> dict[str, Any] | None:
    """What :func:`initialize` passes to :func:`jax.distributed.initialize`, checked:
    ``{"coordinator_address", "num_processes", "process_id", "joined"}``, or None for a
    single-process run. Nothing is started, so this can be called (and tested) freely.

    Each setting is the argument when given, else its variable
    (``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``; an empty
    one counts as unset). When any of the three is given, the run is a multi-process
    one (``joined``: ``"arguments"`` or ``"environment"``) and the others must be given
    too, unless ``detect`` and a cluster job (:func:`detect_cluster`) supplies them, as
    JAX then takes them from the cluster. When none is, a detected cluster job of more
    than one process is joined (``joined``: the cluster's name; JAX takes everything
    from it). ``ValueError``, one line naming the setting, for a missing setting, a
    count or id that is not an integer (``count >= 1``, ``0 <= id < count``) and an
    address without a port. ``names``: how to call each argument in messages (e.g.
    ``{"num_processes": "--num-processes"}``). settings: the variables' values (default
    read now, :func:`fojax.settings.read`).
    """
    settings = process_settings.read() if settings is None else settings
    variables = dict(zip(_SETTINGS, settings.distributed, strict=True))
    names = {key: key for key in _SETTINGS} | dict(names or {})
    arguments = dict(zip(_SETTINGS, (coordinator_address, num_processes, process_id), strict=True))
    values: dict[str, Any] = {}
    labels: dict[str, str] = {}
    for key in _SETTINGS:
        if arguments[key] is not None:
            values[key], labels[key] = arguments[key], names[key]
        elif variables[key] is not None:
            values[key], labels[key] = variables[key], _VARIABLE[key]
    if "coordinator_address" in values:
        values["coordinator_address"] = check_coordinator_address(
            values["coordinator_address"], labels["coordinator_address"]
        )
    if "num_processes" in values:
        values["num_processes"] = _count(values["num_processes"], labels["num_processes"], 1)
    if "process_id" in values:
        values["process_id"] = _count(values["process_id"], labels["process_id"], 0)
    if "num_processes" in values and values.get("process_id", -1) >= values["num_processes"]:
        raise ValueError(
            f"{labels['process_id']} ({values['process_id']}) must be below "
            f"{labels['num_processes']} ({values['num_processes']}): the processes are "
            f"numbered 0 to {values['num_processes'] - 1}"
        )
    cluster = detect_cluster(settings) if detect else None
    if not values:
        if cluster is None or cluster[1] <= 1:
            return None
        return dict.fromkeys(_SETTINGS) | {"joined": cluster[0]}
    missing = [key for key in _SETTINGS if key not in values]
    if missing and cluster is None:
        wanted = ", ".join(names[key] for key in missing)
        variables = ", ".join(_VARIABLE[key] for key in missing)
        given = ", ".join(labels[key] for key in _SETTINGS if key in values)
        if all(labels[key] == _VARIABLE[key] for key in values):  # variables only
            raise ValueError(
                f"a multi-process run needs {variables} too ({given} is set): set "
                f"{', '.join(JAX_VARIABLES)} together (HOST:PORT of process 0, the number "
                "of processes, this process's id from 0), or none of them for a single process"
            )
        raise ValueError(
            f"a multi-process run needs {wanted} too (or {variables}); {given} alone is "
            "not enough: give the coordinator's HOST:PORT, the number of processes and "
            "this process's id (0 to N - 1) together, or none of them for a single process"
        )
    joined = "arguments" if any(v is not None for v in arguments.values()) else "environment"
    return dict.fromkeys(_SETTINGS) | values | {"joined": joined}


def initialize(**options: Any) -> dict[str, int]:
    """Join a multi-process run through :func:`jax.distributed.initialize`, if there is one.

    Joins when any argument is given, when any of ``JAX_COORDINATOR_ADDRESS``,
    ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID`` is set (arguments override them; fojax
    reads all three, JAX itself only the first), or, with ``detect``, when
    :func:`detect_cluster` finds a cluster job of more than one process (e.g. ``srun``
    with several tasks); otherwise this is a single-process run and nothing is done.
    Incomplete or inconsistent settings are a ``ValueError`` naming the setting, raised
    before anything starts. ``options``: those of :func:`distributed_settings`
    (``coordinator_address``, ``num_processes``, ``process_id``, ``detect``, ``names``,
    ``settings``), which checks them. Call it before any other JAX call that touches
    devices; a second call after joining does nothing. On CPUs the processes exchange
    results through JAX's CPU collectives (gloo).

    Returns ``{"process_index", "process_count", "device_count", "local_device_count",
    "joined"}`` (``joined``: how the run was joined: ``"arguments"``, ``"environment"``,
    the cluster's name, ``"earlier"``, or ``None``).
    """
    joined = None
    if jax.distributed.is_initialized():
        joined = "earlier"
    else:
        chosen = distributed_settings(**options)
        if chosen is not None:
            joined = chosen.pop("joined")
            jax.distributed.initialize(**chosen)
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


def default_mesh() -> Mesh | None:
    """A :func:`draw_mesh` of every device of every process (GPUs, or one CPU device
    per core: :func:`fojax.settings.use_host_devices`), or None for one device."""
    return draw_mesh(jax.devices()) if jax.device_count() > 1 else None


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
    return _place(tree, draw_sharding(mesh))


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Place every array of ``tree`` whole on every device of ``mesh``."""
    return _place(tree, replicated_sharding(mesh))


def _place(tree: Any, sharding: NamedSharding) -> Any:
    """Every array of ``tree`` copied from the host onto ``sharding``'s devices."""

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
        raise ValueError(f"batched entries must be True (batched) or False (shared), got {batched}")
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
