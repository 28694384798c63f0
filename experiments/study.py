"""The study layer shared by the commands: a validated Monte Carlo study, running it,
writing its outputs, and what every output records to be rerun exactly.

* :class:`Study`, :func:`run_study`, :func:`write_outputs`: one scenario under one or
  several controllers on the same draws (``fojax simulate``; ``fojax reproduce`` runs
  one per scenario).
* :func:`provenance`: the command line, versions (fojax and its git commit, Python,
  JAX, jaxlib, NumPy), backend and device and process counts; :func:`gains_record`:
  the gains' values and where they came from. ``fojax simulate``, ``tune`` and
  ``bench`` store both with their results.
* :func:`store_differences`: the settings in which a run differs from the one whose
  chunks are already in the output folder, field by field, before anything runs.
* :func:`write_json`: atomic JSON files (a run stopped while writing leaves the old
  file or the new one, never half of one).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

__all__ = [
    "Study",
    "StoreMismatch",
    "check_stores",
    "gains_record",
    "provenance",
    "run_study",
    "snapshot_interval",
    "store_differences",
    "write_json",
    "write_outputs",
]


@dataclasses.dataclass(frozen=True)
class Study:
    """A validated study: everything settled before anything is compiled.

    gains: controller name -> gains NamedTuple, for those not run with their defaults;
    gains_sources: controller name -> the file each of those came from.
    """

    scenario_id: int
    controllers: tuple[str, ...]
    draws: int
    seed: int
    horizon: float
    dt: float
    save_every: int
    gains: dict
    fractional: str
    switching: str
    chunk: int
    keep: int
    dtype: str
    gains_sources: dict = dataclasses.field(default_factory=dict)
    reaching_band: float | tuple[float, ...] = 0.01
    """``fojax.metrics.MetricsConfig.reaching_band``: one band, or six (one per axis)."""

    def metrics_config(self, steps: int):
        from fojax import metrics

        return metrics.MetricsConfig(dt=self.dt, steps=steps, reaching_band=self.reaching_band)


def snapshot_interval(steps: int, dt: float, target: float = 0.1) -> int:
    """Steps between snapshots: the divisor of ``steps`` closest to ``target / dt``."""
    want = max(1, round(target / dt))
    divisors = [d for d in range(1, min(steps, 10 * want) + 1) if steps % d == 0]
    return min(divisors, key=lambda d: (abs(d - want), d))


# ------------------------------------------------------------------------- provenance


def _git_commit(root: Path) -> dict:
    """``{"commit", "dirty"}`` of the checkout holding fojax, or ``{}`` (not one)."""
    if not (root / ".git").exists():
        return {}
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        if commit.returncode != 0:
            return {}
        status = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        dirty = bool(status.stdout.strip()) if status.returncode == 0 else None
        return {"commit": commit.stdout.strip(), "dirty": dirty}
    except (OSError, subprocess.SubprocessError):
        return {}


def _version(package: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def provenance(command: list[str] | None = None, gains: dict | None = None) -> dict:
    """What a result needs to be rerun exactly.

    command: the command line as a list (``["fojax", "simulate", ...]``; default
    ``sys.argv``). gains: optional, recorded as given (see :func:`gains_record`).
    Returns the command (quoted for a shell) and the folder it ran in, the fojax
    version and git commit (``dirty``: uncommitted changes to tracked files), the
    Python, JAX, jaxlib and NumPy versions, the backend, the device and process counts
    and devices (the draws are split over the devices, and a draw's float32 rounding
    depends on the batch it runs in), ``jax_enable_x64``, ``XLA_FLAGS``, the platform
    and the time (UTC).
    """
    import jax
    import numpy as np

    import fojax

    command = list(sys.argv if command is None else command)
    record: dict[str, Any] = {
        "command": shlex.join(command),
        "working_directory": os.getcwd(),
        "fojax_version": _version("fojax") or getattr(fojax, "__version__", None),
        "fojax_git": _git_commit(Path(fojax.__file__).resolve().parent.parent) or None,
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": _version("jaxlib"),
        "numpy": np.__version__,
        "backend": jax.default_backend(),
        "device_count": jax.device_count(),
        "local_device_count": jax.local_device_count(),
        "process_count": jax.process_count(),
        "devices": [str(d) for d in jax.local_devices()],
        "jax_enable_x64": bool(jax.config.jax_enable_x64),
        "xla_flags": os.environ.get("XLA_FLAGS") or None,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    if gains is not None:
        record["gains"] = gains
    return record


def gains_record(gains, source: str | os.PathLike | None) -> dict:
    """``{"source": absolute file path or "defaults", "values": {field: value}}``: the
    values as the run used them (after the cast to its dtype)."""
    import numpy as np

    return {
        "source": str(Path(source).resolve()) if source is not None else "defaults",
        "values": {name: np.asarray(value).tolist() for name, value in gains._asdict().items()},
    }


def write_json(path: Path, document: dict) -> Path:
    """``path`` holding ``document`` (indented JSON), written atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(document, indent=1, default=str) + "\n")
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------------- the chunk store


