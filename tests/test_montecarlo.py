"""Monte Carlo layer: online metrics, chunking, resumable store, summaries, statistics."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax import metrics, plant, scenarios, simulator, statistics, study
from fojax.controllers.afonftsmc import AFONFTSMC, paper_gains

HORIZON = 0.3
SCENARIO = dataclasses.replace(scenarios.get_scenario(2), horizon=HORIZON)
# save_every=1: the snapshots hold every step, so metrics can be recomputed offline.
CONFIG = simulator.SimulationConfig(dt=1e-3, horizon=HORIZON, save_every=1)
CONTROLLER = AFONFTSMC(dt=1e-3, horizon=HORIZON, switching="sat")
METRICS = metrics.MetricsConfig(
    dt=1e-3, steps=CONFIG.steps, position_band=0.02, attitude_band=0.01, reaching_band=0.02
)


@functools.cache
def runner():
    return study.make_chunk_runner(CONTROLLER, SCENARIO, CONFIG, METRICS)


def offline_metrics(tr, dt, cfg):
    """The metrics of one draw from its full-rate trajectory, in plain NumPy.

    Snapshot k holds the state after step k, the reference and inputs of step k; the
    online metrics use the state before step k, i.e. snapshot k - 1 (the initial
    state for k = 0).
    """
    n = tr.time.shape[0]
    t = np.arange(n) * dt
    horizon = n * dt
    state0 = np.asarray(scenarios.initial_state(SCENARIO, jnp.float64))
    state_before = np.concatenate([state0[None], tr.state[:-1]])
    error = np.concatenate(
        [
            state_before[:, :3] - tr.reference[:, :3],
            state_before[:, 3:6] - tr.info.attitude_reference,
        ],
        axis=1,
    )
    mag = np.abs(error)
    bands = np.array([cfg.position_band] * 3 + [cfg.attitude_band] * 3)
    settling = []
    for j in range(6):
        outside = np.nonzero(mag[:, j] > bands[j])[0]
        settling.append(0.0 if outside.size == 0 else min(t[outside[-1]] + dt, horizon))
    overshoot = []
    for j in range(6):
        big = np.nonzero(mag[:, j] > cfg.overshoot_threshold)[0]
        if big.size == 0:
            overshoot.append(0.0)
            continue
        direction = np.sign(error[big[0], j])
        overshoot.append(max(0.0, float(np.max(-direction * error[big[0] :, j]))))
    surfaces = tr.info.surfaces
    reaching = []
    for j in range(6):
        outside = np.nonzero(np.abs(surfaces[:, j]) > cfg.reaching_band)[0]
        if outside.size == 0:
            reaching.append(0.0)
        elif outside[-1] == n - 1:
            reaching.append(np.inf)
        else:
            reaching.append(t[outside[-1]] + dt)
    u = tr.inputs
    p = plant.nominal_params(jnp.float64)
    infeasible = np.array(
        [np.any(np.asarray(plant.rotor_speeds_squared(p, jnp.asarray(row))) < 0) for row in u]
    )
    return {
        "position_rmse": np.sqrt(np.sum(error[:, :3] ** 2) * dt / horizon),
        "attitude_rmse": np.sqrt(np.sum(error[:, 3:] ** 2) * dt / horizon),
        "rmse": np.sqrt(np.sum(error**2, axis=0) * dt / horizon),
        "iae": np.sum(mag, axis=0) * dt,
        "itae": np.sum(t[:, None] * mag, axis=0) * dt,
        "max_error": np.max(mag, axis=0),
        "settling_time": np.array(settling),
        "overshoot": np.array(overshoot),
        "control_effort": np.sqrt(np.sum(u**2, axis=0) * dt / horizon),
        "chattering": np.sum(np.abs(np.diff(u, axis=0)), axis=0),
        "actuator_saturation": np.mean(infeasible),
        "reaching_time": np.array(reaching),
        "initial_surface": surfaces[0],
    }


def test_online_metrics_match_offline_evaluation():
    keys = scenarios.draw_keys(11, [0, 1])
    status, online, snaps = runner()(paper_gains(), keys)
    for d in range(2):
        tr = jax.tree.map(lambda x, d=d: np.asarray(x[d]), snaps)
        want = offline_metrics(tr, CONFIG.dt, METRICS)
        assert set(want) == set(online)
        for name, value in want.items():
            np.testing.assert_allclose(
                np.asarray(online[name][d]), value, rtol=1e-9, atol=1e-12, err_msg=name
            )
    # The run is not trivial: errors, inputs and settling are all non-zero somewhere.
    assert np.all(np.asarray(online["iae"]) > 0)
    assert np.all(np.asarray(online["chattering"]) > 0)
    assert np.any(np.asarray(online["settling_time"]) > 0)


def _run(draws, device_batch=8, store=None, runner=None, keep=2, seed=3, **kw):
    return study.run(
        CONTROLLER,
        paper_gains(),
        SCENARIO,
        CONFIG,
        draws=draws,
        seed=seed,
        device_batch=device_batch,
        keep=keep,
        progress=False,
        metrics_config=METRICS,
        store=store,
        runner=runner,
        **kw,
    )


def _assert_same_draws(a, b, n=None):
    """Bit for bit: draw i's numbers do not depend on the draws around it."""
    n = min(a.draws, b.draws) if n is None else n
    np.testing.assert_array_equal(a.status[:n], b.status[:n])
    assert sorted(a.per_draw) == sorted(b.per_draw)
    for name in a.per_draw:
        np.testing.assert_array_equal(a.per_draw[name][:n], b.per_draw[name][:n], err_msg=name)


