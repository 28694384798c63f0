"""Sensitivity of the Section V verdicts to the open modelling choices.

    python -m experiments.sensitivity [--out results/sensitivity] [--doc docs/sensitivity.md]
                                      [--draws 32] [--dt-draws 16] [--horizon 30] [--seed 0]
                                      [--settings KEY,KEY,...] [--workers 2]
                                      [--tuned-gains FILE] [--tune-steps 20] [--tune-draws 8]
                                      [--tune-horizon 5] [--quiet]

The claims of ``fojax reproduce`` (:mod:`fojax.cli.reproduce.claims`: the same
claim map, margins, Holm correction and four outcomes) are decided again while each
open modelling choice is moved away from the default, one at a time (:data:`SETTINGS`):
the step, the thrust guard of eq. (13), the command filter's bandwidth, the fractional
method, the switching function, the actuators, scenario 3's reference, the Gaussian
disturbances' size, the baseline gains and the floating-point precision. Every setting
flies the same draws (seed ``--seed``, draws ``0 ... n - 1``: common random numbers),
the three scenarios under the five controllers.

Size. The full study (100 draws, 80/80/50 s) takes about 4 minutes per setting on 2
cores, so every setting runs ``--draws`` draws over ``--horizon`` s for all three
scenarios; the step of 0.1 ms, ten times the work per simulated second, runs the first
``--dt-draws`` draws, and is compared with the default's verdicts on those same draws
(the column ``default, first n draws``, no extra runs).

Compilation dominates at this size (one rollout program compiles in 10-20 s on a
loaded 2-core machine, running 32 draws x 30 s takes a few seconds), so:

* one program per (controller, simulation settings, dtype) serves every scenario of
  every setting that shares them: the scenarios are members of one
  :func:`fojax.scenarios.union` (each draw says its member), and a setting that only
  changes a scenario (smoothed reference, larger Gaussian disturbances) or the gains
  (gains are an argument) needs no program of its own;
* a controller that a setting does not change (the FL has no switching function; only
  the AFONFTSMC and FOBSMC have fractional operators) reuses the default's runs;
* the programs compile in the background while the previous one runs, in ``--workers``
  processes (float64 in a process of its own, with ``jax_enable_x64``), next to the
  gain tuning of ``experiments/fair_comparison.py`` (``--tune-*``, or ``--tuned-gains``
  to take the gains of an earlier fair-comparison run); its ``OUT/tuning/results.json``
  is reused when the same code wrote it (its ``code``), else tuned again.

Every run (one controller, one scenario, one set of gains, one program) is a
:func:`fojax.study.run` of the program's union member, stored as soon as it finishes
in ``OUT/runs/<key>/`` (a :class:`fojax.study.ChunkStore`), keyed by everything its
numbers depend on: an interrupted study started again with the same command continues
there.

Outputs: ``OUT/report.json`` (every setting's claims with their comparisons' outcomes,
the float32/float64 table), ``--doc`` (default ``docs/sensitivity.md``: the verdict
matrix, what flips, the precision table; the text above its marker line is kept) and
its figure (``docs/sensitivity.png``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from experiments import _common, sensitivity_report
from experiments.sensitivity_plan import (  # noqa: F401  (the study's names)
    SCENARIO_IDS,
    SETTING_KEYS,
    SETTINGS,
    SIGMA_FACTOR,
    THRUST_TO_WEIGHT,
    Job,
    Plan,
    Run,
    Setting,
    assign_lanes,
    gains_for,
    load_tuned,
    make_plan,
    metrics_config,
    reaching_band,
    rotor_speed_limit,
    run_key,
    scenario_variant,
    simulation_config,
)
from fojax import study
from fojax.cli import arguments, output
from fojax.cli.reproduce import claims as claims_module
from fojax.controllers import registry

__all__ = [
    "SETTINGS",
    "THRUST_TO_WEIGHT",
    "Setting",
    "build_parser",
    "evaluate",
    "main",
    "make_plan",
    "rotor_speed_limit",
]


def _stored(out: Path, run: Run, tuned: dict | None, seed: int):
    """``(status, per_draw)`` of the run's draws stored in ``OUT/runs/<key>``, or ``None``."""
    existing = study.ChunkStore.existing(out / "runs" / run_key(run, tuned, seed))
    return existing and existing.read(run.job.draws)


def compile_job(job: Job):
    """The job's program (:func:`fojax.study.compile_chunk_runner` for the union of its
    scenarios, ``job.draws`` draws a call) and its compile time (s)."""
    dtype = jnp.dtype(job.dtype)
    start = time.perf_counter()
    compiled = study.compile_chunk_runner(
        job.controller, job.controller.default_gains(dtype), job.union(), job.config,
        job.draws, metrics_config(job.config), dtype,
    )  # fmt: skip
    return compiled, time.perf_counter() - start


