"""``fojax simulate``: input checks before compiling, gains files, one tiny end-to-end run."""

import json
import os

import numpy as np
import pytest
from conftest import run_python, usage_error

from fojax import cli
from fojax.cli import arguments, simulate
from fojax.controllers import gains_io
from fojax.controllers.afonftsmc import paper_gains

BASE = ["--scenario", "2", "--controller", "afonftsmc", "--draws", "3"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--scenario", "4", "--controller", "afonftsmc", "--draws", "3"], "invalid choice"),
        (["--scenario", "2", "--controller", "pid", "--draws", "3"], "unknown controller 'pid'"),
        (["--scenario", "2", "--controller", "afonftsmc", "--draws", "0"], "positive integer"),
        (BASE + ["--seed", "-1"], "integer >= 0"),
        (BASE + ["--horizon", "-2"], "finite number > 0"),
        (BASE + ["--dt", "0"], "finite number > 0"),
        (BASE + ["--dt", "nan"], "finite number > 0"),
        (BASE + ["--horizon", "1.0005"], "whole number of steps"),
        (BASE + ["--dt", "2", "--horizon", "1"], "must not exceed the horizon"),
        (BASE + ["--fractional", "crone"], "invalid choice"),
        (BASE + ["--switching", "signum"], "invalid choice"),
    ],
)
def test_bad_arguments_fail_before_compiling(capsys, tmp_path, argv, message):
    err = usage_error(capsys, simulate.parse_args, argv + ["--out", str(tmp_path)])
    assert message in err


@pytest.mark.parametrize(
    "controller, extra, message",
    [
        ("fl", ["--switching", "sat"], "--switching does not apply to fl, which takes no switch"),
        ("fl", ["--switching", "sign"], "--switching does not apply to fl"),
        ("bsmc", ["--fractional", "oustaloup"], "--fractional does not apply to bsmc"),
        ("anftsmc", ["--fractional", "soe"], "anftsmc, which takes no fractional_method"),
        ("fl,bsmc", ["--fractional", "gl"], "--fractional applies to none of fl, bsmc"),
    ],
)
def test_an_option_the_controller_does_not_take_is_an_error(
    capsys, tmp_path, controller, extra, message
):
    argv = ["--scenario", "2", "--controller", controller, "--draws", "3", *extra]
    last = (
        usage_error(capsys, simulate.parse_args, argv + ["--out", str(tmp_path)])
        .strip()
        .splitlines()[-1]
    )
    assert last.startswith("fojax simulate: error: ") and message in last, last


def test_with_several_controllers_an_option_applies_to_those_that_take_it(tmp_path):
    """--controller all --switching sat: the four sliding-mode laws switch with sat,
    the FL runs as it is, and the run says so."""
    from fojax.cli import study as study_layer

    argv = ["--scenario", "2", "--controller", "all", "--draws", "3", "--switching", "sat"]
    study, args = simulate.parse_args(argv + ["--fractional", "gl", "--out", str(tmp_path)])
    assert args.applied == {
        "--fractional": ["afonftsmc", "fobsmc"],
        "--switching": ["afonftsmc", "anftsmc", "fobsmc", "bsmc"],
    }
    assert study_layer.options_applied_to(study) == {
        "fractional_method": ["afonftsmc", "fobsmc"],
        "switching": ["afonftsmc", "anftsmc", "fobsmc", "bsmc"],
    }
    runs = study_layer.prepare_runs(study)[-1]
    assert (
        runs["bsmc"][0].law.switching == "sat" and runs["fobsmc"][0].law.fractional_method == "gl"
    )
    assert not hasattr(runs["fl"][0].law, "switching")
    # Defaults (nothing given) are recorded as before: sign, soe.
    study, args = simulate.parse_args(["--scenario", "2", "--controller", "fl", "--draws", "3",
                                       "--out", str(tmp_path)])  # fmt: skip
    assert (study.switching, study.fractional, args.applied) == ("sign", "soe", {})
    assert study_layer.options_applied_to(study) == {"fractional_method": [], "switching": []}


def _write(path, document):
    path.write_text(json.dumps(document))
    return path


