"""``fojax reproduce``: the command line (argparse, validation, the run, the outputs).

See :mod:`fojax.cli.reproduce` for what it writes, :mod:`.claims` for the claims and
the verdict rule, :mod:`.report` for the report.

The studies (one :class:`fojax.cli.simulate.Study` per scenario) are run by
:func:`fojax.cli.study.run_studies` (the next runs' programs compile while one runs; the
scenarios run as members of one union, so each controller's program serves every
scenario) and summarised by :func:`fojax.cli.simulate.write_outputs`, in :func:`main`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from fojax.cli import arguments, output, simulate
from fojax.cli.reproduce import claims as claims_module
from fojax.cli.reproduce.claims import BASELINE
from fojax.cli.reproduce.report import TABLE_METRICS, write_report

__all__ = ["DEFAULT_DRAWS", "build_parser", "main", "parse_args"]

DEFAULT_DRAWS = 100
"""Draws per scenario and controller by default, sized to finish within 10 minutes on
a 2-core CPU: 3 scenarios x 5 controllers x 100 draws took 196 s on the project's
2-core machine (float32, chunks of 50, load average about 1; about 100 s of it
compiling the 15 (scenario, controller) rollouts, before the scenarios ran as members
of one union: now one rollout per controller, 5 in all, each scenario's draws recorded
up to its own horizon; ``FOJAX_UNION=0`` compiles the 15); the measured time of the
committed example is in ``docs/reproduction.md``."""


# ------------------------------------------------------------------------- figures


def _draw_scenario(scenario_id: int, results: dict, directory: str) -> list[str]:
    """Figs. of one scenario (run in the figure process)."""
    from fojax.cli.reproduce import figures as paper_figures

    return [str(p) for p in paper_figures.plot_all({scenario_id: results}, Path(directory))]


class _FigureDrawer:
    """Draws each scenario's figures in a separate process as soon as its results are
    in, while the next scenarios run: drawing 12 figures takes about as long as
    simulating them (Python and matplotlib, one core), so on two cores it overlaps
    the rest of the run (docs/performance.md). A figure process that fails is a
    warning; the figures are then drawn here."""

    def __init__(self, directory: Path, progress: bool):
        import concurrent.futures
        import multiprocessing

        self.directory, self.progress = Path(directory), progress
        self.pending: dict = {}  # scenario id -> (results, the figure process's future)
        try:
            context = multiprocessing.get_context("spawn")  # no fork of a process using JAX
            self.pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=context)
        except (OSError, ValueError, NotImplementedError):
            self.pool = None

    def submit(self, scenario_id: int, results: dict) -> None:
        import jax
        import numpy as np

        future = None
        if self.pool is not None:  # NumPy arrays only: picklable without JAX
            light = {
                name: r._replace(trajectories=jax.tree.map(np.asarray, r.trajectories))
                for name, r in results.items()
            }
            future = self.pool.submit(_draw_scenario, scenario_id, light, str(self.directory))
        self.pending[scenario_id] = (results, future)

    def finish(self) -> list[Path]:
        output.log(not self.progress, "figures ...")
        paths = []
        for scenario_id, (results, future) in sorted(self.pending.items()):
            try:
                drawn = future.result() if future is not None else None
            except Exception as error:  # noqa: BLE001 - the process died: draw them here
                warning = f"the figure process failed ({type(error).__name__}: {error})"
                print(f"warning: {warning}; drawing the figures here", file=sys.stderr)
                drawn = None
            if drawn is None:
                drawn = _draw_scenario(scenario_id, results, self.directory)
            paths.extend(Path(p) for p in drawn)
        self.close()
        return paths

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None


# ----------------------------------------------------------------------- arguments

COMPARED = ("anftsmc", "fobsmc", "bsmc", "fl")
"""The controllers the AFONFTSMC is compared with by default: the paper's four."""


def _compared(parser, text: str) -> tuple[str, ...]:
    """The controllers of ``--compare`` by their registered names; exits on bad input."""
    from fojax.controllers import registry

    names = []
    for part in text.split(","):
        try:  # a registered name, 'package.module:Class' or an entry point
            names.append(registry.get_controller_class(part.strip()).name)
        except (TypeError, ValueError) as error:
            parser.error(f"--compare: {error}")
    if BASELINE in names:
        parser.error(f"--compare: {BASELINE} is the baseline, always run; list the others")
    if len(set(names)) < len(names):
        parser.error(f"--compare names a controller twice: {text}")
    return tuple(names)


def build_parser() -> argparse.ArgumentParser:
    from fojax import fractional
    from fojax.controllers import SWITCHING_FUNCTIONS

    parser = argparse.ArgumentParser(
        prog="fojax reproduce",
        description="The paper's Section V with Monte Carlo: 3 scenarios x 5 controllers on the "
        "same draws; report, JSON and Figs. 5-16.",
    )
    # fmt: off
    arguments.add_options(
        parser,
        ("--out", dict(required=True, type=Path, metavar="DIR")),
        ("--draws", dict(type=arguments.positive_int, default=DEFAULT_DRAWS,
                         help=f"draws per scenario and controller (default {DEFAULT_DRAWS}: "
                         "< 10 min on 2 cores)")),
        ("--seed", dict(type=arguments.nonnegative_int, default=0)),
        ("--switching", dict(choices=SWITCHING_FUNCTIONS, default="sign", help="switching "
                             "function of the sliding-mode controllers (default sign, the "
                             "paper's)")),
        ("--fractional", dict(choices=fractional.METHODS, default="soe", help="fractional "
                              "operator method (default soe; oustaloup is the paper's CRONE)")),
        ("--scenarios", dict(type=arguments.scenario_ids, default=(1, 2, 3),
                             help="subset, e.g. 1,3")),
        ("--compare", dict(default=",".join(COMPARED), metavar="NAMES", help="the "
                           "controllers the AFONFTSMC is compared with, separated by commas: "
                           "registered names or 'package.module:Class' for a control law of "
                           f"your own (default {','.join(COMPARED)}, the paper's)")),
        ("--horizon", dict(type=arguments.positive_float, help="simulated time (s) for every "
                           "scenario (default: each scenario's, 80/80/50 s)")),
        ("--dt", dict(type=arguments.positive_float, default=1e-3, help="step, s")),
    )
    # fmt: on
    arguments.add_study_options(
        parser, 32, "draws whose trajectories are kept for the figures (32)"
    )
    arguments.add_vehicle(parser)
    arguments.add_runtime_options(parser)
    return parser