def execute(compiled, run: Run, gains, seed: int, store: Path) -> float:
    """Draws ``0 ... job.draws - 1`` of the run (:func:`fojax.study.run` of its union
    member, one call of the compiled program), stored in ``store``; the seconds."""
    job = run.job
    result = study.run(
        job.controller, gains, job.union(), job.config, job.draws, seed,
        device_batch=job.draws, keep=0, progress=False, dtype=job.dtype,
        metrics_config=metrics_config(job.config), store=store, runner=compiled,
        member=run.member,
    )  # fmt: skip
    return result.wall_time


def run_lane(
    plan: Plan, job_indices: list, out: Path, tuned_path: Path, progress: bool, lane: str = "main"
) -> None:
    """Compile and run the lane's jobs (each compiled in a background thread while the
    previous one runs); runs with tuned gains wait for them, at the end. ``lane``: its
    name, in the progress lines."""
    tuned = load_tuned(tuned_path) if tuned_path.exists() else None
    jobs = [plan.jobs[i] for i in job_indices]
    waits = {run for job in jobs for run in job.runs if run.gains == "tuned" and tuned is None}
    work = [  # the runs waiting for the tuned gains or not on disk
        (job, [r for r in job.runs if r in waits or not _stored(out, r, tuned, plan.seed)])
        for job in jobs
    ]
    work = [(job, runs) for job, runs in work if runs]
    log = _logger(progress, lane)

    def execute_and_log(compiled, run) -> None:
        store = out / "runs" / run_key(run, tuned, plan.seed)
        seconds = execute(compiled, run, gains_for(run, tuned), plan.seed, store)
        job, c = run.job, run.job.controller
        log(
            f"ran {c.name} {run.scenario.name[:24]!r} gains={run.gains} {job.dtype} "
            f"dt={job.config.dt:g} guard={c.thrust_floor:g} filter={c.filter_frequency:g}"
            f" {getattr(c.law, 'switching', '-')} {getattr(c.law, 'fractional_method', '-')}"
            f" rotor={job.config.rotor_speed_limit}: {job.draws} draws in {seconds:.1f} s"
        )

    deferred = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        futures = [pool.submit(compile_job, job) for job, _ in work]
        for (job, runs), future in zip(work, futures, strict=True):
            compiled, seconds = future.result()
            log(
                f"compiled job {job.index} ({job.controller.name}, {len(job.members)} "
                f"scenarios, {job.dtype}) in {seconds:.0f} s"
            )
            deferred += [(compiled, run) for run in runs if run in waits]
            for run in runs:
                if run not in waits:
                    execute_and_log(compiled, run)
    if deferred:
        log("waiting for the tuned gains ...")
        tuned = _wait_for_tuned(tuned_path)
    for compiled, run in deferred:
        if not _stored(out, run, tuned, plan.seed):
            execute_and_log(compiled, run)


def _wait_for_tuned(path: Path, poll: float = 5.0) -> dict:
    failed = path.parent / "FAILED"
    while not path.exists():
        if failed.exists():
            raise RuntimeError(f"the gain tuning failed: {failed.read_text()[-2000:]}")
        time.sleep(poll)
    return load_tuned(path)


def _logger(progress: bool, lane: str = "main"):
    start = time.perf_counter()

    def log(text: str) -> None:
        output.log(not progress, f"[{lane} {time.perf_counter() - start:5.0f} s] {text}")

    return log


# ----------------------------------------------------------------------------- results


def load_results(plan: Plan, out: Path, tuned: dict | None) -> dict:
    """``(setting key, scenario id, controller) -> MonteCarloResult`` (first ``n`` draws
    of the cell's run) for every cell whose run is on disk."""
    loaded, results = {}, {}
    for cell, (run, n) in plan.cells.items():
        if run.gains == "tuned" and tuned is None:
            continue
        if run not in loaded:
            loaded[run] = _stored(out, run, tuned, plan.seed)
        if loaded[run]:
            status, per_draw = loaded[run]
            per_draw = {k: v[:n] for k, v in per_draw.items()}
            results[cell] = study.MonteCarloResult(
                run.job.controller.name, np.asarray(status[:n], np.int32), per_draw, None, 0.0, 0.0
            )
    return results


