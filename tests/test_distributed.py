"""Runs over several processes (``jax.distributed`` on localhost, CPU collectives):
the same numbers, draw by draw, as one process; resume after a process is killed.

Each process gets one CPU device, so two processes make a mesh of two devices over
which the draws are split; the reference runs in one process on one device.
"""

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fojax import sharding

ROOT = Path(__file__).resolve().parent.parent

SIMULATE = [
    "simulate", "--scenario", "3", "--controller", "afonftsmc", "--draws", "120",
    "--device-batch", "20", "--horizon", "0.2", "--seed", "11", "--quiet", "--no-figures",
]  # fmt: skip


def _env(cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "SLURM_"))}
    flags = env.get("XLA_FLAGS", "")
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count=1".strip()
    env["JAX_PLATFORMS"] = "cpu"
    env["FOJAX_COMPILE_CACHE"] = str(cache)
    env["PYTHONPATH"] = str(ROOT)
    return env


# ``fojax`` with a pause after each stored call, to kill a process at a known point.
_SLOW_STORE = """
import sys, time
from fojax.study import _store
save = _store.ChunkStore.save
def slow(self, *args, **kwargs):
    path = save(self, *args, **kwargs)
    time.sleep(3)
    return path
_store.ChunkStore.save = slow
from fojax import cli
cli.entry()
"""


def _command(argv, slow=False):
    if slow:
        return [sys.executable, "-c", _SLOW_STORE, *argv]
    return [sys.executable, "-m", "fojax.cli", *argv]


def _start(argv, processes: int, env: dict, slow: bool = False):
    """Start ``processes`` processes of ``fojax argv`` (one alone when 1)."""
    commands = [_command(argv, slow)]
    if processes > 1:
        port = sharding.free_port()
        commands = [
            _command(
                argv
                + ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(processes)]
                + ["--process-id", str(index)],
                slow,
            )
            for index in range(processes)
        ]
    return [
        subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for command in commands
    ]


def _wait(started, timeout=600):
    outputs = []
    for process in started:
        out, err = process.communicate(timeout=timeout)
        outputs.append((process.returncode, out, err))
    for status, _, err in outputs:
        assert status == 0, err[-3000:]
    return outputs


def _draws(folder: Path) -> dict:
    with np.load(folder / "draws.npz") as data:
        return {k: data[k] for k in data.files}


def _assert_identical(a: dict, b: dict):
    assert sorted(a) == sorted(b)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("jax_cache")


@pytest.fixture(scope="module")
def single(tmp_path_factory, cache):
    """The reference: one process, one device."""
    out = tmp_path_factory.mktemp("single") / "run"
    _wait(_start(SIMULATE + ["--out", str(out)], 1, _env(cache)))
    return out


DOC = ROOT / "docs" / "distributed.md"


def _doc_commands(marker: str) -> list[tuple[dict, list[str]]]:
    """The command lines of the bash block of docs/distributed.md holding ``marker``:
    ``(variables set on the line, fojax's arguments)`` per line, comments left out."""
    blocks = [b for b in re.findall(r"```bash\n(.*?)```", DOC.read_text(), re.S) if marker in b]
    assert len(blocks) == 1, f"one block of docs/distributed.md should hold {marker!r}"
    commands = []
    for line in blocks[0].splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        words = shlex.split(line)
        variables = {}
        while "=" in words[0] and not words[0].startswith("-"):
            name, _, value = words.pop(0).partition("=")
            variables[name] = value
        assert words[0] == ".venv/bin/fojax", line  # the set-up's environment
        commands.append((variables, words[1:]))
    return commands


