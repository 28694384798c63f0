"""``fojax tune``: gradient-based gain tuning through the batched simulator.

    fojax tune --scenario {1,2,3} --controller NAME [--draws N] [--steps K]
               [--horizon T] [--init paper|naive|FILE] [--objective mean|cvar]
               [--resume] --out DIR      (fojax tune --help lists every option)

Each step draws a fresh minibatch of ``N`` Monte Carlo draws of the scenario (seed
``--seed``), simulates ``T`` seconds (default 10 s, a tuning horizon; the scenario's
own horizon is 80 s or 50 s) with the controller's switching smoothed to ``tanh``
(annealed towards the evaluation boundary layer), and takes one clipped Adam step on
the gradient of the mean (or CVaR) cost. Writes to ``DIR``:

* ``gains.json``: the tuned gains, the format ``fojax simulate --gains`` reads: the
  best of the start and the validated steps on ``--validation-draws`` validation draws
  (disjoint from the tuning and the held-out draws), with ``--eval-switching``; its
  metadata name the step they come from (``selected_step``, 0: the start) and the
  validation costs, so a run never returns gains worse than its start on them;
* ``history.csv``: one row per step (objective, gradient norm, learning rate,
  boundary-layer scale, diverged draws, simulated draw-steps, wall time, validation
  cost where validated, best step so far);
* ``checkpoint.npz``: the state every ``--checkpoint-every`` steps. After an
  interruption, the same command with ``--resume`` continues and gives the result the
  uninterrupted run would have given;
* ``evaluation.json``: the cost of the initial and the tuned gains on
  ``--eval-draws`` held-out draws (never used in tuning), with ``--eval-switching``;
* ``convergence.png`` (and ``.pdf``): the objective, the held-out costs and the
  gradient norm against step and against wall time, drawn from ``history.csv``;
* ``run.json``: what the run needs to be redone exactly: the initial gains' values and
  their source, and per session (a first run, then each ``--resume``) the command
  line, versions, backend and device counts (:func:`fojax.cli.study.provenance`);
  ``gains.json`` carries the same in its metadata.

Every input is checked before anything is compiled or written; an existing
checkpoint is never overwritten. An option that would change nothing is an error
naming what it applies to: ``--learning-rate``, ``--clip-norm`` and ``--anneal-start``
with L-BFGS, ``--max-step`` with Adam, ``--cvar-fraction`` with ``--objective mean``,
``--validate-every`` without validation draws, ``--eval-horizon`` without held-out
draws, ``--fractional`` for a controller without fractional operators,
``--eval-switching`` for one without a switching function (the FL), ``--anneal-*``
for one without a boundary layer. The results are written before the figure; a
figure that cannot be drawn is a warning.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from fojax.cli import _tuning, arguments, figures, style
from fojax.cli import requirements as requirements_cli
from fojax.cli import study as study_layer

__all__ = ["build_parser", "main", "parse_args"]

_TERMS = ("position", "attitude", "effort", "chattering")
"""The weighted-sum cost's terms (``--<term>-weight``; ``mean_terms`` in ``evaluation.json``)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fojax tune",
        description="Tune a controller's gains by gradient over Monte Carlo draws of a scenario.",
    )
    arguments.add_options(parser, *_problem_options(), *_tuner_options(), *_run_options())
    requirements_cli.add_tune_options(parser)  # --requirements, --rotor-limit, ...
    arguments.add_runtime_options(parser)
    return parser


