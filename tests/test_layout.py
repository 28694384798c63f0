"""Draw i's numbers do not depend on the draw count or the devices, bit for bit, in
float32 and float64, at XLA's default optimisation (the suite compiles at level 0 to
save time; the commands do not), for the AFONFTSMC and the FOBSMC (whose dots XLA's
CPU library kernels round according to a draw's place in its batch)."""

import os
import textwrap

import pytest
from conftest import run_python

_SCRIPT = textwrap.dedent(
    """
    import dataclasses, sys
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from fojax import scenarios, sharding, simulator, study
    from fojax.controllers import registry

    assert jax.device_count() == 2, jax.devices()
    mesh = sharding.draw_mesh()
    horizon = 0.2
    scenario = dataclasses.replace(scenarios.get_scenario(3), horizon=horizon)
    config = simulator.SimulationConfig(dt=1e-3, horizon=horizon, save_every=50)
    for name, dtype in (("afonftsmc", "float32"), ("fobsmc", "float32"), ("fobsmc", "float64")):
        controller = registry.make_controller(name, dt=1e-3, horizon=horizon, switching="sign")
        gains = jax.tree.map(lambda g: jnp.asarray(g, dtype), controller.default_gains())
        setup = (controller, gains, scenario, config)
        kw = dict(seed=11, device_batch=16, keep=4, progress=False, dtype=jnp.dtype(dtype))
        # 40 draws on 2 devices: blocks 0-1 in one call, block 2 with a copy of itself.
        wide = study.run(*setup, 40, mesh=mesh, **kw)
        # 20 draws on one device: blocks 0 and 1 in two calls.
        narrow = study.run(*setup, 20, **kw)
        assert wide.layout["calls"] == 2 and narrow.layout["calls"] == 2
        np.testing.assert_array_equal(wide.status[:20], narrow.status)
        for metric, values in narrow.per_draw.items():
            np.testing.assert_array_equal(wide.per_draw[metric][:20], values, err_msg=metric)
        np.testing.assert_array_equal(wide.trajectories.state, narrow.trajectories.state)
        assert np.ptp(narrow.per_draw["position_rmse"]) > 0
        print("IDENTICAL", name, dtype)
    """
)


@pytest.mark.slow
def test_draws_are_bit_identical_across_draw_counts_and_devices():
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "").replace("--xla_backend_optimization_level=0", "")
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count=2".strip()
    env["JAX_PLATFORMS"] = "cpu"
    out = run_python("-c", _SCRIPT, env=env, timeout=900)
    assert out.count("IDENTICAL") == 3, out