def parse_args(argv) -> tuple[list, argparse.Namespace]:
    """One validated :class:`fojax.cli.simulate.Study` per scenario; exits on bad input."""
    from fojax import scenarios

    parser = build_parser()
    args = parser.parse_args(argv)
    compared = _compared(parser, args.compare)
    arguments.enable_dtype(args.dtype)
    band = claims_module.reaching_band(args.dt)
    studies = []
    for scenario_id in args.scenarios:
        horizon = args.horizon or scenarios.get_scenario(scenario_id).horizon  # horizon > 0
        steps = arguments.horizon_steps(parser, horizon, args.dt, example=False)
        studies.append(
            simulate.Study(
                scenario_id=scenario_id,
                controllers=(BASELINE, *compared),
                draws=args.draws,
                seed=args.seed,
                horizon=float(horizon),
                dt=float(args.dt),
                save_every=simulate.snapshot_interval(steps, args.dt),
                gains={},
                fractional=args.fractional,
                switching=args.switching,
                device_batch=args.device_batch,
                keep=min(args.keep, args.draws),
                dtype=args.dtype,
                reaching_band=band,
                vehicle=args.vehicle,
                rotor_speed_limit=None if args.vehicle is None else args.vehicle.speed_limit(),
            )
        )
    arguments.check_controllers(
        parser, studies[0].controllers, args.dt, studies[0].horizon, args.fractional, args.switching
    )
    return studies, args


# ------------------------------------------------------------------------------- main


def main(argv=None) -> int:
    from fojax.cli import study as study_layer

    argv = list(sys.argv[1:] if argv is None else argv)
    runtime = arguments.setup_runtime(argv, "fojax reproduce")
    studies, args = parse_args(argv)
    out: Path = args.out
    lead = runtime["process_index"] == 0
    if lead:
        out.mkdir(parents=True, exist_ok=True)
    progress = not args.quiet and lead
    if args.vehicle is not None and lead:
        print(arguments.describe_vehicle(args.vehicle, args.vehicle.speed_limit()))
    start = time.perf_counter()
    results_by_scenario, summaries = {}, {}

    def announce(study):
        index = [s.scenario_id for s in studies].index(study.scenario_id)
        output.log(
            not progress,
            f"scenario {study.scenario_id} ({index + 1}/{len(studies)}): "
            f"{len(study.controllers)} controllers x {study.draws} draws, "
            f"{study.horizon:g} s; {time.perf_counter() - start:.0f} s so far",
        )

    drawer = _FigureDrawer(out / "figures", progress) if lead and not args.no_figures else None
    pairs = [(study, out / f"s{study.scenario_id}") for study in studies]
    try:
        runs = study_layer.run_studies(
            pairs, progress, args.overwrite, announce=announce, settings=runtime["settings"]
        )
        for study, results in runs:
            results_by_scenario[study.scenario_id] = results
            if lead:
                directory = out / f"s{study.scenario_id}"
                summary = simulate.write_outputs(study, results, directory, figures=False)
                summary["reaching_band"] = list(study.reaching_band)
                output.write_json(directory / "summary.json", summary)
                summaries[study.scenario_id] = summary
                if drawer is not None:  # while the next scenario runs
                    drawer.submit(study.scenario_id, results)
    except (KeyboardInterrupt, ValueError) as error:
        if drawer is not None:
            drawer.close()
        return simulate.stopped(error, "fojax reproduce", f"under {out}/s*/chunks")
    if not lead:  # process 0 writes the report
        return 0
    figures = drawer.finish() if drawer is not None else []
    claims = claims_module.evaluate_claims(summaries, results_by_scenario)
    tables = claims_module.paired_tables(summaries, results_by_scenario, TABLE_METRICS)
    given = ("draws", "seed", "scenarios", "switching", "fractional", "dt", "dtype")
    settings = {key: getattr(args, key) for key in given} | {
        "scenarios": list(args.scenarios),
        "horizons_s": {str(s.scenario_id): s.horizon for s in studies},
        "controllers": list(studies[0].controllers),
        "reaching_band": list(studies[0].reaching_band),
        **({} if args.vehicle is None
           else {"vehicle": arguments.vehicle_record(args.vehicle, args.vehicle.speed_limit())}),
    }
    wall = time.perf_counter() - start
    report_md, _ = write_report(out, summaries, claims, settings, figures, wall, tables)
    print(f"wrote {report_md}, report.json, figures/ and s*/ in {wall:.0f} s")
    for claim in claims:
        print(f"  {claim['verdict']:>28}: {claim['text']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
