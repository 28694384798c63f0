"""``fojax tune --requirements FILE``: tuning to a requirement set (docs/requirements.md).

:func:`prepare_tune` checks the options and builds the problem before anything
compiles; :func:`tune_main` tunes (:func:`fojax.optimize.constrained.tune_to_requirements`:
an augmented Lagrangian on the mean hinge violation; ``--method cma-es``: the
derivative-free baseline, :func:`fojax.optimize.constrained.cma_es_requirements`) and
writes ``run.json``, ``gains.json`` (what ``fojax simulate --gains`` reads),
``history.csv`` and ``evaluation.json`` (the held-out yield of the initial and the tuned
gains on ``--eval-draws`` draws, with intervals). The options themselves are
:mod:`fojax.cli.requirements`'.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

from fojax.cli import _tuning
from fojax.cli.output import provenance, write_csv, write_json

__all__ = ["CHECKPOINT", "PreparedRequirementRun", "prepare_tune", "tune_main"]

CHECKPOINT = "checkpoint_requirements.npz"
"""The gradient tuner's state after its last outer iteration (``--resume`` continues it)."""


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
    from fojax.cli import requirements as requirements_cli
    from fojax.optimize import constrained as co
    from fojax.optimize import params

    try:
        _tuning.check_law_options(args)
    except ValueError as error:
        parser.error(str(error))
    args.fractional = args.fractional or "soe"
    args.eval_switching = args.eval_switching or "sat"
    reqs, limit = requirements_cli.resolve_requirements(args)
    dtype, fields = _tuning.dtype_and_fields(args)
    gains, label = _tuning.initial_gains(parser, args, dtype)
    try:
        params.make_parameter_map(args.controller, fields, args.share)
        spec = _tuning.problem_spec(args, fields)
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
    checkpoint = Path(args.out) / CHECKPOINT
    if args.method != "cma-es" and checkpoint.exists() and not args.resume:
        parser.error(
            f"{args.out} holds the checkpoint of an earlier run ({checkpoint}); pass --resume "
            "to continue it, or choose another --out"
        )
    if args.resume and not checkpoint.exists():
        parser.error(f"nothing to resume: {checkpoint} does not exist")
    run = PreparedRequirementRun(built, config, reqs, limit, gains, label, args.out)
    if args.resume:
        try:
            co.check_checkpoint(checkpoint, _fingerprint(run, args))
        except ValueError as error:
            parser.error(str(error))
    return run


def _takes_switching(controller: str) -> bool:
    from fojax.controllers import registry

    return "switching" in registry.controller_options(controller)


def _settings(run: PreparedRequirementRun, args) -> dict:
    """What ``run.json`` and ``gains.json`` record of the run's settings."""
    from fojax.cli import requirements as requirements_cli

    problem, spec = run.problem, run.problem.spec
    tuner = (
        dataclasses.asdict(run.config)
        if args.method != "cma-es"
        else {"generations": args.generations, "margin": args.margin, "penalty": 100.0}
    )
    return {
        "requirements": run.requirements.to_dict(),
        "objective": args.objective,
        "method": args.method,
        "actuators": requirements_cli.actuators_record(run.rotor_speed_limit, args),
        "problem": spec.as_dict(),
        "tuner": tuner,
        "evaluation_switching": problem.switching
        if _takes_switching(spec.controller)
        else "none (no switching function)",
    }


def _tune(run: PreparedRequirementRun, args, lead: bool) -> dict:
    """Tune: ``params``, ``selected`` (the validation of the gains returned), their
    label, the history's rows and the draw-steps simulated."""
    from fojax.optimize import constrained as co

    problem, config, spec = run.problem, run.config, run.problem.spec
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
        selected = outcome["selected"] or {}
        return {
            "params": outcome["params"],
            "selected": selected,
            "label": selected.get("candidate", "cma-es mean"),
            "history": outcome["history"],
            "draw_steps": outcome["draw_steps"],
        }
    result = co.tune_to_requirements(
        problem,
        config,
        progress=not args.quiet and lead,
        checkpoint=_checkpoint(run, lead),
        fingerprint=_fingerprint(run, args),
    )
    evaluations = 1 + config.outer_steps * (config.inner_steps + 1)
    return {
        "params": result.params,
        "selected": result.selected,
        "label": f"outer step {result.selected.get('outer_step')}",
        "history": _history_rows(result.history, run.requirements.names),
        "draw_steps": evaluations * spec.draws * spec.steps,
    }


