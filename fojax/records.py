"""Run records: how every result, checkpoint and cache of fojax is written and keyed.

* :func:`atomic_write`: a file written whole or not at all (a temporary file beside it,
  flushed, then ``os.replace``): a run stopped while writing leaves the old file or the
  new one, never half of one. :func:`write_json`, :func:`write_npz`, :func:`write_csv`,
  :func:`write_arrays` are it for JSON, compressed NumPy archives, CSV rows, and arrays
  with a JSON header.
* :func:`digest`: hex digits of SHA-256 naming a JSON-ready document or bytes;
  :func:`source_digest`: the same over a package's ``*.py`` files (caches that must not
  outlive the code that filled them); :func:`code_digest`: that of fojax's whole source
  (``fojax/`` and ``fojax.optimize``), the one code key of stored draws and programs.
* A *fingerprint* is a JSON-ready dict of every setting a result depends on, and nothing
  else. :func:`differences` lists the fields in which two differ (dotted paths),
  :func:`describe` says them one per line, :func:`check` raises a ``ValueError`` that
  names them.
* :func:`cached`: a record computed once and kept under its fingerprint
  (``folder/<stem>-<digest>.json``) and the digest of the code that computed it;
  :func:`stored` reads it back, and neither returns a record of other code.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import io
import json
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "ABSENT",
    "atomic_write",
    "cached",
    "canonical",
    "check",
    "code_digest",
    "describe",
    "differences",
    "digest",
    "read_arrays",
    "source_digest",
    "source_roots",
    "stored",
    "write_arrays",
    "write_csv",
    "write_json",
    "write_npz",
]

ABSENT = "<absent>"
"""What :func:`differences` reports for a field that one side does not have."""


# ------------------------------------------------------------------------- writing


def atomic_write(path: str | os.PathLike, data: bytes | str) -> Path:
    """``path`` holding ``data`` (text is UTF-8), written atomically; parents created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # One temporary name per process and thread: two writers of one file (e.g. two
    # processes exporting the same program) never write into each other's.
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{threading.get_ident()}.tmp")
    try:
        with open(tmp, "wb") as handle:
            handle.write(data.encode() if isinstance(data, str) else data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_json(path: str | os.PathLike, document: Any, default=str, indent: int = 1) -> Path:
    """``path`` holding ``document`` (indented JSON and a newline), atomically;
    ``default``: what stands for a value JSON has no type for (``str(value)``)."""
    return atomic_write(path, json.dumps(document, indent=indent, default=default) + "\n")


def write_npz(path: str | os.PathLike, arrays: dict, compress: bool = True) -> Path:
    """``path`` holding ``arrays`` (a ``.npz``, compressed unless not ``compress``),
    atomically."""
    import numpy as np

    buffer = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buffer, **arrays)
    return atomic_write(path, buffer.getvalue())


def write_csv(path: str | os.PathLike, rows: list[dict], columns=None) -> Path:
    """``path`` holding ``rows`` under a header (``columns``, default the first row's
    keys; a float, NumPy's too, as its ``repr``, ``None`` as an empty cell), atomically."""
    import csv

    buffer = io.StringIO()
    columns = list(columns if columns is not None else (rows[0] if rows else []))
    writer = csv.DictWriter(buffer, fieldnames=columns, lineterminator="\n")
    if columns:
        writer.writeheader()
    writer.writerows({k: _cell(v) for k, v in row.items()} for row in rows)
    return atomic_write(path, buffer.getvalue())


def _cell(value: Any) -> Any:
    """A CSV cell of :func:`write_csv`: ``None`` empty, a float as its ``repr``."""
    if value is None:
        return ""
    return repr(float(value)) if isinstance(value, float) else value


def write_arrays(path: str | os.PathLike, arrays: list, header: dict) -> Path:
    """``path`` (``.npz``) holding the arrays ``arrays`` in order and the JSON-ready
    ``header``, atomically (:func:`read_arrays` reads them back, exactly)."""
    import numpy as np

    named = {f"a{i:05d}": np.asarray(a) for i, a in enumerate(arrays)}
    return write_npz(path, {"header": np.asarray(json.dumps(header)), **named}, compress=False)


def read_arrays(path: str | os.PathLike) -> tuple[list, dict]:
    """``(arrays, header)`` of a file of :func:`write_arrays`; ``ValueError`` when
    ``path`` is not one."""
    import numpy as np

    try:
        with np.load(path) as data:
            header = json.loads(str(data["header"]))
            arrays = [data[k] for k in sorted(k for k in data.files if k != "header")]
    except (OSError, KeyError, ValueError) as error:
        raise ValueError(f"{path} cannot be read back ({error})") from None
    return arrays, header


# ------------------------------------------------------------------------- naming


def canonical(document: Any) -> Any:
    """``document`` JSON-normalised: tuples as lists, keys sorted, NumPy scalars and
    other values as JSON has them (``str`` where it has no type)."""
    return json.loads(json.dumps(document, sort_keys=True, default=str))