def evaluate(plan: Plan, results: dict) -> dict:
    """Setting key -> ``{"claims": evaluate_claims(...), "diverged": ...}``, or
    ``{"missing": [...]}`` when some of its runs are not there."""
    evaluated = {}
    cells = [(s, name) for s in SCENARIO_IDS for name in plan.controllers]
    for setting in plan.settings:
        config = simulation_config(setting, plan.horizon)
        missing = [f"s{s} {name}" for s, name in cells if (setting.key, s, name) not in results]
        if missing:
            evaluated[setting.key] = {"missing": missing}
            continue
        band = reaching_band(config.dt)
        by_scenario = {
            s: {n: results[(setting.key, s, n)] for n in plan.controllers} for s in SCENARIO_IDS
        }
        summaries = {
            s: {
                "horizon_s": config.horizon,
                "dt_s": config.dt,
                "reaching_band": list(band),
                "controllers": {n: study.summarize(r) for n, r in by_name.items()},
            }
            for s, by_name in by_scenario.items()
        }
        evaluated[setting.key] = {
            "claims": claims_module.evaluate_claims(summaries, by_scenario),
            "diverged": {
                s: {n: c["diverged"] for n, c in summary["controllers"].items()}
                for s, summary in summaries.items()
            },
            "draws": next(iter(by_scenario[1].values())).draws,
            "summaries": summaries,
        }
    return evaluated


# ---------------------------------------------------------------------------- command


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser(
        "sensitivity",
        description="The Section V verdicts with each open modelling choice moved in turn.",
    )
    parser.add_argument("--out", type=Path, default=Path("results/sensitivity"), metavar="DIR")
    parser.add_argument(
        "--doc", type=Path, default=Path("docs/sensitivity.md"), help="document to (re)write"
    )
    parser.add_argument("--no-doc", action="store_true", help="write OUT/report.* only")
    _common.add_numbers(
        parser,
        draws=32,
        dt_draws=(16, "draws of the 0.1 ms step (10x the work per simulated second)"),
        horizon=(30.0, "s, every scenario"),
    )
    parser.add_argument("--seed", type=arguments.nonnegative_int, default=0)
    parser.add_argument(
        "--settings", help=f"comma-separated subset of {','.join(SETTING_KEYS)} (default all)"
    )
    parser.add_argument(
        "--controllers",
        help="comma-separated subset of the paper's five, with afonftsmc (quick checks)",
    )
    _common.add_numbers(parser, workers=(2, "float32 worker processes"))
    parser.add_argument(
        "--tuned-gains",
        type=Path,
        help="results.json of an earlier experiments.fair_comparison run (default: tune here)",
    )
    _common.add_numbers(parser, tune_steps=20, tune_draws=8, tune_horizon=5.0)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--lane", help=argparse.SUPPRESS)
    return parser


def parse_args(argv):
    parser = build_parser()
    args = parser.parse_args(argv)
    keys = SETTING_KEYS if args.settings is None else _common.listed(args.settings)
    unknown = [k for k in keys if k not in SETTING_KEYS]
    if unknown or not keys:
        parser.error(f"--settings must be among {', '.join(SETTING_KEYS)}, got {unknown}")
    # a setting needs the one it is compared with
    wanted = {*keys, *(s.reference for s in SETTINGS if s.key in keys and s.reference)}
    args.selected = tuple(s for s in SETTINGS if s.key in wanted)
    paper = registry.PAPER_CONTROLLERS
    names = paper if args.controllers is None else _common.listed(args.controllers)
    if not names or set(names) - set(paper) or claims_module.BASELINE not in names:
        parser.error(
            f"--controllers must be among {', '.join(paper)} and include "
            f"{claims_module.BASELINE}, got {args.controllers!r}"
        )
    args.controllers = tuple(n for n in paper if n in names)
    for dt in (1e-3, 1e-4):
        steps = args.horizon / dt
        if abs(steps - round(steps)) > 1e-6 * steps:
            parser.error(f"--horizon must be a whole number of 0.1 ms steps, got {args.horizon}")
    if args.dt_draws > args.draws:
        parser.error("--dt-draws must not exceed --draws")
    if args.tuned_gains is not None and not args.tuned_gains.is_file():
        parser.error(f"--tuned-gains: no file {args.tuned_gains}")
    return args