def _checkpoint(run: PreparedRequirementRun, lead: bool) -> Path:
    """The checkpoint file; other processes than 0 write a private copy (process 0
    writes the outputs)."""
    checkpoint = Path(run.out) / CHECKPOINT
    if lead:
        return checkpoint
    import shutil
    import tempfile

    private = Path(tempfile.mkdtemp(prefix="fojax-tune-")) / CHECKPOINT
    if checkpoint.is_file():
        shutil.copy2(checkpoint, private)
    return private


def _fingerprint(run: PreparedRequirementRun, args) -> dict:
    """What a checkpoint must have been written with: the settings but the number of
    outer steps (a resumed run may go on for longer)."""
    settings = _settings(run, args)
    settings["tuner"] = {k: v for k, v in settings["tuner"].items() if k != "outer_steps"}
    settings["init_gains"] = _tuning.init_record(run.init_gains, run.init_label)
    return json.loads(json.dumps(settings, default=_plain))


def tune_main(run: PreparedRequirementRun, args, runtime: dict, argv) -> int:
    """Run ``fojax tune --requirements``: tune, write the files, print the report."""
    lead = runtime["process_index"] == 0
    reqs, spec, out = run.requirements, run.problem.spec, Path(run.out)
    session = provenance(["fojax", "tune", *argv])
    settings = _settings(run, args)
    init = _tuning.init_record(run.init_gains, run.init_label)
    if lead:
        out.mkdir(parents=True, exist_ok=True)
        record = {"controller": spec.controller, "init": run.init_label, "init_gains": init}
        sessions = [session]
        if args.resume and (out / "run.json").is_file():
            sessions = json.loads((out / "run.json").read_text()).get("sessions", []) + sessions
        write_json(out / "run.json", {**record, **settings, "sessions": sessions})
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
        outcome = _tune(run, args, lead)
    except KeyboardInterrupt:
        return 130
    wall = time.perf_counter() - start
    if not lead:
        return 0
    gains = run.problem.gains(outcome["params"])
    selected, label = outcome["selected"], outcome["label"]
    metadata = {
        "tuned_to": "requirements",
        "selected": selected,
        "selected_from": label,
        "init_gains": init,
        "provenance": session,
        **settings,
        "tuning_wall_time_s": round(wall, 1),
        "draw_steps": outcome["draw_steps"],
    }
    _save_gains(out / "gains.json", spec.controller, gains, metadata)
    write_csv(out / "history.csv", outcome["history"])
    files = ["gains.json", "history.csv", "run.json"]
    print(
        f"tuned {spec.controller} to the requirements on scenario {spec.scenario} "
        f"({args.method}, {spec.draws} draws x {spec.horizon:g} s, "
        f"{wall:.0f} s); selected {label}"
        + (
            f": validation {selected['yield']:.1%} ({selected['passed']}/{selected['draws']})"
            if "yield" in selected
            else ""
        )
    )
    if args.eval_draws > 0:
        after = {"tuned_gains_from": label, "provenance": session}
        _report_heldout(run, args, settings, gains, after)
        files.append("evaluation.json")
    print(f"wrote {out}/: {', '.join(files)}")
    return 0


def _report_heldout(run, args, settings: dict, gains, after: dict) -> None:
    """``evaluation.json``: the held-out yield of the initial and the tuned gains; printed."""
    problem = run.problem
    keys = problem.heldout_keys(args.eval_draws)
    evaluation = _tuning.heldout_evaluation(
        args.eval_draws,
        problem.spec.horizon,
        settings["evaluation_switching"],
        lambda value: _heldout(problem, value, keys),
        {"initial": run.init_gains, "tuned": gains},
        before={"objective": args.objective, "actuators": settings["actuators"]},
        after=after,
    )
    write_json(Path(run.out) / "evaluation.json", evaluation)
    print(
        f"held-out ({args.eval_draws} draws"
        + (f", {problem.switching} switching" if _takes_switching(problem.spec.controller) else "")
        + "):"
    )
    for label in ("initial", "tuned"):
        value = evaluation[label]
        print(f"  {label:<7} {value['describe']}; {args.objective} {value['objective']:.4g}")


def _save_gains(path: Path, controller: str, gains, metadata: dict) -> None:
    from fojax.controllers import gains_io

    plain = json.loads(json.dumps(metadata, default=_plain))
    gains_io.save_gains(path, controller, gains, plain)


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


def _plain(value):
    import numpy as np

    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return str(value)
