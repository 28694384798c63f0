"""``--requirements FILE`` and ``--rotor-limit T`` of ``fojax simulate`` and ``fojax tune``
(docs/requirements.md, "Commands").

``fojax simulate --requirements FILE`` measures, after the Monte Carlo runs, every metric
of :data:`fojax.requirements.METRICS` on the same draws (the study's seed, controllers,
gains and actuators; :func:`fojax.requirements.measure`) and reports per controller the
yield (draws meeting every requirement) with its 95 % Clopper-Pearson interval, the
failures per requirement and the one failing most often: printed, in ``summary.json``
(``summary["requirements"]``: the set, once; ``summary["controllers"][NAME]
["requirements"]``: :meth:`fojax.requirements.YieldResult.to_dict`), the per-draw metrics
in ``requirements.npz`` and the figure ``requirements.png``.

``fojax tune --requirements FILE`` tunes to the requirements
(:func:`fojax.optimize.constrained.tune_to_requirements`: an augmented Lagrangian on the
mean hinge violation, Adam; ``--method cma-es``: the derivative-free baseline,
:func:`fojax.optimize.constrained.cma_es_requirements`), writes ``gains.json`` (what
``fojax simulate --gains`` reads), ``history.csv``, ``evaluation.json`` (the held-out
yield of the initial and the tuned gains on ``--eval-draws`` draws, with intervals) and
``run.json``.

Actuators are rotor-limited (squared rotor speeds clipped to ``[0, w_max^2]``) when the
file's ``[settings]`` ask for it, or with ``--rotor-limit T`` (thrust-to-weight ratio at
``w_max``; it replaces the file's limit). A file that cannot be used is an error (exit
status 2) before anything compiles, as is an option that applies to the other tuner.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

from fojax.cli import arguments
from fojax.cli._requirement_tuning import PreparedRequirementRun, prepare_tune, tune_main

__all__ = [
    "PreparedRequirementRun",
    "add_simulate_options",
    "add_tune_options",
    "check_tune_options",
    "configure_study",
    "prepare_tune",
    "report_simulate",
    "requirements_file",
    "thrust_to_weight",
    "tune_main",
]

# Defaults of ``fojax tune --requirements`` (docs/requirements.md: the AFONFTSMC from the
# paper's gains to the example set, 8 tuning draws, 10 outer x 10 inner Adam steps at
# learning rate 0.1, mean hinge, 32 validation draws).
TUNE_DEFAULTS = {
    "draws": 8,
    "outer_steps": 10,
    "inner_steps": 10,
    "learning_rate": 0.1,
    "margin": 0.05,
    "formulation": "mean",
    "eval_draws": 128,
    "objective": "effort",
    "generations": 24,
}
REQUIREMENT_OBJECTIVES = ("effort", "tracking")

# Options of the weighted-sum tuner (optimize/tuner.py) that do nothing with
# --requirements, and the other way round (dest -> why).
_WEIGHTED_ONLY = {
    "cvar_fraction": "the weighted-sum objective's CVaR",
    "error": "the weighted-sum cost's error measure",
    "position_weight": "a weight of the weighted-sum cost",
    "attitude_weight": "a weight of the weighted-sum cost",
    "effort_weight": "a weight of the weighted-sum cost",
    "chattering_weight": "a weight of the weighted-sum cost",
    "steps": "the weighted-sum tuner's step count (with --requirements: --outer-steps, "
    "--inner-steps)",
    "max_step": "the weighted-sum L-BFGS's step limit",
    "anneal_start": "the weighted-sum tuner's boundary-layer annealing",
    "anneal_end": "the weighted-sum tuner's boundary-layer annealing",
    "checkpoint_every": "the weighted-sum tuner's checkpoints",
    "validate_every": "the weighted-sum tuner's validation interval (with --requirements "
    "every outer step is validated)",
    "device_batch": "the weighted-sum tuner's sharded minibatch",
    "eval_horizon": "the weighted-sum tuner's held-out horizon (with --requirements the "
    "held-out draws run the tuning horizon, which the bounds refer to)",
}
_REQUIREMENTS_ONLY = ("rotor_limit", "outer_steps", "inner_steps", "margin", "formulation")
_GRADIENT_ONLY = (
    "outer_steps",
    "inner_steps",
    "formulation",
    "learning_rate",
    "clip_norm",
    "resume",
)


# ------------------------------------------------------------------ argument types


def requirements_file(text: str):
    """argparse type: a requirement file (TOML or JSON), loaded and checked
    (:func:`fojax.requirements.load`); every problem in one message."""
    from fojax import requirements as rq

    try:
        path = arguments.check_input_file(text, "requirement file")
        return rq.load(path)
    except ValueError as error:  # RequirementError is a ValueError
        raise argparse.ArgumentTypeError(str(error)) from None


def thrust_to_weight(text: str) -> float:
    """argparse type: a thrust-to-weight ratio > 1 (a vehicle that can hover)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value <= 1:
        raise argparse.ArgumentTypeError(
            f"expected the thrust-to-weight ratio at full rotor speed, a number > 1 (2 is a "
            f"typical minimum; 1 or less cannot hover), got {text!r}"
        )
    return value


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--requirements",
        type=requirements_file,
        metavar="FILE",
        help="requirement file (TOML or JSON, docs/requirements.md; e.g. "
        "examples/requirements/small_quadrotor.toml); checked before anything compiles",
    )
    parser.add_argument(
        "--rotor-limit",
        type=thrust_to_weight,
        metavar="T",
        help="rotor-limited actuators: squared rotor speeds clipped to [0, w_max^2], "
        "w_max giving T times the weight (e.g. 2); replaces the requirement file's limit",
    )


