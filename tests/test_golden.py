"""Numbers that a refactor must keep: float64 rollouts, metrics and gradients.

``tests/data/golden_f64.npz`` holds, for every controller, short float64 rollouts of
each scenario (snapshots, final status, every metric) and the per-draw gradient of
the tuning cost with respect to every gain field (``tanh`` switching, fractional
orders included). The file was written by ``python tests/test_golden.py --write``
before the code was reorganised (one cascade, declared gains, observers, the
fractional package); a refactor must reproduce it to 1e-12 relative (values) and
1e-10 relative (gradients). Regenerate it only for a change that is meant to move
the numbers, and say so in the commit.
"""

from __future__ import annotations

import functools
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

DATA = pathlib.Path(__file__).resolve().parent / "data" / "golden_f64.npz"
CONTROLLERS = ("afonftsmc", "anftsmc", "fobsmc", "bsmc", "fl")
SEED = 3
DRAWS = (0, 1)
FORWARD_HORIZON = 0.4
GRADIENT_HORIZON = 0.3
SAVE_EVERY = 20

# (controller, scenario, switching, fractional method) of the forward cases.
FORWARD_CASES = [
    *[(name, 1, "sign", "soe") for name in CONTROLLERS],
    *[(name, 2, "sat", "soe") for name in CONTROLLERS],
    *[(name, 3, "sign", "soe") for name in CONTROLLERS],
    ("afonftsmc", 2, "sat", "oustaloup"),
    ("afonftsmc", 2, "sat", "gl"),
    ("fobsmc", 2, "sat", "oustaloup"),
]
GRADIENT_CASES = [(name, 2, "tanh", "soe") for name in CONTROLLERS] + [
    ("afonftsmc", 3, "tanh", "soe")
]


# The sum-of-exponentials setting the saved values were made with (32 modes; the
# default now has 23).
SOE_OPTIONS = (("log_step", 0.6), ("tail_modes", 8))


def _options(method: str) -> tuple:
    return SOE_OPTIONS if method == "soe" else ()


def _setup(case, horizon: float):
    """The case's scenario, configuration, controller (with the switching and fractional
    settings that its law takes: the FL neither, the BSMC and ANFTSMC no fractional
    method) and the controller's default gains in float64."""
    from fojax import scenarios, simulator
    from fojax.controllers import registry

    name, scenario_id, switching, method = case
    shared = dict(
        switching=switching, fractional_method=method, fractional_options=_options(method)
    )
    controller = registry.make_controller(
        name, dt=1e-3, horizon=horizon, **registry.options_for(name, shared)
    )
    config = simulator.SimulationConfig(dt=1e-3, horizon=horizon, save_every=SAVE_EVERY)
    gains = jax.tree.map(lambda g: jnp.asarray(g, jnp.float64), controller.default_gains())
    return scenarios.get_scenario(scenario_id), config, controller, gains


def _key(kind, case) -> str:
    return f"{kind}/{case[0]}/s{case[1]}/{case[2]}/{case[3]}"


def _forward(case) -> dict[str, np.ndarray]:
    from fojax import scenarios, study

    scenario, config, controller, gains = _setup(case, FORWARD_HORIZON)
    runner = study.make_chunk_runner(controller, scenario, config, dtype=jnp.float64)
    status, metrics, snapshots = runner(gains, scenarios.draw_keys(SEED, DRAWS))
    out = {"status": np.asarray(status)}
    out.update({f"metric.{k}": np.asarray(v) for k, v in metrics.items()})
    out["snap.state"] = np.asarray(snapshots.state)
    out["snap.inputs"] = np.asarray(snapshots.inputs)
    out["snap.reference"] = np.asarray(snapshots.reference)
    out.update({f"snap.info.{k}": np.asarray(v) for k, v in snapshots.info._asdict().items()})
    return out


def _gradient(case) -> dict[str, np.ndarray]:
    from fojax import scenarios
    from fojax.optimize import cost as cost_lib

    scenario, config, controller, gains = _setup(case, GRADIENT_HORIZON)
    batch_cost = cost_lib.make_batch_cost(
        controller, scenario, config, cost_lib.CostConfig(), jnp.float64
    )
    # Per-draw gradients as the tuner takes them: one batch-last rollout, one copy of the
    # gains per draw.
    grad = jax.jit(lambda g, keys: cost_lib.per_draw_gradients(batch_cost, g, keys))
    cost, terms, _, grads = grad(gains, scenarios.draw_keys(SEED, DRAWS))
    out = {"cost": np.asarray(cost), "terms": np.asarray(terms)}
    out.update({f"grad.{k}": np.asarray(v) for k, v in grads._asdict().items()})
    return out


def compute() -> dict[str, np.ndarray]:
    values = {}
    for case in FORWARD_CASES:
        for k, v in _forward(case).items():
            values[f"{_key('forward', case)}/{k}"] = v
    for case in GRADIENT_CASES:
        for k, v in _gradient(case).items():
            values[f"{_key('gradient', case)}/{k}"] = v
    return values


@functools.cache
def _saved() -> dict[str, np.ndarray]:
    with np.load(DATA) as data:
        return {k: data[k] for k in data.files}


def _compare(prefix: str, computed: dict, rtol: float) -> None:
    saved = {k[len(prefix) + 1 :]: v for k, v in _saved().items() if k.startswith(prefix + "/")}
    assert saved, f"no saved values for {prefix}"
    assert set(computed) == set(saved), (sorted(computed), sorted(saved))
    for name, expected in saved.items():
        got = computed[name]
        assert got.shape == expected.shape, (name, got.shape, expected.shape)
        if expected.dtype.kind in "iub":
            np.testing.assert_array_equal(got, expected, err_msg=f"{prefix}/{name}")
            continue
        finite = np.isfinite(expected)
        np.testing.assert_array_equal(np.isfinite(got), finite, err_msg=f"{prefix}/{name}")
        np.testing.assert_array_equal(got[~finite], expected[~finite])
        # Relative to each array's own scale (the largest magnitude), so that entries
        # that are zero up to rounding (a surface crossing zero) do not demand a
        # relative precision of their own.
        scale = np.max(np.abs(expected[finite])) if finite.any() else 0.0
        if name.startswith("metric."):
            # A metric can be small where the signals it is taken from are not (the
            # overshoot: a difference of positions near 1 m); its rounding follows
            # theirs, whose scale is of order one in the metric's unit (m, rad, s, N).
            scale = max(scale, 1.0)
        error = np.max(np.abs(got[finite] - expected[finite]), initial=0.0)
        assert error <= rtol * scale, (
            f"{prefix}/{name}: max |difference| {error:.3g} > {rtol:g} x scale {scale:.3g}"
        )


@pytest.mark.parametrize("case", FORWARD_CASES, ids=lambda c: _key("f", c))
def test_forward_matches_saved(case):
    _compare(_key("forward", case), _forward(case), rtol=1e-12)


@pytest.mark.parametrize("case", GRADIENT_CASES, ids=lambda c: _key("g", c))
def test_gradient_matches_saved(case):
    _compare(_key("gradient", case), _gradient(case), rtol=1e-10)


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        raise SystemExit("usage: python tests/test_golden.py --write")
    jax.config.update("jax_enable_x64", True)
    DATA.parent.mkdir(exist_ok=True)
    np.savez_compressed(DATA, **compute())
    print(f"wrote {DATA}")