def test_gains_files_are_validated(capsys, tmp_path):
    good = gains_io.gains_to_dict(paper_gains())
    cases = {
        "missing": (
            {"controller": "afonftsmc", "gains": {k: v for k, v in good.items() if k != "mu"}},
            "missing entries: mu",
        ),
        "extra": ({"controller": "afonftsmc", "gains": {**good, "kd": 1.0}}, "unknown entries: kd"),
        "text": (
            {"controller": "afonftsmc", "gains": {**good, "mu": "small"}},
            "'mu' must be numeric",
        ),
        "shape": ({"controller": "afonftsmc", "gains": {**good, "mu": [1e-3, 1e-3]}}, "shape (6,)"),
        "ratio": ({"controller": "afonftsmc", "gains": {**good, "ratio": 2.5}}, "1 < p/q < 2"),
        "gamma": ({"controller": "afonftsmc", "gains": {**good, "gamma1": 1.0}}, "0 < gamma1 < 1"),
        "negative": (
            {"controller": "afonftsmc", "gains": {**good, "reaching_h2": -1}},
            "reaching_h2 must be > 0",
        ),
        "controller": ({"controller": "lqr", "gains": good}, "unknown controller 'lqr'"),
        "keys": ({"controller": "afonftsmc", "gain": good}, "missing keys ['gains']"),
    }
    for label, (document, message) in cases.items():
        path = _write(tmp_path / f"{label}.json", document)
        err = usage_error(
            capsys, simulate.parse_args, BASE + ["--gains", str(path), "--out", str(tmp_path)]
        )
        assert message in err, (label, err)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    assert "not valid JSON" in usage_error(
        capsys, simulate.parse_args, BASE + ["--gains", str(broken), "--out", "x"]
    )
    assert "does not exist" in usage_error(
        capsys, simulate.parse_args, BASE + ["--gains", str(tmp_path / "no.json"), "--out", "x"]
    )


