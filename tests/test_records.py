"""fojax.records: atomic writes, digests, fingerprint differences and cached records,
the one place fojax writes and keys its results."""

import hashlib
import json
import os
import threading

import numpy as np
import pytest

from fojax import records, study
from fojax.cli import output


def test_writes_are_whole_and_leave_no_temporary_files(tmp_path):
    path = records.write_json(tmp_path / "a" / "b.json", {"x": (1, 2), "y": np.float64(0.5)})
    assert json.loads(path.read_text()) == {"x": [1, 2], "y": 0.5}
    records.write_npz(tmp_path / "c.npz", {"z": np.arange(3)}, compress=False)
    with np.load(tmp_path / "c.npz") as data:
        np.testing.assert_array_equal(data["z"], np.arange(3))
    rows = [{"a": np.float64(0.1), "b": None, "c": 3}]
    records.write_csv(tmp_path / "d.csv", rows)
    assert (tmp_path / "d.csv").read_text() == "a,b,c\n0.1,,3\n"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b.json", "c.npz", "d.csv"]
    # The commands' writers are these ones.
    assert output.write_json is records.write_json and output.write_csv is records.write_csv


def test_concurrent_writers_of_one_file_do_not_collide(tmp_path):
    path = tmp_path / "shared.bin"
    errors = []

    def write(value: int):
        try:
            for _ in range(20):
                records.atomic_write(path, bytes([value]) * 100_000)
        except Exception as error:  # pragma: no cover - what the test looks for
            errors.append(error)

    threads = [threading.Thread(target=write, args=(v,)) for v in (1, 2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    assert len(set(path.read_bytes())) == 1 and os.listdir(tmp_path) == ["shared.bin"]


def test_digest_is_the_stores_key():
    """Stores keep the key they had: SHA-256 of the canonical JSON, 16 digits."""
    document = {"b": (1, 2.5), "a": {"c": np.int64(3)}}
    text = json.dumps(json.loads(json.dumps(document, sort_keys=True, default=str)), sort_keys=True)
    assert records.digest(document) == hashlib.sha256(text.encode()).hexdigest()[:16]
    assert records.digest(b"abc", 8) == hashlib.sha256(b"abc").hexdigest()[:8]


def test_source_digest_follows_every_root(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    for root in (one, two):
        (root / "sub").mkdir(parents=True)
        (root / "sub" / "m.py").write_text("x = 1\n")
    before = records.source_digest(one, two)
    (two / "sub" / "m.py").write_text("x = 2\n")
    assert records.source_digest(one, two) != before
    assert records.source_digest(one) == records.source_digest(one)
    roots = records.source_roots()
    assert [r.name for r in roots] == ["fojax", "optimize"]
    assert records.code_digest() == records.source_digest(*roots)


def test_differences_are_named_field_by_field():
    assert study.fingerprint_differences is records.differences
    assert study.describe_differences is records.describe
    found = records.differences({"a": {"b": 1}, "c": 2}, {"a": {"b": 2}, "d": 3})
    assert found == [("a.b", 1, 2), ("c", 2, records.ABSENT), ("d", records.ABSENT, 3)]
    assert records.describe(found[:1], lambda f: "--b") == ["a.b (--b): earlier 1, now 2"]
    with pytest.raises(ValueError, match="a.b: earlier 1, now 2"):
        records.check({"a": {"b": 1}}, {"a": {"b": 2}}, "the checkpoint")
    records.check({"a": (1,)}, {"a": [1]}, "the checkpoint")


def test_a_record_is_computed_once_per_fingerprint(tmp_path):
    calls = []

    def compute():
        calls.append(1)
        return {"value": len(calls)}

    assert records.cached(tmp_path, "run", {"seed": 1}, compute) == {"value": 1}
    assert records.cached(tmp_path, "run", {"seed": 1}, compute) == {"value": 1}
    assert records.cached(tmp_path, "run", {"seed": 2}, compute) == {"value": 2}
    assert records.stored(tmp_path, "run", {"seed": 3}) is None
    assert len(list(tmp_path.glob("run-*.json"))) == 2


def test_a_record_of_other_code_is_computed_again(tmp_path):
    calls = []

    def compute():
        calls.append(1)
        return {"value": len(calls)}

    assert records.cached(tmp_path, "run", {"seed": 1}, compute, code="old") == {"value": 1}
    assert records.stored(tmp_path, "run", {"seed": 1}, code="old") == {"value": 1}
    assert records.stored(tmp_path, "run", {"seed": 1}, code="new") is None
    assert records.stored(tmp_path, "run", {"seed": 1}) is None  # default: fojax's source
    assert records.cached(tmp_path, "run", {"seed": 1}, compute, code="new") == {"value": 2}
    assert records.stored(tmp_path, "run", {"seed": 1}, code="old") is None  # replaced
    assert len(list(tmp_path.glob("run-*.json"))) == 1


def test_manifest_differences_before_anything_runs(tmp_path):
    fingerprint = {"seed": 3, "dtype": "float64"}
    assert study.manifest_differences(tmp_path, fingerprint) is None
    study.ChunkStore(tmp_path, fingerprint)
    assert study.manifest_differences(tmp_path, fingerprint) == []
    assert study.manifest_differences(tmp_path, {**fingerprint, "seed": 4}) == [("seed", 3, 4)]
    (tmp_path / "manifest.json").write_text("{")
    found = study.manifest_differences(tmp_path, fingerprint)
    assert found == [("manifest.json", "cannot be read", "readable")]
    with pytest.raises(study.StoreMismatch, match="cannot be read"):
        study.ChunkStore(tmp_path, fingerprint)