def _counting(calls):
    compiled = runner()

    def counting(g, keys):
        calls.append(int(keys.shape[0]))
        return compiled(g, keys)

    return counting


def test_blocks_do_not_change_draws_and_store_resumes(tmp_path):
    whole = _run(draws=21)
    few = _run(draws=5, keep=2)
    _assert_same_draws(few, whole)  # the first 5 of 21: the same numbers
    np.testing.assert_array_equal(few.trajectories.state, whole.trajectories.state)
    calls = []
    store = tmp_path / "chunks"
    stored_run = _run(draws=21, store=store, runner=_counting(calls))
    # Blocks of 8 draws, one per call on one device, the last one completed with the
    # draws that follow: one shape, one compilation.
    assert calls == [8, 8, 8]
    assert stored_run.layout["device_batch"] == 8 and stored_run.layout["calls"] == 3
    _assert_same_draws(stored_run, whole)
    np.testing.assert_array_equal(stored_run.trajectories.state, whole.trajectories.state)
    assert stored_run.trajectories.state.shape[0] == 2

    # Interrupted after the first two calls: the third is computed, the rest read.
    stored = sorted(p.name for p in store.glob("draws_*.npz"))
    assert stored == [
        "draws_0000000000-0000000008.npz",
        "draws_0000000008-0000000016.npz",
        "draws_0000000016-0000000024.npz",  # whole blocks, draws 21-23 included
    ]
    (store / stored[2]).unlink()
    calls.clear()
    resumed = _run(draws=21, store=store, runner=_counting(calls))
    assert calls == [8] and resumed.layout["computed"] == 5
    _assert_same_draws(resumed, whole)

    # Other settings in the same store are refused, naming what differs, not mixed in.
    with pytest.raises(study.StoreMismatch, match="seed") as info:
        _run(draws=21, seed=4, store=store, runner=_counting(calls))
    assert [d[0] for d in info.value.differences] == ["seed"]
    assert isinstance(info.value, ValueError)
    with pytest.raises(study.StoreMismatch, match="device_batch: earlier 8, now 16"):
        _run(draws=21, device_batch=16, store=store, runner=_counting(calls))


def test_a_longer_run_extends_the_stored_draws(tmp_path):
    """More draws and more kept trajectories in the same store: the stored draws are
    reused, and the result equals a run made at the larger size from scratch."""
    store = tmp_path / "chunks"
    calls = []
    _run(draws=5, keep=2, store=store, runner=_counting(calls))
    assert calls == [8]
    calls.clear()
    extended = _run(draws=40, keep=3, store=store, runner=_counting(calls))
    # Draws 0-1 have snapshots stored and 3-7 need none; draw 2 now needs one: its
    # block is computed again, and blocks 1-4 (draws 8-39) for the first time.
    assert calls == [8] * 5 and extended.layout["loaded"] == 7
    scratch = _run(draws=40, keep=3)
    _assert_same_draws(extended, scratch)
    np.testing.assert_array_equal(extended.trajectories.state, scratch.trajectories.state)
    # Fewer draws than stored: read, nothing computed.
    calls.clear()
    shorter = _run(draws=7, keep=1, store=store, runner=_counting(calls))
    assert calls == [] and shorter.layout["computed"] == 0
    _assert_same_draws(shorter, scratch, 7)
    assert shorter.trajectories.state.shape[0] == 1
    # The store read as it is, under its own manifest (as a study reads its runs).
    assert study.ChunkStore.existing(tmp_path / "none") is None
    found = study.ChunkStore.existing(store)
    assert found.key == study.ChunkStore(store, found.fingerprint, writable=False).key
    assert found.read(41) is None
    with pytest.raises(ValueError, match="draws must be an integer >= 1"):
        found.read(0)
    status, per_draw = found.read(40)
    np.testing.assert_array_equal(status, scratch.status)
    for name, values in scratch.per_draw.items():
        np.testing.assert_array_equal(per_draw[name], values, err_msg=name)


