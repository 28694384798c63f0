"""The commands' shared runtime options: the persistent compilation cache (on by
default, a flag and a variable to turn it off) and joining a multi-process run."""

import os
from pathlib import Path

import pytest
from conftest import run_python, usage_error

from fojax import cli
from fojax.cli import arguments, reproduce, simulate, tune

ROOT = Path(__file__).resolve().parent.parent


def test_cache_folder_follows_xdg_and_the_variable(monkeypatch, tmp_path):
    monkeypatch.delenv(arguments.CACHE_VARIABLE, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert arguments.compile_cache_dir() == tmp_path / "xdg" / "fojax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert arguments.compile_cache_dir() == tmp_path / "home" / ".cache" / "fojax" / "jax"
    assert arguments.compile_cache_dir(disabled=True) is None
    for off in ("0", "off", "false", "NO"):
        monkeypatch.setenv(arguments.CACHE_VARIABLE, off)
        assert arguments.compile_cache_dir() is None
    monkeypatch.setenv(arguments.CACHE_VARIABLE, str(tmp_path / "elsewhere"))
    assert arguments.compile_cache_dir() == tmp_path / "elsewhere"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--coordinator", "localhost"], "HOST:PORT"),
        (["--coordinator", "h:99999", "--num-processes", "2", "--process-id", "0"], "1-65535"),
        (["--coordinator", "h:1234"], "needs --num-processes, --process-id too"),
        (["--num-processes", "2", "--process-id", "0"], "needs --coordinator too"),
        (["--coordinator", "h:1", "--num-processes", "0", "--process-id", "0"], ">= 1"),
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"], "below"),
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "x"], "integer"),
    ],
)
def test_bad_distributed_options_exit_2_with_a_message(capsys, monkeypatch, argv, message):
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    err = usage_error(capsys, lambda argv: arguments.setup_runtime(argv, "fojax simulate"), argv)
    assert message in err


def test_every_command_has_the_runtime_options():
    for module in (simulate, reproduce, tune):
        text = module.build_parser().format_help()
        for flag in ("--no-compile-cache", "--coordinator", "--num-processes", "--process-id"):
            assert flag in text, (module.__name__, flag)
    assert "reproduce" in cli.HOST_DEVICE_COMMANDS and "simulate" in cli.HOST_DEVICE_COMMANDS


def test_single_process_runs_join_nothing(monkeypatch):
    from fojax import sharding

    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    for name in [k for k in os.environ if k.startswith("SLURM_")]:
        monkeypatch.delenv(name)
    info = sharding.initialize()
    assert info["process_count"] == 1 and info["joined"] is None
    # A SLURM job of one task is not a distributed run.
    monkeypatch.setenv("SLURM_JOB_ID", "12")
    monkeypatch.setenv("SLURM_STEP_NODELIST", "node01")
    monkeypatch.setenv("SLURM_NTASKS", "1")
    monkeypatch.setenv("SLURM_PROCID", "0")
    monkeypatch.setenv("SLURM_LOCALID", "0")
    assert sharding.detect_cluster() == ("slurm", 1)
    assert sharding.initialize()["joined"] is None
    monkeypatch.setenv("SLURM_NTASKS", "4")
    assert sharding.detect_cluster() == ("slurm", 4)
    with pytest.raises(ValueError, match="num_processes"):
        sharding.initialize(num_processes=0)


def _clean(monkeypatch):
    """No JAX_* distributed variable and no cluster job in the environment."""
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    for name in [k for k in os.environ if k.startswith(("SLURM_", "OMPI_", "KUBERNETES_"))]:
        monkeypatch.delenv(name)


@pytest.mark.parametrize(
    "variables, message",
    [
        ({"JAX_COORDINATOR_ADDRESS": "h:1234"}, "needs JAX_NUM_PROCESSES, JAX_PROCESS_ID too"),
        ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}, "needs JAX_COORDINATOR_ADDRESS too"),
        (
            {"JAX_COORDINATOR_ADDRESS": "h", "JAX_NUM_PROCESSES": "2"},
            "JAX_COORDINATOR_ADDRESS must",
        ),
        ({"JAX_NUM_PROCESSES": "two", "JAX_PROCESS_ID": "0"}, "JAX_NUM_PROCESSES must be an int"),
        ({"JAX_NUM_PROCESSES": "0"}, "JAX_NUM_PROCESSES must be an integer >= 1"),
        ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "-1"}, "JAX_PROCESS_ID must be an int"),
        ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"}, "JAX_PROCESS_ID (2) must be below"),
        ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1.0"}, "JAX_PROCESS_ID must be an int"),
    ],
)
def test_bad_distributed_variables_exit_2_with_a_message(capsys, monkeypatch, variables, message):
    """JAX reads only JAX_COORDINATOR_ADDRESS; fojax reads the three and says what is
    missing or wrong before anything starts."""
    _clean(monkeypatch)
    for name, value in variables.items():
        monkeypatch.setenv(name, value)
    err = usage_error(capsys, lambda argv: arguments.setup_runtime(argv, "fojax simulate"), [])
    err = err.strip().splitlines()
    assert message in err[-1] and len(err) == 3  # usage (2 lines), then one line


