"""The checkpoint of :func:`fojax.optimize.constrained.minimize`: its state after an
outer iteration (the iterate, the selected iterate, the multipliers ``lam`` as arrays;
``rho``, the scale, the history and the selection as JSON), written atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def plain(value):
    """JSON for NumPy scalars and arrays (the history's validation counts)."""
    return value.tolist() if hasattr(value, "tolist") else str(value)


def save(path: Path, state: dict, params: Any, best_params: Any, lam: Any) -> None:
    """Writes ``state`` (JSON-ready but for NumPy scalars) and the arrays to ``path``."""
    arrays = {f"params_{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(params))}
    arrays |= {f"best_{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(best_params))}
    arrays |= {"lam": np.asarray(lam), "state": np.asarray(json.dumps(state, default=plain))}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.partial.npz")
    np.savez(temporary, **arrays)
    os.replace(temporary, path)


def load(path: Path, like: Any, fingerprint: dict | None):
    """``(state, params, best_params, lam)`` of the checkpoint ``path`` (the parameters
    shaped as ``like``), or None when there is none; a ``ValueError`` when it was
    written with another ``fingerprint``."""
    path = Path(path)
    if not path.is_file():
        return None
    with np.load(path) as stored:
        state = json.loads(str(stored["state"]))
        treedef = jax.tree.structure(like)
        leaves = [jnp.asarray(stored[f"params_{i}"]) for i in range(treedef.num_leaves)]
        best = [jnp.asarray(stored[f"best_{i}"]) for i in range(treedef.num_leaves)]
        lam = jnp.asarray(stored["lam"])
    _compare(path, state.pop("fingerprint", None), fingerprint)
    return state, jax.tree.unflatten(treedef, leaves), jax.tree.unflatten(treedef, best), lam


def check(path: Path, fingerprint: dict | None) -> None:
    """``ValueError`` naming the settings that differ when the checkpoint ``path`` was
    written with another ``fingerprint``."""
    with np.load(path) as stored:
        saved = json.loads(str(stored["state"])).get("fingerprint")
    _compare(path, saved, fingerprint)


def _compare(path, saved: dict | None, fingerprint: dict | None) -> None:
    saved = saved or {}
    now = json.loads(json.dumps(fingerprint or {}, default=plain))
    differing = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
    if differing:
        raise ValueError(
            f"{path} was written by a run with other settings ({', '.join(differing)}); "
            "rerun with the original options, or choose another --out"
        )
