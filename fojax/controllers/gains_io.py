"""Gains files: JSON that ``fojax simulate --gains`` reads and ``fojax tune`` writes.

Format::

    {
      "controller": "afonftsmc",
      "gains": {"surface_c1": [0.1797, 0.1797, 4.4265, 35.5118, 35.5118, 35.5118], ...},
      "metadata": {...}            # optional, free-form (how the gains were obtained)
    }

Each entry of ``"gains"`` is one field of the controller's gains (its
:class:`fojax.controllers.GainSpec`); its value is a number (applied to every
component) or a nested list of the field's exact shape. Every field must be present,
no other may be, and every value must be a finite number. The declared bounds of each
field apply on top. ``"metadata"``, when present, is a JSON object. :func:`save_gains`
checks the same before writing.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from fojax import records
from fojax.controllers import registry

__all__ = ["gains_from_dict", "gains_to_dict", "load_gains", "save_gains"]

FORMAT_KEYS = {"controller", "gains", "metadata"}


def gains_to_dict(gains) -> dict[str, Any]:
    """Gains NamedTuple -> ``{field: nested list}``."""
    return {name: np.asarray(value).tolist() for name, value in gains._asdict().items()}


def _numeric(name: str, value: Any, source: str) -> np.ndarray:
    def check(v):
        if isinstance(v, list | tuple):
            for item in v:
                check(item)
            return
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ValueError(f"{source}: entry {name!r} must be numeric, got {v!r}")
        if not math.isfinite(v):
            raise ValueError(f"{source}: entry {name!r} must be finite, got {v!r}")

    check(value)
    try:
        return np.asarray(value, dtype=np.float64)
    except ValueError:
        raise ValueError(f"{source}: entry {name!r} is a ragged list: {value!r}") from None


def gains_from_dict(controller: str, data: dict, source: str = "gains", dtype: Any = None):
    """Validated gains of ``controller`` from ``{field: value}``.

    Raises ``ValueError`` naming every missing, extra or malformed entry, then the
    controller's constraint violations.
    """
    cls = registry.get_controller_class(controller)
    template = cls.default_gains(dtype)
    if not isinstance(data, dict):
        raise ValueError(f"{source}: gains must be a JSON object, got {type(data).__name__}")
    fields = list(template._fields)
    missing = [f for f in fields if f not in data]
    extra = sorted(set(data) - set(fields))
    problems = []
    if missing:
        problems.append(f"missing entries: {', '.join(missing)}")
    if extra:
        problems.append(f"unknown entries: {', '.join(extra)} (valid: {', '.join(fields)})")
    if problems:
        raise ValueError(f"{source}: " + "; ".join(problems))
    values = {}
    for name in fields:
        expected = np.shape(getattr(template, name))
        array = _numeric(name, data[name], source)
        if array.ndim == 0:
            array = np.broadcast_to(array, expected)
        if array.shape != expected:
            raise ValueError(
                f"{source}: entry {name!r} must be a number or have shape {expected}, "
                f"got shape {array.shape}"
            )
        values[name] = jnp.asarray(array, dtype=getattr(template, name).dtype)
    gains = template._replace(**values)
    try:
        cls.check_gains(gains)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from None
    return gains


def save_gains(path: str | os.PathLike, controller: str, gains, metadata: dict | None = None):
    """Write ``gains`` of ``controller`` to ``path`` (atomically).

    The gains are checked against the controller's declaration first, so that a file
    is never written that :func:`load_gains` would refuse (another controller's gains,
    a value out of bounds): ``ValueError`` naming the problem. ``metadata``: a dict (or
    None), written as the file's ``"metadata"``.
    """
    cls = registry.get_controller_class(controller)
    try:
        cls.check_gains(gains)
    except ValueError as error:
        raise ValueError(f"cannot save these gains as {controller!r} gains: {error}") from None
    if metadata is not None and not isinstance(metadata, dict):
        raise ValueError(
            f"metadata must be a dict (or None), got {type(metadata).__name__}: {metadata!r}"
        )
    path = Path(path)
    document = {"controller": controller, "gains": gains_to_dict(gains)}
    if metadata:
        document["metadata"] = metadata
    records.atomic_write(path, json.dumps(document, indent=2) + "\n")


def load_gains(path: str | os.PathLike, dtype: Any = None) -> tuple[str, Any, dict]:
    """Read a gains file: ``(controller name, gains, metadata)``, validated."""
    path = Path(path)
    source = str(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ValueError(f"gains file {source} does not exist") from None
    except IsADirectoryError:
        raise ValueError(
            f"{source} is a folder, not a gains file; give the JSON file (e.g. "
            f"{Path(source) / 'gains.json'})"
        ) from None
    except PermissionError:
        raise ValueError(f"cannot read gains file {source} (permission denied)") from None
    except OSError as error:
        raise ValueError(f"cannot read gains file {source}: {error.strerror or error}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(
            f"{source} is not a gains file: not UTF-8 text ({error}); a gains file is "
            "JSON as fojax tune writes it"
        ) from None
    try:
        document = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{source} is not valid JSON: {error}") from None
    except RecursionError:
        raise ValueError(f"{source} is not a gains file: JSON nested too deeply") from None
    if not isinstance(document, dict):
        raise ValueError(f"{source}: expected a JSON object with 'controller' and 'gains'")
    unknown = sorted(set(document) - FORMAT_KEYS)
    missing = sorted({"controller", "gains"} - set(document))
    if missing or unknown:
        parts = []
        if missing:
            parts.append(f"missing keys {missing}")
        if unknown:
            parts.append(f"unknown keys {unknown}")
        raise ValueError(
            f"{source}: " + "; ".join(parts) + " (a gains file has 'controller', 'gains' "
            "and optionally 'metadata')"
        )
    controller = document["controller"]
    if not isinstance(controller, str):
        raise ValueError(f"{source}: 'controller' must be a name, got {controller!r}")
    try:
        registry.get_controller_class(controller)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from None
    metadata = document.get("metadata", {})
    if not isinstance(metadata, dict):
        raise ValueError(
            f"{source}: 'metadata' must be a JSON object (or left out), got "
            f"{type(metadata).__name__} {metadata!r}"
        )
    gains = gains_from_dict(controller, document["gains"], source, dtype)
    return controller, gains, metadata
