"""Bad input to every command ends in a message naming what to change, exit status 2,
no traceback, and nothing written or compiled: output folders and files, input files,
numbers (nan, inf, out of range), lists, controllers, seeds; a run whose settings
differ from the chunks already in its folder names only the fields that differ."""

import json
import os
import subprocess
import sys

import pytest
from conftest import usage_error

from fojax import cli
from fojax.cli import accuracy as fractional_accuracy
from fojax.cli import arguments, bench, simulate, study, tune

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0

SIM = ["--scenario", "2", "--controller", "afonftsmc", "--draws", "3", "--horizon", "0.2"]
TUNE = ["--scenario", "2", "--controller", "afonftsmc", "--steps", "1"]


@pytest.fixture
def places(tmp_path):
    """An existing file, a folder, a path under the file, a read-only folder."""
    file = tmp_path / "a_file.txt"
    file.write_text("not a folder")
    folder = tmp_path / "folder"
    folder.mkdir()
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    yield {"file": file, "folder": folder, "under": file / "sub", "locked": locked}
    locked.chmod(0o700)


# ----------------------------------------------------------------- shared argument types


@pytest.mark.parametrize(
    "kind, text, message",
    [
        ("int", "0", "positive integer"),
        ("int", "2.5", "positive integer"),
        ("int", "1e3", "write it as 1000"),
        ("int", "", "positive integer"),
        ("float", "nan", "finite number > 0"),
        ("float", "inf", "finite number > 0"),
        ("float", "-inf", "finite number > 0"),
        ("float", "0", "finite number > 0"),
        ("float", "ten", "finite number > 0"),
        ("seed", "-1", "integer >= 0"),
        ("seed", str(2**64), "<= 9223372036854775807"),
        ("ints", "1,,2", "comma-separated list"),
        ("ints", "1,x", "positive integer"),
        ("ints", "", "comma-separated list"),
        ("floats", "0.5,nan", "finite number > 0"),
    ],
)
def test_number_types_reject_with_a_reason(kind, text, message):
    convert = {
        "int": arguments.positive_int,
        "float": arguments.positive_float,
        "seed": arguments.seed,
        "ints": arguments.positive_ints,
        "floats": arguments.positive_floats,
    }[kind]
    with pytest.raises(Exception) as info:
        convert(text)
    assert message in str(info.value)


def test_path_types(places, tmp_path, monkeypatch):
    check_dir, check_file = arguments.check_output_directory, arguments.check_output_file
    for bad, message in (
        ("", "empty name"),
        ("   ", "empty name"),
        (str(places["file"]), "is a file, not a folder"),
        (str(places["under"]), "is a file; choose a folder that is not under a file"),
        (str(places["under"] / "deeper"), "is a file"),
        ("a\0b", "NUL"),
    ):
        with pytest.raises(ValueError) as info:
            check_dir(bad)
        assert message in str(info.value), (bad, info.value)
    assert check_dir(str(tmp_path / "new" / "deeper")) == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # nothing created
    assert check_dir("~").is_absolute()  # ~ expanded
    for bad, message in (
        ("", "empty name"),
        (str(places["folder"]), "is a folder; name a file"),
        (str(places["under"] / "x.json"), "is a file"),
    ):
        with pytest.raises(ValueError) as info:
            check_file(bad)
        assert message in str(info.value), (bad, info.value)
    for bad, message in (
        ("", "empty name"),
        (str(places["folder"]), "is a folder, not a gains file"),
        (str(tmp_path / "missing.json"), "does not exist"),
    ):
        with pytest.raises(ValueError) as info:
            arguments.check_input_file(bad, "gains file")
        assert message in str(info.value), (bad, info.value)
    # Without write permission (simulated: root may write anywhere).
    real_access = os.access
    monkeypatch.setattr(
        os,
        "access",
        lambda p, mode: False if str(p) == str(places["folder"]) else real_access(p, mode),
    )
    with pytest.raises(ValueError, match="permission denied"):
        check_dir(str(places["folder"]))
    with pytest.raises(ValueError, match="no permission to write in"):
        check_dir(str(places["folder"] / "new"))
    with pytest.raises(ValueError, match="cannot write"):
        check_file(str(places["folder"] / "bench.json"))


