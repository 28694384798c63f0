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
import csv
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

__all__ = [
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
    "resume": "the weighted-sum tuner's checkpoints",
    "device_batch": "the weighted-sum tuner's sharded minibatch",
    "eval_horizon": "the weighted-sum tuner's held-out horizon (with --requirements the "
    "held-out draws run the tuning horizon, which the bounds refer to)",
}
_REQUIREMENTS_ONLY = ("rotor_limit", "outer_steps", "inner_steps", "margin", "formulation")
_GRADIENT_ONLY = ("outer_steps", "inner_steps", "formulation", "learning_rate", "clip_norm")


# ------------------------------------------------------------------ argument types


def requirements_file(text: str):
    """argparse type: a requirement file (TOML or JSON), loaded and checked
    (:func:`fojax.requirements.load`); every problem in one message."""
    from fojax import requirements as rq
    from fojax.cli import arguments

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


def _resolve(args):
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


def _actuators(limit: float | None, args) -> dict:
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
    reqs, limit = _resolve(args)
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

    _, scenario, config, dtype, runs = study_layer._prepared(study)
    keys = np.asarray(scenarios.draw_keys(study.seed, np.arange(study.draws)))
    out = {}
    for name, (controller, gains) in runs.items():
        out[name] = rq.measure(controller, gains, scenario, reqs, keys, config, dtype=dtype)
    return out


def report_simulate(study, args, out: Path, summary: dict, figures: bool = True) -> dict:
    """After ``write_outputs``: the actuators in ``summary.json`` and, with
    ``--requirements``, the yield per controller (printed, in ``summary.json``,
    ``requirements.npz``, ``requirements.png``). Returns the updated summary."""
    import numpy as np

    from fojax import requirements as rq
    from fojax.cli import style
    from fojax.cli.output import write_json

    reqs = getattr(args, "requirement_set", None)
    limit = getattr(args, "rotor_speed_limit", None)
    if reqs is None and limit is None:
        return summary
    out = Path(out)
    summary["actuators"] = _actuators(limit, args)
    if limit is not None:
        print(
            f"rotor-limited actuators: w_max {limit:.4g} rad/s (thrust-to-weight "
            f"{summary['actuators']['thrust_to_weight']:.3g}, {summary['actuators']['source']})"
        )
    if reqs is None:
        write_json(out / "summary.json", summary)
        return summary
    start = time.perf_counter()
    measured = measure_study(study, reqs)
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
    _savez(out / "requirements.npz", arrays)
    files = summary.setdefault("files", [])
    if "requirements.npz" not in files:
        files.append("requirements.npz")
    write_json(out / "summary.json", summary)
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


def _savez(path: Path, arrays: dict) -> None:
    import os

    import numpy as np

    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


def plot_yield(results: dict, path: Path, title: str) -> Path:
    """Left: the yield per controller with its 95 % Clopper-Pearson interval. Right: the
    share of draws failing each requirement, per controller."""
    import numpy as np

    from fojax.cli import style

    plt = style.pyplot()
    names = list(results)
    first = results[names[0]]
    requirements = list(first.names)
    fig, (left, right) = plt.subplots(
        1,
        2,
        figsize=(10.5, 0.5 + 0.45 * max(4, len(requirements) * len(names) ** 0.5)),
        layout="constrained",
        gridspec_kw={"width_ratios": [1, 1.6]},
    )
    y = np.arange(len(names))
    for i, name in enumerate(names):
        result = results[name]
        low, high = result.interval
        value = result.yield_
        color = style.color(name, i)
        left.barh(i, 100 * value, color=color, alpha=0.35, height=0.6)
        left.errorbar(
            100 * value,
            i,
            xerr=[[100 * (value - low)], [100 * (high - value)]],
            fmt="o",
            color=color,
            capsize=4,
        )
        left.annotate(
            f"{value:.0%} ({result.passed}/{result.draws})",
            (100 * high, i),
            xytext=(4, 0),
            textcoords="offset points",
            va="center",
            fontsize=8,
        )
    left.set_yticks(y, names)
    left.invert_yaxis()
    left.set_xlim(0, 125)
    left.set_xticks([0, 25, 50, 75, 100])
    left.set_xlabel("yield (%), 95 % Clopper-Pearson interval")
    left.set_title("draws meeting every requirement", fontsize=9)
    left.grid(axis="x", alpha=0.3)
    height = 0.8 / len(names)
    rows = np.arange(len(requirements))
    for i, name in enumerate(names):
        result = results[name]
        share = 100 * np.asarray(result.failures) / result.draws
        offset = (i - (len(names) - 1) / 2) * height
        right.barh(rows + offset, share, height=height, color=style.color(name, i), label=name)
    right.set_yticks(rows, requirements)
    right.invert_yaxis()
    right.set_xlim(0, 100)
    right.set_xlabel("draws failing the requirement (%)")
    right.set_title("failures per requirement", fontsize=9)
    right.grid(axis="x", alpha=0.3)
    if len(names) > 1:
        right.legend(fontsize=8, loc="best")
    style.suptitle(fig, title, "a diverged draw fails every requirement")
    return style.save(fig, path)


