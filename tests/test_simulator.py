"""Closed loop: plant + AFONFTSMC + scenarios."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax import observers, plant, scenarios, simulator
from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains


def _undisturbed(scenario_id):
    """The scenario's reference and initial state, exact model, no disturbance."""
    return dataclasses.replace(
        scenarios.get_scenario(scenario_id),
        disturbance=lambda t: jnp.zeros(6),
        drag_variation=0.0,
        noise_std_position=0.0,
        noise_std_attitude=0.0,
        mass_uncertainty=0.0,
        inertia_uncertainty=0.0,
    )


def _ise(config):
    return observers.TrackingISE(config.dt)


def _run(scenario, controller, config, gains, keys):
    draws = jax.vmap(lambda k: scenarios.sample_draw(scenario, k, config.dt))(keys)
    return jax.vmap(
        lambda g, d: simulator.rollout(
            controller,
            g,
            plant.nominal_params(),
            scenario,
            d,
            config,
            observers.TrackingISE(config.dt),
        ),
        in_axes=(None, 0),
    )(gains, draws)


@pytest.mark.parametrize("scenario_id", (1, 3))
def test_tracks_reference_without_disturbances(scenario_id):
    scenario = _undisturbed(scenario_id)
    config = simulator.SimulationConfig(dt=1e-3, horizon=scenario.horizon, save_every=500)
    controller = AFONFTSMC(dt=1e-3, horizon=scenario.horizon, switching="sat")
    result = jax.jit(_run, static_argnums=(0, 1, 2))(
        scenario, controller, config, paper_gains(), scenarios.draw_keys(0, [0])
    )
    trajectory = jax.tree.map(lambda x: np.asarray(x[0]), result.trajectory)
    position_error = trajectory.state[:, :3] - trajectory.reference[:, :3]
    yaw_error = trajectory.state[:, 5] - trajectory.reference[:, 3]
    last_5s = trajectory.time >= scenario.horizon - 5.0
    assert np.max(np.abs(position_error[last_5s])) < 1e-2
    assert np.max(np.abs(yaw_error[last_5s])) < 1e-3
    # The initial error is not small: tracking is really achieved, not started there.
    assert np.max(np.abs(position_error)) > 0.04
    assert int(result.status[0]) & simulator.NONFINITE == 0


SHORT = simulator.SimulationConfig(dt=1e-3, horizon=0.4, save_every=50)
SHORT_CONTROLLER = AFONFTSMC(dt=1e-3, horizon=0.4, switching="tanh")
SCENARIO_2 = scenarios.get_scenario(2)
_short_run = jax.jit(_run, static_argnums=(0, 1, 2))


def test_vmap_equals_loop_and_draws_do_not_depend_on_batch():
    gains = paper_gains()
    batch = _short_run(SCENARIO_2, SHORT_CONTROLLER, SHORT, gains, scenarios.draw_keys(7, range(8)))
    for i in (0, 5):
        alone = _short_run(SCENARIO_2, SHORT_CONTROLLER, SHORT, gains, scenarios.draw_keys(7, [i]))
        np.testing.assert_allclose(batch.final_state[i], alone.final_state[0], rtol=1e-12)
        np.testing.assert_allclose(batch.outputs[i], alone.outputs[0], rtol=1e-12)
    # Draw 5 among 1000 draws equals draw 5 among 8.
    keys = scenarios.draw_keys(7, range(1000))
    wide = _short_run(SCENARIO_2, SHORT_CONTROLLER, SHORT, gains, keys)
    np.testing.assert_allclose(wide.final_state[5], batch.final_state[5], rtol=1e-12)
    # The same seed gives identical results; another seed does not.
    again = _short_run(SCENARIO_2, SHORT_CONTROLLER, SHORT, gains, scenarios.draw_keys(7, range(8)))
    np.testing.assert_array_equal(np.asarray(again.final_state), np.asarray(batch.final_state))
    other = _short_run(SCENARIO_2, SHORT_CONTROLLER, SHORT, gains, scenarios.draw_keys(8, range(8)))
    assert not np.allclose(np.asarray(other.final_state), np.asarray(batch.final_state))


def test_gradient_with_respect_to_gains_matches_finite_differences():
    scenario = SCENARIO_2
    draw = scenarios.sample_draw(scenario, scenarios.draw_keys(3, [0])[0], SHORT.dt)
    base = paper_gains()
    direction = jax.tree.map(
        lambda x: jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, x.shape)) * x, base
    )
    # Perturb only smooth gains (the fractional orders included).
    names = ("surface_c1", "surface_c2", "reaching_h1", "reaching_h2", "gamma1", "gamma2")
    direction = base._replace(
        **{
            f: (getattr(direction, f) if f in names else jnp.zeros_like(getattr(base, f)))
            for f in base._fields
        }
    )

    def cost(scale):
        gains = jax.tree.map(lambda g, d: g + scale * 1e-2 * d, base, direction)
        cost = observers.TrackingISE(SHORT.dt)
        return simulator.rollout(
            SHORT_CONTROLLER, gains, plant.nominal_params(), scenario, draw, SHORT, cost
        ).outputs

    grad = jax.jit(jax.grad(cost))(0.0)
    eps = 1e-4
    fd = (cost(eps) - cost(-eps)) / (2 * eps)
    assert np.isfinite(float(grad)) and abs(float(grad)) > 0
    assert float(grad) == pytest.approx(float(fd), rel=1e-5)


@pytest.mark.parametrize(
    "field,value,match",
    [
        ("ratio", 2.5, "1 < p/q < 2"),
        ("ratio", 1.0, "1 < p/q < 2"),
        ("gamma1", 1.2, "0 < gamma1 < 1"),
        ("gamma2", 0.0, "0 < gamma2 < 1"),
        ("reaching_h1", -1.0, "reaching_h1 must be > 0"),
        ("surface_c2", float("nan"), "must be finite"),
    ],
)
def test_bad_gains_are_rejected(field, value, match):
    gains = paper_gains()
    gains = gains._replace(**{field: getattr(gains, field).at[0].set(value)})
    with pytest.raises(ValueError, match=match):
        AFONFTSMC.check_gains(gains)


def test_bad_configuration_is_rejected():
    # The laws' own settings: tests/test_controllers.py.
    with pytest.raises(ValueError, match="horizon"):
        simulator.SimulationConfig(horizon=-1.0)
    with pytest.raises(ValueError, match="dt"):
        simulator.SimulationConfig(dt=0.0)
    AFONFTSMC.check_gains(paper_gains())  # the paper's gains are valid