@pytest.mark.skipif(IS_ROOT, reason="root may write into a read-only folder")
def test_read_only_folder_is_refused(places):
    with pytest.raises(ValueError, match="no permission to write"):
        arguments.check_output_directory(str(places["locked"] / "run"))


# ------------------------------------------------------------------------------ simulate


# Options that are wrong whatever the output folder (given one that is fine).
SIM_OPTIONS = [
    (["--gains", ""], "empty name"),
    (["--seed", "-1"], "integer >= 0"),
    (["--seed", str(2**64)], "<= 9223372036854775807"),
    (["--draws", "1e3"], "write it as 1000"),
    (["--horizon", "nan"], "finite number > 0"),
    (["--horizon", "inf"], "finite number > 0"),
    (["--dt", "inf"], "finite number > 0"),
    (["--dt", "0.0003"], "e.g. --horizon"),
    (["--keep", "-1"], "integer >= 0"),
    (["--device-batch", "0"], "positive integer"),
    (["--chunk", "8"], "--chunk was removed"),
    (["--dtype", "float16"], "invalid choice"),
    (["--controller", ""], "unknown controller"),
    (["--controller", "afonftsmc,pid"], "'pid'"),
    (["--controller", "fl,fl"], "names fl twice"),
    (["--controller", "afonftsmc,"], "unknown controller"),
    (["--frobnicate"], "unrecognized arguments"),
    (["--controller", "fl", "--switching", "sat"], "--switching does not apply to fl, which "
     "takes no switching"),
]  # fmt: skip


def test_simulate_bad_inputs(capsys, places):
    folder = str(places["folder"])
    cases = [
        (SIM + ["--out", ""], "empty name"),
        (SIM + ["--out", str(places["file"])], "is a file, not a folder"),
        (SIM + ["--out", str(places["under"])], "is a file; choose a folder"),
        (SIM + ["--gains", folder, "--out", folder], "is a folder, not a gains"),
        (SIM, "required: --out"),
        *[(SIM + extra + ["--out", folder], message) for extra, message in SIM_OPTIONS],
    ]
    for argv, message in cases:
        err = usage_error(capsys, simulate.parse_args, argv)
        assert message in err, (argv, err)
    assert list(places["folder"].iterdir()) == []  # nothing written


def test_simulate_bad_gains_files(capsys, places, tmp_path):
    from fojax.controllers import gains_io
    from fojax.controllers.afonftsmc import paper_gains

    binary = tmp_path / "gains.bin"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    err = usage_error(
        capsys, simulate.parse_args, SIM + ["--gains", str(binary), "--out", str(tmp_path)]
    )
    assert str(binary) in err and "codec" in err
    fl = tmp_path / "fl.json"
    gains_io.save_gains(fl, "fl", __import__("fojax").controllers.FL.default_gains())
    err = usage_error(
        capsys, simulate.parse_args, SIM + ["--gains", str(fl), "--out", str(tmp_path)]
    )
    assert "does not simulate" in err and "add it to --controller" in err
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    gains_io.save_gains(a, "afonftsmc", paper_gains())
    gains_io.save_gains(b, "afonftsmc", paper_gains())
    argv = SIM + ["--gains", str(a), "--gains", str(b), "--out", str(tmp_path)]
    assert f"two gains files for 'afonftsmc': {a} and {b}" in usage_error(
        capsys, simulate.parse_args, argv
    )


@pytest.mark.skipif(IS_ROOT, reason="root reads and writes regardless of permissions")
def test_simulate_unreadable_gains_and_unwritable_out(capsys, places, tmp_path):
    secret = tmp_path / "secret.json"
    secret.write_text("{}")
    secret.chmod(0o000)
    argv = SIM + ["--gains", str(secret), "--out", str(tmp_path / "run")]
    assert "permission denied" in usage_error(capsys, simulate.parse_args, argv)
    argv = SIM + ["--out", str(places["locked"] / "run")]
    assert "no permission to write" in usage_error(capsys, simulate.parse_args, argv)


