"""``fojax simulate``: a Monte Carlo study of one scenario under one or all controllers.

    fojax simulate --scenario {1,2,3} --controller NAME|all --draws N --seed S
                   [--horizon T] [--dt DT] [--gains FILE ...] [--fractional METHOD]
                   [--switching sign|sat|tanh] [--chunk N] [--dtype float32|float64]
                   --out DIR

Writes to ``DIR``:

* ``summary.json``: per controller, each metric's mean and 95 % confidence interval
  over the draws that did not diverge, the number of draws with each status flag, and
  ``diverged`` (non-finite, or roll/pitch beyond pi/2); with several controllers,
  paired differences against the first (common random numbers).
* ``draws.npz``: per-draw metrics, ``<controller>.<metric>``, and
  ``<controller>.status``.
* ``trajectories.npz``: decimated trajectories of the first draws.
* figures: ``tracking.png``, ``errors.png``, ``inputs.png``, ``path3d.png``,
  ``adaptive.png``.
* ``chunks/``: finished chunks. An interrupted run started again with the same
  command continues from them.

Every input is checked before anything is compiled.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

from experiments import arguments

__all__ = ["main", "parse_args", "run_study"]


def build_parser() -> argparse.ArgumentParser:
    from fojax import fractional, scenarios
    from fojax.controllers import SWITCHING_FUNCTIONS, registry

    parser = argparse.ArgumentParser(
        prog="fojax simulate",
        description="Monte Carlo study of a scenario of the paper under one or all controllers.",
    )
    parser.add_argument("--scenario", type=int, required=True, choices=scenarios.SCENARIO_IDS)
    parser.add_argument(
        "--controller",
        required=True,
        help=f"one of {', '.join(registry.controller_names())}, or 'all'",
    )
    parser.add_argument("--draws", type=arguments.positive_int, required=True)
    parser.add_argument("--seed", type=arguments.nonnegative_int, default=0)
    parser.add_argument(
        "--horizon", type=arguments.positive_float, help="s (default: the scenario's)"
    )
    parser.add_argument("--dt", type=arguments.positive_float, default=1e-3, help="step, s (1e-3)")
    parser.add_argument(
        "--gains",
        action="append",
        default=[],
        metavar="FILE",
        help="gains file (JSON); repeat for several controllers",
    )
    parser.add_argument(
        "--fractional",
        choices=fractional.METHODS,
        default="soe",
        help="fractional operator method (default soe; oustaloup is the paper's)",
    )
    parser.add_argument(
        "--switching",
        choices=SWITCHING_FUNCTIONS,
        default="sign",
        help="switching function of the sliding-mode controllers (default sign, the paper's)",
    )
    parser.add_argument(
        "--chunk", type=arguments.positive_int, default=1024, help="draws per compiled call"
    )
    parser.add_argument(
        "--keep",
        type=arguments.nonnegative_int,
        default=64,
        help="draws whose trajectories are kept for figures (64)",
    )
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--no-figures", action="store_true", help="skip the figures")
    parser.add_argument(
        "--overwrite", action="store_true", help="discard chunks of an earlier run in DIR/chunks"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR")
    return parser


@dataclasses.dataclass(frozen=True)
class Study:
    """A validated study: everything settled before anything is compiled."""

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
    reaching_band: float | tuple[float, ...] = 0.01
    """``fojax.metrics.MetricsConfig.reaching_band``: one band, or six (one per axis)."""


def snapshot_interval(steps: int, dt: float, target: float = 0.1) -> int:
    """Steps between snapshots: the divisor of ``steps`` closest to ``target / dt``."""
    want = max(1, round(target / dt))
    divisors = [d for d in range(1, min(steps, 10 * want) + 1) if steps % d == 0]
    return min(divisors, key=lambda d: (abs(d - want), d))


def parse_args(argv) -> tuple[Study, argparse.Namespace]:
    """Parse and validate; raises ``SystemExit`` with a message on bad input."""
    from fojax import scenarios
    from fojax.controllers import gains_io, registry

    parser = build_parser()
    args = parser.parse_args(argv)
    names = registry.controller_names()
    if args.controller == "all":
        controllers = names
    elif args.controller in names:
        controllers = (args.controller,)
    else:
        parser.error(
            f"unknown controller {args.controller!r}; choose one of {', '.join(names)} or 'all'"
        )
    scenario = scenarios.get_scenario(args.scenario)
    horizon = args.horizon if args.horizon is not None else scenario.horizon
    if args.dt > horizon:
        parser.error(f"--dt ({args.dt}) must not exceed the horizon ({horizon})")
    steps = horizon / args.dt
    if abs(steps - round(steps)) > 1e-6 * steps:
        parser.error(f"the horizon ({horizon} s) must be a whole number of steps of {args.dt} s")
    steps = round(steps)
    gains = {}
    dtype = args.dtype
    if dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    for path in args.gains:
        try:
            name, value, _ = gains_io.load_gains(path, dtype)
        except ValueError as error:
            parser.error(str(error))
        if name not in controllers:
            parser.error(
                f"{path} holds gains of {name!r}, which this run does not simulate "
                f"({', '.join(controllers)})"
            )
        if name in gains:
            parser.error(f"two gains files for {name!r}")
        gains[name] = value
    study = Study(
        scenario_id=args.scenario,
        controllers=controllers,
        draws=args.draws,
        seed=args.seed,
        horizon=float(horizon),
        dt=float(args.dt),
        save_every=snapshot_interval(steps, args.dt),
        gains=gains,
        fractional=args.fractional,
        switching=args.switching,
        chunk=args.chunk,
        keep=min(args.keep, args.draws),
        dtype=dtype,
    )
    # Build every controller now: bad configurations fail before compiling.
    for name in controllers:
        try:
            registry.make_controller(
                name,
                dt=study.dt,
                horizon=study.horizon,
                fractional_method=study.fractional,
                switching=study.switching,
            )
        except ValueError as error:
            parser.error(f"{name}: {error}")
    return study, args


def run_study(study: Study, out: Path, progress: bool = True, overwrite: bool = False) -> dict:
    """Run every controller of ``study`` on the same draws; returns the results by name."""
    import jax
    import jax.numpy as jnp

    from fojax import metrics, scenarios, sharding, simulator
    from fojax import study as monte_carlo
    from fojax.controllers import registry

    # Every local device (GPUs, or one CPU device per core: see experiments.cli).
    mesh = sharding.draw_mesh(jax.local_devices()) if jax.local_device_count() > 1 else None
    scenario = dataclasses.replace(scenarios.get_scenario(study.scenario_id), horizon=study.horizon)
    config = simulator.SimulationConfig(
        dt=study.dt, horizon=study.horizon, save_every=study.save_every
    )
    metrics_config = metrics.MetricsConfig(
        dt=study.dt, steps=config.steps, reaching_band=study.reaching_band
    )
    dtype = jnp.dtype(study.dtype)
    chunks = out / "chunks"
    if overwrite and chunks.exists():
        shutil.rmtree(chunks)
    results = {}
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
            metrics_config=metrics_config,
            store=chunks / name,
            mesh=mesh,
        )
    return results


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


def write_outputs(study: Study, results: dict, out: Path, figures: bool = True) -> dict:
    """summary.json, draws.npz, trajectories.npz and figures; returns the summary."""
    import numpy as np

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
        "gains": {name: ("file" if name in study.gains else "default") for name in results},
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
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    np.savez_compressed(out / "draws.npz", **arrays)
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
        trajectories[f"{name}.attitude_reference"] = tr.info.attitude_reference[few]
        trajectories[f"{name}.surfaces"] = tr.info.surfaces[few]
        trajectories[f"{name}.adaptive"] = tr.info.adaptive[few]
    if trajectories:
        np.savez_compressed(out / "trajectories.npz", **trajectories)
    if figures:
        from experiments import figures as figs

        figs.plot_all(results, out)
    return summary


def _print_summary(summary: dict) -> None:
    print(
        f"scenario {summary['scenario']}, {summary['draws']} draws, seed {summary['seed']}, "
        f"{summary['horizon_s']} s at dt = {summary['dt_s']} s"
    )
    header = f"  {'controller':<10} {'position_rmse (m)':>26} {'attitude_rmse (rad)':>26}  diverged"
    print(header)
    for name, entry in summary["controllers"].items():
        cells = []
        for key in ("position_rmse", "attitude_rmse"):
            m = entry["metrics"][key]
            if m["mean"] is None:
                cells.append(f"{'n/a':>26}")
            elif m["ci95"] is None:
                cells.append(f"{m['mean']:>26.4g}")
            else:
                lo, hi = m["ci95"]
                cells.append(f"{m['mean']:.4g} [{lo:.4g}, {hi:.4g}]".rjust(26))
        print(f"  {name:<10} {cells[0]} {cells[1]}  {entry['diverged']}/{entry['draws']}")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    study, args = parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    try:
        results = run_study(study, out, progress=not args.quiet, overwrite=args.overwrite)
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: finished chunks are kept in {out / 'chunks'}; run the same "
            "command again to continue",
            file=sys.stderr,
        )
        return 130
    except ValueError as error:
        print(f"fojax simulate: error: {error}", file=sys.stderr)
        return 2
    summary = write_outputs(study, results, out, figures=not args.no_figures)
    summary["wall_time_s"] = round(time.perf_counter() - start, 1)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    _print_summary(summary)
    print(
        f"wrote {out}/summary.json, draws.npz, trajectories.npz"
        + ("" if args.no_figures else ", figures")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
