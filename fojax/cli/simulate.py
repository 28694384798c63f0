"""``fojax simulate``: a Monte Carlo study of one scenario under one or more controllers.

    fojax simulate --scenario {1,2,3} --controller NAME[,NAME...]|all --draws N --seed S
                   [--horizon T] [--dt DT] [--gains FILE ...] [--fractional METHOD]
                   [--switching sign|sat|tanh] [--device-batch N] [--dtype float32|float64]
                   --out DIR

``--switching`` and ``--fractional`` set the controllers that have a switching function
(all but the FL) or fractional operators (AFONFTSMC, FOBSMC): given for one controller
that has none they are an error; given with several controllers they apply to those
that have one, and the summary (``options_applied_to``) and the printed lines say which.

Writes to ``DIR``, the results first and the figures after them:

* ``summary.json``: per controller, each metric's mean and 95 % confidence interval
  over the draws that did not diverge, the number of draws with each status flag, and
  ``diverged`` (non-finite, or roll/pitch beyond pi/2); with several controllers,
  paired differences against the first (common random numbers); the gains' values
  and their source (a file or the defaults), and ``provenance``: the command line,
  versions, backend and device counts (:func:`fojax.cli.study.provenance`).
* ``draws.npz``: per-draw metrics, ``<controller>.<metric>``, and
  ``<controller>.status``.
* ``trajectories.npz``: decimated trajectories of the first draws.
* figures, PNG and PDF: ``tracking``, ``errors``, ``inputs``, ``path3d``,
  ``adaptive`` (a figure that cannot be drawn is a warning; the results stay).
* ``chunks/``: finished draws. An interrupted run started again with the same
  command continues from them, and one with more draws (or on other devices or
  processes) reuses them: draw ``i``'s numbers do not depend on the draw count or the
  layout, only on ``--device-batch`` (:mod:`fojax.study`). One with other settings is
  refused, naming the settings that differ (``--overwrite`` starts afresh).

Over several processes (``--coordinator HOST:PORT --num-processes N --process-id I``
on each, the ``JAX_COORDINATOR_ADDRESS``/``JAX_NUM_PROCESSES``/``JAX_PROCESS_ID``
variables, or a detected cluster job such as SLURM's ``srun``): the draws are split
over every process's devices and process 0 writes the outputs (``docs/distributed.md``).

Every input is checked before anything is compiled. The study itself
(:class:`Study`, :func:`run_study`, :func:`write_outputs`) lives in
:mod:`fojax.cli.study`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from fojax.cli import arguments
from fojax.cli import requirements as requirements_cli
from fojax.cli.study import Study, run_study, snapshot_interval
from fojax.cli.study_files import write_outputs

__all__ = ["Study", "main", "parse_args", "run_study", "snapshot_interval", "write_outputs"]


def build_parser() -> argparse.ArgumentParser:
    from fojax import fractional, scenarios
    from fojax.controllers import SWITCHING_FUNCTIONS, registry

    parser = argparse.ArgumentParser(
        prog="fojax simulate",
        description="Monte Carlo study of a scenario of the paper under one or more controllers.",
    )
    per_law = " With one controller that has none, an error; with several, the summary says "
    per_law += "which it applied to"
    # fmt: off
    arguments.add_options(
        parser,
        ("--scenario", dict(type=int, required=True, choices=scenarios.SCENARIO_IDS)),
        ("--controller", dict(required=True, help=f"one of {', '.join(registry.controller_names())}"
                              ", several separated by commas (the first is the baseline of the "
                              "paired differences), or 'all'")),
        ("--draws", dict(type=arguments.positive_int, required=True)),
        ("--seed", dict(type=arguments.seed, default=0)),
        ("--horizon", dict(type=arguments.positive_float, help="s (default: the scenario's)")),
        ("--dt", arguments.STEP),
        ("--gains", dict(action="append", default=[], type=arguments.input_file, metavar="FILE",
                         help="gains file (JSON, as fojax tune writes); repeat for several "
                         "controllers")),
        ("--fractional", dict(choices=fractional.METHODS, help="fractional operator method of "
                              "the controllers with fractional operators (afonftsmc, fobsmc; "
                              "default soe; oustaloup is the paper's)." + per_law)),
        ("--switching", dict(choices=SWITCHING_FUNCTIONS, help="switching function of the "
                             "sliding-mode controllers (all but fl; default sign, the paper's)."
                             + per_law)),
    )
    # fmt: on
    arguments.add_study_options(
        parser,
        64,
        "draws whose trajectories are kept for figures (64; 0: no trajectories, no figures)",
    )
    arguments.add_options(parser, ("--out", arguments.OUTPUT_FOLDER))
    requirements_cli.add_simulate_options(parser)  # --requirements, --rotor-limit
    arguments.add_vehicle(parser)
    parser.add_argument(
        "--reference", type=arguments.reference_file, metavar="FILE",
        help="reference file of timed waypoints (TOML, docs/model.md), flown in place of the "
        "scenario's reference; its last waypoint within the run",
    )  # fmt: skip
    arguments.add_infeasible(parser)
    arguments.add_runtime_options(parser)
    return parser


def _controllers(parser, text: str) -> tuple[str, ...]:
    from fojax.controllers import registry

    names = registry.PAPER_CONTROLLERS
    if text.strip() == "all":
        return tuple(names)
    chosen = tuple(part.strip() for part in text.split(","))
    if not text.strip() or "" in chosen:
        parser.error(
            f"unknown controller {text!r}; choose one of {', '.join(names)}, several separated "
            "by commas, 'all', or 'package.module:Class' for a control law of your own"
        )
    resolved = []
    for name in chosen:
        try:  # a registered name, 'package.module:Class' or an entry point
            resolved.append(registry.get_controller_class(name).name)
        except (TypeError, ValueError) as error:
            parser.error(str(error))
    chosen = tuple(resolved)
    repeated = sorted({name for name in chosen if chosen.count(name) > 1})
    if repeated:
        parser.error(f"--controller names {', '.join(repeated)} twice")
    return chosen


def parse_args(argv) -> tuple[Study, argparse.Namespace]:
    """Parse and validate; raises ``SystemExit`` with a message on bad input."""
    from fojax import scenarios
    from fojax.controllers import gains_io

    parser = build_parser()
    args = parser.parse_args(argv)
    controllers = _controllers(parser, args.controller)
    try:  # an option the chosen law does not take is an error, not ignored
        args.applied = arguments.controller_flags(
            controllers,
            {
                "--fractional": ("fractional_method", args.fractional),
                "--switching": ("switching", args.switching),
            },
        )
    except ValueError as error:
        parser.error(str(error))
    scenario = scenarios.get_scenario(args.scenario)
    horizon = args.horizon if args.horizon is not None else scenario.horizon
    steps = arguments.horizon_steps(parser, horizon, args.dt)
    args.reference_peaks = arguments.check_reference(parser, args.reference, horizon)
    if args.allow_infeasible_reference and args.reference is None:
        parser.error("--allow-infeasible-reference applies with --reference only; leave it out")
    gains, sources = {}, {}
    dtype = args.dtype
    arguments.enable_dtype(dtype)
    for path in args.gains:
        try:
            name, value, _ = gains_io.load_gains(path, dtype)
        except ValueError as error:
            message = str(error)
            parser.error(message if str(path) in message else f"--gains {path}: {message}")
        if name not in controllers:
            parser.error(
                f"{path} holds gains of {name!r}, which this run does not simulate "
                f"({', '.join(controllers)}); add it to --controller or drop this --gains"
            )
        if name in gains:
            parser.error(f"two gains files for {name!r}: {sources[name]} and {path}")
        gains[name] = value
        sources[name] = path
    study = Study(
        scenario_id=args.scenario,
        controllers=controllers,
        draws=args.draws,
        seed=args.seed,
        horizon=float(horizon),
        dt=float(args.dt),
        save_every=snapshot_interval(steps, args.dt),
        gains=gains,
        fractional=args.fractional or "soe",
        switching=args.switching or "sign",
        device_batch=args.device_batch,
        keep=min(args.keep, args.draws),
        dtype=dtype,
        gains_sources=sources,
        vehicle=args.vehicle,
        reference=args.reference,
    )
    study = requirements_cli.configure_study(parser, args, study)  # rotor-limited actuators
    arguments.check_controllers(
        parser, controllers, study.dt, study.horizon, study.fractional, study.switching
    )
    return study, args


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
            cell = "n/a" if m["mean"] is None else f"{m['mean']:.4g}"
            if m["mean"] is not None and m["ci95"] is not None:
                cell += " [{:.4g}, {:.4g}]".format(*m["ci95"])
            cells.append(cell.rjust(26))
        print(f"  {name:<10} {cells[0]} {cells[1]}  {entry['diverged']}/{entry['draws']}")


def stopped(error: BaseException, prog: str, chunks: str) -> int:
    """Says why a study stopped: interrupted (``KeyboardInterrupt``; the finished draws
    are kept ``chunks``) or bad input (``ValueError``); returns the exit status, 130 or 2."""
    if isinstance(error, KeyboardInterrupt):
        print(
            f"\ninterrupted: finished draws are kept {chunks}; run the same command again to "
            "continue",
            file=sys.stderr,
        )
        return 130
    print(f"{prog}: error: {error}", file=sys.stderr)
    return 2


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    runtime = arguments.setup_runtime(argv, "fojax simulate")
    study, args = parse_args(argv)
    out: Path = args.out
    command = ["fojax", "simulate", *argv]
    lead = runtime["process_index"] == 0
    if lead:
        out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    try:
        progress = not args.quiet and lead
        results = run_study(study, out, progress, args.overwrite, runtime["settings"])
    except (KeyboardInterrupt, ValueError) as error:  # e.g. study.StoreMismatch, before compiling
        return stopped(error, "fojax simulate", f"in {out / 'chunks'}")
    if not lead:  # process 0 writes the outputs
        return 0
    wall = round(time.perf_counter() - start, 1)
    summary = write_outputs(
        study,
        results,
        out,
        figures=not args.no_figures,
        command=command,
        extra={"wall_time_s": wall},
    )
    if study.reference is not None:
        print(arguments.describe_reference(study.reference, args.reference_peaks))
    if study.vehicle is not None or study.rotor_speed_limit is not None:
        print(arguments.describe_vehicle(study.vehicle, study.rotor_speed_limit))
    _print_summary(summary)
    summary = requirements_cli.report_simulate(study, args, out, summary, not args.no_figures)
    for flag, users in args.applied.items():
        if len(users) < len(study.controllers):
            value = getattr(args, flag.removeprefix("--"))
            others = [name for name in study.controllers if name not in users]
            print(f"{flag} {value} applied to {', '.join(users)} (not {', '.join(others)})")
    written = summary["files"] + [f"{name} (+ .pdf)" for name in summary.get("figures", [])]
    print(f"wrote {out}/: {', '.join(written)}")
    if study.keep == 0:
        print("no trajectories kept (--keep 0): no trajectories.npz and no trajectory figures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