def resolve_requirements(args):
    """``(requirement set or None, w_max or None)``: the file's set with ``--rotor-limit``
    applied, and the rotor speed limit the simulation uses (None: ideal actuators)."""
    from fojax import requirements as rq

    reqs = args.requirements
    if args.rotor_limit is not None:
        if reqs is not None:
            settings = dataclasses.replace(
                reqs.settings,
                thrust_to_weight=args.rotor_limit,
                rotor_speed_limit=None,
                rotor_limited=True,
            )
            reqs = dataclasses.replace(reqs, settings=settings)
        return reqs, rq.rotor_speed_limit(args.rotor_limit)
    if reqs is not None:
        return reqs, reqs.settings.simulation_limit()
    return None, None


def actuators_record(limit: float | None, args) -> dict:
    from fojax import requirements as rq

    if limit is None:
        return {"rotor_limited": False}
    ratio = args.rotor_limit
    source = "--rotor-limit"
    if ratio is None:
        source = "the requirement file's settings"
        settings = args.requirements.settings
        ratio = settings.thrust_to_weight
    out = {"rotor_limited": True, "rotor_speed_limit_rad_s": limit, "source": source}
    if ratio is not None:
        out["thrust_to_weight"] = ratio
    else:
        w_max_ratio = (limit / rq.rotor_speed_limit(1.0)) ** 2
        out["thrust_to_weight"] = w_max_ratio
    return out


# ------------------------------------------------------------------------ simulate


def add_simulate_options(parser: argparse.ArgumentParser) -> None:
    """``--requirements FILE`` and ``--rotor-limit T`` of ``fojax simulate``."""
    _add_common(parser)


def configure_study(parser, args, study):
    """The study on the actuators asked for (rotor-limited by ``--rotor-limit`` or the
    requirement file); keeps the resolved set in ``args.requirement_set``."""
    reqs, limit = resolve_requirements(args)
    args.requirement_set, args.rotor_speed_limit = reqs, limit
    if limit is None:
        return study
    return dataclasses.replace(study, rotor_speed_limit=limit)


def measure_study(study, reqs) -> dict:
    """Per controller of ``study``: ``(metrics, status)`` of every requirement metric on
    the study's draws (same keys, controllers, gains and actuators)."""
    import numpy as np

    from fojax import requirements as rq
    from fojax import scenarios
    from fojax.cli import study as study_layer

    _, scenario, config, dtype, runs = study_layer.prepare_runs(study)
    keys = np.asarray(scenarios.draw_keys(study.seed, np.arange(study.draws)))
    out = {}
    for name, (controller, gains) in runs.items():
        out[name] = rq.measure(controller, gains, scenario, reqs, keys, config, dtype=dtype)
    return out