# fmt: off
def _problem_options() -> tuple:
    """What is tuned, on which draws, to which cost."""
    from fojax import scenarios
    from fojax.controllers import registry
    from fojax.optimize import cost, params

    defaults, count, real = cost.CostConfig(), arguments.positive_int, arguments.positive_float
    weights = (
        (f"--{name}-weight", dict(type=arguments.nonnegative_float, default=value,
                                  help=f"({value:g})"))
        for name in _TERMS
        for value in [getattr(defaults, f"{name}_weight")]
    )
    return (
        ("--scenario", dict(type=int, required=True, choices=scenarios.SCENARIO_IDS)),
        ("--controller", dict(required=True,
                              help=f"one of {', '.join(registry.controller_names())}")),
        ("--draws", dict(type=count, default=16,
                         help="draws per step (16: with --method lbfgs one fixed sample)")),
        ("--steps", dict(type=count, default=6, help="optimisation steps (6)")),
        ("--horizon", dict(type=real, default=10.0, help="tuning horizon, s (10)")),
        ("--dt", arguments.STEP),
        ("--init", dict(default="paper", metavar="paper|naive|FILE",
                        help="initial gains: the controller's defaults (paper), a knowledge-free "
                        "guess (naive: positive gains 1, p/q = 1.5, orders 0.5), or a gains file "
                        "(paper)")),
        ("--objective", dict(choices=cost.OBJECTIVES, default=defaults.objective)),
        ("--cvar-fraction", dict(type=real, help="worst fraction of draws averaged by "
                                 f"--objective cvar ({defaults.cvar_fraction}; an error with "
                                 "--objective mean)")),
        ("--error", dict(choices=cost.ERRORS, default=defaults.error)),
        *weights,
        ("--seed", dict(type=arguments.seed, default=0, help="draws' seed (0)")),
        ("--fields", dict(default="default", help="comma-separated gain fields to tune; "
                          "'default': every bounded field except the constant and smoothing "
                          "ones (mu, boundary_layer); 'all': every field")),
        ("--share", dict(choices=tuple(params.SHARING), default="paper")),
    )


def _tuner_options() -> tuple:
    """The optimiser: its method and step, annealing, checkpoints and validation."""
    from fojax.optimize.tuner import TunerConfig

    tuner, real = TunerConfig(), arguments.positive_float
    return (
        ("--method", dict(choices=("adam", "lbfgs"), default=tuner.method,
                          help="adam: fresh minibatches each step; lbfgs: quasi-Newton on one "
                          f"fixed sample of --draws draws ({tuner.method})")),
        ("--learning-rate", dict(type=real, help=f"Adam's step ({tuner.learning_rate}; "
                                 "--method adam only)")),
        ("--max-step", dict(type=real, help="L-BFGS's largest change of a parameter per step "
                            f"({tuner.max_step}; --method lbfgs only)")),
        ("--clip-norm", dict(type=real, help=f"Adam's gradient-norm clip ({tuner.clip_norm}; "
                             "--method adam only)")),
        ("--anneal-start", dict(type=real, help="boundary-layer scale of the first step "
                                f"({tuner.anneal_start}; --method adam only, L-BFGS keeps "
                                "--anneal-end; controllers with a boundary layer only)")),
        ("--anneal-end", dict(type=real, help="boundary-layer scale of the last step "
                              f"({tuner.anneal_end}; controllers with a boundary layer only)")),
        ("--checkpoint-every", dict(type=arguments.positive_int,
                                    default=tuner.checkpoint_every)),
        ("--validation-draws", dict(type=arguments.nonnegative_int,
                                    default=tuner.validation_draws,
                                    help="validation draws scoring the start and every "
                                    "--validate-every steps; the best validated gains are "
                                    f"returned ({tuner.validation_draws}; 0: no validation, "
                                    "the last step's gains are returned)")),
        ("--validate-every", dict(type=arguments.positive_int, help="steps between validations "
                                  f"({tuner.validate_every}; the last step is always "
                                  "validated; an error with --validation-draws 0)")),
    )


def _run_options() -> tuple:
    """How the run computes (operators, dtype, compilation, devices), its held-out
    evaluation and its output folder."""
    from fojax import fractional
    from fojax.controllers import SWITCHING_FUNCTIONS

    return (
        ("--fractional", dict(choices=fractional.METHODS, help="fractional operator method "
                              "(soe; controllers with fractional operators only: afonftsmc, "
                              "fobsmc)")),
        ("--dtype", dict(choices=("float32", "float64"), default="float32")),
        ("--compile", dict(choices=("optimized", "fast"), default="optimized",
                           help="fast: compile the gradient without LLVM's optimisation passes "
                           "(about 3x faster to compile, about 2x slower per step: for short "
                           "runs); optimized (default)")),
        ("--eval-draws", dict(type=arguments.nonnegative_int, default=32,
                              help="held-out draws (32; 0: none)")),
        ("--eval-horizon", dict(type=arguments.positive_float, help="s (default: the tuning "
                                "horizon; an error with --eval-draws 0)")),
        ("--eval-switching", dict(choices=SWITCHING_FUNCTIONS, help="switching function of "
                                  "the validation and held-out runs (sat; controllers with a "
                                  "switching function only: all but fl)")),
        ("--resume", dict(action="store_true", help="continue the run in DIR")),
        ("--quiet", dict(action="store_true", help="no progress display")),
        ("--out", arguments.OUTPUT_FOLDER),
        ("--device-batch", dict(type=arguments.positive_int, metavar="N",
                                help="draws of a minibatch each device differentiates in one "
                                "call (default: the whole minibatch). The steps depend on it "
                                "(rounding), not on the devices or processes: over P devices, "
                                "--device-batch DRAWS/P splits each minibatch")),
    )