def _start_tuning(args, directory: Path, log) -> subprocess.Popen:
    """The gain tuning (``experiments.fair_comparison``) in a process of its own."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "FAILED").unlink(missing_ok=True)
    command = [
        sys.executable, "-m", "experiments.fair_comparison", "--out", str(directory),
        "--steps", str(args.tune_steps), "--draws", str(args.tune_draws),
        "--horizon", f"{args.tune_horizon:g}", "--seed", str(args.seed), "--eval-draws", "1",
        "--eval-scenarios", "2", "--eval-horizon", "0.1", "--quiet",
    ]  # fmt: skip
    log("tuning the five controllers: " + " ".join(command[1:]))
    stderr = open(directory / "stderr.log", "w")  # noqa: SIM115  (the child's, left open)
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr)


def _wait_for_tuning(tuning, tuned_path: Path, started: float, log) -> float:
    """Wait for the gain tuning; on failure, leave ``FAILED`` for the lanes that wait for
    its gains. Its wall time (s)."""
    rc = tuning.wait()
    tuning_wall = time.perf_counter() - started
    if rc != 0 or not tuned_path.exists():
        tail = (tuned_path.parent / "stderr.log").read_text()[-3000:]
        (tuned_path.parent / "FAILED").write_text(f"exit status {rc}\n{tail}")
        log(f"the gain tuning failed (exit status {rc}); see {tuned_path.parent}")
    else:
        log(f"tuned gains written in {tuning_wall:.0f} s")
    return tuning_wall


def _finished_files(out: Path) -> set:
    return set((out / "runs").glob("*/draws_*.npz"))


def _meta(args, argv, plan: Plan, wall, load_start, tuning_wall, before) -> dict:
    """The report's account of the run: its size, settings, tuning and invocations
    (``OUT/invocations.json``, this invocation appended)."""
    tuning_s = None if tuning_wall is None else round(tuning_wall, 1)
    command = "python -m experiments.sensitivity " + " ".join(argv)
    history_path = args.out / "invocations.json"
    history = json.loads(history_path.read_text()) if history_path.exists() else []
    history.append(
        {
            "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(time.time() - wall)),
            "wall_s": round(wall, 1),
            "runs_computed": len(_finished_files(args.out) - before),
            "runs_on_disk_before": len(before),
            "tuning_s": tuning_s,
            "load_average_start": load_start,
            "load_average_end": output.load_average(),
            "command": command,
        }
    )
    output.write_json(history_path, history)
    return {
        "draws": args.draws,
        "dt_draws": args.dt_draws,
        "horizon_s": args.horizon,
        "seed": args.seed,
        "workers": args.workers,
        "rotor_speed_limit": rotor_speed_limit(),
        "thrust_to_weight": THRUST_TO_WEIGHT,
        "sigma_factor": SIGMA_FACTOR,
        "tuning": {
            "source": str(args.tuned_gains) if args.tuned_gains else "fair_comparison here",
            "steps": args.tune_steps,
            "draws": args.tune_draws,
            "horizon_s": args.tune_horizon,
            "wall_s": tuning_s,
        },
        "programs": len(plan.jobs),
        "runs": len(plan.runs),
        "wall_s": round(wall, 1),
        "load_average_start": load_start,
        "load_average_end": output.load_average(),
        "cpus": os.cpu_count(),
        "command": command,
        "invocations": history,
    }


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    _common.enable_float64(args.lane == "f64")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    plan = make_plan(
        args.selected, args.horizon, args.draws, args.dt_draws, args.seed, args.controllers
    )
    lanes = assign_lanes(plan, args.workers)
    tuned_path = args.tuned_gains or (out / "tuning" / "results.json")
    if args.lane is not None:
        run_lane(plan, lanes.get(args.lane, []), out, tuned_path, not args.quiet, args.lane)
        return 0

    start = time.perf_counter()
    load_start = output.load_average()
    before = _finished_files(out)
    log = _logger(not args.quiet)
    log(
        f"{len(plan.settings)} settings, {len(plan.jobs)} programs, {len(plan.runs)} runs; "
        f"lanes {', '.join(f'{k}: {len(v)} programs' for k, v in lanes.items())}"
    )
    tuning, tuning_wall = None, None
    if args.tuned_gains is None and tuned_path.exists():
        # the fair comparison's results.json holds its code (experiments._common.code):
        if json.loads(tuned_path.read_text()).get("code") != _common.code():
            tuned_path.unlink()  # tuned by other code: tuned again
    if any(s.gains == "tuned" for s in plan.settings) and not tuned_path.exists():
        tuning, tuning_start = _start_tuning(args, tuned_path.parent, log), time.perf_counter()
    command = [sys.executable, "-m", "experiments.sensitivity", *argv, "--lane"]
    processes = {lane: subprocess.Popen([*command, lane]) for lane in lanes}
    try:
        if tuning is not None:
            tuning_wall = _wait_for_tuning(tuning, tuned_path, tuning_start, log)
        failed = [lane for lane, process in processes.items() if process.wait() != 0]
    except KeyboardInterrupt:
        for process in filter(None, [*processes.values(), tuning]):
            process.terminate()
        print(
            f"\ninterrupted: finished runs are kept under {out}/runs; run the same command "
            "again to continue",
            file=sys.stderr,
        )
        return 130
    if failed:
        log(f"lanes {failed} failed; the settings they left unfinished are marked missing")
    tuned = load_tuned(tuned_path) if tuned_path.exists() else None
    results = load_results(plan, out, tuned)
    evaluated = evaluate(plan, results)
    wall = time.perf_counter() - start
    meta = _meta(args, argv, plan, wall, load_start, tuning_wall, before)
    doc = None if args.no_doc else args.doc
    report = sensitivity_report.write(out, plan, evaluated, meta, doc, results)
    log(f"wrote {report} in {wall:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
