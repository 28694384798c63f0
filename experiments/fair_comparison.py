"""Section V made fair: every controller tuned the same way, then compared.

    python -m experiments.fair_comparison [--out results/fair_comparison]
                                          [--steps N] [--draws 16] [--horizon 10]
                                          [--controllers afonftsmc,anftsmc,...]
                                          [--eval-draws 64] [--tiny]

The paper compares its AFONFTSMC, tuned with MATLAB's optimisation toolbox, against
baselines whose gains are not published. Here every registered controller starts from
its documented default gains (``docs/model.md``) and gets the same tuning on the engine
(:mod:`fojax.optimize`): the same problem (scenario ``--scenario``, ``--horizon`` s, the
cost of :mod:`fojax.optimize.cost` with the ``fojax tune`` defaults, the same draws:
common random numbers), the same method (``--method``, default ``fojax tune``'s
``auto``: CMA-ES on small fresh samples; ``cma-lbfgs`` hands CMA-ES's mean to L-BFGS
after ``--switch`` generations), the same budget (the method's own, as ``fojax tune``
runs it: its step cap and, where it has one, its convergence stop, a method's budget
declared once in :data:`fojax.optimize.strategies.METHODS`; ``--steps N`` caps every
run at ``N`` steps instead, without the convergence stop; a CMA-ES generation is one
step, its population growing with the controller's parameters; a sample is ``--draws``
draws, except under ``auto``, which samples its own) and the same validation (the
driver's: 32 validation draws, scheduled by the work done since the last validation and
at the last step, the best validated gains returned). Then default and tuned gains of
every controller are evaluated with ``sat`` switching (the gains' boundary layers) on
the same ``--eval-draws`` held-out draws at each scenario's full horizon, on scenarios
1, 2 and 3, and every controller's tuned cost is compared with the tuned AFONFTSMC's
draw by draw (95 % Student-t).
``--tiny`` (the smoke test) evaluates on the tuning scenario only.

Each controller's tuning run checkpoints under ``--out/tuning/<name>/`` (the driver's
checkpoint): an interrupted study started again with the same command continues where
it stopped, to the result the uninterrupted run gives; a checkpoint of other settings or
other code (``fojax.optimize.run``'s ``resume="if-same"``) is run again from the start.
``results.json`` records the studies' code digest (:func:`experiments._common.code`).

Writes ``results.json`` and ``table.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time

import numpy as np

from experiments import _common
from fojax.cli import arguments, output
from fojax.optimize.strategies import METHODS

__all__ = ["main", "table"]

BASELINE = "afonftsmc"
TERMS = ("position", "attitude", "effort", "chattering")
"""The cost's terms, in the order of :class:`experiments._common.DrawCosts` ``terms``."""


def parse_args(argv) -> argparse.Namespace:
    """Validated arguments; exits with a message naming what to change."""
    from fojax.controllers import registry

    parser = _common.parser("fair_comparison")
    number = functools.partial(_common.add_numbers, parser)
    parser.add_argument("--scenario", type=int, choices=(1, 2, 3), default=2)
    number(horizon=(10.0, "tuning horizon (s)"))
    own = " then ".join(map(str, METHODS["auto"].own_draws()))
    number(draws=(16, f"draws per sample (not auto's, which samples its own: {own} draws "
                      "per point)"))  # fmt: skip
    parser.add_argument("--steps", type=arguments.positive_int, help="steps (CMA-ES: "
                        "generations); default the method's own budget, with its convergence "
                        "stop")  # fmt: skip
    parser.add_argument(
        "--method", choices=METHODS, default="auto", help="fojax tune's methods (auto)"
    )
    number(switch=(None, "CMA-ES generations before L-BFGS (the method's; cma-lbfgs only)"))
    number(learning_rate=(None, "Adam's step (the method's; --method adam only)"))
    parser.add_argument("--seed", type=arguments.nonnegative_int, default=0)
    parser.add_argument("--controllers", help="comma-separated names (default: all registered)")
    number(eval_draws=64)
    scenarios = "comma-separated scenario ids for the evaluation (default 1,2,3)"
    parser.add_argument(
        "--eval-scenarios", type=arguments.scenario_ids, default=(1, 2, 3), help=scenarios
    )
    number(eval_horizon=(None, "s (default: each scenario's)"))
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    block = "markdown file whose <!-- fair-comparison:begin/end --> block to replace"
    _common.add_outputs(parser, "fair_comparison", update_doc=block)
    args = parser.parse_args(argv)
    if args.learning_rate is not None and args.method != "adam":
        parser.error(
            f"--learning-rate applies to --method adam only, not to --method {args.method}; "
            "leave it out or add --method adam"
        )
    if args.switch is not None and args.method != "cma-lbfgs":
        parser.error(f"--switch applies to --method cma-lbfgs only, not to --method {args.method}")
    known = registry.controller_names()
    names = known if args.controllers is None else _common.listed(args.controllers)
    if not names or set(names) - set(known):
        parser.error(f"--controllers must be among {', '.join(known)}, got {args.controllers!r}")
    if BASELINE not in names:
        parser.error(f"--controllers must include {BASELINE} (the comparison's baseline)")
    args.controllers = (BASELINE,) + tuple(n for n in names if n != BASELINE)
    if args.tiny:
        vars(args).update(horizon=0.3, draws=3, steps=2, dtype="float64", eval_draws=3)
        args.eval_horizon = args.eval_horizon or 0.3
        args.eval_scenarios = (args.scenario,)
        if args.method == "cma-lbfgs":
            args.switch = args.switch or 1  # both of cma-lbfgs's phases
    steps = args.horizon / 1e-3
    if abs(steps - round(steps)) > 1e-6 * steps:
        parser.error(f"--horizon must be a whole number of 1 ms steps, got {args.horizon}")
    return args