# fmt: on


def _options_that_do_not_apply(args) -> str | None:
    """What is wrong when an option given on the command line would change nothing:
    one of the other method, the other objective, validation or held-out draws that
    are not run, or an option the controller's law does not take (None: all apply)."""
    from fojax.controllers import registry

    method = f"--method {args.method}"
    given = {
        "--learning-rate": args.learning_rate,
        "--clip-norm": args.clip_norm,
        "--anneal-start": args.anneal_start,
    }
    for flag, value in given.items():
        if value is not None and args.method != "adam":
            also = " (L-BFGS keeps the boundary-layer scale at --anneal-end)"
            return (
                f"{flag} applies to --method adam only, not to {method}"
                f"{also if flag == '--anneal-start' else ''}; leave it out or add --method adam"
            )
    if args.max_step is not None and args.method != "lbfgs":
        return (
            f"--max-step applies to --method lbfgs only, not to {method} (Adam's step is "
            "--learning-rate); leave it out"
        )
    if args.cvar_fraction is not None and args.objective != "cvar":
        return (
            f"--cvar-fraction applies to --objective cvar only, not to --objective "
            f"{args.objective}; leave it out or add --objective cvar"
        )
    if args.validate_every is not None and args.validation_draws == 0:
        return "--validate-every applies with validation draws only (--validation-draws is 0)"
    if args.eval_horizon is not None and args.eval_draws == 0:
        return "--eval-horizon applies with held-out draws only (--eval-draws is 0)"
    try:
        _tuning.check_law_options(args)
    except ValueError as error:
        return str(error)
    cls = registry.get_controller_class(args.controller)
    if not cls.GAINS.with_role("smoothing"):
        for flag in ("--anneal-start", "--anneal-end"):
            if getattr(args, flag[2:].replace("-", "_")) is not None:
                return (
                    f"{flag} does not apply to {args.controller}, which has no boundary layer "
                    "(no gain of role 'smoothing') to anneal; leave it out"
                )
    return None


def _defaults(args) -> None:
    """The defaults of the options left out (None in ``args`` until checked)."""
    from fojax.optimize import cost, tuner

    defaults, config = cost.CostConfig(), tuner.TunerConfig()
    for name, value in (
        ("cvar_fraction", defaults.cvar_fraction),
        ("learning_rate", config.learning_rate),
        ("max_step", config.max_step),
        ("clip_norm", config.clip_norm),
        ("anneal_start", config.anneal_start),
        ("anneal_end", config.anneal_end),
        ("validate_every", config.validate_every),
        ("fractional", "soe"),
        ("eval_switching", config.validation_switching),
    ):
        if getattr(args, name) is None:
            setattr(args, name, value)


def parse_args(argv):
    """Parse and validate; returns ``(PreparedRun, args)``. Raises ``SystemExit`` with
    a message on bad input, before anything is compiled or written."""
    from fojax.controllers import registry
    from fojax.optimize import params, tuner

    parser = build_parser()
    args = parser.parse_args(argv)
    try:  # a registered name, 'package.module:Class' or an entry point
        args.controller = registry.get_controller_class(args.controller).name
    except (TypeError, ValueError) as error:
        parser.error(str(error))
    requirements_cli.check_tune_options(parser, args, argv)  # the other tuner's options
    if args.requirements is not None:
        return requirements_cli.prepare_tune(parser, args), args
    problem_text = _options_that_do_not_apply(args)
    if problem_text:
        parser.error(problem_text)
    _defaults(args)
    dtype, fields = _tuning.dtype_and_fields(args)
    try:
        spec, config = _problem_and_tuner(args, fields)
        params.make_parameter_map(args.controller, fields, args.share)
    except ValueError as error:
        parser.error(str(error))
    gains, label = _tuning.initial_gains(parser, args, dtype)
    try:
        run = tuner.prepare(spec, config, gains, label, args.out, resume=args.resume)
    except ValueError as error:
        parser.error(str(error))
    return run, args