def test_flags_and_variables_combine(monkeypatch):
    """A flag overrides its variable; a flag left out comes from its variable; the id is
    checked against the count wherever each comes from."""
    from fojax import sharding

    _clean(monkeypatch)
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "node01:12355")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "4")
    monkeypatch.setenv("JAX_PROCESS_ID", "3")
    assert sharding.distributed_settings() == {
        "coordinator_address": "node01:12355",
        "num_processes": 4,
        "process_id": 3,
        "joined": "environment",
    }
    settings = sharding.distributed_settings(process_id=1, names=arguments.DISTRIBUTED_FLAGS)
    assert settings["process_id"] == 1 and settings["joined"] == "arguments"
    with pytest.raises(ValueError, match=r"--process-id \(5\) must be below JAX_NUM_PROC"):
        sharding.distributed_settings(process_id=5, names=arguments.DISTRIBUTED_FLAGS)
    monkeypatch.setenv("JAX_NUM_PROCESSES", "")  # empty: unset
    with pytest.raises(ValueError, match="needs JAX_NUM_PROCESSES too"):
        sharding.distributed_settings()


def _fake_slurm(monkeypatch, tasks: int, rank: int = 0):
    for name, value in (
        ("SLURM_JOB_ID", "4242"),
        ("SLURM_STEP_NODELIST", "node[07-08]"),
        ("SLURM_NTASKS", str(tasks)),
        ("SLURM_PROCID", str(rank)),
        ("SLURM_LOCALID", "0"),
    ):
        monkeypatch.setenv(name, value)


def test_a_detected_cluster_job_supplies_what_is_not_given(monkeypatch):
    """SLURM faked by its variables (nothing is started: distributed_settings only says
    what initialize would pass to jax.distributed.initialize, which takes the rest from
    the job)."""
    from fojax import sharding

    _clean(monkeypatch)
    _fake_slurm(monkeypatch, 4, 2)
    assert sharding.detect_cluster() == ("slurm", 4)
    assert sharding.distributed_settings() == {
        "coordinator_address": None,
        "num_processes": None,
        "process_id": None,
        "joined": "slurm",
    }
    assert sharding.distributed_settings(detect=False) is None
    # A variable or flag set inside the job overrides the job's value, the job gives the rest.
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "node07:5000")
    settings = sharding.distributed_settings()
    assert settings["coordinator_address"] == "node07:5000" and settings["num_processes"] is None
    with pytest.raises(ValueError, match="needs JAX_NUM_PROCESSES, JAX_PROCESS_ID too"):
        sharding.distributed_settings(detect=False)
    # JAX's own detection agrees on what it fills in.
    from jax._src import clusters

    filled = clusters.ClusterEnv.auto_detect_unset_distributed_params(
        None, None, None, None, None, None
    )
    assert filled[:3] == ("node07:61586", 4, 2)  # port: 4242 % 4096 + 61440


_COUNT_CACHE = """
import sys
import jax.monitoring
events = {"hits": 0, "misses": 0}
def listen(name, **kwargs):
    if name.endswith("cache_hits"):
        events["hits"] += 1
    elif name.endswith("cache_misses"):
        events["misses"] += 1
jax.monitoring.register_event_listener(listen)
from fojax import cli
status = cli.main(sys.argv[1:])
print("CACHE", events["hits"], events["misses"])
sys.exit(status)
"""


def _simulate(tmp_path, name, env, *extra):
    argv = ["simulate", "--scenario", "3", "--controller", "fl", "--draws", "2"]
    argv += ["--horizon", "0.05", "--no-figures", "--quiet", "--out", str(tmp_path / name)]
    out = run_python("-c", _COUNT_CACHE, *argv, *extra, env=env)
    hits, misses = (int(v) for v in out.split("CACHE")[1].split())
    return hits, misses


def test_a_second_run_reads_its_programs_from_the_cache(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["JAX_PLATFORMS"] = "cpu"
    # The rollout compiled at XLA's default optimisation (seconds: kept by the cache).
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace("--xla_backend_optimization_level=0", "")
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    env.pop(arguments.CACHE_VARIABLE, None)
    env["PYTHONPATH"] = str(ROOT)
    cache = tmp_path / "xdg" / "fojax" / "jax"
    hits, misses = _simulate(tmp_path, "first", env)
    assert hits == 0 and misses >= 1 and any(cache.iterdir())
    hits, _ = _simulate(tmp_path, "second", env)
    assert hits >= 1  # the rollout (programs compiled in under 1 s are not kept)
    # Off by flag or by variable: nothing read or written.
    before = sorted(cache.iterdir())
    assert _simulate(tmp_path, "flag", env, "--no-compile-cache") == (0, 0)
    env[arguments.CACHE_VARIABLE] = "0"
    assert _simulate(tmp_path, "variable", env) == (0, 0)
    assert sorted(cache.iterdir()) == before