# ---------------------------------------------------------------------------- tune


def add_tune_options(parser: argparse.ArgumentParser) -> None:
    """``fojax tune``'s options of the requirement tuner; ``--objective`` and
    ``--method`` take its choices too (checked by :func:`check_tune_options`)."""
    from fojax.optimize import cost

    _add_common(parser)
    group = parser.add_argument_group(
        "tuning to requirements (--requirements FILE; docs/requirements.md)"
    )
    d = TUNE_DEFAULTS
    group.add_argument(
        "--outer-steps",
        type=_positive_int,
        help=f"augmented-Lagrangian multiplier updates, each validated ({d['outer_steps']})",
    )
    group.add_argument(
        "--inner-steps",
        type=_positive_int,
        help=f"optimiser steps per outer step ({d['inner_steps']})",
    )
    group.add_argument(
        "--formulation",
        choices=("mean", "chance"),
        help="constraint per requirement: mean (the mean hinge violation over the draws, "
        "every draw must meet it; default) or chance (a smooth share of draws violating, "
        "at most 5 %%)",
    )
    group.add_argument(
        "--margin",
        type=_nonnegative_float,
        help=f"a draw must beat each bound by this share of its scale ({d['margin']})",
    )
    group.add_argument(
        "--generations",
        type=_positive_int,
        help=f"CMA-ES generations (--method cma-es only; {d['generations']})",
    )
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


def _positive_int(text):
    from fojax.cli import arguments

    return arguments.positive_int(text)


def _nonnegative_float(text):
    from fojax.cli import arguments

    return arguments.nonnegative_float(text)


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


@dataclasses.dataclass
class PreparedRequirementRun:
    """``fojax tune --requirements``, checked: the problem and the tuner's settings."""

    problem: object
    config: object
    requirements: object
    rotor_speed_limit: float | None
    init_gains: object
    init_label: str
    out: Path


