"""Section V on real rotors: every controller tuned to one requirement set on
rotor-limited actuators with the same budget, then its yield on held-out draws of every
scenario, ``sign`` (the paper's ``sgn``) and ``sat`` switching.

    python -m experiments.requirements_study [--out results/requirements_study]
        [--requirements examples/requirements/small_quadrotor.toml]
        [--controllers afonftsmc,anftsmc,fobsmc,bsmc,fl] [--scenarios 1,2,3]
        [--switching sign,sat] [--draws 1024] [--tune-scenario 2] [--horizon 10]
        [--tune-draws 8] [--outer-steps 10] [--inner-steps 10] [--update-doc]

Every controller starts from its default gains (the paper's for the AFONFTSMC) and is
tuned on the engine as ``fojax tune --requirements`` tunes (the augmented Lagrangian of
the mean hinge around ``--method``'s strategy, default Adam at learning rate 0.1 on the
fixed sample; ``--method auto`` is ``fojax tune``'s default) on scenario
``--tune-scenario`` (several: their union, draw ``i`` of member ``i % members``),
minimising effort, with the requirement file's rotor limit, validated on
``--validation-draws`` draws after every outer step (the best validated gains kept);
then the default and the tuned gains are measured on ``--draws`` held-out draws
(indices from 2**31, never used in tuning or validation) of each scenario at the tuning
horizon, with each switching function (the FL has none: one row), and the yield with
its 95 % Clopper-Pearson interval is reported with the most-failed requirement and the
mean effort.

Everything is cached in ``--out``: ``tuned/<controller>.json`` (the gains and the
tuner's record) and ``yield/<label>.json`` (one evaluation); a run started again
reuses them and computes only what is missing (a changed budget or requirement file
is a new key: the cache names carry a digest of the settings). Writes
``results.json`` and ``table.md``; ``--update-doc`` replaces the block
``requirements-study`` of docs/requirements.md (``requirements-study-union`` when tuned
on several scenarios).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import sys
import time
from pathlib import Path

from experiments import _common
from fojax.cli import arguments, output
from fojax.optimize.strategies import METHODS

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "requirements.md"
EXAMPLE = ROOT / "examples" / "requirements" / "small_quadrotor.toml"


def build_parser() -> argparse.ArgumentParser:
    from fojax.cli import requirements as requirements_cli
    from fojax.controllers import registry

    parser = _common.parser("requirements_study")
    parser.add_argument(
        "--out", type=arguments.output_directory, default=Path("results/requirements_study")
    )
    parser.add_argument(
        "--requirements", type=requirements_cli.requirements_file, default=None,
        help=f"requirement file ({EXAMPLE.relative_to(ROOT)})",
    )  # fmt: skip
    parser.add_argument("--controllers", default=",".join(registry.PAPER_CONTROLLERS))
    parser.add_argument("--scenarios", type=arguments.scenario_ids, default=(1, 2, 3))
    parser.add_argument("--switching", default="sign,sat")
    _common.add_numbers(parser, draws=1024)
    parser.add_argument(
        "--tune-scenario", type=arguments.scenario_ids, default=(2,),
        help="the scenario tuned on, or several (2,3: their union, draws alternating)",
    )  # fmt: skip
    _common.add_numbers(parser, horizon=10.0, tune_draws=8, outer_steps=10, inner_steps=10)
    _common.add_numbers(parser, validation_draws=32)
    parser.add_argument("--method", choices=METHODS, default="adam", help="the inner strategy")
    parser.add_argument("--seed", type=arguments.seed, default=0)
    parser.add_argument("--update-doc", action="store_true")
    return parser


def tune_one(name: str, reqs, args) -> dict:
    """Tune ``name`` to ``reqs`` (the study's budget); the gains and the record."""
    from fojax import optimize
    from fojax.controllers import gains_io, registry

    ids = args.tune_scenario if isinstance(args.tune_scenario, list) else [args.tune_scenario]
    spec = optimize.ProblemSpec(
        controller=name,
        scenario=tuple(ids) if len(ids) > 1 else ids[0],
        horizon=args.horizon,
        draws=args.tune_draws,
        seed=args.seed,
    )
    gains = registry.get_controller_class(name).default_gains()
    limit = reqs.settings.simulation_limit()
    objective = optimize.Objective(spec, gains, reqs, "effort", rotor_speed_limit=limit)
    start = time.perf_counter()
    result = _common.to_requirements(
        objective, objective.x0, args.method, args.outer_steps, args.inner_steps,
        validation_draws=args.validation_draws, progress=True, learning_rate=0.1, seed=args.seed,
    )  # fmt: skip
    return {
        "controller": name,
        "gains": gains_io.gains_to_dict(objective.gains(result.x)),
        "selected": {"step": result.returned_step, **result.validation["best"]},
        "initial_validation": result.validation["initial"],
        "history": [
            {k: row[k] for k in ("step", "outer_step", "loss", "penalty", "wall_time_s")}
            | {"validation_yield": row["validation"]}
            for row in result.history
            if row["validation"] is not None
        ],
        "wall_time_s": round(time.perf_counter() - start, 1),
        "draw_steps": result.draw_steps,
        "load_average": output.load_average(),
    }


def evaluate_one(name: str, gains_dict: dict | None, scenario_id: int, switching, reqs, args):
    """The yield of ``name`` (default gains when ``gains_dict`` is None) on the held-out
    draws of ``scenario_id`` with ``switching``, rotor-limited as the set asks."""
    import numpy as np

    from fojax import requirements as rq
    from fojax import scenarios
    from fojax.controllers import gains_io, registry
    from fojax.optimize import draw_keys

    options = {"dt": 1e-3, "horizon": args.horizon}
    if switching is not None:
        options["switching"] = switching
    controller = registry.make_controller(name, **registry.options_for(name, options))
    if gains_dict is None:
        gains = controller.default_gains()
    else:
        gains = gains_io.gains_from_dict(name, gains_dict, "study")
    config = rq.simulation_config(reqs, args.horizon)
    scenario = scenarios.get_scenario(scenario_id)
    keys = draw_keys(args.seed, "heldout", args.draws)
    start = time.perf_counter()
    metrics, status = rq.measure(controller, gains, scenario, reqs, keys, config)
    valid = (status & rq.DIVERGED) == 0
    result = rq.evaluate(reqs, metrics, valid=valid)
    return {
        **result.to_dict(),
        "diverged": int(np.sum(~valid)),
        "mean_thrust_effort_N": float(np.nanmean(metrics["thrust_effort"])),
        "mean_torque_effort_Nm": float(np.nanmean(metrics["torque_effort"])),
        "wall_time_s": round(time.perf_counter() - start, 1),
    }


def table(results: dict) -> str:
    lines = [
        "| controller | gains | scenario | switching | yield (95 % interval) | failures "
        "(draws) | torque effort (N m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in results["rows"]:
        low, high = row["interval"]
        failing = sorted(row["failures"].items(), key=lambda item: -item[1])
        failed = ", ".join(f"{n} {c}" for n, c in failing if c) or "-"
        lines.append(
            f"| {row['controller']} | {row['gains']} | {row['scenario']} | {row['switching']} "
            f"| {row['passed']}/{row['draws']}, {row['yield']:.1%} ({low:.1%} - {high:.1%}) "
            f"| {failed} | {row['mean_torque_effort_Nm']:.3g} |"
        )
    return "\n".join(lines)


def _budget(args, reqs) -> dict:
    """What the tuned gains depend on: the requirements and the tuning budget."""
    names = "tune_scenario horizon tune_draws outer_steps inner_steps validation_draws seed method"
    budget = {k: getattr(args, k) for k in names.split()} | {"engine": "fojax.optimize"}
    return {"requirements": reqs.to_dict(), **budget}


def _rows(name: str, record: dict, switchings, budget: dict, reqs, args) -> list[dict]:
    """The default and the tuned gains of ``name`` on each scenario and switching (one
    row per evaluation, cached)."""
    from fojax.controllers import registry

    rows = []
    takes = "switching" in registry.controller_options(name)
    gain_sets = (("default", None), ("tuned", record["gains"]))
    cases = itertools.product(args.scenarios, switchings if takes else [None], gain_sets)
    for scenario_id, switching, (label, gains) in cases:
        fingerprint = [budget if gains else reqs.to_dict(), name, label, scenario_id,
                       switching, args.draws, args.horizon]  # fmt: skip
        stem = f"{name}-{label}-s{scenario_id}-{switching}"
        evaluate = functools.partial(evaluate_one, name, gains, scenario_id, switching, reqs, args)
        row = _common.cached(args.out / "yield", stem, fingerprint, evaluate)
        where = {"scenario": scenario_id, "switching": switching or "-"}
        rows.append({"controller": name, "gains": label, **where, **row})
        print(f"{name} {label} scenario {scenario_id} {switching or '-'}: "
              f"{row['passed']}/{row['draws']}", flush=True)  # fmt: skip
    return rows


def _tuned_on(args) -> str:
    ids = args.tune_scenario
    if not isinstance(ids, list):
        return f"scenario {ids}"
    return f"scenarios {' and '.join(map(str, ids))} (their union, draws alternating)"


def _doc_head(args, results: dict, tuned_records: dict) -> str:
    walls = ", ".join(
        f"{n} {r['wall_time_s']:.0f} s (selected step {r['selected'].get('step')})"
        for n, r in tuned_records.items()
    )
    return (
        f"Run: `{' '.join(results['command'])}`. Budget per controller: "
        f"{args.outer_steps} outer x {args.inner_steps} inner {args.method} steps on "
        f"{args.tune_draws} draws x {args.horizon:g} s of {_tuned_on(args)}, "
        f"{args.validation_draws} validation draws; held-out: {args.draws} draws per "
        f"row at {args.horizon:g} s. Tuning wall time: {walls} (2 shared cores, load "
        f"average at the end {results['load_average']})."
    )


def main(argv=None) -> int:
    from fojax import requirements as rq
    from fojax.controllers import registry

    args = build_parser().parse_args(argv)
    args.out = Path(args.out)
    # One scenario stays a number (the cache keys of earlier runs); several, a list.
    ids = args.tune_scenario
    args.tune_scenario = ids[0] if len(ids) == 1 else list(ids)
    reqs = args.requirements or rq.load(EXAMPLE)
    controllers = _common.listed(args.controllers)
    for name in controllers:
        registry.get_controller_class(name)
    budget = _budget(args, reqs)
    rows, tuned_records = [], {}
    for name in controllers:
        record = _common.cached(
            args.out / "tuned", name, budget, lambda n=name: tune_one(n, reqs, args)
        )
        tuned_records[name] = record
        rows += _rows(name, record, _common.listed(args.switching), budget, reqs, args)
    results = {
        "budget": budget,
        "held_out_draws": args.draws,
        "rows": rows,
        "tuning": {
            n: {k: v for k, v in r.items() if k != "gains"} for n, r in tuned_records.items()
        },
        "command": ["python", "-m", "experiments.requirements_study", *(argv or sys.argv[1:])],
        "load_average": output.load_average(),
    }
    text = table(results)
    doc_text = _doc_head(args, results, tuned_records) + "\n\n" + text if args.update_doc else None
    doc = DOC if args.update_doc else None
    block = "requirements-study" + ("-union" if isinstance(args.tune_scenario, list) else "")
    return _common.finish(args.out, results, text, doc, block, doc_text)


if __name__ == "__main__":
    sys.exit(main())
