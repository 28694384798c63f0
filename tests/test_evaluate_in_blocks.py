"""fojax.blocks: many draws in blocks, one per device and call, padded by repeating the
last key; the same numbers as a direct call; a bounded cache of evaluators."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_python

from fojax import blocks, metrics, plant, scenarios, sharding, simulator, study
from fojax.controllers import registry

DT, HORIZON = 1e-3, 0.02


def _rollout():
    """A closed-loop rollout of draws from their keys, per-draw outputs first."""
    scenario = dataclasses.replace(scenarios.get_scenario(2), horizon=HORIZON)
    config = simulator.SimulationConfig(dt=DT, horizon=HORIZON, save_every=10)
    controller = registry.make_controller("fl", dt=DT, horizon=HORIZON)
    model = plant.nominal_params(jnp.float64)
    observer = metrics.Metrics(metrics.MetricsConfig(dt=DT, steps=config.steps))

    def run(gains, keys):
        draws = scenarios.sample_draws(scenario, keys, DT, jnp.float64)
        result = simulator.rollout(controller, gains, model, scenario, draws, config, observer)
        return scenarios.batch_first((result.status, result.outputs))

    return run, controller.default_gains(jnp.float64)


def _same(got, want):
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        assert isinstance(a, np.ndarray)
        np.testing.assert_array_equal(a, b)


def test_blocks_give_a_direct_calls_numbers_in_float64():
    """7 draws in blocks of 3 (the last block completed by repeating the last key), on
    no mesh and on a one-device mesh: each draw as an unpadded call of all 7 has it."""
    assert jnp.zeros(()).dtype == jnp.float64
    run, gains = _rollout()
    keys = np.asarray(scenarios.draw_keys(3, range(7)))
    direct = jax.tree.map(np.asarray, jax.jit(run)(gains, keys))
    _same(blocks.evaluate_in_blocks(jax.jit(run), gains, keys, block=3), direct)
    mesh = sharding.one_device_mesh()
    on_mesh = sharding.sharded_batch(run, mesh, batched=(False, True))
    _same(blocks.evaluate_in_blocks(on_mesh, gains, keys, mesh, 3), direct)
    assert study.evaluate_in_blocks is blocks.evaluate_in_blocks


_TWO_DEVICES = """
from fojax import settings
assert settings.use_host_devices(2) == 2
import jax, jax.numpy as jnp, numpy as np
from fojax import blocks, sharding
mesh = sharding.draw_mesh()
calls = []
def per_block(scale, keys):
    return {"value": keys[:, 0] * scale + jnp.arange(keys.shape[0])}
program = sharding.sharded_batch(per_block, mesh, batched=(False, True))
def fn(scale, keys):
    calls.append(keys.shape)
    return program(scale, keys)
keys = np.stack([np.arange(5), np.zeros(5)], 1).astype(np.uint32)
out = blocks.evaluate_in_blocks(fn, jnp.asarray(10, jnp.uint32), keys, mesh, block=2)
# draw i sits at position i % 2 of its block: value 10 i + i % 2
assert out["value"].tolist() == [10 * i + i % 2 for i in range(5)], out
assert calls == [(4, 2), (4, 2)], calls
print(mesh.devices.size)
"""


def test_blocks_split_over_two_devices():
    """Two calls of one block per device for 5 draws in blocks of 2 (3 keys of padding),
    each draw where its block puts it."""
    assert run_python("-c", _TWO_DEVICES, timeout=300).split() == ["2"]


def test_bad_blocks_are_named():
    with pytest.raises(ValueError, match="at least one key"):
        blocks.evaluate_in_blocks(lambda s, k: k, None, np.zeros((0, 2)))
    with pytest.raises(ValueError, match="block must be a positive integer"):
        blocks.evaluate_in_blocks(lambda s, k: k, None, np.zeros((3, 2)), block=0)


def test_the_evaluator_cache_is_bounded():
    cache = blocks.EvaluatorCache(2)
    built = []

    def build(name):
        def make():
            built.append(name)
            return name

        return make

    assert [cache.get(k, build(k)) for k in ("a", "b", "a", "c", "a", "b")] == list("abacab")
    assert built == ["a", "b", "c", "b"] and len(cache) == 2  # b was the least recent
    assert cache.get(["unhashable"], build("x")) == "x" and len(cache) == 2
    with pytest.raises(ValueError, match="size"):
        blocks.EvaluatorCache(0)