def digest(document: Any, length: int = 16) -> str:
    """``length`` hex digits of SHA-256 of ``document``: bytes as they are, anything
    else as its canonical JSON (:func:`canonical`, keys sorted)."""
    if not isinstance(document, bytes | bytearray):
        document = json.dumps(canonical(document), sort_keys=True).encode()
    return hashlib.sha256(document).hexdigest()[:length]


def source_digest(*roots: str | os.PathLike) -> str:
    """16 hex digits of SHA-256 over every ``*.py`` below each of ``roots`` (its name,
    the relative paths and the contents, in sorted order)."""
    hashed = hashlib.sha256()
    for root in map(Path, roots):
        hashed.update(root.name.encode())
        for path in sorted(root.rglob("*.py")):
            hashed.update(path.relative_to(root).as_posix().encode())
            hashed.update(path.read_bytes())
    return hashed.hexdigest()[:16]


def source_roots() -> tuple[Path, Path]:
    """The folders of fojax's source: ``fojax/`` and ``fojax.optimize`` (installed from
    ``optimize/``, beside it), found without importing the latter."""
    spec = importlib.util.find_spec("fojax.optimize")
    optimize = Path(next(iter(spec.submodule_search_locations)))
    return Path(__file__).resolve().parent, optimize.resolve()


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """:func:`source_digest` of fojax's whole source (:func:`source_roots`), once per
    process: what stored draws and exported programs are keyed by, so that none is
    reused by other code (a changed default changes numbers, not settings)."""
    return source_digest(*source_roots())


# -------------------------------------------------------------------- fingerprints


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for key in value:
            out.update(_flatten(value[key], f"{prefix}.{key}" if prefix else str(key)))
        return out
    return {prefix: value}


def differences(stored: dict, current: dict) -> list[tuple[str, Any, Any]]:
    """``[(field, stored value, current value)]`` for every leaf that differs (dotted
    paths; :data:`ABSENT` where a field exists on one side only), sorted by field."""
    old, new = _flatten(canonical(stored)), _flatten(canonical(current))
    return [
        (field, old.get(field, ABSENT), new.get(field, ABSENT))
        for field in sorted(set(old) | set(new))
        if old.get(field, ABSENT) != new.get(field, ABSENT)
    ]


def _short(value: Any, width: int = 60) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= width else text[: width - 3] + "..."


def describe(
    found: list[tuple[str, Any, Any]], hint=lambda field: "", earlier: str = "earlier"
) -> list[str]:
    """One line per difference: ``field (hint): earlier X, now Y`` (``earlier``: what
    the stored side is called; ``hint(field)``: e.g. the option that sets it)."""
    return [
        f"{field}{f' ({extra})' if (extra := hint(field)) else ''}: {earlier} {_short(old)}, "
        f"now {_short(new)}"
        for field, old, new in found
    ]


def check(
    stored: dict,
    current: dict,
    what: str,
    advice: str = "rerun with the original options, or choose another --out",
    earlier: str = "earlier",
) -> None:
    """``ValueError`` naming every field in which ``stored`` differs from ``current``:
    ``"<what> was written by another configuration; it differs in: ..."``."""
    found = differences(stored, current)
    if found:
        raise ValueError(
            f"{what} was written by another configuration; it differs in:\n  "
            + "\n  ".join(describe(found, earlier=earlier))
            + f"\n{advice}"
        )


# ------------------------------------------------------------------------- records


def _record_path(folder: str | os.PathLike, stem: str, fingerprint: Any) -> Path:
    return Path(folder) / f"{stem}-{digest(fingerprint, 10)}.json"


def stored(
    folder: str | os.PathLike,
    stem: str,
    fingerprint: Any,
    code: str | None = None,
    any_code: bool = False,
) -> dict | None:
    """The record :func:`cached` keeps for ``stem`` and ``fingerprint``, or ``None``
    (also where it was computed by other code: ``code``, default :func:`code_digest`,
    unless ``any_code``: a study that checks for itself that the code it depends on
    returns the same, :mod:`experiments.tuning_study`'s ``--carry``)."""
    path = _record_path(folder, stem, fingerprint)
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    kept, kept_code = record.pop("fingerprint", None), record.pop("code", None)
    same_code = any_code or kept_code == (code_digest() if code is None else code)
    return record if same_code and (kept is None or not differences(kept, fingerprint)) else None


def cached(
    folder: str | os.PathLike,
    stem: str,
    fingerprint: Any,
    compute: Callable[[], dict],
    code: str | None = None,
):
    """A run computed once: ``folder/<stem>-<digest of fingerprint>.json`` holds the
    record ``compute()`` returned, with ``fingerprint`` and ``code`` beside it. A later
    call with the same fingerprint and code reads it back; other settings are another
    file, so runs of several settings share a folder and none is reused for settings it
    was not made with. ``code`` (default :func:`code_digest`, fojax's source; a study
    adds its own, :func:`source_digest`): a record computed by other code is computed
    again and replaced, so no number outlives the code that made it. Written
    atomically: an interrupted study loses only the run in progress."""
    code = code_digest() if code is None else code
    record = stored(folder, stem, fingerprint, code)
    if record is None:
        record = compute()
        document = {**record, "fingerprint": fingerprint, "code": code}
        write_json(_record_path(folder, stem, fingerprint), document)
    return record