def budget_of(args):
    """The tuning budget: ``--steps`` alone, or the method's own (its step cap and its
    convergence stop, :data:`fojax.optimize.strategies.METHODS`)."""
    from fojax import optimize

    if args.steps is not None:
        return optimize.Budget(steps=args.steps)
    method = METHODS[args.method]
    return optimize.Budget(steps=method.steps, patience=method.patience,
                           tolerance=method.tolerance)  # fmt: skip


def tune(args, index: int, name: str):
    """Tune ``name`` from its default gains (resuming its checkpoint): its objective,
    its default and tuned points, and the tuning's record."""
    import jax.numpy as jnp

    from fojax import optimize
    from fojax.controllers import registry
    from fojax.optimize import strategies

    spec = optimize.ProblemSpec(
        name, args.scenario, args.horizon, draws=args.draws, seed=args.seed, dtype=args.dtype
    )
    defaults = registry.get_controller_class(name).default_gains(jnp.dtype(args.dtype))
    objective = optimize.Objective(spec, defaults)
    given = {"switch": args.switch, "learning_rate": args.learning_rate}
    options = {k: v for k, v in given.items() if v is not None}
    strategy = strategies.make(
        args.method, strategies.Problem(objective, objective.x0, args.seed),
        budget_of(args).steps, **options,
    )  # fmt: skip
    run_dir = args.out / "tuning" / name
    found = (run_dir / optimize.CHECKPOINT).exists()
    goes_on = " (its checkpoint goes on if of these settings and code)" if found else ""
    output.log(
        args.quiet,
        f"[{index}/{len(args.controllers)}] tuning {name} ({args.method}): "
        f"{budget_of(args).steps} steps at most x "
        f"{f'{spec.draws} draws' if METHODS[args.method].draws else 'its own samples'} x "
        f"{spec.horizon:g} s{goes_on}",
    )
    t0 = time.perf_counter()
    budget = budget_of(args)
    result = optimize.run(
        objective, strategy, budget, out=run_dir, resume="if-same", progress=not args.quiet
    )
    record = {
        "draw_steps": result.draw_steps,
        "tuning_wall_time_s": result.wall_time_s,
        "this_invocation_s": round(time.perf_counter() - t0, 1),
        "steps": result.steps,
        "first_objective": result.history[0]["loss"],
        "final_objective": result.history[-1]["loss"],
        "returned_step": result.returned_step,
        "validation": result.validation,
        "parameters": objective.size,
        "strategy": strategy.settings(),
    }
    return objective, {"default": objective.x0, "tuned": result.x}, record


def _compare(by_gains: dict, base) -> dict:
    """One controller's held-out costs (default and tuned gains), the tuning's gain and,
    against the baseline's tuned costs ``base`` (None: the baseline), the differences."""
    from fojax import statistics

    record = {}
    for which, c in by_gains.items():
        terms = np.where(c.diverged[:, None], np.nan, c.terms)
        record[which] = {
            "cost": statistics.mean_ci(c.cost),
            "terms_mean": dict(zip(TERMS, np.nanmean(terms, 0).tolist(), strict=True)),
            "diverged": int(np.sum(c.diverged)),
        }
    tuned, difference = by_gains["tuned"], statistics.paired_difference
    record["tuned_minus_default"] = difference(tuned.cost, by_gains["default"].cost)
    if base is not None:
        record["tuned_minus_baseline"] = difference(tuned.cost, base.cost)
        record["baseline_better_fraction"] = float(np.mean(base.cost < tuned.cost))
        record["position_term_minus_baseline"] = difference(tuned.terms[:, 0], base.terms[:, 0])
    return record


def evaluate(args, objectives: dict, points: dict) -> dict:
    """Every controller's default and tuned points on the same held-out draws of each
    scenario of ``--eval-scenarios``, compared with the tuned baseline's."""
    from fojax import scenarios
    from fojax.optimize import draw_keys

    keys = draw_keys(args.seed, "heldout", args.eval_draws)
    evaluation = {}
    for k in args.eval_scenarios:
        t0 = time.perf_counter()
        scenario = scenarios.get_scenario(k)
        horizon = args.eval_horizon or scenario.horizon
        own = None if k == args.scenario else scenario  # None: the objectives' own (compiled)
        draw = functools.partial(_common.draw_costs, keys=keys, horizon=horizon, scenario=own)
        costs = {n: {w: draw(objectives[n], x) for w, x in p.items()} for n, p in points.items()}
        base = costs[BASELINE]["tuned"]
        evaluation[f"scenario {k}"] = {
            "horizon_s": horizon,
            "draws": args.eval_draws,
            "controllers": {
                n: _compare(c, None if n == BASELINE else base) for n, c in costs.items()
            },
        }
        output.log(args.quiet, f"evaluated scenario {k} ({time.perf_counter() - t0:.0f} s)")
    return evaluation