def report_simulate(study, args, out: Path, summary: dict, figures: bool = True) -> dict:
    """After ``write_outputs``: the actuators in ``summary.json`` and, with
    ``--requirements``, the yield per controller (printed, in ``summary.json``,
    ``requirements.npz``, ``requirements.png``). Returns the updated summary."""
    from fojax.cli import style
    from fojax.cli.figures import plot_yield
    from fojax.cli.output import write_json, write_npz

    reqs = getattr(args, "requirement_set", None)
    limit = getattr(args, "rotor_speed_limit", None)
    if reqs is None and limit is None:
        return summary
    out = Path(out)
    summary["actuators"] = actuators_record(limit, args)
    if limit is not None:
        print(
            f"rotor-limited actuators: w_max {limit:.4g} rad/s (thrust-to-weight "
            f"{summary['actuators']['thrust_to_weight']:.3g}, {summary['actuators']['source']})"
        )
    if reqs is None:
        write_json(out / "summary.json", summary)
        return summary
    start = time.perf_counter()
    results, arrays = _yields(measure_study(study, reqs), reqs, summary)
    summary["requirements"] = {
        **reqs.to_dict(),
        "names": list(reqs.names),
        "bounds": {r.name: r.describe() for r in reqs},
        "per_draw": "requirements.npz: <controller>.<metric> (canonical units, NaN for "
        "diverged draws), <controller>.status, <controller>.passed",
        "measured_on": "the study's draws (same seed, gains, actuators); diverged draws "
        "fail every requirement",
        "interval": "Clopper-Pearson, 95 %",
        "wall_time_s": round(time.perf_counter() - start, 2),
    }
    write_npz(out / "requirements.npz", arrays)
    files = summary.setdefault("files", [])
    if "requirements.npz" not in files:
        files.append("requirements.npz")
    write_json(out / "summary.json", summary)
    _print_yields(reqs, results)
    if figures:
        drawn = style.attempt(
            "requirements.png",
            plot_yield,
            results,
            out / "requirements.png",
            f"Requirements: scenario {study.scenario_id}, {study.draws} draws x "
            f"{study.horizon:g} s"
            + (f", rotor-limited (w_max {limit:.3g} rad/s)" if limit else ", ideal actuators"),
        )
        if drawn is not None:
            summary.setdefault("figures", []).append(drawn.name)
            write_json(out / "summary.json", summary)
    return summary


def _yields(measured: dict, reqs, summary: dict) -> tuple[dict, dict]:
    """``({name: YieldResult}, per-draw arrays)`` of the measured metrics; each result in
    ``summary["controllers"][name]["requirements"]``."""
    import numpy as np

    from fojax import requirements as rq

    results, arrays = {}, {}
    for name, (metrics, status) in measured.items():
        valid = (status & rq.DIVERGED) == 0
        result = rq.evaluate(reqs, metrics, valid=valid)
        results[name] = result
        entry = result.to_dict()
        entry["diverged"] = int(np.sum(~valid))
        summary["controllers"].setdefault(name, {})["requirements"] = entry
        for metric, values in metrics.items():
            arrays[f"{name}.{metric}"] = values
        arrays[f"{name}.status"] = status
        arrays[f"{name}.passed"] = np.all(result.matrix, axis=0)
    return results, arrays


def _print_yields(reqs, results: dict) -> None:
    print(f"requirements ({len(reqs)}: {', '.join(reqs.names)}):")
    width = max(len(n) for n in results)
    for name, result in results.items():
        print(f"  {name:<{width}} {result.describe()}")
        failing = [(n, f) for n, f in zip(result.names, result.failures, strict=True) if f]
        if failing:
            print(
                f"  {'':<{width}} failures: "
                + ", ".join(f"{n} {f}/{result.draws}" for n, f in failing)
            )


# ---------------------------------------------------------------------------- tune