def test_simulate_names_only_the_settings_that_differ(capsys, tmp_path):
    """An earlier run's chunks with another seed and switching: the message lists those
    two fields and how to start afresh, before anything runs."""
    earlier, _ = simulate.parse_args(SIM + ["--switching", "sat", "--out", str(tmp_path)])
    from fojax.study import ChunkStore, store_fingerprint

    _, scenario, config, dtype, runs = study.prepare_runs(earlier)
    controller, gains = runs["afonftsmc"]
    fingerprint = store_fingerprint(controller, gains, scenario, config, earlier, dtype)
    store = tmp_path / "chunks" / "afonftsmc"
    ChunkStore(store, fingerprint)  # the earlier run's (empty) store
    status = cli.main(["simulate"] + SIM + ["--seed", "7", "--out", str(tmp_path), "--quiet"])
    assert status == 2
    err = capsys.readouterr().err
    lines = [line.strip() for line in err.splitlines() if line.startswith("  ")]
    assert lines == [
        'controller_config.law.switching (--switching): earlier "sat", now "sign"',
        "seed (--seed): earlier 0, now 7",
    ], err
    assert "--overwrite" in err and "another --out" in err and len(err) < 600
    assert sorted(p.name for p in store.iterdir()) == ["manifest.json"]  # nothing ran


# ---------------------------------------------------------------------------------- tune


def test_tune_bad_inputs(capsys, places, tmp_path):
    out = ["--out", str(tmp_path / "run")]
    cases = [
        (TUNE + ["--out", ""], "empty name"),
        (TUNE + ["--out", str(places["file"])], "is a file, not a folder"),
        (TUNE + ["--out", str(places["under"])], "is a file; choose a folder"),
        (TUNE + ["--init", str(places["folder"])] + out, "is a folder, not a gains file"),
        (TUNE + ["--init", "papr"] + out, "give paper, naive or a gains file"),
        (TUNE + ["--seed", "-3"] + out, "integer >= 0"),
        (TUNE + ["--horizon", "inf"] + out, "finite number > 0"),
        (TUNE + ["--learning-rate", "nan"] + out, "finite number > 0"),
        (TUNE + ["--anneal-start", "inf"] + out, "finite number > 0"),
        (TUNE + ["--eval-horizon", "nan"] + out, "finite number > 0"),
        (TUNE + ["--eval-draws", "-1"] + out, "integer >= 0"),
        (TUNE + ["--cvar-fraction", "0"] + out, "finite number > 0"),
        (TUNE + ["--position-weight", "-1"] + out, "finite number >= 0"),
        (TUNE + ["--checkpoint-every", "0"] + out, "positive integer"),
        (TUNE + ["--method", "adam", "--max-step", "2"] + out, "--max-step applies to --method"),
        (TUNE + ["--controller", "fl", "--fractional", "gl"] + out, "does not apply to fl"),
    ]
    for argv, message in cases:
        err = usage_error(capsys, tune.parse_args, argv)
        assert message in err, (argv, err)
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(IS_ROOT, reason="root writes regardless of permissions")
def test_tune_unwritable_out(capsys, places):
    argv = TUNE + ["--out", str(places["locked"] / "run")]
    assert "no permission to write" in usage_error(capsys, tune.parse_args, argv)


# --------------------------------------------------------------------------------- bench