def prepare_tune(parser, args) -> PreparedRequirementRun:
    """The requirement problem and the tuner's settings; every error is a ``parser.error``
    before anything compiles."""
    from fojax.cli import arguments
    from fojax.cli import tune as tune_cli
    from fojax.controllers import registry
    from fojax.optimize import constrained as co
    from fojax.optimize import params, problem

    try:
        arguments.controller_flags(
            [args.controller],
            {
                "--fractional": ("fractional_method", args.fractional),
                "--eval-switching": ("switching", args.eval_switching),
            },
        )
    except ValueError as error:
        parser.error(str(error))
    args.fractional = args.fractional or "soe"
    args.eval_switching = args.eval_switching or "sat"
    reqs, limit = _resolve(args)
    if args.dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    dtype = jnp.dtype(args.dtype)
    if args.fields == "default":
        fields = None
    elif args.fields == "all":
        fields = registry.get_controller_class(args.controller).GAINS.names
    else:
        fields = tuple(f.strip() for f in args.fields.split(",") if f.strip())
    gains, label = tune_cli._initial_gains(parser, args, dtype)
    try:
        params.make_parameter_map(args.controller, fields, args.share)
        spec = problem.ProblemSpec(
            controller=args.controller,
            scenario=args.scenario,
            horizon=float(args.horizon),
            dt=float(args.dt),
            draws=args.draws,
            seed=args.seed,
            fields=fields,
            share=args.share,
            fractional=args.fractional,
            dtype=args.dtype,
            compile=args.compile,
        )
        config = co.ConstrainedConfig(
            formulation=args.formulation,
            outer_steps=args.outer_steps,
            inner_steps=args.inner_steps,
            method="lbfgs" if args.method == "lbfgs" else "adam",
            learning_rate=args.learning_rate,
            clip_norm=args.clip_norm,
            margin=args.margin,
            allowed_share=0.05 if args.formulation == "chance" else 0.0,
            validation_draws=args.validation_draws,
        )
        built = co.RequirementProblem(
            spec,
            gains,
            reqs,
            objective=args.objective,
            rotor_limited=limit is not None,
            switching=args.eval_switching,
        )
    except ValueError as error:
        parser.error(str(error))
    return PreparedRequirementRun(built, config, reqs, limit, gains, label, args.out)


def _history_rows(history: list, names) -> list[dict]:
    rows = []
    for row in history:
        validation = row.get("validation") or {}
        out = {
            "outer_step": row["outer_step"],
            "objective": row["objective"],
            "loss": row["loss"],
            "max_constraint": max(max(row["constraints"]), 0.0),
            "penalty": row["penalty"],
            "valid_draws": row["valid_draws"],
            "validation_yield": validation.get("yield"),
            "validation_passed": validation.get("passed"),
            "validation_draws": validation.get("draws"),
            "validation_objective": validation.get("objective"),
            "wall_time_s": row["wall_time_s"],
        }
        for name, c, lam in zip(names, row["constraints"], row["multipliers"], strict=True):
            out[f"constraint[{name}]"] = c
            out[f"multiplier[{name}]"] = lam
        rows.append(out)
    return rows