class StoreMismatch(ValueError):
    """The output folder holds chunks of a run with other settings."""


_FLAGS = {
    "seed": "--seed",
    "dtype": "--dtype",
    "keep": "--keep (capped at --draws)",
    "chunk": "--chunk or --draws (draws per call: the smaller, rounded up to a multiple "
    "of the device count)",
    "gains": "--gains",
    "controller_config.law.switching": "--switching",
    "controller_config.law.fractional_method": "--fractional",
    "controller_config.law.dt": "--dt",
    "controller_config.law.horizon": "--horizon",
    "scenario.horizon": "--horizon",
    "simulation.horizon": "--horizon",
    "simulation.dt": "--dt",
    "simulation.save_every": "snapshot interval (follows --horizon and --dt)",
    "metrics": "metric settings (follow --horizon and --dt)",
}


def _flag(field: str) -> str:
    for prefix in sorted(_FLAGS, key=len, reverse=True):
        if field == prefix or field.startswith(prefix + "."):
            return _FLAGS[prefix]
    return ""


def _flatten(value, prefix: str = "") -> dict:
    if isinstance(value, dict):
        out = {}
        for key in value:
            out.update(_flatten(value[key], f"{prefix}.{key}" if prefix else str(key)))
        return out
    return {prefix: value}


def _short(value, width: int = 60) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= width else text[: width - 3] + "..."


def _differences(stored: dict, current: dict) -> list[str]:
    old, new = _flatten(stored), _flatten(current)
    lines = []
    for field in sorted(set(old) | set(new)):
        if old.get(field, "<absent>") == new.get(field, "<absent>"):
            continue
        flag = _flag(field)
        lines.append(
            f"{field}{f' ({flag})' if flag else ''}: earlier "
            f"{_short(old.get(field, '<absent>'))}, now {_short(new.get(field, '<absent>'))}"
        )
    return lines


