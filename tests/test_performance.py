"""The benchmark's pieces: NumPy reference, sharding over devices, bench smoke test.

No test here asserts a speed; speed lives in ``fojax bench``.
"""

import json
import os
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_python
from jax import lax

from experiments import bench_report, blocks
from fojax import fractional, observers, plant, scenarios, sharding, simulator
from fojax.cli import bench, bench_measure, numpy_reference, output
from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains

SCENARIO_2 = scenarios.get_scenario(2)


@pytest.mark.parametrize("switching", ("tanh", "sat"))
def test_numpy_reference_agrees_with_jax_rollout(switching):
    config = simulator.SimulationConfig(dt=1e-3, horizon=0.3, save_every=50)
    controller = AFONFTSMC(dt=1e-3, horizon=80.0, switching=switching)
    draws = jax.vmap(lambda k: scenarios.sample_draw(SCENARIO_2, k, config.dt))(
        scenarios.draw_keys(11, range(3))
    )
    gains = paper_gains()
    model = plant.nominal_params()
    result = jax.jit(
        jax.vmap(
            lambda d: simulator.rollout(
                controller, gains, model, SCENARIO_2, d, config, observers.TrackingISE(config.dt)
            )
        )
    )(draws)
    reference = numpy_reference.rollout(controller, gains, model, SCENARIO_2, draws, config)
    assert np.asarray(result.final_state).dtype == np.float64
    # The draws really differ and the state really moved: the comparison is not vacuous.
    assert np.ptp(reference.final_state[:, 0]) > 1e-6
    np.testing.assert_allclose(reference.final_state, result.final_state, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(reference.cost, result.outputs, rtol=1e-9)
    np.testing.assert_array_equal(reference.status, result.status)


def test_numpy_reference_rejects_what_it_does_not_implement():
    config = simulator.SimulationConfig(dt=1e-3, horizon=0.01, save_every=10)
    draws = jax.vmap(lambda k: scenarios.sample_draw(SCENARIO_2, k, config.dt))(
        scenarios.draw_keys(0, range(2))
    )
    oustaloup = AFONFTSMC(dt=1e-3, horizon=1.0, fractional_method="oustaloup")
    with pytest.raises(ValueError, match="'soe' fractional method only"):
        numpy_reference.rollout(
            oustaloup, paper_gains(), plant.nominal_params(), SCENARIO_2, draws, config
        )
    with pytest.raises(ValueError, match="scenarios 1 and 2 only"):
        numpy_reference.rollout(
            AFONFTSMC(dt=1e-3, horizon=1.0),
            paper_gains(),
            plant.nominal_params(),
            scenarios.get_scenario(3),
            draws,
            config,
        )


@pytest.mark.parametrize("method", ("soe", "oustaloup"))
def test_integral_with_rate_equals_multi_order(method):
    # One memory giving I^b u and its rate D^(1-b) u equals the two orders run apart.
    dt = 1e-3
    operator = fractional.make_operator(method, dt, 1.0)
    pair = fractional.integral_with_rate(operator)
    multi = fractional.MultiOrder(operator, 2)
    t = np.arange(1001) * dt
    u = jnp.asarray(np.stack([np.sin(1.7 * t), np.cos(t) + t], axis=1))
    b = jnp.asarray([0.3, 0.01])
    pair_coeffs = pair.coefficients(b, u.dtype)
    multi_coeffs = multi.coefficients((-b, 1.0 - b), u.dtype)
    _, (integral, rate) = lax.scan(
        lambda s, x: pair.step(pair_coeffs, s, x), pair.init((2,), u.dtype), u
    )
    _, (integral_ref, rate_ref) = lax.scan(
        lambda s, x: multi.step(multi_coeffs, s, x), multi.init((2,), u.dtype), u
    )
    assert isinstance(pair, fractional.SOEIntegralWithRate) == (method == "soe")
    assert float(jnp.max(jnp.abs(rate_ref))) > 0.5
    np.testing.assert_allclose(integral, integral_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rate, rate_ref, rtol=1e-10, atol=1e-10)


_SHARDED_SCRIPT = textwrap.dedent(
    """
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert jax.device_count() == 4, jax.devices()
    from fojax import plant, scenarios, sharding, simulator
    from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains

    scenario = scenarios.get_scenario(2)
    config = simulator.SimulationConfig(dt=1e-3, horizon=0.05, save_every=10)
    controller = AFONFTSMC(dt=1e-3, horizon=80.0, switching="sat")
    model = plant.nominal_params()

    def batch(gains, keys):
        draws = scenarios.sample_draws(scenario, keys, config.dt)
        result = simulator.rollout(controller, gains, model, scenario, draws, config)
        return scenarios.batch_first(result)

    keys, count = sharding.pad_draws(np.asarray(scenarios.draw_keys(5, range(10))), 4)
    assert count == 10 and keys.shape[0] == 12
    mesh = sharding.draw_mesh()
    placed = sharding.shard_draws(keys, mesh)
    assert len(placed.sharding.device_set) == 4
    sharded = sharding.sharded_batch(batch, mesh, batched=(False, True))(paper_gains(), placed)
    assert len(sharded.final_state.sharding.device_set) == 4
    run = sharding.sharded_batch(batch, sharding.one_device_mesh(), batched=(False, True))
    whole = run(paper_gains(), keys)
    # One device, the same program as each shard's (3 draws at a time): bit for bit.
    chunks = [run(paper_gains(), keys[i : i + 3]) for i in range(0, 12, 3)]
    for leaf, *parts in zip(jax.tree.leaves(sharded), *map(jax.tree.leaves, chunks)):
        np.testing.assert_array_equal(np.asarray(leaf), np.concatenate(parts))
    # One device, all draws in one batch: the same to rounding (XLA may vectorise a
    # batch of 12 differently from one of 3).
    for a, b in zip(jax.tree.leaves(sharded), jax.tree.leaves(whole)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)
    assert np.ptp(np.asarray(whole.final_state)[:, 0]) > 0
    # The Monte Carlo layer on the mesh: blocks of 3 draws, one per device and call
    # (10 draws: 4 blocks, one call); one device: 4 calls. Bit for bit the same.
    from fojax import study
    setup = (controller, paper_gains(), scenario, config, 10)
    on_mesh = study.run(*setup, seed=5, device_batch=3, keep=3, progress=False, mesh=mesh)
    alone = study.run(*setup, seed=5, device_batch=3, keep=3, progress=False)
    assert on_mesh.layout["calls"] == 1 and alone.layout["calls"] == 4
    assert on_mesh.status.shape == (10,)
    np.testing.assert_array_equal(on_mesh.status, alone.status)
    assert sorted(on_mesh.per_draw) == sorted(alone.per_draw)
    for name, values in alone.per_draw.items():
        assert values.shape[0] == 10, name
        np.testing.assert_array_equal(on_mesh.per_draw[name], values)
    assert on_mesh.trajectories.state.shape[0] == 3
    np.testing.assert_array_equal(on_mesh.trajectories.state, alone.trajectories.state)
    assert np.ptp(alone.per_draw["position_rmse"]) > 0
    print("IDENTICAL", len(jax.tree.leaves(whole)))
    """
)


def test_sharded_run_is_identical_to_single_device_run():
    env = dict(os.environ)
    # Keep the suite's flags (conftest), add the four host devices.
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"
    env["JAX_PLATFORMS"] = "cpu"
    assert "IDENTICAL" in run_python("-c", _SHARDED_SCRIPT, env=env)


def test_sharding_validates_before_placing():
    mesh = sharding.draw_mesh(jax.devices()[:1])
    with pytest.raises(ValueError, match="same leading"):
        sharding.shard_draws({"a": np.zeros((3, 2)), "b": np.zeros((4,))}, mesh)
    with pytest.raises(ValueError, match="True .batched. or False"):
        sharding.sharded_batch(lambda x: x, mesh, batched=(1,))
    with pytest.raises(ValueError, match="positive integer"):
        sharding.pad_draws(np.zeros((3,)), 0)
    padded, count = sharding.pad_draws({"a": np.arange(5.0)}, 4)
    assert count == 5
    np.testing.assert_array_equal(padded["a"], [0, 1, 2, 3, 4, 4, 4, 4])
    info = sharding.initialize()  # single process: nothing to join
    assert info["process_count"] == 1


def test_bench_rejects_bad_sizes_before_running(capsys):
    for bad in (["--draws", "0"], ["--draws", "1,x"], ["--long-horizon", "-1"]):
        with pytest.raises(SystemExit):
            bench.main(bad)
        assert "positive" in capsys.readouterr().err


def test_bench_smoke(tmp_path):
    out = tmp_path / "bench.json"
    result = bench.main(["--small", "--json", str(out)])
    stored = json.loads(out.read_text())
    assert stored["workload"]["scenario"] == 2 and stored["units"]
    for section in ("forward", "numpy", "gradient", "comparison"):
        assert stored[section], section
    forward = stored["forward"][0]
    assert forward["draw_steps_per_s"] > 0 and forward["compile_s"] > 0
    assert forward["steps"] == round(forward["horizon_s"] / 1e-3)
    gradient = stored["gradient"][0]
    assert gradient["gradient_draw_steps_per_s"] > 0
    assert gradient["gradient_memory"].get("peak_bytes", 1) > 0
    assert result["forward"][0]["draws"] == forward["draws"]
    assert set(forward["compile_phases_s"]) == {"trace_s", "lower_s", "xla_s"}
    assert forward["loop_kernels"][0] > 0 and gradient["gradient_loop_kernels"][0] > 0
    machine = stored["machine"]
    assert machine["cpu_model"] == output.cpu_model() and machine["cores"] >= 1
    assert len(machine["load_average"]) == len(machine["load_average_end"]) == 3
    # experiments/bench_report.py renders it, labelled from the JSON
    doc = tmp_path / "performance.md"
    doc.write_text("<!-- bench:begin -->\n<!-- bench:end -->\n")
    assert bench_report.main(["--from", str(out), "--update-doc", str(doc)]) == 0
    text = blocks.block_text(doc.read_text(), blocks.Block("bench", "d", ("python",), ()))
    label = blocks.read_label(text)
    assert label["commit"] == stored["provenance"]["fojax_git"]["commit"]
    assert label["command"] == stored["provenance"]["command"]
    assert f"| {forward['draws']} | {forward['horizon_s']:g} s |" in text


_HLO = """HloModule m

%inner (p: (s32[], f32[4])) -> (s32[], f32[4]) {
  %p = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%p), index=0
  %x = f32[4]{0} get-tuple-element(%p), index=1
  %one = s32[] constant(1)
  %j = s32[] add(%i, %one)
  %y = f32[4]{0} fusion(%x), kind=kLoop, calls=%f
  %z = f32[4]{0} copy(%y)
  %b = f32[4]{0} bitcast(%z)
  ROOT %t = (s32[], f32[4]{0}) tuple(%j, %b)
}

%outer (q: (s32[], f32[4])) -> (s32[], f32[4]) {
  %q = (s32[], f32[4]{0}) parameter(0)
  %c = f32[4]{0} copy(%q)
  ROOT %w = (s32[], f32[4]{0}) while(%q), condition=%cond, body=%inner
}

ENTRY %main (a: f32[4]) -> f32[4] {
  %a = f32[4]{0} parameter(0)
  %v = (s32[], f32[4]{0}) while(%a), condition=%cond, body=%outer
  ROOT %r = f32[4]{0} get-tuple-element(%v), index=1
}
"""


def test_loop_kernels_counts_the_innermost_loops_instructions():
    class Compiled:
        def as_text(self):
            return _HLO

    # add, fusion and copy in the inner loop; the outer loop holds a loop
    assert bench_measure.loop_kernels(Compiled()) == [3]

    def scan(x):
        return lax.scan(lambda c, _: (jnp.sin(c) * 2.0 + c, None), x, None, length=8)[0]

    compiled = jax.jit(scan).lower(jnp.ones(4)).compile()
    counts = bench_measure.loop_kernels(compiled)
    assert counts and counts[0] >= 1


def test_bench_forward_runs_big_batches_in_chunks():
    mesh = sharding.draw_mesh(jax.devices()[:1])
    entry = bench.measure_forward(5, 0.01, 1, mesh, chunk=2)
    assert entry["calls"] == 3 and entry["chunk"] == 2 and entry["draws_computed"] == 6
    assert entry["draw_steps_per_s"] > 0 and entry["one_call_draw_steps_per_s"] > 0
    assert bench.measure_forward(2, 0.01, 1, mesh, chunk=8)["calls"] == 1