def _run_doc_commands(marker: str, cwd: Path, env: dict):
    """docs/distributed.md's lines as written (in ``cwd``), on a free port instead of
    the document's 12355, every process started at once."""
    port = str(sharding.free_port())
    started = []
    for variables, argv in _doc_commands(marker):
        argv = [word.replace("12355", port) for word in argv]
        variables = {name: value.replace("12355", port) for name, value in variables.items()}
        started.append(
            subprocess.Popen(
                _command(argv),
                env=env | variables,
                cwd=cwd,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    return _wait(started)


def _check_two_process_run(out: Path, outputs, single: Path):
    assert "wrote" in outputs[0][1] and "wrote" not in outputs[1][1]  # process 0 writes
    _assert_identical(_draws(out), _draws(single))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["provenance"]["process_count"] == 2
    assert summary["provenance"]["device_count"] == 2
    assert summary["batch"]["processes"] == 2 and summary["batch"]["devices"] == 2
    # 120 draws in blocks of 20, one per device and call: 3 calls over 2 processes.
    assert summary["batch"]["device_batch"] == 20 and summary["batch"]["calls"] == 3
    reference = json.loads((single / "summary.json").read_text())
    assert reference["batch"]["processes"] == 1
    assert summary["controllers"] == reference["controllers"] | {
        "afonftsmc": {
            **reference["controllers"]["afonftsmc"],
            "wall_time_s": summary["controllers"]["afonftsmc"]["wall_time_s"],
        }
    }


def test_the_documented_starts_are_the_run_of_the_tests():
    """docs/distributed.md's commands are this file's SIMULATE run, so that the
    one-process reference fits them (without --quiet, which changes no number)."""
    expected = [w for w in SIMULATE if w != "--quiet"]
    for marker, out in (
        ("--coordinator 127", "results/two"),
        ("JAX_COORDINATOR", "results/two_env"),
    ):
        commands = _doc_commands(marker)
        assert len(commands) == 2
        for index, (variables, argv) in enumerate(commands):
            if variables:
                assert variables == {
                    "JAX_COORDINATOR_ADDRESS": "127.0.0.1:12355",
                    "JAX_NUM_PROCESSES": "2",
                    "JAX_PROCESS_ID": str(index),
                }
                assert argv == expected + ["--out", out]
            else:
                assert argv == expected + ["--out", out, "--coordinator", "127.0.0.1:12355"] + [
                    "--num-processes",
                    "2",
                    "--process-id",
                    str(index),
                ]


@pytest.mark.slow
@pytest.mark.parametrize(
    "marker", ["--coordinator 127", "JAX_COORDINATOR"], ids=["flags", "variables"]
)
def test_two_processes_started_as_documented_simulate_the_draws_of_one(
    tmp_path, cache, single, marker
):
    """Started as docs/distributed.md says, with the flags and with JAX's variables
    (JAX 0.10 reads only JAX_COORDINATOR_ADDRESS: fojax reads the other two)."""
    outputs = _run_doc_commands(marker, tmp_path, _env(cache))
    out = tmp_path / ("results/two_env" if marker.startswith("JAX") else "results/two")
    _check_two_process_run(out, outputs, single)


@pytest.mark.slow
def test_two_processes_of_a_slurm_job_simulate_the_draws_of_one(tmp_path, cache, single):
    """A SLURM job of two tasks, faked by its variables on this machine: nothing but
    the job's variables (and JAX_COORDINATOR_PORT, as docs/distributed.md says, on a
    free port) tells the processes how to join."""
    env = _env(cache) | {
        "SLURM_JOB_ID": "4242",
        "SLURM_STEP_NODELIST": "127.0.0.1",
        "SLURM_NTASKS": "2",
        "JAX_COORDINATOR_PORT": str(sharding.free_port()),
    }
    out = tmp_path / "run"
    command = _command([w for w in SIMULATE if w != "--quiet"] + ["--out", str(out)])
    outputs = _wait(
        [
            subprocess.Popen(
                command,
                env=env | {"SLURM_PROCID": str(rank), "SLURM_LOCALID": str(rank)},
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for rank in range(2)
        ]
    )
    _check_two_process_run(out, outputs, single)


@pytest.mark.slow
def test_resume_is_exact_after_a_process_is_killed(tmp_path, cache, single):
    """Blocks of 20 draws, one per device and call, over 2 processes; process 1 is
    killed once the first call's draws are stored, process 0 then fails (or is
    killed); the same
    command started again computes the rest, and every draw equals the one-process
    run's."""
    out = tmp_path / "run"
    argv = SIMULATE + ["--out", str(out)]
    env = _env(cache)
    started = _start(argv, 2, env, slow=True)  # process 0 pauses 3 s after storing
    store = out / "chunks" / "afonftsmc"
    deadline = time.time() + 400
    while time.time() < deadline and not list(store.glob("draws_*.npz")):
        assert started[0].poll() is None, started[0].communicate()[1][-3000:]
        time.sleep(0.2)
    stored = sorted(p.name for p in store.glob("draws_*.npz"))
    assert stored == ["draws_0000000000-0000000040.npz"]
    started[1].send_signal(signal.SIGKILL)
    started[1].wait(timeout=60)
    try:
        started[0].wait(timeout=30)
    except subprocess.TimeoutExpired:  # waiting for its peer: stopped like a killed job
        started[0].send_signal(signal.SIGKILL)
        started[0].wait(timeout=60)
    for process in started:
        process.communicate()
    assert not (out / "draws.npz").exists()
    _wait(_start(argv, 2, env))
    summary = json.loads((out / "summary.json").read_text())
    entry = summary["controllers"]["afonftsmc"]
    assert entry["draws_from_store"] == 40 and entry["draws_computed"] == 80
    _assert_identical(_draws(out), _draws(single))


TUNE = [
    "tune",
    "--scenario",
    "2",
    "--controller",
    "afonftsmc",
    "--draws",
    "4",
    "--steps",
    "2",
    "--horizon",
    "0.1",
    "--eval-draws",
    "0",
    "--method",
    "adam",
    "--quiet",
]


@pytest.mark.slow
def test_two_processes_take_the_tuning_steps_of_one(tmp_path, cache):
    """Adam steps (fresh draws each step), compiled as the suite compiles (unoptimised):
    the objective's values and the gains bit for bit; the gradient's norm to its last
    digits, where the unoptimised 1- and 2-device gradient programs round apart
    (docs/distributed.md; equal on some CPUs, not on others). Compiled optimised, as a
    user's run is, the default L-BFGS was checked by hand (equal bit for bit); compiling
    the gradient optimised twice would double this test's time."""
    env = _env(cache)
    one, two = tmp_path / "one", tmp_path / "two"
    first = _start(TUNE + ["--out", str(one)], 1, env)
    _wait(first)
    _wait(_start(TUNE + ["--out", str(two)], 2, env))
    assert (one / "history.csv").is_file() and (two / "history.csv").is_file()
    rows = [
        [{k: v for k, v in row.items() if k != "wall_time_s"} for row in _history(path)]
        for path in (one, two)
    ]
    assert len(rows[0]) == len(rows[1]) == 2
    for alone, shared in zip(*rows, strict=True):
        norms = float(alone.pop("grad_norm")), float(shared.pop("grad_norm"))
        assert norms[0] == pytest.approx(norms[1], rel=1e-6, abs=0.0)
        assert alone == shared
    gains = [json.loads((path / "gains.json").read_text())["gains"] for path in (one, two)]
    assert gains[0] == gains[1]
    sessions = json.loads((two / "run.json").read_text())["sessions"]
    assert sessions[-1]["process_count"] == 2


def _history(folder: Path):
    import csv

    with open(folder / "history.csv", newline="") as handle:
        return list(csv.DictReader(handle))