def _problem_and_tuner(args, fields):
    """``(ProblemSpec, TunerConfig)`` of the options; ``ValueError`` on a bad setting."""
    from fojax.optimize import cost, tuner

    def take(*names) -> dict:
        return {name: getattr(args, name) for name in names}

    weights = (f"{term}_weight" for term in _TERMS)
    cost_config = cost.CostConfig(**take("error", *weights, "objective", "cvar_fraction"))
    spec = _tuning.problem_spec(args, fields, cost=cost_config)
    config = tuner.TunerConfig(
        **take("steps", "method", "learning_rate", "max_step", "clip_norm", "anneal_start"),
        **take("anneal_end", "checkpoint_every", "validation_draws", "validate_every"),
        validation_switching=args.eval_switching,
    )
    if args.eval_horizon is not None:
        steps = args.eval_horizon / args.dt
        if abs(steps - round(steps)) > 1e-6 * steps:
            raise ValueError(
                f"--eval-horizon ({args.eval_horizon} s) must be a whole number of steps "
                f"of {args.dt} s"
            )
    return spec, config


def _evaluate(run, result, args) -> dict:
    """The held-out cost of the initial and the tuned gains (``evaluation.json``)."""
    import numpy as np

    from fojax.optimize import problem as problem_lib

    horizon = args.eval_horizon or run.spec.horizon
    keys = result.problem.heldout_keys(args.eval_draws)

    def score(gains) -> dict:
        costs = problem_lib.evaluate(
            run.spec, gains, keys, horizon=horizon, switching=args.eval_switching
        )
        terms = np.mean(costs.terms, 0).tolist()
        return {
            "mean_cost": float(np.mean(costs.cost)),
            "std_cost": float(np.std(costs.cost, ddof=1)) if args.eval_draws > 1 else None,
            "mean_terms": dict(zip(_TERMS, terms, strict=True)),
            "diverged": int(np.sum(costs.diverged)),
        }

    gains = {"initial": run.init_gains, "tuned": result.gains}
    before = {"tuned_gains_from_step": result.best_step}
    return _tuning.heldout_evaluation(
        args.eval_draws, horizon, args.eval_switching, score, gains, before
    )


def _record_session(run, command: list[str], device_batch: int | None = None) -> dict:
    """``run.json``: the initial gains and one provenance entry per session."""
    path = run.out / "run.json"
    record = {}
    if run.resume and path.is_file():
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            record = {}
    record.update(
        {
            "controller": run.spec.controller,
            "init": run.init_label,
            "init_gains": _tuning.init_record(run.init_gains, run.init_label),
            "problem": run.fingerprint["problem"],
            "tuner": run.fingerprint["tuner"],
        }
    )
    session = study_layer.provenance(command)
    session["device_batch"] = device_batch or run.spec.draws  # draws per device and call
    record["sessions"] = list(record.get("sessions", [])) + [session]
    run.out.mkdir(parents=True, exist_ok=True)
    study_layer.write_json(path, record)
    return record


def _finished_before(run) -> bool:
    """Whether this is a ``--resume`` of a run whose steps were all done."""
    meta = run.checkpoint_meta or {}
    return bool(run.resume) and int(meta.get("step", -1)) >= run.config.steps


def _save_tuned_gains(run, record: dict, earlier: str | None) -> None:
    """Add the run's record to ``gains.json``'s metadata (fojax simulate reads it); a
    finished run resumed keeps its file as it was (``earlier``)."""
    path = run.out / "gains.json"
    if not path.is_file():
        return
    if earlier is not None:
        text = earlier
    else:
        document = json.loads(path.read_text())
        document.setdefault("metadata", {}).update(
            init_gains=record["init_gains"], provenance=record["sessions"][-1]
        )
        text = json.dumps(document, indent=2) + "\n"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def _tuning_problem(run, device_batch=None):
    """The problem with its draws over every device of every process: per-draw
    gradients computed where the draws are, gathered, reduced the same way on each
    process (:class:`fojax.optimize.problem.TuningProblem`'s ``mesh``), so that a run over
    several processes takes the steps a one-process run takes."""
    import jax

    from fojax import sharding
    from fojax.optimize import problem

    mesh = sharding.draw_mesh(jax.devices())
    return problem.TuningProblem(run.spec, run.init_gains, mesh=mesh, device_batch=device_batch)


