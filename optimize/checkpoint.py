"""The gradient tuner's checkpoint (:mod:`fojax.optimize.tuner`): what a run must agree
on to be resumed (:func:`fingerprint`, compared field by field), the state and the
counters in ``checkpoint.npz`` and the history in ``history.csv``, each written
atomically (a temporary file, then ``os.replace``)."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fojax.controllers import gains_io
from fojax.study import describe_differences, fingerprint_differences

FORMAT = 2
HISTORY_COLUMNS = (
    "step",
    "objective",
    "mean_cost",
    "max_cost",
    "grad_norm",
    "learning_rate",
    "width_scale",
    "diverged",
    "bad_gradients",
    "draw_steps",
    "wall_time_s",
    "validation_cost",
    "best_step",
    "accepted",
)
"""Columns of ``history.csv``, one row per step. ``validation_cost``: the mean cost on
the validation draws after this step (empty where the step was not validated);
``best_step``: the step whose gains are the best validated so far (0: the start);
``accepted``: 1 when the step moved the iterate (always for Adam; L-BFGS rejects a
trial without sufficient decrease). For L-BFGS, ``objective`` is the trial point's and
``learning_rate`` the trial's step length along its direction."""


def fingerprint(spec, config, init_label: str, init_gains) -> dict:
    """Everything a checkpoint must agree on to be resumed."""
    return {
        "format": FORMAT,
        "problem": spec.as_dict(),
        "tuner": dataclasses.asdict(config),
        "init": init_label,
        "init_gains": gains_io.gains_to_dict(
            type(init_gains)(*(np.asarray(g, np.float64) for g in init_gains))
        ),
    }


def _canonical(document: Any) -> Any:
    """JSON round trip, so that tuples and lists compare equal."""
    return json.loads(json.dumps(document))


# ---------------------------------------------------------------------- checkpoint io


def _write_atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def _save_checkpoint(path: Path, state: tuple, meta: dict) -> None:
    leaves = jax.tree.leaves(state)
    arrays = {f"leaf_{i:05d}": np.asarray(leaf) for i, leaf in enumerate(leaves)}
    arrays["meta"] = np.asarray(json.dumps(meta))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    _write_atomic_bytes(path, buffer.getvalue())


def _read_meta(path: Path) -> dict:
    try:
        with np.load(path) as data:
            return json.loads(str(data["meta"]))
    except (OSError, KeyError, ValueError) as error:
        raise ValueError(f"{path} is not a fojax tune checkpoint ({error})") from None


def _load_state(path: Path, template: tuple) -> tuple:
    leaves, treedef = jax.tree.flatten(template)
    with np.load(path) as data:
        names = sorted(k for k in data.files if k.startswith("leaf_"))
        if len(names) != len(leaves):
            raise ValueError(
                f"{path} holds {len(names)} arrays, this run needs {len(leaves)}: it was "
                "written by another configuration"
            )
        loaded = []
        for name, leaf in zip(names, leaves, strict=True):
            value = data[name]
            if value.shape != np.shape(leaf) or value.dtype != np.asarray(leaf).dtype:
                raise ValueError(
                    f"{path}: array {name} has shape {value.shape} {value.dtype}, this run "
                    f"needs {np.shape(leaf)} {np.asarray(leaf).dtype}"
                )
            loaded.append(jnp.asarray(value))
    return jax.tree.unflatten(treedef, loaded)


def write_history(path: Path, history: list[dict]) -> None:
    """``history.csv`` (atomically): one row per step, :data:`HISTORY_COLUMNS`."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=HISTORY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in history:
        writer.writerow(
            {
                k: ("" if v is None else repr(v) if isinstance(v, float) else v)
                for k, v in row.items()
            }
        )
    _write_atomic_bytes(path, buffer.getvalue().encode())


def check_checkpoint(path: Path, fingerprint: dict | None) -> None:
    """``ValueError`` naming the settings that differ when the checkpoint ``path`` (of
    :func:`fojax.optimize.constrained.minimize`) was written with another ``fingerprint``."""
    stored = _read_meta(path).get("fingerprint") or {}
    differences = describe_differences(
        fingerprint_differences(stored, fingerprint or {}), earlier="checkpoint"
    )
    if differences:
        raise ValueError(
            f"{path} was written by another configuration; it differs in:\n  "
            + "\n  ".join(differences)
            + "\nrerun with the original options, or choose another --out"
        )
