"""Compiled programs reused across processes without tracing them again.

JAX's persistent compilation cache (``jax_compilation_cache_dir``) keeps the compiled
executable, but every new process still traces the Python function and lowers it to
StableHLO before it can look the executable up: for the tuner's gradient (the
checkpointed reverse pass of a whole closed-loop rollout) that is seconds of every
start. :func:`reusable` keeps the lowered program as well (``jax.export``): the first
process exports it into ``<compilation cache>/exported/``, later ones deserialise it
and call it, so that a warm start traces nothing and compiles nothing.

The program is identified by what it closes over (``key``: the caller's description,
e.g. a tuning problem's settings and base gains), the arguments' tree, shapes, dtypes
and shardings, the source of ``fojax`` and ``fojax.optimize``, and the JAX version and
devices. Every call, the first included, runs the exported program, so a cold and a
warm start compute the same numbers. Nothing is kept (the function is jitted as it is)
when the persistent compilation cache is off or when several processes run
(``jax.distributed``).
"""

from __future__ import annotations

import importlib.metadata
import json
import pkgutil
from collections.abc import Callable, Mapping
from pathlib import Path

import jax
import numpy as np

from fojax import records

__all__ = ["reusable"]

_FORMAT = 1
_REGISTERED: dict[type, str] = {}


def _folder() -> Path | None:
    """``<jax_compilation_cache_dir>/exported`` when the persistent cache is on."""
    root = jax.config.jax_compilation_cache_dir
    return Path(root) / "exported" if root and jax.config.jax_enable_compilation_cache else None


def _node_types(treedef) -> set[type]:
    """The NamedTuple types of ``treedef``'s nodes, and the static nodes' types that say
    how to serialise themselves (``to_bytes`` and ``from_bytes``, e.g.
    :class:`fojax.rotors.Layout`)."""
    found, stack = set(), [treedef]
    while stack:
        node = stack.pop()
        data = node.node_data()
        if data is not None and isinstance(data[0], type) and (
            hasattr(data[0], "_fields") or hasattr(data[0], "from_bytes")
        ):
            found.add(data[0])
        stack.extend(node.children())
    return found


def _register(types) -> list[str]:
    """Registers NamedTuple types, and static types by their ``to_bytes`` and
    ``from_bytes``, with ``jax.export`` (by ``module:qualname``)."""
    for cls in set(types) - _REGISTERED.keys():
        name = f"{cls.__module__}:{cls.__qualname__}"
        if hasattr(cls, "_fields"):
            jax.export.register_namedtuple_serialization(cls, serialized_name=name)
        else:
            jax.export.register_pytree_node_serialization(
                cls, serialized_name=name, serialize_auxdata=lambda aux: aux.to_bytes(),
                deserialize_auxdata=cls.from_bytes,
            )  # fmt: skip
        _REGISTERED[cls] = name
    return [_REGISTERED[c] for c in sorted(types, key=lambda c: (c.__module__, c.__qualname__))]


def _signature(args) -> tuple:
    leaves, treedef = jax.tree.flatten(args)
    return str(treedef), tuple(
        (
            tuple(leaf.shape) if hasattr(leaf, "shape") else np.shape(leaf),
            str(getattr(leaf, "dtype", type(leaf).__name__)),
            str(getattr(leaf, "sharding", None)),
        )
        for leaf in leaves
    )


def _digest(name: str, key: Mapping, signature: tuple, options) -> str:
    devices = jax.devices()
    document = {
        "format": _FORMAT,
        "name": name,
        "key": key,
        "signature": signature,
        "compiler_options": options,
        "source": records.code_digest(),
        "jax": [jax.__version__, importlib.metadata.version("jaxlib")],
        "x64": bool(jax.config.jax_enable_x64),
        "devices": [len(devices), devices[0].platform, devices[0].device_kind],
    }
    return records.digest(document, 24)


def _load(path: Path):
    """The program exported to ``path``, or None (no file, or a damaged or foreign one)."""
    try:
        header, _, payload = path.read_bytes().partition(b"\n")
        _register([pkgutil.resolve_name(name) for name in json.loads(header)["types"]])
        return jax.export.deserialize(bytearray(payload))
    except Exception:
        return None


def _export(path: Path, jitted: Callable, args):
    """``jitted`` exported for ``args``, saved to ``path`` (its node types named in a JSON
    header line) for :func:`_load`."""
    exported = jax.export.export(jitted)(*args)
    types = _node_types(exported.in_tree) | _node_types(exported.out_tree)
    header = json.dumps({"types": _register(types)}).encode()
    records.atomic_write(path, header + b"\n" + exported.serialize())
    return exported


def reusable(
    jitted: Callable, name: str, key: Mapping, compiler_options: dict | None = None
) -> Callable:
    """``jitted`` (a ``jax.jit`` function), its lowered program kept across processes.

    name: a short name for the file. key: JSON-ready description of everything
    ``jitted`` closes over (the arguments' shapes, the source and JAX's version are
    added here); two functions with the same name and key must compute the same.
    compiler_options: XLA's options for compiling the (deserialised) program, those
    ``jitted`` was given. Returns a function of the same arguments; one program per
    argument signature, loaded or exported at its first call. A file that cannot be
    read is exported again.
    """

    programs: dict[tuple, Callable] = {}

    def program_for(args):
        signature = _signature(args)
        program = programs.get(signature)
        if program is None:
            path = folder / f"{name}-{_digest(name, key, signature, compiler_options)}.bin"
            # No file, or a damaged or foreign one: export (again).
            exported = _load(path) or _export(path, jitted, args)
            program = programs[signature] = jax.jit(
                exported.call, compiler_options=compiler_options
            )
        return program

    def call(*args):
        nonlocal folder
        folder = _folder()
        if folder is None or jax.process_count() > 1:
            return jitted(*args)
        return program_for(args)(*args)

    def ahead(*abstract):
        """Compile for arguments of these shapes (``jax.ShapeDtypeStruct`` trees, their
        shardings those the call's arguments will have), running nothing."""
        nonlocal folder
        folder = _folder()
        target = jitted if folder is None or jax.process_count() > 1 else program_for(abstract)
        target.lower(*abstract).compile()

    folder = None
    call.ahead = ahead
    return call
