"""Requirements: parsing and its errors, the yield against counts made by hand, the
Clopper-Pearson interval, the requirement metrics of a short rollout."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from fojax import requirements as rq

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "requirements" / "small_quadrotor.toml"


def _entry(**kw):
    base = {"name": "r", "metric": "position_rmse", "max": 0.1, "unit": "m"}
    base.update(kw)
    return base


def _errors(data) -> str:
    with pytest.raises(rq.RequirementError) as info:
        rq.parse(data)
    return str(info.value)


# ------------------------------------------------------------------------- parsing


def test_example_file_parses():
    reqs = rq.load(EXAMPLE)
    assert len(reqs) == 6
    assert reqs.settings.thrust_to_weight == 2.0
    assert reqs.settings.simulation_limit() == pytest.approx(34.7836, abs=1e-3)
    overshoot = reqs.requirements[0]
    assert (overshoot.metric, overshoot.bound, overshoot.unit) == (
        "position_overshoot",
        "upper",
        "cm",
    )
    assert overshoot.canonical_value == pytest.approx(0.10)
    tilt = next(r for r in reqs if r.metric == "max_tilt")
    assert tilt.canonical_value == pytest.approx(math.radians(30))
    share = next(r for r in reqs if r.metric == "rotor_saturation")
    assert share.canonical_value == pytest.approx(0.02)


def test_json_and_python_give_the_same_set(tmp_path):
    reqs = rq.load(EXAMPLE)
    path = tmp_path / "r.json"
    path.write_text(json.dumps(reqs.to_dict()))
    again = rq.load(path)
    assert again == reqs
    built = rq.RequirementSet(reqs.requirements, reqs.settings, reqs.description)
    assert built == reqs
    with pytest.raises(dataclasses.FrozenInstanceError):
        reqs.requirements[0].value = 3.0  # immutable


def test_unknown_metric_lists_the_known_ones():
    message = _errors({"requirements": [_entry(metric="overshoot")]})
    assert "unknown metric 'overshoot'" in message
    for name in rq.METRICS:
        assert name in message


def test_wrong_unit_says_which_units_to_write():
    message = _errors({"requirements": [_entry(metric="max_tilt", max=10, unit="m")]})
    assert "'rad' or 'deg'" in message and "got 'm'" in message
    message = _errors({"requirements": [_entry(unit="furlong")]})
    assert "'m' or 'cm' or 'mm'" in message


def test_units_convert():
    reqs = rq.parse(
        {
            "requirements": [
                _entry(name="a", max=50, unit="mm"),
                _entry(name="b", metric="settling_time", max=1500, unit="ms"),
                _entry(name="c", metric="peak_rotor_speed", max=300, unit="rpm"),
            ]
        }
    )
    values = [r.canonical_value for r in reqs]
    assert values == pytest.approx([0.05, 1.5, 300 * 2 * math.pi / 60])


@pytest.mark.parametrize(
    "entry, expected",
    [
        (_entry(max=-0.1), "never negative"),
        (_entry(metric="rotor_saturation", max=1.5, unit="1"), "share in [0, 1]"),
        (_entry(metric="rotor_saturation", max=120, unit="%"), "share in [0, 1]"),
        (_entry(max=float("nan")), "finite"),
        (_entry(max=float("inf")), "finite"),
        (_entry(max="0.1"), "must be a number"),
        ({"name": "r", "metric": "position_rmse", "unit": "m"}, "exactly one of max"),
        (_entry(min=0.01), "exactly one of max"),
        ({"name": "r", "metric": "position_rmse", "min": 0.0, "unit": "m"}, "always met"),
        (_entry(bound="upper"), "unknown keys 'bound'"),
        ({"metric": "position_rmse", "max": 1, "unit": "m"}, "missing name"),
    ],
)
def test_impossible_or_malformed_bounds(entry, expected):
    assert expected in _errors({"requirements": [entry]})


def test_lower_not_below_upper_and_duplicates():
    message = _errors(
        {
            "requirements": [
                {"name": "low", "metric": "position_rmse", "min": 20, "unit": "cm"},
                _entry(name="high", max=0.1),
                _entry(name="high", metric="max_tilt", max=0.3, unit="rad"),
            ]
        }
    )
    assert "lower bound 'low'" in message and "upper bound 'high'" in message
    assert "'high' is used 2 times" in message


def test_every_problem_is_reported_at_once():
    message = _errors(
        {
            "requirements": [_entry(name="a", metric="nope"), _entry(name="b", unit="s")],
            "settings": {"thrust_to_weight": 0.5, "colour": "red"},
            "extra": 1,
        }
    )
    for part in ("unknown metric 'nope'", "got 's'", "cannot hover", "'colour'", "'extra'"):
        assert part in message


def test_file_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[requirements]\nname = 1")
    with pytest.raises(rq.RequirementError, match="not valid TOML"):
        rq.load(bad)
    other = tmp_path / "r.yaml"
    other.write_text("")
    with pytest.raises(rq.RequirementError, match=".toml or .json"):
        rq.load(other)
    with pytest.raises(rq.RequirementError, match="no requirements"):
        rq.parse({"requirements": []})
    with pytest.raises(rq.RequirementError, match="cannot read"):
        rq.load(tmp_path / "missing.toml")


# --------------------------------------------------------------------------- yield

YIELD_SET = rq.parse(
    {
        "requirements": [
            {"name": "rmse", "metric": "position_rmse", "max": 0.1, "unit": "m"},
            {"name": "tilt", "metric": "max_tilt", "max": 0.5, "unit": "rad"},
            {"name": "speed", "metric": "peak_rotor_speed", "min": 10, "unit": "rad/s"},
        ]
    }
)


def test_yield_against_a_count_by_hand():
    # Eight draws, typed in. Pass (P) / fail (F) per requirement, by hand:
    #   draw:        0    1    2     3    4    5    6     7
    #   rmse<=0.1:   P    F    P     P    F    P    P(=)  F(nan)
    #   tilt<=0.5:   P    P    F     P    F    P    P     P
    #   speed>=10:   P    P    P     F    P    P(=) P     P
    # every requirement: draws 0, 5, 6 -> 3 of 8.
    metrics = {
        "position_rmse": np.array([0.05, 0.2, 0.01, 0.09, 0.3, 0.0, 0.1, np.nan]),
        "max_tilt": np.array([0.1, 0.2, 0.6, 0.4, 0.9, 0.5, 0.0, 0.1]),
        "peak_rotor_speed": np.array([20.0, 30.0, 12.0, 9.0, 11.0, 10.0, 15.0, 40.0]),
        "thrust_effort": np.zeros(8),  # not bounded: ignored
    }
    result = rq.evaluate(YIELD_SET, metrics)
    assert result.draws == 8 and result.passed == 3
    assert result.yield_ == pytest.approx(3 / 8)
    assert result.failures == (3, 2, 1)
    assert result.most_failed == "rmse"
    expected = np.array(
        [[1, 0, 1, 1, 0, 1, 1, 0], [1, 1, 0, 1, 0, 1, 1, 1], [1, 1, 1, 0, 1, 1, 1, 1]], bool
    )
    np.testing.assert_array_equal(result.matrix, expected)
    # Clopper-Pearson for 3 of 8 (beta quantiles, values from R's binom.test(3, 8)).
    assert result.interval == pytest.approx((0.08523341, 0.75513678), abs=1e-6)
    summary = result.to_dict()
    json.dumps(summary)
    assert summary["failures"] == {"rmse": 3, "tilt": 2, "speed": 1}
    assert summary["yield"] == 0.375 and summary["most_failed"] == "rmse"
    # An invalid (diverged) draw fails every requirement.
    valid = np.ones(8, bool)
    valid[0] = False
    again = rq.evaluate(YIELD_SET, metrics, valid=valid)
    assert again.passed == 2 and again.failures == (4, 3, 2)
    assert result.describe().endswith("most failed: rmse (3 draws)")
    one = rq.evaluate(YIELD_SET, {k: v[:2] for k, v in metrics.items()})
    assert one.describe().endswith("most failed: rmse (1 draw)")


def test_missing_metric_is_an_error():
    with pytest.raises(KeyError, match="max_tilt"):
        rq.evaluate(YIELD_SET, {"position_rmse": np.zeros(3), "peak_rotor_speed": np.ones(3)})


def test_all_pass_has_no_most_failed():
    metrics = {
        "position_rmse": np.zeros(5),
        "max_tilt": np.zeros(5),
        "peak_rotor_speed": np.full(5, 20.0),
    }
    result = rq.evaluate(YIELD_SET, metrics)
    assert result.passed == 5 and result.most_failed is None


@pytest.mark.parametrize("n", [1, 7, 32, 1024])
def test_clopper_pearson_closed_forms(n):
    # k = 0: [0, 1 - (a/2)^(1/n)]; k = n: [(a/2)^(1/n), 1].
    low, high = rq.clopper_pearson(0, n)
    assert low == 0.0 and high == pytest.approx(1 - 0.025 ** (1 / n), rel=1e-10)
    low, high = rq.clopper_pearson(n, n)
    assert high == 1.0 and low == pytest.approx(0.025 ** (1 / n), rel=1e-10)
    with pytest.raises(ValueError):
        rq.clopper_pearson(n + 1, n)


# ------------------------------------------------------------------ the observer


@pytest.fixture(scope="module")
def short_rollout():
    """FL, scenario 2, 0.3 s, four draws, ideal actuators: the requirement metrics and
    fojax.metrics folded over the same rollout."""
    import jax.numpy as jnp

    import fojax
    from fojax import metrics, observers, plant, scenarios, simulator

    config = simulator.SimulationConfig(dt=1e-3, horizon=0.3, save_every=100)
    scenario = scenarios.get_scenario(2)
    controller = fojax.make_controller("fl", dt=1e-3, horizon=0.3)
    from fojax.controllers import registry

    gains = registry.get_controller_class("fl").default_gains(jnp.float64)
    observer = observers.Chain(
        reference=metrics.Metrics(metrics.MetricsConfig(dt=config.dt, steps=config.steps)),
        requirements=rq.RequirementMetrics(config.dt, config.steps),
    )
    keys = scenarios.draw_keys(0, np.arange(4))
    draws = scenarios.sample_draws(scenario, keys, config.dt, jnp.float64)
    model = plant.nominal_params(jnp.float64)
    result = simulator.rollout(controller, gains, model, scenario, draws, config, observer)
    return result.outputs


def test_requirement_metrics_agree_with_fojax_metrics(short_rollout):
    ref = {k: np.asarray(v) for k, v in short_rollout["reference"].items()}
    got = rq.draw_metrics(short_rollout["requirements"])
    assert set(got) == set(rq.METRICS)
    assert all(v.shape == (4,) for v in got.values())
    np.testing.assert_allclose(got["position_rmse"], ref["position_rmse"], rtol=1e-10)
    np.testing.assert_allclose(got["attitude_rmse"], ref["attitude_rmse"], rtol=1e-10)
    np.testing.assert_allclose(got["position_overshoot"], ref["overshoot"][:3].max(0), rtol=1e-10)
    np.testing.assert_allclose(got["settling_time"], ref["settling_time"][:3].max(0), rtol=1e-10)
    np.testing.assert_allclose(got["rotor_saturation"], ref["actuator_saturation"], atol=1e-12)
    torque = np.sqrt(np.sum(ref["control_effort"][1:] ** 2, 0))
    np.testing.assert_allclose(got["torque_effort"], torque, rtol=1e-8)
    assert np.all(got["max_position_error"] >= got["steady_state_error"])
    assert np.all((got["max_tilt"] >= 0) & (got["max_tilt"] < np.pi / 2))


def test_violations_sign_matches_the_pass_matrix():
    metrics = {
        "position_rmse": np.array([0.05, 0.2]),
        "max_tilt": np.array([0.6, 0.1]),
        "peak_rotor_speed": np.array([5.0, 12.0]),
    }
    v = np.asarray(rq.violations(YIELD_SET, metrics))
    np.testing.assert_array_equal(v <= 0, rq.pass_matrix(YIELD_SET, metrics))
    assert v[0, 1] == pytest.approx((0.2 - 0.1) / 0.1)


def test_docs_list_every_metric():
    page = (ROOT / "docs" / "requirements.md").read_text()
    for name in rq.METRICS:
        assert f"`{name}`" in page, name


def test_measure_in_chunks_matches_the_rollout(short_rollout):
    import jax.numpy as jnp

    import fojax
    from fojax import scenarios, simulator
    from fojax.controllers import registry

    reqs = rq.parse(
        {"requirements": [{"name": "tilt", "metric": "max_tilt", "max": 1, "unit": "deg"}]}
    )
    config = simulator.SimulationConfig(dt=1e-3, horizon=0.3, save_every=100)
    assert rq.simulation_config(reqs, 0.3) == config  # no limit: ideal actuators
    controller = fojax.make_controller("fl", dt=1e-3, horizon=0.3)
    gains = registry.get_controller_class("fl").default_gains(jnp.float64)
    keys = scenarios.draw_keys(0, np.arange(4))
    metrics, status = rq.measure(
        controller, gains, scenarios.get_scenario(2), reqs, keys, config, chunk=3
    )
    want = rq.draw_metrics(short_rollout["requirements"])
    assert status.shape == (4,) and np.all(status & rq.DIVERGED == 0)
    for name in rq.METRICS:
        np.testing.assert_allclose(metrics[name], want[name], rtol=1e-9, atol=1e-12)
    result = rq.evaluate(reqs, metrics)
    assert result.draws == 4 and result.passed == int(np.sum(metrics["max_tilt"] <= np.pi / 180))
