"""``fojax.study.run_studies`` (``fojax.cli.study``'s): studies of several scenarios
share one compiled program per controller (a union of their scenarios) and give the
results of each scenario run alone."""

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from conftest import close_normwise  # noqa: E402

from fojax import study as monte_carlo  # noqa: E402
from fojax.cli import study as study_layer  # noqa: E402

CONTROLLERS = ("afonftsmc", "fl")


def _study(scenario_id, horizon, fractional="oustaloup", dtype="float64"):
    return study_layer.Study(
        scenario_id=scenario_id,
        controllers=CONTROLLERS,
        draws=3,
        seed=2,
        horizon=horizon,
        dt=1e-3,
        save_every=100,
        gains={},
        fractional=fractional,
        switching="sat",
        device_batch=2,
        keep=2,
        dtype=dtype,
    )


def _run(studies, root, monkeypatch, union: bool):
    """``({scenario_id: results}, programs compiled)``."""
    monkeypatch.setenv("FOJAX_UNION", "1" if union else "0")
    compiled = []
    original = monte_carlo.compile_chunk_runner

    def counting(*args, **kwargs):
        compiled.append(args[2])  # the scenario
        return original(*args, **kwargs)

    # where the study engine (fojax.study._jobs) finds it
    monkeypatch.setattr(monte_carlo._run, "compile_chunk_runner", counting)
    pairs = [(s, root / f"s{s.scenario_id}") for s in studies]
    results = {
        study.scenario_id: found
        for study, found in study_layer.run_studies(pairs, progress=False, threads=0)
    }
    monkeypatch.setattr(monte_carlo._run, "compile_chunk_runner", original)
    return results, compiled


def _assert_same(got, want, same=np.testing.assert_array_equal):
    assert got.keys() == want.keys()
    for name in want:
        a, b = got[name], want[name]
        np.testing.assert_array_equal(a.status, b.status)
        assert a.per_draw.keys() == b.per_draw.keys()
        for metric, value in b.per_draw.items():
            same(a.per_draw[metric], value, err_msg=f"{name}.{metric}")
        assert a.trajectories.time.shape == b.trajectories.time.shape
        for x, y in zip(
            jax.tree.leaves(a.trajectories), jax.tree.leaves(b.trajectories), strict=True
        ):
            same(x, y)


def test_studies_of_three_scenarios_compile_one_program_per_controller(tmp_path, monkeypatch):
    studies = [_study(1, 0.3), _study(2, 0.3), _study(3, 0.2)]
    plans = study_layer.plan_unions(studies)
    assert [p.member for p in plans] == [0, 1, 2] and plans[0].scenario.horizon == 0.3
    together, compiled = _run(studies, tmp_path / "union", monkeypatch, union=True)
    assert len(compiled) == len(CONTROLLERS)
    assert all(scenario.members for scenario in compiled)
    alone, compiled = _run(studies, tmp_path / "alone", monkeypatch, union=False)
    assert len(compiled) == len(CONTROLLERS) * len(studies)
    for study in studies:
        _assert_same(together[study.scenario_id], alone[study.scenario_id])
        assert together[study.scenario_id]["fl"].trajectories.time.shape[1] == round(
            study.horizon / 1e-3 / study.save_every
        )
        for name in CONTROLLERS:
            a = monte_carlo.summarize(together[study.scenario_id][name])
            b = monte_carlo.summarize(alone[study.scenario_id][name])
            assert a == b
    # Started again: the union's stores are read back, nothing compiles.
    again, compiled = _run(studies, tmp_path / "union", monkeypatch, union=True)
    assert compiled == []
    _assert_same(again[3], together[3])
    # Folders of a run without the union: the union run continues them alone.
    more = [_study(1, 0.3), _study(3, 0.2)]
    continued, compiled = _run(more, tmp_path / "alone", monkeypatch, union=True)
    assert compiled == []
    assert continued[1]["fl"].layout["loaded"] == 3
    _assert_same(continued[1], alone[1])


def test_only_studies_with_the_same_settings_share_a_union(monkeypatch):
    studies = [_study(1, 0.3), _study(3, 0.2), _study(2, 0.3, fractional="soe"), _study(1, 0.2)]
    plans = study_layer.plan_unions(studies)
    assert plans[2] is None  # no other study with its settings
    assert [p.member for p in (plans[0], plans[1], plans[3])] == [0, 1, 2]
    assert plans[0].scenario.horizon == 0.3
    assert study_layer.plan_unions([_study(1, 0.3), _study(1, 0.3)]) == [None, None]
    assert study_layer.plan_unions([_study(1, 0.3)]) == [None]
    monkeypatch.setenv("FOJAX_UNION", "0")
    assert study_layer.plan_unions(studies) == [None] * 4
    monkeypatch.setenv("FOJAX_UNION", "maybe")
    with pytest.raises(ValueError, match="FOJAX_UNION"):
        study_layer.plan_unions(studies)


def test_float32_and_a_horizon_dependent_operator_stay_within_rounding(tmp_path, monkeypatch):
    """The default reproduce settings' kind: float32, and sum-of-exponentials fractional
    operators, which the union sizes for its longest horizon (0.3 s) where scenario 3
    alone has 0.2 s: the same metrics to rounding and the kernel's approximation."""
    studies = [_study(1, 0.3, "soe", "float32"), _study(3, 0.2, "soe", "float32")]
    together, compiled = _run(studies, tmp_path / "union", monkeypatch, union=True)
    assert len(compiled) == len(CONTROLLERS)
    alone, _ = _run(studies, tmp_path / "alone", monkeypatch, union=False)
    for study in studies:
        _assert_same(together[study.scenario_id], alone[study.scenario_id], close_normwise)