def test_store_plan_reads_what_is_there_and_computes_the_rest():
    from fojax.study import _store

    def item(first, stop, kept):
        return _store.StoredRange(first, stop, kept, None)

    stored = [item(0, 16, 2), item(16, 32, 0), item(40, 48, 0)]
    plan = [(k, a, b) for k, a, b, _ in _store.plan(stored, 50, keep=2)]
    assert plan == [
        ("load", 0, 16),
        ("load", 16, 32),
        ("compute", 32, 40),
        ("load", 40, 48),
        ("compute", 48, 50),
    ]
    # keep 4: draws 2-3 need snapshots the first file lacks.
    plan = [(k, a, b) for k, a, b, _ in _store.plan(stored, 20, keep=4)]
    assert plan == [("load", 0, 2), ("compute", 2, 4), ("load", 4, 16), ("load", 16, 20)]
    # Overlapping files: the one reaching further is read.
    plan = [(k, a, b) for k, a, b, _ in _store.plan([item(0, 8, 0), item(0, 24, 0)], 20, 0)]
    assert plan == [("load", 0, 20)]
    assert _store.plan([], 3, 3) == [("compute", 0, 3, None)]


def test_store_mismatch_names_the_fields(tmp_path):
    fingerprint = study.fingerprint(
        CONTROLLER, paper_gains(), SCENARIO, CONFIG, 3, jnp.float64, METRICS, 8
    )
    assert not {"draws", "chunk", "keep"} & set(fingerprint)
    assert fingerprint["device_batch"] == 8 and fingerprint["backend"] == "cpu"
    # The suite's optimisation-level flag changes arithmetic: it is part of the key.
    assert "--xla_backend_optimization_level=0" in fingerprint["xla_flags"]
    study.ChunkStore(tmp_path, fingerprint)
    other = dict(fingerprint, seed=4, dtype="float32")
    with pytest.raises(study.StoreMismatch) as info:
        study.ChunkStore(tmp_path, other)
    assert [field for field, _, _ in info.value.differences] == ["dtype", "seed"]
    message = str(info.value)
    assert 'dtype: earlier "float64", now "float32"' in message
    assert "seed: earlier 3, now 4" in message and "afresh" in message
    # A store of the earlier format (chunk and keep in its settings) is named as such.
    (tmp_path / "manifest.json").write_text(
        '{"key": "x", "fingerprint": {"chunk": 50, "keep": 32}}'
    )
    with pytest.raises(study.StoreMismatch, match="store_format: earlier 1, now 2"):
        study.ChunkStore(tmp_path, fingerprint)
    assert study.numeric_xla_flags(
        "--xla_force_host_platform_device_count=2 --xla_dump_to=/tmp/x --xla_cpu_foo=1"
    ) == ["--xla_cpu_foo=1"]


def test_store_keys_the_library_code(tmp_path, monkeypatch):
    """Draws stored by other fojax code (a changed default changes numbers, not
    settings) are refused, naming the code."""
    from fojax.study import _run

    key = _run.code_version()
    assert len(key) == 16 and key == _run.code_version()
    args = (CONTROLLER, paper_gains(), SCENARIO, CONFIG, 3, jnp.float64, METRICS, 8)
    study.ChunkStore(tmp_path, study.fingerprint(*args))
    monkeypatch.setattr(_run, "code_version", lambda: "0123456789abcdef")
    with pytest.raises(study.StoreMismatch, match="fojax_code") as info:
        study.ChunkStore(tmp_path, study.fingerprint(*args))
    assert [field for field, _, _ in info.value.differences] == ["fojax_code"]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"draws": 2**32 + 1}, "at most 2\\*\\*32"),
        ({"draws": 0}, "positive integer"),
        ({"draws": 3, "seed": 2**63}, "at most 2\\*\\*63 - 1"),
        ({"draws": 3, "seed": -1}, "non-negative"),
        ({"draws": 3, "device_batch": 0}, "device_batch must be a positive integer"),
    ],
)
def test_run_rejects_out_of_range_draws_and_seeds_before_tracing(kwargs, message):
    def never(*args):
        raise AssertionError("nothing may run")

    with pytest.raises(ValueError, match=message):
        study.run(CONTROLLER, paper_gains(), SCENARIO, CONFIG, runner=never, **kwargs)