def test_bench_bad_inputs(capsys, places):
    cases = [
        (["--json", ""], "empty name"),
        (["--json", str(places["folder"])], "is a folder; name a file"),
        (["--json", str(places["under"] / "bench.json")], "is a file"),
        (["--draws", "0"], "positive integer"),
        (["--draws", "1,,4"], "comma-separated list"),
        (["--long-horizon", "nan"], "positive number of seconds"),
        (["--short-horizon", "0.0005"], "whole number of 1 ms steps"),
        (["--gradient-horizons", "0.25,inf"], "finite number > 0"),
        (["--numpy-horizon", "-1"], "positive"),
        (["--repeats", "0"], "positive integer"),
        (["--devices", "0"], "positive integer"),
        (["--chunk", "x"], "positive integer"),
        # --small sets these itself: given with it they would be ignored.
        (["--small", "--repeats", "5"], "--small sets the sizes itself; leave --repeats out"),
        (["--small", "--draws=8", "--numpy-horizon", "1"], "leave --draws, --numpy-horizon out"),
    ]
    for argv, message in cases:
        err = usage_error(capsys, bench.main, argv)
        assert message in err, (argv, err)
    assert list(places["folder"].iterdir()) == []


def test_bench_records_provenance_and_checks_json_first(monkeypatch, tmp_path):
    """The output file is checked before measuring; the JSON holds the provenance."""
    stub = {"draws": 1, "horizon_s": 0.02, "steps": 20, "run_s": 1.0, "compile_s": 1.0,
            "calls": 1, "chunk": 1, "draw_steps_per_s": 20.0}  # fmt: skip
    gradient = {**stub, "save_every": 5, "gradient_draw_steps_per_s": 1.0,
                "gradient_over_forward": 2.0, "gradient_over_forward_cpu_time": 2.0,
                "gradient_memory": {},
                "gradient_compile_s": 1.0}  # fmt: skip
    monkeypatch.setattr(bench, "measure_forward", lambda *a, **k: dict(stub))
    monkeypatch.setattr(bench, "measure_numpy", lambda *a, **k: dict(stub))
    monkeypatch.setattr(bench, "measure_gradient", lambda *a, **k: dict(gradient))
    path = tmp_path / "deeper" / "bench.json"
    bench.main(["--small", "--json", str(path)])
    stored = json.loads(path.read_text())
    record = stored["provenance"]
    assert record["command"].startswith("fojax bench --small --json")
    for key in ("fojax_version", "jax", "jaxlib", "backend", "device_count", "process_count"):
        assert record[key] is not None, key


# ------------------------------------------------------------------------------ accuracy


def test_accuracy_bad_inputs(capsys, places):
    cases = [
        (["--dt", "nan"], "finite number > 0"),
        (["--horizon", "inf"], "finite number > 0"),
        (["--dt", "0"], "finite number > 0"),
        (["--dt", "2", "--horizon", "1"], "must be smaller than --horizon"),
        (["--horizon", "0.5", "--dt", "0.05"], "must be at least 1 s"),
        (["--dt", "1e-5", "--horizon", "80"], "at most 1000000"),
        (["--out", str(places["file"])], "is a file, not a folder"),
        (["--out", ""], "empty name"),
        (["--out", str(places["under"])], "is a file; choose a folder"),
    ]
    for argv, message in cases:
        err = usage_error(capsys, fractional_accuracy.main, argv)
        assert message in err, (argv, err)


# ----------------------------------------------------------------------------------- cli


def test_cli_version_unknown_command_and_os_errors(capsys, monkeypatch):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("fojax ")
    assert "invalid choice: 'simulte'" in usage_error(capsys, cli.main, ["simulte"])

    def disk_full(argv):
        raise OSError(28, "No space left on device", "results/draws.npz")

    monkeypatch.setattr(simulate, "main", disk_full)
    assert cli.main(["simulate"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == (
        "fojax simulate: error: cannot write or read results/draws.npz: No space left on device"
    )


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate"] + SIM + ["--out", "{file}"], "is a file, not a folder"),
        (["tune"] + TUNE + ["--out", "{under}"], "is a file; choose a folder"),
        (["bench", "--json", "{folder}"], "is a folder; name a file"),
        (["accuracy", "--dt", "nan"], "finite number > 0"),
    ],
)
def test_commands_exit_2_without_traceback(places, argv, message):
    argv = [a.format(**{k: str(v) for k, v in places.items()}) for a in argv]
    done = subprocess.run(
        [sys.executable, "-m", "fojax.cli", *argv],
        capture_output=True,
        text=True,
        timeout=180,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and message in done.stderr, done.stderr[-2000:]
