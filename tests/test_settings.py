"""fojax.settings: the environment read once into a frozen value, never written."""

import dataclasses
import os
from pathlib import Path

import jax
import pytest

from fojax import settings, sharding
from fojax.cli import study as study_layer


def test_every_variable_is_read_into_one_frozen_value(tmp_path):
    environ = {
        "XLA_FLAGS": "--xla_cpu_foo=1 --xla_force_host_platform_device_count=3",
        "XDG_CACHE_HOME": str(tmp_path),
        "FOJAX_COMPILE_CACHE": " off ",
        "FOJAX_UNION": "0",
        "FOJAX_COMPILE_THREADS": "2",
        "JAX_COORDINATOR_ADDRESS": "node01:1234",
        "JAX_NUM_PROCESSES": " ",
        "SLURM_NTASKS": "4",
    }
    found = settings.read(environ)
    assert found.xla_flags == environ["XLA_FLAGS"] and found.host_device_flag
    assert found.cache_home == tmp_path and found.compile_cache == "off"
    assert settings.compile_cache_dir(settings=found) is None
    assert not found.union and found.threads == 2
    assert found.distributed == ("node01:1234", None, None)
    assert found.slurm == (None, "4", None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        found.union = True
    assert hash(found) == hash(settings.read(environ))
    default = settings.read({"XDG_CACHE_HOME": str(tmp_path)})
    assert default.union and default.threads == min(4, default.cores)
    assert settings.default_cache_dir(default) == tmp_path / "fojax" / "jax"
    assert settings.compile_cache_dir(settings=default) == tmp_path / "fojax" / "jax"
    moved = settings.read({"FOJAX_COMPILE_CACHE": "~/elsewhere"})
    assert settings.compile_cache_dir(settings=moved) == Path("~/elsewhere").expanduser()


@pytest.mark.parametrize(
    "environ, message",
    [
        ({"FOJAX_UNION": "maybe"}, "FOJAX_UNION must be 0 or 1"),
        ({"FOJAX_COMPILE_THREADS": "x"}, "FOJAX_COMPILE_THREADS must be an integer >= 0"),
        ({"FOJAX_COMPILE_THREADS": "-1"}, "FOJAX_COMPILE_THREADS must be an integer >= 0"),
    ],
)
def test_a_value_fojax_cannot_use_is_named(environ, message):
    with pytest.raises(ValueError, match=message):
        settings.read(environ)


def test_values_are_passed_down_not_read_from_the_environment():
    """What a function is given wins over the environment, which nothing writes."""
    before = dict(os.environ)
    off = settings.read({"FOJAX_UNION": "0", "FOJAX_COMPILE_THREADS": "0"})
    assert study_layer.union_enabled(off) is False and study_layer.compile_threads(off) == 0
    joined = settings.read(
        {"JAX_COORDINATOR_ADDRESS": "h:1", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}
    )
    assert sharding.distributed_settings(detect=False, settings=joined) == {
        "coordinator_address": "h:1",
        "num_processes": 2,
        "process_id": 1,
        "joined": "environment",
    }
    jax.devices()
    assert settings.use_host_devices(settings=off) is None  # JAX has started: nothing changes
    assert dict(os.environ) == before
