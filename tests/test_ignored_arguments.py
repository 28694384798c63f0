"""Arguments of the public entry points that would be accepted and then ignored, or
misread, are errors that say what to change (issue 22). Nothing here compiles: every
check runs in Python before a rollout is traced.

The controllers' options (``make_controller``) are tested in tests/test_controllers.py,
the tuner's problem in tests/test_optimize.py, the commands' options in
tests/test_simulate_cli.py, tests/test_tune_cli.py and tests/test_bad_inputs.py.
"""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import usage_error

from fojax import metrics, scenarios, simulator, study
from fojax.controllers import FL, gains_io, make_controller, paper_gains

DT = 1e-3
CONFIG = simulator.SimulationConfig(dt=DT, horizon=0.2, save_every=50)
SCENARIO = dataclasses.replace(scenarios.get_scenario(2), horizon=0.2)


# ----------------------------------------------------------------------------- scenarios


@pytest.mark.parametrize("given", [2.7, True, "2.5", "two", None, 0, 4, np.float32(1.5)])
def test_a_scenario_id_that_is_not_one_is_an_error(given):
    """``int(2.7)`` would silently be scenario 2, ``True`` scenario 1."""
    with pytest.raises(ValueError, match="unknown scenario id"):
        scenarios.get_scenario(given)


def test_a_scenario_id_may_be_an_integer_in_any_spelling():
    for given in (2, 2.0, "2", np.int64(2), jnp.asarray(2)):
        assert scenarios.get_scenario(given).scenario_id == 2


@pytest.mark.parametrize(
    "change, message",
    [
        ({"noise_std_position": -0.1}, "noise_std_position must be >= 0"),
        ({"mass_uncertainty": -0.3}, "mass_uncertainty must be >= 0"),
        ({"drag_variation": -0.2}, r"drag_variation must lie in \[0, 1\)"),
        ({"drag_variation": 1.5}, r"drag_variation must lie in \[0, 1\)"),
        ({"horizon": 0.0}, "horizon must be > 0"),
        ({"noise_hold": float("nan")}, "noise_hold must be finite"),
        ({"drag_hold": "1"}, "drag_hold must be a number"),
        ({"initial_position": (0.0, 0.0)}, "initial_position must be three numbers"),
        ({"reference": 3.0}, "reference must be a function of time"),
    ],
)
def test_scenario_settings_that_would_be_ignored_are_errors(change, message):
    """A negative standard deviation or variation used to turn the process off
    (``has_noise``, ``has_drag_variation`` test ``> 0``) without a word."""
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(scenarios.get_scenario(2), **change)


def test_a_member_index_is_checked_where_it_is_known():
    key = scenarios.draw_keys(0, [0])[0]
    with pytest.raises(ValueError, match="member=1 given for .* not a union"):
        scenarios.sample_draw(SCENARIO, key, DT, member=1)
    bank = scenarios.union(SCENARIO, dataclasses.replace(scenarios.get_scenario(3), horizon=0.1))
    with pytest.raises(ValueError, match="member must be 0 to 1 for this union of 2"):
        scenarios.sample_draw(bank, key, DT, member=2)  # JAX would clamp it to 1
    with pytest.raises(ValueError, match="member must be an integer index"):
        scenarios.sample_draw(bank, key, DT, member=0.5)
    assert int(scenarios.sample_draw(bank, key, DT, member=np.int32(1)).member) == 1


@pytest.mark.parametrize("indices", [[2**32], [-1], np.asarray([0, 2**32 + 5], np.int64)])
def test_draw_indices_that_would_wrap_are_errors(indices):
    """Index 2**32 would be folded in as 0: draw 0 again."""
    with pytest.raises(ValueError, match=r"draw indices must lie in \[0, 2\*\*32\)"):
        scenarios.draw_keys(0, indices)


def test_draw_keys_are_unchanged_by_the_check():
    keys = np.asarray(scenarios.draw_keys(7, 2**31 + np.arange(3)))
    again = np.asarray(scenarios.draw_keys(7, [2**31, 2**31 + 1, 2**31 + 2]))
    np.testing.assert_array_equal(keys, again)
    assert scenarios.draw_keys(7, []).shape == (0, 2)


