"""A study's files (:mod:`fojax.cli.study`): ``summary.json`` (the settings, the
provenance, every metric's summary), ``draws.npz`` (per-draw metrics, status and the
Eq. (34) reaching-time bounds), ``trajectories.npz`` (the kept draws), then the
figures (:mod:`fojax.cli.figures`)."""

from __future__ import annotations

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from fojax import metrics, sharding, statistics
from fojax import study as monte_carlo
from fojax.cli import arguments
from fojax.cli.output import provenance, write_json, write_npz
from fojax.cli.study import Study, gains_record, options_applied_to
from fojax.controllers import registry

__all__ = ["write_outputs"]


def _reaching_bounds(name: str, study: Study, result) -> dict:
    """Eq. (34) bound per draw, for controllers that define one."""
    law = registry.make_controller(name, dt=study.dt, horizon=study.horizon).law
    if not hasattr(law, "reaching_time_bound"):
        return {}
    gains = study.gains.get(name) or law.default_gains(jnp.dtype(study.dtype))
    bound = np.asarray(
        law.reaching_time_bound(gains, jnp.asarray(result.per_draw["initial_surface"]))
    )
    names = metrics.component_names("reaching_time_bound", bound.shape[1:])
    return {component: bound[:, j] for j, component in enumerate(names)}


def _used_gains(study: Study, name: str):
    gains = study.gains.get(name)
    if gains is None:
        gains = registry.get_controller_class(name).default_gains(jnp.dtype(study.dtype))
    return type(gains)(*(jnp.asarray(g, jnp.dtype(study.dtype)) for g in gains))


def _batch_layout(study: Study) -> dict:
    """How the draws were laid out over processes and devices (a draw's numbers do not
    depend on it, only on the block size ``device_batch``)."""
    layout = monte_carlo.batch_layout(study.draws, study.device_batch, sharding.default_mesh())
    layout["note"] = (
        "each call computes one block of device_batch consecutive draws per device of "
        "every process; a draw's numbers depend on device_batch, not on the draw count, "
        "the devices or the processes"
    )
    return layout


def write_outputs(
    study: Study,
    results: dict,
    out: Path,
    figures: bool = True,
    command: list[str] | None = None,
    extra: dict | None = None,
) -> dict:
    """``summary.json``, ``draws.npz``, ``trajectories.npz``, then the figures.

    The results are on disk before any figure is drawn, and a figure that fails is a
    warning naming it (the others are still drawn). ``command``: the command line
    recorded in the summary's provenance (default ``sys.argv``); ``extra``: further
    summary entries. Returns the summary, with ``"files"``: the files written.
    """
    summary = _header(study, results)
    arrays = _controller_entries(study, results, summary)
    if len(results) > 1:
        summary["paired_differences"] = _paired(results)
    summary.update(extra or {})
    summary["provenance"] = provenance(command)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    trajectories = _first_trajectories(results)
    files = ["summary.json", "draws.npz", "trajectories.npz"]
    summary["files"] = files if trajectories else files[:2]
    write_json(out / "summary.json", summary)
    write_npz(out / "draws.npz", arrays)
    if trajectories:
        write_npz(out / "trajectories.npz", trajectories)
    if figures and trajectories:
        _draw_figures(study, results, out, summary)
    return summary


def _header(study: Study, results: dict) -> dict:
    """The summary's settings and gains, before the controllers' entries."""
    return {
        "scenario": study.scenario_id,
        "draws": study.draws,
        "seed": study.seed,
        "horizon_s": study.horizon,
        "dt_s": study.dt,
        "fractional_method": study.fractional,
        "switching": study.switching,
        "options_applied_to": options_applied_to(study),
        "dtype": study.dtype,
        "device_batch": study.device_batch or monte_carlo.default_device_batch(),
        "batch": _batch_layout(study),
        "keep": study.keep,
        "gains": {
            name: gains_record(_used_gains(study, name), study.gains_sources.get(name))
            for name in results
        },
        "excluded_from_metrics": "draws flagged nonfinite or tilt_limit (counted in 'diverged')",
        "vehicle": arguments.vehicle_record(study.vehicle, study.rotor_speed_limit),
        **({} if study.reference is None else {"reference": reference_record(study)}),
        "controllers": {},
    }


def reference_record(study: Study) -> dict:
    """The study's reference file as ``summary.json`` records it, with its peaks over the
    run (speed m/s, acceleration m/s^2, the tilt it implies in degrees)."""
    peaks = study.reference.peaks(study.horizon)
    return {
        **study.reference.to_dict(),
        "peaks": {
            "speed_m_per_s": peaks["speed"],
            "acceleration_m_per_s2": peaks["acceleration"],
            "tilt_deg": math.degrees(peaks["tilt"]),
        },  # fmt: skip
    }


def _controller_entries(study: Study, results: dict, summary: dict) -> dict:
    """Each controller's summary entry into ``summary["controllers"]``; returns the
    per-draw arrays of ``draws.npz``."""
    arrays = {}
    for name, result in results.items():
        bounds = _reaching_bounds(name, study, result)
        entry = monte_carlo.summarize(result, extra=bounds)
        entry["wall_time_s"] = round(result.wall_time, 2)
        if getattr(result, "layout", None):
            entry["draws_computed"] = result.layout["computed"]
            entry["draws_from_store"] = result.layout["loaded"]
        summary["controllers"][name] = entry
        arrays[f"{name}.status"] = result.status
        for metric, values in {**result.per_draw, **bounds}.items():
            arrays[f"{name}.{metric}"] = values
    return arrays


def _paired(results: dict) -> dict:
    """Each controller's paired differences from the first one's, metric by metric."""
    baseline, *others = list(results)
    base_table = monte_carlo.metric_table(results[baseline])
    paired = {}
    for name in others:
        table = monte_carlo.metric_table(results[name])
        paired[name] = {
            metric: statistics.paired_difference(table[metric][0], base_table[metric][0])
            for metric in table
            if metric in base_table
        }
    return {"baseline": baseline, "minus_baseline": paired}


def _first_trajectories(results: dict) -> dict:
    """The first (at most eight) kept trajectories of each controller, by array name."""
    trajectories = {}
    for name, result in results.items():
        tr = result.trajectories
        if tr is None:
            continue
        few = slice(0, min(8, tr.time.shape[0]))
        fields = ("time", "state", "reference", "inputs", "inputs_low", "inputs_high")
        info = ("attitude_reference", "surfaces", "adaptive")
        arrays = [(field, getattr(tr, field, None)) for field in fields]
        arrays += [(field, getattr(tr.info, field)) for field in info]
        for field, values in arrays:
            if values is not None:
                trajectories[f"{name}.{field}"] = values[few]
    return trajectories


def _draw_figures(study: Study, results: dict, out: Path, summary: dict) -> None:
    """The figures, each a warning when it fails; their names into the summary."""
    from fojax.cli import figures as figs
    from fojax.cli import style

    applied = options_applied_to(study)
    parts = [f"scenario {study.scenario_id}"]
    if applied["switching"]:
        parts.append(f"{study.switching} switching")
    if applied["fractional_method"]:
        parts.append(f"{study.fractional} fractional operators")
    context = ", ".join(parts + [f"dt {study.dt * 1e3:g} ms"])
    drawn = style.attempt("(all)", figs.plot_all, results, out, "", context) or []
    if drawn:
        summary["figures"] = [p.name for p in drawn]
        write_json(out / "summary.json", summary)