def _write_csv(path: Path, rows: list[dict]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("w", newline="") as handle:
        if rows:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    tmp.replace(path)


def _heldout(problem, params_or_gains, keys) -> dict:
    from fojax import requirements as rq

    evaluated = problem.evaluate(params_or_gains, keys)
    result = evaluated["yield"]
    return {
        **result.to_dict(),
        "objective": evaluated["objective"],
        "diverged": int(((evaluated["status"] & rq.DIVERGED) != 0).sum()),
        "describe": result.describe(),
    }


def tune_main(run: PreparedRequirementRun, args, runtime: dict, argv) -> int:
    """Run ``fojax tune --requirements``: tune, write the files, print the report."""
    from fojax.cli import study as study_layer
    from fojax.controllers import gains_io
    from fojax.optimize import constrained as co
    from fojax.optimize import problem as problem_lib

    lead = runtime["process_index"] == 0
    problem, config, reqs = run.problem, run.config, run.requirements
    spec = problem.spec
    out = Path(run.out)
    from fojax.controllers import registry

    takes_switching = "switching" in registry.controller_options(spec.controller)
    switching = problem.switching if takes_switching else "none (no switching function)"
    command = ["fojax", "tune", *argv]
    session = study_layer.provenance(command)
    actuators = _actuators(run.rotor_speed_limit, args)
    init_record = study_layer.gains_record(
        run.init_gains, None if run.init_label in ("paper", "naive") else run.init_label
    )
    if run.init_label in ("paper", "naive"):
        init_record["source"] = "defaults" if run.init_label == "paper" else "naive"
    settings = {
        "requirements": reqs.to_dict(),
        "objective": args.objective,
        "method": args.method,
        "actuators": actuators,
        "problem": spec.as_dict(),
        "tuner": dataclasses.asdict(config)
        if args.method != "cma-es"
        else {"generations": args.generations, "margin": args.margin, "penalty": 100.0},
        "evaluation_switching": switching,
    }
    if lead:
        out.mkdir(parents=True, exist_ok=True)
        record = {
            "controller": spec.controller,
            "init": run.init_label,
            "init_gains": init_record,
            **settings,
            "sessions": [session],
        }
        study_layer.write_json(out / "run.json", record)
    if not args.quiet and lead:
        print(
            f"tuning {spec.controller} to {len(reqs)} requirements ({', '.join(reqs.names)}) "
            f"on scenario {spec.scenario}, {spec.draws} draws x {spec.horizon:g} s, "
            + ("rotor-limited" if run.rotor_speed_limit else "ideal actuators")
            + f", minimising {args.objective}, {args.method}",
            file=sys.stderr,
            flush=True,
        )
    start = time.perf_counter()
    try:
        if args.method == "cma-es":
            x0, _ = problem.param_map.ravel(problem.initial_params())
            popsize = 4 + int(3 * math.log(max(int(x0.size), 1)))
            per_generation = popsize * spec.draws * spec.steps
            outcome = co.cma_es_requirements(
                problem,
                args.generations * per_generation,
                margin=args.margin,
                popsize=popsize,
                seed=spec.seed,
                validation_draws=config.validation_draws,
            )
            params, selected = outcome["params"], outcome["selected"] or {}
            history_rows = outcome["history"]
            selected_label = selected.get("candidate", "cma-es mean")
            draw_steps = outcome["draw_steps"]
        else:
            result = co.tune_to_requirements(problem, config, progress=not args.quiet and lead)
            params, selected = result.params, result.selected
            history_rows = _history_rows(result.history, reqs.names)
            selected_label = f"outer step {selected.get('outer_step')}"
            evaluations = 1 + config.outer_steps * (config.inner_steps + 1)
            draw_steps = evaluations * spec.draws * spec.steps
    except KeyboardInterrupt:
        return 130
    tuning_wall = time.perf_counter() - start
    if not lead:
        return 0
    gains = problem.gains(params)
    metadata = {
        "tuned_to": "requirements",
        "selected": selected,
        "selected_from": selected_label,
        "init_gains": init_record,
        "provenance": session,
        **settings,
        "tuning_wall_time_s": round(tuning_wall, 1),
        "draw_steps": draw_steps,
    }
    gains_io.save_gains(
        out / "gains.json", spec.controller, gains, json.loads(json.dumps(metadata, default=_plain))
    )
    _write_csv(out / "history.csv", history_rows)
    files = ["gains.json", "history.csv", "run.json"]
    print(
        f"tuned {spec.controller} to the requirements on scenario {spec.scenario} "
        f"({args.method}, {spec.draws} draws x {spec.horizon:g} s, "
        f"{tuning_wall:.0f} s); selected {selected_label}"
        + (
            f": validation {selected['yield']:.1%} ({selected['passed']}/{selected['draws']})"
            if "yield" in selected
            else ""
        )
    )
    if args.eval_draws > 0:
        keys = problem.heldout_keys(args.eval_draws)
        initial = _heldout(problem, run.init_gains, keys)
        tuned = _heldout(problem, gains, keys)
        evaluation = {
            "draws": args.eval_draws,
            "horizon_s": spec.horizon,
            "switching": switching,
            "draw_indices": f"{problem_lib.HELDOUT_OFFSET} + [0, {args.eval_draws})",
            "objective": args.objective,
            "actuators": actuators,
            "initial": initial,
            "tuned": tuned,
            "tuned_gains_from": selected_label,
            "provenance": session,
        }
        study_layer.write_json(out / "evaluation.json", evaluation)
        files.append("evaluation.json")
        print(
            f"held-out ({args.eval_draws} draws"
            + (f", {problem.switching} switching" if takes_switching else "")
            + "):"
        )
        print(f"  initial {initial['describe']}; {args.objective} {initial['objective']:.4g}")
        print(f"  tuned   {tuned['describe']}; {args.objective} {tuned['objective']:.4g}")
    print(f"wrote {out}/: {', '.join(files)}")
    return 0


def _plain(value):
    import numpy as np

    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return str(value)