def test_batch_layout():
    layout = study.batch_layout(100, 64)
    assert layout == {
        "processes": 1,
        "devices": 1,
        "device_batch": 64,
        "draws_per_call": 64,
        "blocks": 2,
        "calls": 2,
    }
    assert study.default_device_batch("cpu") == 50
    assert study.default_device_batch("gpu") == study.OTHER_DEVICE_BATCH


def test_summary_excludes_diverged_draws_and_counts_flags():
    n = 6
    values = np.arange(n, dtype=float) + 1.0
    per_draw = {"position_rmse": values, "iae": np.tile(values[:, None], (1, 6))}
    status = np.array(
        [0, simulator.NONFINITE, simulator.ACTUATOR_LIMIT, simulator.TILT_LIMIT, 0, 0], np.int32
    )
    result = study.MonteCarloResult("test", status, per_draw, None, 0.0, 0.0)
    summary = study.summarize(result)
    assert summary["draws"] == 6 and summary["valid"] == 4 and summary["diverged"] == 2
    assert summary["status_counts"] == {"nonfinite": 1, "tilt_limit": 1, "actuator_limit": 1}
    kept = values[[0, 2, 4, 5]]
    entry = summary["metrics"]["position_rmse"]
    assert entry["n"] == 4 and entry["unit"] == "m"
    assert entry["mean"] == pytest.approx(np.mean(kept))
    assert summary["metrics"]["iae_psi"]["unit"] == "rad s"


def test_student_t_and_confidence_intervals():
    scipy_stats = pytest.importorskip("scipy.stats")
    for df in (1, 2, 5, 10, 11, 20, 50, 200, 5000):
        assert statistics.student_t_975(df) == pytest.approx(scipy_stats.t.ppf(0.975, df), rel=2e-4)
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, 40)
    out = statistics.mean_ci(np.concatenate([x, [np.inf, np.nan]]))
    lo, hi = scipy_stats.t.interval(0.95, 39, loc=np.mean(x), scale=scipy_stats.sem(x))
    assert out["n"] == 40 and out["n_nonfinite"] == 2
    np.testing.assert_allclose(out["ci95"], [lo, hi], rtol=1e-5)
    # Paired: a constant shift has zero width.
    paired = statistics.paired_difference(x + 1.5, x)
    assert paired["mean"] == pytest.approx(1.5)
    assert paired["ci95"][1] - paired["ci95"][0] == pytest.approx(0.0, abs=1e-12)
    # Coverage: about 95 % of intervals of normal samples hold the true mean.
    hits = sum(
        lo <= 0.0 <= hi
        for lo, hi in (statistics.mean_ci(rng.normal(0, 1, 12))["ci95"] for _ in range(2000))
    )
    assert 0.93 < hits / 2000 < 0.97


def test_reaching_time_bound_matches_comparison_system():
    # |S|' = -(h1 + mu) - h2 |S| reaches 0 exactly at the bound (Lemma 1 with nu = 1/2).
    gains = paper_gains()
    s0 = jnp.array([0.3, -0.2, 1.0, 2.0, -0.5, 0.1])
    bound = np.asarray(AFONFTSMC.reaching_time_bound(gains, s0))
    h1 = np.asarray(gains.reaching_h1 + gains.mu)
    h2 = np.asarray(gains.reaching_h2)
    for j in range(6):
        s, t, dt = abs(float(s0[j])), 0.0, 1e-6
        while s > 0:

            def f(v, j=j):
                return -h1[j] - h2[j] * v

            k1 = f(s)
            k2 = f(s + 0.5 * dt * k1)
            k3 = f(s + 0.5 * dt * k2)
            k4 = f(s + dt * k3)
            s_next = s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            if s_next <= 0:
                t += dt * s / (s - s_next)
                break
            s, t = s_next, t + dt
        assert bound[j] == pytest.approx(t, rel=1e-5, abs=1e-8)
    # Lemma 1's own form, with V = S^2/2, lambda1 = sqrt(2)(h1 + mu), lambda2 = 2 h2.
    lam1, lam2 = math.sqrt(2) * h1, 2 * h2
    v0 = np.asarray(s0) ** 2 / 2
    np.testing.assert_allclose(bound, 2 / lam2 * np.log((lam2 * np.sqrt(v0) + lam1) / lam1))