# ---------------------------------------------------------------------------- Monte Carlo


def _run(controller=None, scenario=SCENARIO, config=CONFIG, **kwargs):
    controller = controller or make_controller("afonftsmc", dt=DT, horizon=0.2)
    return study.run(controller, paper_gains(), scenario, config, 4, progress=False, **kwargs)


def test_a_controller_made_for_another_step_is_an_error():
    """Its command filter and fractional weights are discretised for its own dt."""
    with pytest.raises(ValueError, match=r"made for dt=0.002 but the simulation steps at dt=0.001"):
        _run(make_controller("afonftsmc", dt=2e-3, horizon=0.2))
    with pytest.raises(ValueError, match="made for dt=0.002"):
        study.make_chunk_runner(make_controller("fl", dt=2e-3), SCENARIO, CONFIG)


def test_a_horizon_that_is_not_a_whole_number_of_steps_is_an_error():
    """SimulationConfig(horizon=0.0105, dt=0.002) would run 5 steps, 0.01 s."""
    config = simulator.SimulationConfig(dt=2e-3, horizon=0.0105, save_every=5)
    with pytest.raises(ValueError, match=r"not a whole number of steps .* e.g. horizon=0.01"):
        _run(make_controller("afonftsmc", dt=2e-3, horizon=0.0105), config=config)


def test_a_scenario_shorter_than_the_simulation_is_an_error():
    """Its random tables end at its own horizon; past it the last row would be held."""
    short = dataclasses.replace(SCENARIO, horizon=0.1)
    with pytest.raises(ValueError, match=r"scenario's horizon \(0.1 s\) is shorter"):
        _run(scenario=short)


def test_metrics_settings_made_for_another_run_are_an_error():
    other = metrics.MetricsConfig(dt=2e-3, steps=100)
    with pytest.raises(ValueError, match="metrics_config is made for dt=0.002, 100 steps"):
        _run(metrics_config=other)


@pytest.mark.parametrize("keep", [-1, 2.5, True])
def test_a_keep_that_is_not_a_count_is_an_error(keep):
    """A negative keep used to be read as 0, 2.5 as 2."""
    with pytest.raises(ValueError, match="keep must be an integer >= 0"):
        _run(keep=keep)


# ---------------------------------------------------------------------------- gains files


def test_save_gains_writes_only_what_load_gains_reads(tmp_path):
    path = tmp_path / "gains.json"
    with pytest.raises(ValueError, match="cannot save these gains as 'afonftsmc' gains"):
        gains_io.save_gains(path, "afonftsmc", FL.default_gains())
    bad = paper_gains()._replace(gamma1=jnp.full(6, 1.5))
    with pytest.raises(ValueError, match="0 < gamma1 < 1"):
        gains_io.save_gains(path, "afonftsmc", bad)
    with pytest.raises(ValueError, match="metadata must be a dict"):
        gains_io.save_gains(path, "afonftsmc", paper_gains(), metadata="tuned")
    assert not path.exists()
    gains_io.save_gains(path, "afonftsmc", paper_gains(), {"note": "ok"})
    assert gains_io.load_gains(path)[2] == {"note": "ok"}


@pytest.mark.parametrize("metadata", [[], "tuned by hand", 0, None])
def test_metadata_that_is_not_an_object_is_an_error(tmp_path, metadata):
    """It used to be returned as it was, or as {} when empty."""
    path = tmp_path / "gains.json"
    gains = gains_io.gains_to_dict(paper_gains())
    path.write_text(json.dumps({"controller": "afonftsmc", "gains": gains, "metadata": metadata}))
    with pytest.raises(ValueError, match="'metadata' must be a JSON object"):
        gains_io.load_gains(path)


# ------------------------------------------------------------------------------ scripts


def test_fair_comparison_refuses_adams_step_for_lbfgs(capsys):
    from experiments import fair_comparison

    err = usage_error(capsys, fair_comparison.parse_args, ["--learning-rate", "0.2"])
    assert "--learning-rate applies to --method adam only" in err
    args = fair_comparison.parse_args(["--method", "adam", "--learning-rate", "0.2"])
    assert args.learning_rate == 0.2
    assert fair_comparison.parse_args([]).learning_rate is None  # the method table's default