def main(argv=None) -> int:
    """Tune every controller alike, evaluate and write ``results.json`` and ``table.md``;
    the document's block with ``--update-doc``."""
    args = parse_args(argv)
    _common.enable_float64(args.dtype == "float64")
    from fojax.controllers import gains_io

    start_all = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    objectives, points, tuning = {}, {}, {}
    for index, name in enumerate(args.controllers, 1):
        objectives[name], points[name], tuning[name] = tune(args, index, name)
    evaluation = evaluate(args, objectives, points)
    results = {
        "problem": {
            "scenario": args.scenario,
            "horizon_s": args.horizon,
            "draws": args.draws,
            "seed": args.seed,
            "dtype": args.dtype,
            "cost": dataclasses.asdict(objectives[BASELINE].spec.cost),
            "start": "each controller's default gains",
        },
        "tuner": {k: getattr(args, k) for k in ("method", "steps", "switch", "learning_rate")}
        | {"budget": {k: getattr(budget_of(args), k) for k in ("steps", "patience", "tolerance")}},
        "evaluation_switching": "sat",
        "tuning": tuning,
        "evaluation": evaluation,
        "gains": {
            name: {w: gains_io.gains_to_dict(objectives[name].gains(x)) for w, x in p.items()}
            for name, p in points.items()
        },
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
        "code": _common.code(),
    }
    text = doc_text = table(results)
    if args.update_doc is not None:
        p = output.run_context(["python", "-m", "experiments.fair_comparison", *(argv or [])])
        doc_text = (
            f"Run: `{p['command']}`; commit {output.commit_label(p)}, {p.get('cpu_model')}, "
            f"load average {p['load_average'][0]} at the end; "
            f"{results['total_wall_time_s']:.0f} s in all (tuning resumed from checkpoints "
            f"counts only the steps this invocation ran).\n\n{text}"
        )
    wrote = f" ({results['total_wall_time_s']:.0f} s in all)"
    return _common.finish(
        args.out, results, text, args.update_doc, "fair-comparison", doc_text, wrote
    )


def _difference(diff: dict, fraction: float | None = None) -> str:
    def verdict(low, high):
        said = "**baseline better**" if low > 0 else "**baseline worse**" if high < 0 else "n.s."
        share = "" if fraction is None else f", baseline better on {100 * fraction:.0f} %"
        return f" {said}{share}"

    return _common.difference_cell(diff, verdict)


def table(results: dict) -> str:
    """Markdown tables: held-out cost of default and tuned gains, and paired differences."""
    evaluation = results["evaluation"]
    labels = list(evaluation)
    controllers = [evaluation[label]["controllers"] for label in labels]
    names = list(controllers[0])
    columns = [f"{label} ({evaluation[label]['horizon_s']:g} s)" for label in labels]
    lines = _common.table_head("controller | gains | " + " | ".join(columns))
    for name in names:
        for which in ("default", "tuned"):
            cells = [_common.mean_cell(c[name][which], "diverged") for c in controllers]
            lines.append(f"| {name} | {which} | " + " | ".join(cells) + " |")
    total = f"Tuned cost minus the tuned {BASELINE}'s on the same draw (mean [95 % CI]):"
    position = "Position term alone (ISE of the position error, m^2 s), tuned minus the tuned "
    paired = (
        (total, "tuned_minus_baseline", "baseline_better_fraction"),
        (f"{position}{BASELINE}'s:", "position_term_minus_baseline", None),
    )
    for title, key, fraction in paired:
        lines += ["", title, "", *_common.table_head("controller | " + " | ".join(labels))]
        for name in names[1:]:
            records = [c[name] for c in controllers]
            cells = [_difference(r[key], r[fraction] if fraction else None) for r in records]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    tuning = results["tuning"]
    lines += [""] + _common.table_head(
        "controller | tuned parameters | steps run | tuning draw-steps | tuning wall time (s) | "
        "objective, first -> last step | returned step: validation cost, start -> returned"
    )
    for name in names:
        t = tuning[name]
        returned = "-"
        if v := t.get("validation"):
            step, first, best = v["returned_step"], v["initial"]["cost"], v["best"]["cost"]
            returned = f"{step}: {first:.4g} -> {best:.4g}"
        lines.append(
            f"| {name} | {t['parameters']} | {t.get('steps', '-')} | {t['draw_steps']:.3g} | "
            f"{t['tuning_wall_time_s']:.0f} | {t['first_objective']:.4g} -> "
            f"{t['final_objective']:.4g} | {returned} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