def _private_copy(run):
    """For processes other than 0: the run writing into a private temporary folder
    (process 0 writes the outputs), holding a copy of the checkpoint to resume from."""
    import shutil
    import tempfile

    from fojax.optimize import tuner

    folder = Path(tempfile.mkdtemp(prefix="fojax-tune-"))
    checkpoint = run.out / tuner.CHECKPOINT
    if run.resume and checkpoint.is_file():
        shutil.copy2(checkpoint, folder / tuner.CHECKPOINT)
    import dataclasses

    return dataclasses.replace(run, out=folder)


def main(argv=None) -> int:
    from fojax.optimize import tuner

    argv = list(sys.argv[1:] if argv is None else argv)
    runtime = arguments.setup_runtime(argv, "fojax tune")
    run, args = parse_args(argv)
    if args.requirements is not None:
        return requirements_cli.tune_main(run, args, runtime, argv)
    lead = runtime["process_index"] == 0
    if not lead:
        run = _private_copy(run)
    record = _record_session(run, ["fojax", "tune", *argv], args.device_batch) if lead else None
    gains_file = run.out / "gains.json"
    earlier = gains_file.read_text() if _finished_before(run) and gains_file.is_file() else None
    start = time.perf_counter()
    try:
        result = tuner.tune(
            run, progress=not args.quiet and lead, problem=_tuning_problem(run, args.device_batch)
        )
    except KeyboardInterrupt:
        return 130
    if not lead:
        import shutil

        shutil.rmtree(run.out, ignore_errors=True)
        return 0
    _print_result(run, result, runtime, time.perf_counter() - start)
    _save_tuned_gains(run, record, earlier)
    files = ["gains.json", "history.csv", "run.json"]
    evaluation = None
    if args.eval_draws > 0:
        evaluation = _evaluate(run, result, args)
        evaluation["provenance"] = record["sessions"][-1]
        study_layer.write_json(args.out / "evaluation.json", evaluation)
        files.append("evaluation.json")
        print(
            f"held-out cost ({evaluation['draws']} draws, {evaluation['horizon_s']:g} s, "
            f"{evaluation['switching']}): initial {evaluation['initial']['mean_cost']:.5g}, "
            f"tuned {evaluation['tuned']['mean_cost']:.5g}"
        )
    if _draw_convergence(run, result, args, evaluation) is not None:
        files.append("convergence.png (+ .pdf)")
    print(f"wrote {args.out}/: {', '.join(files)}")
    return 0


def _print_result(run, result, runtime: dict, wall: float) -> None:
    """The run's steps and final objective, and which gains it returned."""
    print(
        f"tuned {run.spec.controller} on scenario {run.spec.scenario}: {result.completed} "
        f"steps x {run.spec.draws} draws x {run.spec.horizon:g} s, final objective "
        f"{result.history[-1]['objective']:.5g} ({wall:.0f} s)"
    )
    if runtime["process_count"] > 1:
        print(f"over {runtime['process_count']} processes, {runtime['device_count']} devices")
    if result.validation is not None:
        v = result.validation
        chosen = (
            "the start's (no step validated better)"
            if v["best_step"] == 0
            else (f"step {v['best_step']}'s")
        )
        print(
            f"returned {chosen} gains: validation cost {v['best']:.5g} against "
            f"{v['initial']:.5g} at the start and {v['final']:.5g} at the last step "
            f"({v['draws']} validation draws, {v['switching']}, {v['horizon_s']:g} s)"
        )


def _draw_convergence(run, result, args, evaluation: dict | None):
    """``convergence.png`` (and ``.pdf``); None (a warning) when it cannot be drawn."""
    return style.attempt(
        "convergence.png",
        figures.plot_convergence,
        args.out / "history.csv",
        args.out / "convergence.png",
        evaluation,
        run.config.clip_norm if run.config.method == "adam" else None,
        f"fojax tune: {run.spec.controller}, scenario {run.spec.scenario}, "
        f"{run.spec.draws} draws x {run.spec.horizon:g} s per step, {args.objective} objective",
        None if result.validation is None else result.validation["initial"],
    )


if __name__ == "__main__":
    sys.exit(main())