def test_gains_round_trip_and_scalar_broadcast(tmp_path):
    gains = paper_gains()
    path = tmp_path / "gains.json"
    gains_io.save_gains(path, "afonftsmc", gains, {"source": "test"})
    name, loaded, metadata = gains_io.load_gains(path)
    assert name == "afonftsmc" and metadata == {"source": "test"}
    for a, b in zip(loaded, gains, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    document = json.loads(path.read_text())
    document["gains"]["mu"] = 0.002
    path.write_text(json.dumps(document))
    _, loaded, _ = gains_io.load_gains(path)
    np.testing.assert_allclose(loaded.mu, np.full(6, 0.002))


def test_simulate_end_to_end_tiny(tmp_path, capsys, monkeypatch):
    gains_path = tmp_path / "gains.json"
    gains_io.save_gains(gains_path, "afonftsmc", paper_gains())
    out = tmp_path / "run"
    argv = [
        "simulate", "--scenario", "3", "--controller", "afonftsmc", "--draws", "3",
        "--device-batch", "2", "--horizon", "0.2", "--seed", "5", "--switching", "sat",
        "--gains", str(gains_path), "--out", str(out), "--quiet",
    ]  # fmt: skip
    assert cli.main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    entry = summary["controllers"]["afonftsmc"]
    assert entry["draws"] == 3 and "diverged" in entry
    for key, unit in (("position_rmse", "m"), ("attitude_rmse", "rad")):
        assert entry["metrics"][key]["unit"] == unit
        assert entry["metrics"][key]["n"] + entry["diverged"] == 3
    assert "reaching_time_bound_x" in entry["metrics"]
    with np.load(out / "draws.npz") as draws:
        assert draws["afonftsmc.position_rmse"].shape == (3,)
        assert draws["afonftsmc.iae"].shape == (3, 6)
        np.testing.assert_allclose(
            np.mean(draws["afonftsmc.position_rmse"]),
            entry["metrics"]["position_rmse"]["mean"],
            rtol=1e-6,
        )
    with np.load(out / "trajectories.npz") as tr:
        assert tr["afonftsmc.state"].shape[0] == 3
        assert np.all(tr["afonftsmc.inputs_low"] <= tr["afonftsmc.inputs_high"])
    _check_recorded_metadata(summary, gains_path, argv)
    for figure in ("tracking", "errors", "inputs", "path3d", "adaptive"):
        assert (out / f"{figure}.png").stat().st_size > 10_000
        assert (out / f"{figure}.pdf").read_bytes().startswith(b"%PDF")
    from PIL import Image

    with Image.open(out / "tracking.png") as image:  # 11 x 8 in at >= 150 dpi
        assert image.size[0] >= 11 * 150 and image.size[1] >= 8 * 150
    assert summary["figures"] == [
        f"{f}.png" for f in ("tracking", "errors", "inputs", "path3d", "adaptive")
    ]
    # Started again, the same command reuses the finished chunks and agrees.
    assert cli.main(argv) == 0
    again = json.loads((out / "summary.json").read_text())
    assert again["controllers"]["afonftsmc"]["metrics"] == entry["metrics"]
    # A figure that cannot be drawn (here: no plotting library) is a warning naming it;
    # the results are written and the command succeeds.
    from fojax.cli import style

    def no_matplotlib():
        raise ModuleNotFoundError("No module named 'matplotlib'")

    (out / "summary.json").unlink()
    monkeypatch.setattr(style, "pyplot", no_matplotlib)
    capsys.readouterr()
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    for figure in ("tracking", "errors", "inputs", "path3d", "adaptive"):
        assert f"warning: figure {figure}.png was not drawn (ModuleNotFoundError" in captured.err
    assert "Traceback" not in captured.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controllers"]["afonftsmc"]["metrics"] == entry["metrics"]
    assert "figures" not in summary
    # --keep 0: no trajectories, and the report says so instead of listing them.
    monkeypatch.undo()
    keep0 = tmp_path / "keep0"
    argv0 = [a if a != str(out) else str(keep0) for a in argv] + ["--keep", "0"]
    assert cli.main(argv0) == 0
    printed = capsys.readouterr().out
    assert "no trajectories kept (--keep 0)" in printed and "trajectories.npz," not in printed
    assert sorted(p.name for p in keep0.iterdir()) == ["chunks", "draws.npz", "summary.json"]


def _check_recorded_metadata(summary, gains_path, argv):
    """summary.json records what the run needs to be redone exactly."""
    import jax

    import fojax

    gains = summary["gains"]["afonftsmc"]
    assert gains["source"] == str(gains_path.resolve())
    expected = gains_io.gains_to_dict(paper_gains("float32"))
    assert gains["values"] == expected
    record = summary["provenance"]
    assert record["command"].startswith("fojax simulate --scenario 3 --controller afonftsmc")
    assert record["command"].endswith("--quiet") and str(gains_path) in record["command"]
    assert record["fojax_version"] == fojax.__version__
    assert record["jax"] == jax.__version__ and record["jaxlib"]
    assert record["backend"] == jax.default_backend()
    assert record["device_count"] == jax.device_count() >= 1
    assert record["local_device_count"] == jax.local_device_count()
    assert record["process_count"] == 1 and record["python"]
    batch = summary["batch"]
    assert batch["devices"] == jax.local_device_count()
    assert batch["draws_per_call"] % batch["devices"] == 0
    assert summary["files"] == ["summary.json", "draws.npz", "trajectories.npz"]


def test_default_gains_are_recorded_as_defaults():
    from fojax.cli import study

    record = study.gains_record(paper_gains(), None)
    assert record["source"] == "defaults"
    assert record["values"]["surface_c1"] == np.asarray(paper_gains().surface_c1).tolist()


_HOST_DEVICES_SCRIPT = """
import os, sys
from fojax.cli import arguments
assert arguments.use_host_devices(3) == 3
import jax
assert arguments.use_host_devices(5) is None  # JAX has started: nothing changes
print(jax.local_device_count(), "XLA_FLAGS" in os.environ)
"""


def test_host_devices_are_set_before_jax_starts_and_never_after():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    out = run_python("-c", _HOST_DEVICES_SCRIPT, env=env, timeout=120).split()
    assert out[:2] == ["3", "False"]  # through jax.config, not the environment
    # In this process JAX has started: the flag is left as it is.
    import jax

    jax.devices()
    before = os.environ.get("XLA_FLAGS")
    assert arguments.use_host_devices() is None
    assert os.environ.get("XLA_FLAGS") == before
    assert "simulate" in cli.HOST_DEVICE_COMMANDS and "reproduce" in cli.HOST_DEVICE_COMMANDS


def test_a_control_law_of_ones_own_reaches_the_command_line(tmp_path, capsys, monkeypatch):
    from fojax.controllers import registry

    (tmp_path / "my_cli_law.py").write_text(
        "import dataclasses\n"
        "import jax.numpy as jnp\n"
        "from fojax.controllers import Bounds, ControlLaw, GainField, GainSpec, LawOutput\n"
        "@dataclasses.dataclass(frozen=True)\n"
        "class PD(ControlLaw):\n"
        "    name = 'cli_pd'\n"
        "    GAINS = GainSpec('PDGains', [GainField('k', [1.0, 1.0, 30.0, 900.0, 900.0, 900.0],"
        " Bounds(0.0))], 'PD')\n"
        "    def step(self, params, state, e1, e2):\n"
        "        e1, e2 = jnp.stack(e1), jnp.stack(e2)\n"
        "        return state, LawOutput(-params.k * e1 - 2 * jnp.sqrt(params.k) * e2, e2)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "_LAWS", dict(registry._LAWS))
    out = tmp_path / "run"
    argv = ["simulate", "--scenario", "1", "--controller", "my_cli_law:PD", "--draws", "2"]
    argv += ["--horizon", "0.2", "--out", str(out), "--quiet", "--no-figures"]
    assert cli.main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["controllers"]) == ["cli_pd"]
    assert summary["controllers"]["cli_pd"]["diverged"] == 0


def test_load_gains_names_the_file_for_folders_and_undecodable_files(tmp_path):
    folder = tmp_path / "gains_folder"
    folder.mkdir()
    with pytest.raises(ValueError, match="is a folder, not a gains file") as info:
        gains_io.load_gains(folder)
    assert str(folder) in str(info.value)
    binary = tmp_path / "gains.bin"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match="not UTF-8 text") as info:
        gains_io.load_gains(binary)
    assert str(binary) in str(info.value)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match="nested too deeply|not valid JSON") as info:
        gains_io.load_gains(deep)
    assert str(deep) in str(info.value)
    if os.geteuid() != 0:  # root reads regardless of permissions
        secret = tmp_path / "secret.json"
        secret.write_text("{}")
        secret.chmod(0o000)
        with pytest.raises(ValueError, match="permission denied") as info:
            gains_io.load_gains(secret)
        assert str(secret) in str(info.value)
