"""The resumable chunk store of a Monte Carlo run: one ``.npz`` per finished chunk."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from fojax import simulator
from fojax.controllers.base import ControlInfo


def _fingerprint_hash(fingerprint: dict) -> str:
    text = json.dumps(fingerprint, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class ChunkStore:
    """One ``.npz`` per finished chunk under ``directory``, keyed by a fingerprint."""

    def __init__(self, directory: Path, fingerprint: dict):
        self.directory = Path(directory)
        self.key = _fingerprint_hash(fingerprint)
        manifest = self.directory / "manifest.json"
        if manifest.exists():
            stored = json.loads(manifest.read_text())
            if stored.get("key") != self.key:
                raise ValueError(
                    f"{self.directory} holds chunks of a run with other settings "
                    f"({stored.get('fingerprint')}); remove it or choose another output "
                    "directory"
                )
        else:
            self.directory.mkdir(parents=True, exist_ok=True)
            tmp = manifest.with_suffix(".tmp")
            tmp.write_text(
                json.dumps({"key": self.key, "fingerprint": fingerprint}, indent=1, default=str)
            )
            os.replace(tmp, manifest)

    def _path(self, first: int) -> Path:
        return self.directory / f"chunk_{first:07d}.npz"

    def load(self, first: int):
        path = self._path(first)
        if not path.exists():
            return None
        with np.load(path) as data:
            status = data["status"]
            per_draw = {k[2:]: data[k] for k in data.files if k.startswith("m.")}
            snaps = {k[2:]: data[k] for k in data.files if k.startswith("s.")}
        return status, per_draw, snaps or None

    def save(self, first: int, status, per_draw, snapshots) -> None:
        arrays = {"status": status}
        arrays.update({f"m.{k}": v for k, v in per_draw.items()})
        if snapshots is not None:
            arrays.update({f"s.{k}": v for k, v in snapshots.items()})
        path = self._path(first)
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)


def flatten_snapshot(snapshot) -> dict[str, np.ndarray]:
    leaves = {
        "time": snapshot.time,
        "state": snapshot.state,
        "reference": snapshot.reference,
        "inputs": snapshot.inputs,
        "inputs_low": snapshot.inputs_low,
        "inputs_high": snapshot.inputs_high,
    }
    leaves.update({f"info.{k}": v for k, v in snapshot.info._asdict().items()})
    return {k: np.asarray(v) for k, v in leaves.items()}


def unflatten_snapshot(flat: dict[str, np.ndarray]) -> simulator.Snapshot:
    info = ControlInfo(**{k[5:]: v for k, v in flat.items() if k.startswith("info.")})
    return simulator.Snapshot(
        time=flat["time"],
        state=flat["state"],
        reference=flat["reference"],
        inputs=flat["inputs"],
        info=info,
        inputs_low=flat["inputs_low"],
        inputs_high=flat["inputs_high"],
    )
