"""fojax.export_cache: lowered programs kept across processes, the same numbers."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax import export_cache


class Pair(NamedTuple):
    gain: jax.Array
    offset: jax.Array


class Out(NamedTuple):
    value: jax.Array
    parts: dict


def _set(name, value):
    before = getattr(jax.config, name)
    jax.config.update(name, value)
    return before


@pytest.fixture
def cache_dir(tmp_path):
    """The persistent compilation cache in a private folder (restored afterwards)."""
    before = _set("jax_compilation_cache_dir", str(tmp_path))
    enabled = _set("jax_enable_compilation_cache", True)
    yield tmp_path
    jax.config.update("jax_compilation_cache_dir", before)
    jax.config.update("jax_enable_compilation_cache", enabled)


def _make(traces: list, scale: float = 3.0):
    def fn(pair, x):
        traces.append(1)  # runs once per trace, never when a program is reused
        y = jnp.sin(pair.gain * x) * scale + pair.offset
        return Out(jnp.sum(y), {"y": y, "max": jnp.max(y)})

    return jax.jit(fn)


ARGS = (Pair(jnp.float64(1.5), jnp.float64(-0.25)), jnp.linspace(0.0, 2.0, 7))


def _equal(a, b):
    return jax.tree.all(jax.tree.map(lambda p, q: bool(np.array_equal(p, q)), a, b))


def test_a_new_process_reuses_the_exported_program_without_tracing(cache_dir):
    traces = []
    first = export_cache.reusable(_make(traces), "toy", {"scale": 3.0})
    got = first(*ARGS)
    assert traces == [1]
    files = sorted((cache_dir / "exported").glob("toy-*.bin"))
    assert len(files) == 1
    # A second wrapper stands for a new process: it loads the file, traces nothing.
    later = []
    again = export_cache.reusable(_make(later), "toy", {"scale": 3.0})(*ARGS)
    assert later == []
    assert type(again) is Out and set(again.parts) == {"y", "max"}
    plain = _make([])(*ARGS)
    assert _equal(got, plain) and _equal(again, plain)
    assert sorted((cache_dir / "exported").glob("toy-*.bin")) == files


def test_another_key_or_shape_is_another_program(cache_dir):
    traces = []
    call = export_cache.reusable(_make(traces), "toy", {"scale": 3.0})
    call(*ARGS)
    call(ARGS[0], jnp.linspace(0.0, 1.0, 5))
    other = []
    result = export_cache.reusable(_make(other, scale=2.0), "toy", {"scale": 2.0})(*ARGS)
    assert traces == [1, 1] and other == [1]
    assert len(list((cache_dir / "exported").glob("toy-*.bin"))) == 3
    assert _equal(result, _make([], scale=2.0)(*ARGS))


def test_a_damaged_file_is_exported_again(cache_dir):
    export_cache.reusable(_make([]), "toy", {"scale": 3.0})(*ARGS)
    (path,) = (cache_dir / "exported").glob("toy-*.bin")
    path.write_bytes(b"{}\nnot a program")
    traces = []
    result = export_cache.reusable(_make(traces), "toy", {"scale": 3.0})(*ARGS)
    assert traces == [1]
    assert _equal(result, _make([])(*ARGS))
    assert path.read_bytes() != b"{}\nnot a program"


def test_nothing_is_kept_without_the_persistent_cache(cache_dir):
    jax.config.update("jax_enable_compilation_cache", False)
    traces = []
    call = export_cache.reusable(_make(traces), "toy", {"scale": 3.0})
    assert _equal(call(*ARGS), _make([])(*ARGS))
    assert traces == [1]
    assert not (cache_dir / "exported").exists()


def test_a_rotor_layout_in_the_arguments_is_kept_and_named_by_its_geometry(cache_dir):
    """A plant with a :class:`fojax.rotors.Layout` (a static node): exported, reloaded
    without tracing, the same numbers; another layout is another program."""
    from fojax import plant, rotors

    def make(traces):
        def fn(params, inputs):
            traces.append(1)
            return plant.rotor_speeds_squared(params, inputs)

        return jax.jit(fn)

    inputs = jnp.array([7.5, 0.01, -0.02, 0.003])
    x = plant.nominal_params(jnp.float64)._replace(layout=rotors.x(0.21))
    first = export_cache.reusable(make([]), "mix", {"k": 1})(x, inputs)
    later = []
    again = export_cache.reusable(make(later), "mix", {"k": 1})(x, inputs)
    assert later == [] and np.array_equal(first, again)
    np.testing.assert_array_equal(again, make([])(x, inputs))
    other = []
    tilted = x._replace(layout=rotors.Layout(x.layout.positions, (-1, 1, -1, 1)))
    flipped = export_cache.reusable(make(other), "mix", {"k": 1})(tilted, inputs)
    assert other == [1] and not np.array_equal(flipped, first)
    assert rotors.Layout.from_bytes(x.layout.to_bytes()) == x.layout
