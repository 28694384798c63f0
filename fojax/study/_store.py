"""The resumable store of a Monte Carlo run: one ``.npz`` per finished range of draws.

A file holds draws ``[first, stop)`` of one run (status, per-draw metrics and the
snapshots of those of its draws below the run's ``keep``); the folder's
``manifest.json`` holds the run's fingerprint (:func:`fojax.study.fingerprint`: every
setting a draw's numbers depend on, and nothing else). Since draw ``i``'s numbers do not
depend on the draw count, the chunking or the devices (:mod:`fojax.study`), a store
serves any run with the same fingerprint: a longer run reuses the draws already there,
a run with another chunk size or on other devices reads them as they are.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from fojax import records, simulator
from fojax.controllers.base import ControlInfo

STORE_FORMAT = 2
"""Version of the store's layout (1: one file per fixed chunk, keyed by the chunk size
and ``keep`` too; 2: files per range of draws, keyed by what draw ``i`` depends on)."""

_FILE = re.compile(r"^draws_(\d{10})-(\d{10})\.npz$")


class StoreMismatch(ValueError):
    """The store holds draws of a run with other settings (the one error for it, of
    :func:`fojax.study.run` and of the commands' checks before they compile).

    directory: the store. differences: ``[(field, earlier, now), ...]``, the fingerprint
    fields (dotted paths) that differ, with the stored and the current value. stores:
    ``[(directory, differences), ...]``, every store that differs (default: the one);
    ``directory`` and ``differences`` are the first's. hint: ``hint(field)``, the option
    that sets a field, shown beside it; advice: the message's last line.
    """

    ADVICE = "remove that folder (or the run's chunks) to start afresh, or store this run elsewhere"

    def __init__(
        self,
        directory: str | os.PathLike,
        differences: list[tuple[str, Any, Any]],
        *,
        stores: list | None = None,
        hint=lambda field: "",
        advice: str | None = None,
    ):
        self.stores = [(Path(d), list(x)) for d, x in (stores or [(directory, differences)])]
        self.directory, self.differences = self.stores[0]
        text = "\n".join(
            f"{store} holds draws of a run with other settings; it differs in:\n  "
            + "\n  ".join(records.describe(found, hint))
            for store, found in self.stores
        )
        super().__init__(f"{text}\n{advice or self.ADVICE}")


def manifest_differences(directory: str | os.PathLike, fingerprint: dict) -> list | None:
    """``[(field, earlier, now), ...]`` where ``fingerprint`` (without the store's
    format, which is added) differs from the one of the draws in ``directory``: ``[]``
    the same settings, None nothing stored there. A manifest of the first format
    (no ``store_format``) is named as such; one that cannot be read, or holds no
    settings, is one difference saying so."""
    manifest = Path(directory) / "manifest.json"
    if not manifest.is_file():
        return None
    try:
        stored = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return [("manifest.json", "cannot be read", "readable")]
    if not isinstance(stored, dict) or not isinstance(stored.get("fingerprint"), dict):
        return [("manifest.json", "no settings", "settings")]
    current = _keyed(fingerprint)
    key = records.digest(current)
    if stored.get("key") == key:
        return []
    earlier = {"store_format": 1, **stored["fingerprint"]}
    found = records.differences(earlier, current)
    return found or [("key", stored.get("key"), key)]  # same settings, other hashing


def _keyed(fingerprint: dict) -> dict:
    """The fingerprint a store keeps: the run's, with the store's format."""
    return {"store_format": STORE_FORMAT, **records.canonical(fingerprint)}


class StoredRange(NamedTuple):
    """A file of the store: draws ``[first, stop)``, snapshots of ``[first, first + kept)``."""

    first: int
    stop: int
    kept: int
    path: Path


class ChunkStore:
    """Files of finished draws under ``directory``, keyed by a fingerprint.

    Opening a folder whose manifest holds another fingerprint raises
    :class:`StoreMismatch` naming the fields that differ. ``writable=False``: read only
    (the other processes of a distributed run); nothing is created.
    """

    def __init__(self, directory: str | os.PathLike, fingerprint: dict, writable: bool = True):
        self.directory = Path(directory)
        self.fingerprint = _keyed(fingerprint)
        self.key = records.digest(self.fingerprint)
        self.writable = writable
        found = manifest_differences(self.directory, fingerprint)
        if found:
            raise StoreMismatch(self.directory, found)
        if found is None and writable:
            document = {"key": self.key, "fingerprint": self.fingerprint}
            records.write_json(self.directory / "manifest.json", document)

    @classmethod
    def existing(cls, directory: str | os.PathLike) -> ChunkStore | None:
        """The store in ``directory`` as it is, read only, under its manifest's own
        fingerprint; None where there is no store yet."""
        try:
            stored = json.loads((Path(directory) / "manifest.json").read_text())
        except (OSError, ValueError):
            return None
        return cls(directory, stored.get("fingerprint", {}), writable=False)

    def read(self, draws: int) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
        """``(status (draws,), per-draw metrics)`` of draws ``[0, draws)`` where the
        store holds them all; None where any is missing."""
        if not isinstance(draws, int) or draws < 1:
            raise ValueError(f"draws must be an integer >= 1, got {draws!r}")
        segments = plan(self.ranges(), draws, keep=0)
        if any(kind != "load" for kind, *_ in segments):
            return None
        parts = [self.load(item, first, stop)[:2] for _, first, stop, item in segments]
        status = np.concatenate([s for s, _ in parts])
        return status, {k: np.concatenate([m[k] for _, m in parts]) for k in parts[0][1]}

    # ---------------------------------------------------------------------- reading
    def ranges(self) -> list[StoredRange]:
        """The finished ranges, sorted by their first draw."""
        if not self.directory.is_dir():
            return []
        found = []
        for path in self.directory.iterdir():
            match = _FILE.match(path.name)
            if not match:
                continue
            first, stop = int(match.group(1)), int(match.group(2))
            try:
                with np.load(path) as data:
                    kept = int(data["s.time"].shape[0]) if "s.time" in data.files else 0
                    if data["status"].shape != (stop - first,):
                        continue  # not written by this store
            except (OSError, ValueError, KeyError):
                continue  # unreadable (a partial copy): computed again
            found.append(StoredRange(first, stop, kept, path))
        return sorted(found)

    def load(self, stored: StoredRange, first: int, stop: int):
        """Draws ``[first, stop)`` (within ``stored``): ``(status, per_draw, snapshots)``;
        snapshots cover the file's kept draws within the range (None: none)."""
        lo, hi = first - stored.first, stop - stored.first
        with np.load(stored.path) as data:
            status = data["status"][lo:hi]
            per_draw = {k[2:]: data[k][lo:hi] for k in data.files if k.startswith("m.")}
            snaps = {k[2:]: data[k][lo:hi] for k in data.files if k.startswith("s.")}
        if not snaps or next(iter(snaps.values())).shape[0] == 0:
            snaps = None
        return status, per_draw, snaps

    # ---------------------------------------------------------------------- writing
    def save(self, first: int, status, per_draw, snapshots) -> Path:
        """Store draws ``[first, first + len(status))``; ``snapshots`` (or None) hold
        the first of them. Files wholly inside the new range are removed."""
        stop = first + int(np.shape(status)[0])
        arrays = {"status": np.asarray(status)}
        arrays.update({f"m.{k}": np.asarray(v) for k, v in per_draw.items()})
        if snapshots is not None:
            arrays.update({f"s.{k}": np.asarray(v) for k, v in snapshots.items()})
        path = self.directory / f"draws_{first:010d}-{stop:010d}.npz"
        records.write_npz(path, arrays, compress=False)
        for other in self.ranges():
            if other.path != path and first <= other.first and other.stop <= stop:
                other.path.unlink(missing_ok=True)
        return path


def plan(
    stored: list[StoredRange], draws: int, keep: int
) -> list[tuple[str, int, int, StoredRange | None]]:
    """How to obtain draws ``[0, draws)``: segments ``("load", first, stop, file)`` and
    ``("compute", first, stop, None)`` in order, covering it exactly.

    A stored draw ``i`` is usable when the file has its snapshot or ``i >= keep``; where
    files overlap, the one reaching furthest is read.
    """
    usable: list[tuple[int, int, StoredRange]] = []
    for item in stored:
        parts = [(item.first, min(item.stop, item.first + item.kept))]
        parts.append((max(item.first, keep), item.stop))
        for a, b in parts:
            a, b = max(a, 0), min(b, draws)
            if a < b:
                usable.append((a, b, item))
    segments: list[tuple[str, int, int, StoredRange | None]] = []
    position = 0
    while position < draws:
        covering = [u for u in usable if u[0] <= position < u[1]]
        if covering:
            _, stop, item = max(covering, key=lambda u: u[1])
            # adjacent segments from the same file: one
            start = segments.pop()[1] if segments and segments[-1][3] is item else position
            segments.append(("load", start, stop, item))
        else:
            stop = min((u[0] for u in usable if u[0] > position), default=draws)
            segments.append(("compute", position, stop, None))
        position = stop
    return segments


def flatten_snapshot(snapshot) -> dict[str, np.ndarray]:
    leaves = {k: v for k, v in snapshot._asdict().items() if k != "info"}
    leaves.update({f"info.{k}": v for k, v in snapshot.info._asdict().items()})
    return {k: np.asarray(v) for k, v in leaves.items()}


def unflatten_snapshot(flat: dict[str, np.ndarray]) -> simulator.Snapshot:
    info = ControlInfo(**{k[5:]: v for k, v in flat.items() if k.startswith("info.")})
    fields = [k for k in simulator.Snapshot._fields if k != "info"]
    return simulator.Snapshot(info=info, **{k: flat[k] for k in fields})