def add_tune_options(parser: argparse.ArgumentParser) -> None:
    """``fojax tune``'s options of the requirement tuner; ``--objective`` and
    ``--method`` take its choices too (checked by :func:`check_tune_options`)."""
    from fojax.optimize import cost

    _add_common(parser)
    group = parser.add_argument_group(
        "tuning to requirements (--requirements FILE; docs/requirements.md)"
    )
    d, count = TUNE_DEFAULTS, arguments.positive_int
    arguments.add_options(
        group,
        ("--outer-steps", dict(type=count, help="augmented-Lagrangian multiplier updates, each "
                               f"validated ({d['outer_steps']})")),
        ("--inner-steps", dict(type=count, help="optimiser steps per outer step "
                               f"({d['inner_steps']})")),
        ("--formulation", dict(choices=("mean", "chance"), help="constraint per requirement: "
                               "mean (the mean hinge violation over the draws, every draw must "
                               "meet it; default) or chance (a smooth share of draws violating, "
                               "at most 5 %%)")),
        ("--margin", dict(type=arguments.nonnegative_float, help="a draw must beat each bound by "
                          f"this share of its scale ({d['margin']})")),
        ("--generations", dict(type=count, help="CMA-ES generations (--method cma-es only; "
                               f"{d['generations']})")),
    )  # fmt: skip
    for action in parser._actions:
        if action.dest == "objective":
            action.choices = tuple(cost.OBJECTIVES) + REQUIREMENT_OBJECTIVES
            action.default = None
            action.help = (
                f"{', '.join(cost.OBJECTIVES)}: of the weighted-sum cost "
                f"({cost.CostConfig().objective}); "
                f"with --requirements, what is minimised subject to them: effort (the "
                f"commanded accelerations squared; default) or tracking (P + A)"
            )
        elif action.dest == "method":
            action.choices = tuple(action.choices) + ("cma-es",)
            action.default = None
            action.help = (
                f"{action.help}; with --requirements: adam (default) or lbfgs for the "
                "augmented Lagrangian, or cma-es (the derivative-free baseline)"
            )


def _given(parser: argparse.ArgumentParser, argv) -> set[str]:
    """The ``dest`` of every option given on the command line (abbreviations and
    ``--flag=value`` included): ``argv`` parsed again with every default suppressed."""
    saved = [(action, action.default) for action in parser._actions]
    try:
        for action, _ in saved:
            action.default = argparse.SUPPRESS
        namespace, _ = parser.parse_known_args(argv)
    finally:
        for action, default in saved:
            action.default = default
    return set(vars(namespace))


def _flag(parser, dest: str) -> str:
    for action in parser._actions:
        if action.dest == dest and action.option_strings:
            return action.option_strings[0]
    return dest


def check_tune_options(parser, args, argv) -> None:
    """Errors (exit 2, one line naming the option) for an option of the other tuner;
    fills the defaults of the options left out (None until here)."""
    from fojax.optimize import cost, tuner

    given = _given(parser, argv)
    args.given = given
    if args.requirements is None:
        for dest in _REQUIREMENTS_ONLY + ("generations",):
            if dest in given:
                parser.error(
                    f"{_flag(parser, dest)} applies with --requirements FILE only (tuning "
                    "to requirements); leave it out or add --requirements"
                )
        if args.objective in REQUIREMENT_OBJECTIVES:
            parser.error(
                f"--objective {args.objective} applies with --requirements FILE only; the "
                f"weighted-sum tuner takes {' or '.join(cost.OBJECTIVES)}"
            )
        if args.method == "cma-es":
            parser.error(
                "--method cma-es applies with --requirements FILE only (the weighted-sum "
                "tuner takes adam or lbfgs)"
            )
        if args.objective is None:
            args.objective = cost.CostConfig().objective
        if args.method is None:
            args.method = tuner.TunerConfig().method
        return
    for dest, why in _WEIGHTED_ONLY.items():
        if dest in given:
            parser.error(
                f"{_flag(parser, dest)} applies to the weighted-sum tuner only ({why}), not "
                "with --requirements; leave it out"
            )
    if args.objective in cost.OBJECTIVES:
        parser.error(
            f"--objective {args.objective} is the weighted-sum tuner's; with --requirements "
            f"choose {' or '.join(REQUIREMENT_OBJECTIVES)}"
        )
    if args.method is None:
        args.method = "adam"
    if args.method == "cma-es":
        for dest in _GRADIENT_ONLY:
            if dest in given:
                parser.error(
                    f"{_flag(parser, dest)} applies to the gradient tuner (--method adam or "
                    "lbfgs), not to --method cma-es; leave it out"
                )
    elif "generations" in given:
        parser.error(
            f"--generations applies to --method cma-es only, not to --method {args.method}"
        )
    if args.method == "lbfgs":
        for dest in ("learning_rate", "clip_norm"):
            if dest in given:
                parser.error(f"{_flag(parser, dest)} applies to --method adam only; leave it out")
    for dest, value in TUNE_DEFAULTS.items():
        if dest not in given:
            setattr(args, dest, value)
    if args.clip_norm is None:
        args.clip_norm = 1.0