def test_metrics_config_rejects_bad_values():
    with pytest.raises(ValueError, match="position_band"):
        metrics.MetricsConfig(dt=1e-3, steps=10, position_band=0.0)
    with pytest.raises(ValueError, match="steps"):
        metrics.MetricsConfig(dt=1e-3, steps=0)
    with pytest.raises(ValueError, match="draws"):
        study.run(CONTROLLER, paper_gains(), SCENARIO, CONFIG, draws=0)


# ---------------------------------------------------------------- union scenarios


def _union_members():
    return (SCENARIO, dataclasses.replace(scenarios.get_scenario(3), horizon=0.2))


def test_a_union_member_runs_as_its_scenario_alone(tmp_path):
    """``run(union, member=i)``: one compiled program for both members (of different
    horizons), and each member's draws, status and trimmed snapshots are those of its
    scenario run alone, bit for bit in float64; the store is keyed by the member."""
    members = _union_members()
    bank = scenarios.union(*members)
    config = simulator.SimulationConfig(dt=1e-3, horizon=bank.horizon, save_every=50)
    shared = study.make_chunk_runner(CONTROLLER, bank, config, dtype=jnp.float64)
    gains = paper_gains()
    common = dict(draws=3, seed=5, device_batch=2, keep=3, progress=False, dtype=jnp.float64)
    for index, member in enumerate(members):
        together = study.run(CONTROLLER, gains, bank, config, runner=shared, member=index, **common)
        alone_config = dataclasses.replace(config, horizon=member.horizon)
        alone = study.run(CONTROLLER, gains, member, alone_config, **common)
        np.testing.assert_array_equal(together.status, alone.status)
        assert together.per_draw.keys() == alone.per_draw.keys()
        for name, value in alone.per_draw.items():
            np.testing.assert_array_equal(together.per_draw[name], value, err_msg=name)
        assert together.trajectories.time.shape == alone.trajectories.time.shape
        assert alone.trajectories.time.shape[1] == round(member.horizon / 1e-3) // 50
        for got, want in zip(
            jax.tree.leaves(together.trajectories), jax.tree.leaves(alone.trajectories), strict=True
        ):
            np.testing.assert_array_equal(got, want)
    if hasattr(shared, "_cache_size"):
        assert shared._cache_size() == 1  # one program served both members
    # The store: the member's draws are read back; another member's are not.
    store = tmp_path / "store"
    first = study.run(CONTROLLER, gains, bank, config, member=1, store=store, **common)
    again = study.run(CONTROLLER, gains, bank, config, member=1, store=store, **common)
    assert again.layout["loaded"] == 3
    np.testing.assert_array_equal(again.trajectories.state, first.trajectories.state)
    with pytest.raises(study.StoreMismatch, match="member: earlier 1, now 0"):
        study.run(CONTROLLER, gains, bank, config, member=0, store=store, **common)
    settings = study.fingerprint(
        CONTROLLER, gains, bank, config, 5, jnp.float64, METRICS, 2, member=1
    )
    assert settings["member"] == 1
    assert [m["horizon"] for m in settings["scenario"]["members"]] == [0.3, 0.2]
    assert settings["scenario"]["members"][1]["reference"] == "reference_57"
    assert "member" not in study.fingerprint(
        CONTROLLER, gains, SCENARIO, CONFIG, 5, jnp.float64, METRICS, 2
    )


@pytest.mark.parametrize(
    "member, message",
    [
        (None, "pass member="),
        (2, "member must be 0 to 1"),
        (-1, "member must be 0 to 1"),
        (True, "integer index"),
        (0.0, "integer index"),
    ],  # fmt: skip
)
def test_a_union_needs_a_member_in_range_before_compiling(monkeypatch, member, message):
    bank = scenarios.union(*_union_members())
    config = simulator.SimulationConfig(dt=1e-3, horizon=bank.horizon, save_every=50)

    def no_compiling(*args, **kwargs):
        raise AssertionError("compiled")

    monkeypatch.setattr(study._run, "make_chunk_runner", no_compiling)
    with pytest.raises(ValueError, match=message):
        study.run(CONTROLLER, paper_gains(), bank, config, 2, member=member, progress=False)
    with pytest.raises(ValueError, match="not a union"):
        study.run(CONTROLLER, paper_gains(), SCENARIO, CONFIG, 2, member=1, progress=False)