def _fingerprint(controller, gains, scenario, config, study: Study, devices: int, dtype):
    """The chunk store's fingerprint of this run (as :func:`fojax.study.run` makes
    it), JSON-normalised; None when fojax does not expose how it makes one."""
    from fojax import study as monte_carlo

    make = getattr(monte_carlo, "fingerprint", None)
    if make is None:
        return None
    chunk = min(study.chunk, study.draws)
    chunk = -(-chunk // devices) * devices
    keep = min(max(study.keep, 0), study.draws)
    metrics_config = study.metrics_config(config.steps)
    fingerprint = make(
        controller, gains, scenario, config, study.seed, chunk, keep, dtype, metrics_config
    )
    return json.loads(json.dumps(fingerprint, sort_keys=True, default=str))


def store_differences(store: Path, fingerprint: dict | None) -> list[str] | None:
    """How ``fingerprint`` differs from the one of the chunks in ``store``: one line
    per field (``[]``: the same settings; None: nothing stored there to compare)."""
    manifest = Path(store) / "manifest.json"
    if fingerprint is None or not manifest.is_file():
        return None
    try:
        stored = json.loads(manifest.read_text()).get("fingerprint")
    except (OSError, ValueError):
        return [f"{manifest} cannot be read"]
    if not isinstance(stored, dict):
        return [f"{manifest} holds no settings"]
    return _differences(stored, fingerprint)


def _prepared(study: Study):
    """``(mesh, scenario, config, dtype, {name: (controller, gains)})``."""
    import jax
    import jax.numpy as jnp

    from fojax import scenarios, sharding, simulator
    from fojax.controllers import registry

    # Every local device (GPUs, or one CPU device per core: see experiments.cli).
    mesh = sharding.draw_mesh(jax.local_devices()) if jax.local_device_count() > 1 else None
    scenario = dataclasses.replace(scenarios.get_scenario(study.scenario_id), horizon=study.horizon)
    config = simulator.SimulationConfig(
        dt=study.dt, horizon=study.horizon, save_every=study.save_every
    )
    dtype = jnp.dtype(study.dtype)
    runs = {}
    for name in study.controllers:
        controller = registry.make_controller(
            name,
            dt=study.dt,
            horizon=study.horizon,
            fractional_method=study.fractional,
            switching=study.switching,
        )
        gains = study.gains.get(name)
        if gains is None:
            gains = controller.default_gains(dtype)
        gains = type(gains)(*(jnp.asarray(g, dtype) for g in gains))
        runs[name] = (controller, gains)
    return mesh, scenario, config, dtype, runs


def check_stores(study: Study, out: Path) -> None:
    """Raise :class:`StoreMismatch` naming the fields that differ when ``out/chunks``
    holds chunks of a run with other settings (before anything is compiled)."""
    mesh, scenario, config, dtype, runs = _prepared(study)
    devices = 1 if mesh is None else int(mesh.devices.size)
    problems = []
    for name, (controller, gains) in runs.items():
        store = Path(out) / "chunks" / name
        fingerprint = _fingerprint(controller, gains, scenario, config, study, devices, dtype)
        lines = store_differences(store, fingerprint)
        if lines:
            problems.append((store, lines))
    if problems:
        text = "\n".join(
            f"{store} holds chunks of an earlier run that differs in:\n  " + "\n  ".join(lines)
            for store, lines in problems
        )
        raise StoreMismatch(
            f"{text}\nto start afresh, add --overwrite (discards those chunks), or choose "
            "another --out"
        )


def run_study(study: Study, out: Path, progress: bool = True, overwrite: bool = False) -> dict:
    """Run every controller of ``study`` on the same draws; returns the results by name.

    Finished chunks go to ``out/chunks/<controller>``; a run started again with the
    same settings continues from them. Raises :class:`StoreMismatch` (a ValueError)
    naming the fields that differ when they hold a run with other settings (unless
    ``overwrite``: then they are discarded).
    """
    from fojax import study as monte_carlo

    chunks = Path(out) / "chunks"
    if overwrite and chunks.exists():
        shutil.rmtree(chunks)
    elif chunks.exists():
        check_stores(study, out)
    mesh, scenario, config, dtype, runs = _prepared(study)
    results = {}
    for name, (controller, gains) in runs.items():
        results[name] = monte_carlo.run(
            controller,
            gains,
            scenario,
            config,
            study.draws,
            seed=study.seed,
            chunk=study.chunk,
            keep=study.keep,
            progress=progress,
            dtype=dtype,
            metrics_config=study.metrics_config(config.steps),
            store=chunks / name,
            mesh=mesh,
        )
    return results


# ---------------------------------------------------------------------------- outputs


def _reaching_bounds(name: str, study: Study, result) -> dict:
    """Eq. (34) bound per draw, for controllers that define one."""
    import jax.numpy as jnp
    import numpy as np

    from fojax import metrics
    from fojax.controllers import registry

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
    import jax.numpy as jnp

    from fojax.controllers import registry

    gains = study.gains.get(name)
    if gains is None:
        gains = registry.get_controller_class(name).default_gains(jnp.dtype(study.dtype))
    return type(gains)(*(jnp.asarray(g, jnp.dtype(study.dtype)) for g in gains))


def _batch_layout(study: Study) -> dict:
    """How the draws were batched: a draw's float32 rounding depends on its batch."""
    import jax

    devices = jax.local_device_count()
    per_call = -(-min(study.chunk, study.draws) // devices) * devices
    return {
        "devices": devices,
        "draws_per_call": per_call,
        "calls": -(-study.draws // per_call),
        "note": "draws per call: the smaller of --chunk and --draws, rounded up to a "
        "multiple of the device count; each call's draws are split over the devices",
    }


def _savez(path: Path, arrays: dict) -> None:
    import numpy as np

    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


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

    from fojax import statistics
    from fojax import study as monte_carlo

    summary = {
        "scenario": study.scenario_id,
        "draws": study.draws,
        "seed": study.seed,
        "horizon_s": study.horizon,
        "dt_s": study.dt,
        "fractional_method": study.fractional,
        "switching": study.switching,
        "dtype": study.dtype,
        "chunk": study.chunk,
        "batch": _batch_layout(study),
        "keep": study.keep,
        "gains": {
            name: gains_record(_used_gains(study, name), study.gains_sources.get(name))
            for name in results
        },
        "excluded_from_metrics": "draws flagged nonfinite or tilt_limit (counted in 'diverged')",
        "controllers": {},
    }
    arrays = {}
    for name, result in results.items():
        bounds = _reaching_bounds(name, study, result)
        entry = monte_carlo.summarize(result, extra=bounds)
        entry["wall_time_s"] = round(result.wall_time, 2)
        summary["controllers"][name] = entry
        arrays[f"{name}.status"] = result.status
        for metric, values in result.per_draw.items():
            arrays[f"{name}.{metric}"] = values
        for metric, values in bounds.items():
            arrays[f"{name}.{metric}"] = values
    names = list(results)
    if len(names) > 1:
        baseline = names[0]
        base_table = monte_carlo.metric_table(results[baseline])
        paired = {}
        for name in names[1:]:
            table = monte_carlo.metric_table(results[name])
            paired[name] = {
                metric: statistics.paired_difference(table[metric][0], base_table[metric][0])
                for metric in table
                if metric in base_table
            }
        summary["paired_differences"] = {"baseline": baseline, "minus_baseline": paired}
    summary.update(extra or {})
    summary["provenance"] = provenance(command)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = ["summary.json", "draws.npz"]
    trajectories = {}
    for name, result in results.items():
        tr = result.trajectories
        if tr is None:
            continue
        few = slice(0, min(8, tr.time.shape[0]))
        trajectories[f"{name}.time"] = tr.time[few]
        trajectories[f"{name}.state"] = tr.state[few]
        trajectories[f"{name}.reference"] = tr.reference[few]
        trajectories[f"{name}.inputs"] = tr.inputs[few]
        for field in ("inputs_low", "inputs_high"):
            if getattr(tr, field, None) is not None:
                trajectories[f"{name}.{field}"] = getattr(tr, field)[few]
        trajectories[f"{name}.attitude_reference"] = tr.info.attitude_reference[few]
        trajectories[f"{name}.surfaces"] = tr.info.surfaces[few]
        trajectories[f"{name}.adaptive"] = tr.info.adaptive[few]
    if trajectories:
        files.append("trajectories.npz")
    summary["files"] = files
    write_json(out / "summary.json", summary)
    _savez(out / "draws.npz", arrays)
    if trajectories:
        _savez(out / "trajectories.npz", trajectories)
    if figures and trajectories:
        from experiments import figures as figs
        from experiments import style

        context = (
            f"scenario {study.scenario_id}, {study.switching} switching, "
            f"{study.fractional} fractional operators, dt {study.dt * 1e3:g} ms"
        )
        drawn = style.attempt("(all)", figs.plot_all, results, out, "", context) or []
        if drawn:
            summary["figures"] = [p.name for p in drawn]
            write_json(out / "summary.json", summary)
    return summary
