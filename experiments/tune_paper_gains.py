"""Reproduce the paper's gains: tune the AFONFTSMC from a naive guess, by gradient and
by derivative-free baselines, and compare against the paper's gains on held-out draws.

    python -m experiments.tune_paper_gains [--out results/tune_paper_gains]
                                           [--steps 50] [--draws 16] [--horizon 10] ...
                                           [--tiny]   (a seconds-long smoke run)

Protocol (every number in ``docs/tuning.md`` comes from this script):

1. Tuning problem: scenario ``--scenario`` (2: drag uncertainty, disturbances (53),
   Gaussian disturbances), reference (54)-(55), ``--horizon`` seconds, the cost of
   :mod:`fojax.optimize.cost` with the CLI defaults, draws from the tuning stream of seed
   ``--seed``; start: :func:`fojax.optimize.params.naive_gains`.
2. Tuners, same problem, same starting point:
   * gradient (:mod:`fojax.optimize.tuner`): ``--steps`` steps of ``--draws`` draws,
     ``--gradient-method`` (``lbfgs``: quasi-Newton on one fixed sample; ``adam``: a
     fresh minibatch every step), returning its best validated iterate (its own
     ``--tuner-validation-draws`` validation draws, every ``--validate-every``
     steps);
   * CMA-ES (each generation in one batched call) and Nelder-Mead
     (:mod:`fojax.optimize.derivative_free`) with
     ``--df-budget-factor`` times the gradient tuner's simulated draw-steps (a
     gradient step simulates its draws once forward; its reverse pass costs a few
     forward passes more in wall time, which the wall-time axis shows).
   Along the way each tuner's current answer is scored on ``--validation-draws``
   held-out draws at the tuning horizon (``sat`` switching), not counted in any
   budget or wall time.
3. Evaluation of the paper's, the naive and the three tuned gain sets with the
   evaluation switching (``sat``, the gains' boundary layers) on ``--eval-draws``
   held-out draws at the scenario's full horizon, on: the tuning scenario; the same
   disturbances with a reference not used in tuning (:func:`unseen_reference`); and
   scenario 3 (other disturbances, 30 % mass/inertia uncertainty, reference (57)).
   Paired differences against the paper's gains use the same draws (95 % Student-t).

Each tuner's run is kept in ``--out/runs`` under its settings (a study started again
reuses the tuners that finished). Writes ``results.json`` (with the run's provenance:
commit, versions, CPU, load),
``table.md``, ``curves.csv`` and ``tuning.png`` to ``--out``; ``--update-doc FILE``
replaces the block between ``<!-- tune-paper-gains:begin -->`` and
``<!-- tune-paper-gains:end -->`` of FILE with the tables and copies the figure beside
it as ``tuning.png``.

Reproducibility: on one machine a rerun gives the same numbers (XLA's CPU code is
deterministic; wall times aside). The float32 rounding of the gradient depends on the
code and on the instructions XLA picks for the CPU, and a tuner's path amplifies
rounding differences (docs/tuning.md measures by how much), so the gradient row is
reproduced exactly only by the same commit on the same kind of CPU; ``results.json``
records both.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _common
from fojax import records
from fojax.cli import output

__all__ = ["main", "unseen_reference"]

VALIDATION_OFFSET = 100_000  # validation draws: held-out indices from here on
METHODS = ("gradient", "cma-es", "nelder-mead")


def unseen_reference(t):
    """A reference not used in tuning: a figure-eight with a climb and a varying yaw.

    ``x_r = 0.8 sin(pi t / 20)``, ``y_r = 0.4 sin(pi t / 10)``,
    ``z_r = 1.5 (1 - cos(pi t / 40))`` (m), ``psi_r = 0.3 + 0.2 sin(pi t / 20)`` (rad).
    Returns ``(4,)``.
    """
    import jax.numpy as jnp

    t = jnp.asarray(t)
    return jnp.stack(
        [
            0.8 * jnp.sin(jnp.pi * t / 20.0),
            0.4 * jnp.sin(jnp.pi * t / 10.0),
            1.5 * (1.0 - jnp.cos(jnp.pi * t / 40.0)),
            0.3 + 0.2 * jnp.sin(jnp.pi * t / 20.0),
        ]
    )


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("tune_paper_gains")
    number = functools.partial(_common.add_numbers, parser, int, float)
    number(scenario=2, horizon=(10.0, "tuning horizon (s)"), draws=(16, "draws per gradient step"))
    number(steps=(50, "gradient steps"))
    parser.add_argument("--gradient-method", choices=("lbfgs", "adam"), default="lbfgs")
    number(learning_rate=(0.1, "Adam's"), max_step=(1.0, "L-BFGS's"), tuner_validation_draws=32)
    number(seed=0)
    parser.add_argument("--dtype", default="float32")
    number(df_budget_factor=3.0, cma_sigma=0.5, validation_draws=32)
    number(validate_every=(5, "gradient steps"), eval_draws=64)
    number(eval_horizon=(None, "s (default: each scenario's)"))
    _common.add_outputs(parser, "tune_paper_gains")
    # Cost weights (default: the fojax tune defaults).
    number(effort_weight=None, chattering_weight=None, attitude_weight=None)
    return parser


def parse_args(argv) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    if args.tiny:
        # The small problem of the tests (shares their compiled code).
        args.horizon, args.draws, args.steps = 0.3, 3, 2
        args.seed, args.dtype = 5, "float64"
        args.effort_weight, args.chattering_weight, args.attitude_weight = 1e-3, 1e-3, 2.0
        args.validation_draws, args.validate_every, args.eval_draws = 2, 1, 2
        args.tuner_validation_draws = 2
        args.eval_horizon = args.eval_horizon or 0.3
        args.df_budget_factor = max(args.df_budget_factor, 40.0)
    return args


class _Study:
    """The tuning problem, its validation draws (held-out, scored along the way), and
    the tuners' curves: ``(method, draw-steps, wall time (s), validation cost)``."""

    def __init__(self, args):
        import jax.numpy as jnp

        from fojax.controllers.afonftsmc import paper_gains
        from fojax.optimize import cost as cost_lib
        from fojax.optimize import draw_keys
        from fojax.optimize import params as params_lib
        from fojax.optimize import problem as problem_lib

        self.args = args
        weights = ("effort_weight", "chattering_weight", "attitude_weight")
        overrides = {k: getattr(args, k) for k in weights if getattr(args, k) is not None}
        self.spec = problem_lib.ProblemSpec(
            controller="afonftsmc",
            scenario=args.scenario,
            horizon=args.horizon,
            draws=args.draws,
            seed=args.seed,
            cost=cost_lib.CostConfig(**overrides),
            dtype=args.dtype,
        )
        self.config = _common.tuner_config(args, args.steps, args.tuner_validation_draws)
        dtype = jnp.dtype(args.dtype)
        self.naive = params_lib.naive_gains("afonftsmc", dtype)
        self.paper = paper_gains(dtype)
        self.problem = problem_lib.TuningProblem(self.spec, self.naive)
        self.validation_keys = draw_keys(
            self.spec.seed, "heldout", args.validation_draws, VALIDATION_OFFSET
        )
        self.curves = []

    def validate(self, gains) -> float:
        from fojax.optimize import problem as problem_lib

        return float(np.mean(problem_lib.evaluate(self.spec, gains, self.validation_keys).cost))

    def compile(self) -> float:
        """Compile the tuners' functions first, so that no tuner's wall time counts them;
        the seconds it took."""
        t0 = time.perf_counter()
        problem, warm = self.problem, self.problem.initial_params()
        problem.value_and_grad(warm, 1.0, problem.minibatch_keys(0)).objective.block_until_ready()
        problem.value(warm, 1.0, problem.minibatch_keys(0)).objective.block_until_ready()
        return time.perf_counter() - t0

    def gradient(self, start_cost: float) -> dict:
        """The gradient tuner from the naive start (validation cost ``start_cost``): its
        record (:func:`_record`)."""
        from fojax.optimize import tuner as tuner_lib

        curve = []

        def on_step(step, params, row):
            # The tuner's answer so far: its best validated iterate (the start until a
            # validated step beats it).
            if row["validation_cost"] is None:
                return
            if row["best_step"] == step:
                value = self.validate(self.problem.gains(params))
            else:
                value = curve[-1][3] if curve else start_cost
            curve.append(("gradient", row["draw_steps"], row["wall_time_s"], value))

        quiet, spec, config = self.args.quiet, self.spec, self.config
        output.log(
            quiet, f"gradient tuner: {config.steps} steps x {spec.draws} draws x {spec.horizon:g} s"
        )
        run = tuner_lib.prepare(spec, config, self.naive, "naive", None)
        result = tuner_lib.tune(run, progress=not quiet, callback=on_step, problem=self.problem)
        last = result.history[-1]
        summary = {
            "draw_steps": last["draw_steps"],
            "wall_time_s": last["wall_time_s"],
            "steps": config.steps,
            "final_objective": last["objective"],
            "method": config.method,
            "returned_step": result.best_step,
            "validation": result.validation,
        }
        return _record(result.gains, curve, summary)

    def _recorder(self, method: str, curve: list):
        def callback(draw_steps, params, row):
            value = self.validate(self.problem.gains(params))
            curve.append((method, draw_steps, row["wall_time_s"], value))
            best = row["best_objective"]
            output.log(self.args.quiet, f"  {method}: {draw_steps} draw-steps, best {best:.4g}")

        return callback

    def cma_es(self, budget: int) -> dict:
        """CMA-ES from the naive start with ``budget`` draw-steps: its record."""
        from fojax.optimize import derivative_free

        curve = []
        output.log(self.args.quiet, f"CMA-ES: budget {budget} draw-steps")
        es = derivative_free.cma_es(
            self.problem,
            budget,
            sigma0=self.args.cma_sigma,
            seed=self.args.seed,
            width_scale=self.config.anneal_end,
            callback=self._recorder("cma-es", curve),
        )
        summary = {
            "draw_steps": es.draw_steps,
            "wall_time_s": round(es.wall_time_s, 3),
            "evaluations": es.evaluations,
            "generations": len(es.history),
            "popsize": es.evaluations // max(len(es.history), 1),
        }
        return _record(es.gains, curve, summary)

    def nelder_mead(self, budget: int, every: int) -> dict:
        """Nelder-Mead from the naive start with ``budget`` draw-steps, scored every
        ``every`` evaluations (CMA-ES's population): its record."""
        from fojax.optimize import derivative_free

        curve = []
        output.log(self.args.quiet, f"Nelder-Mead: budget {budget} draw-steps")
        nm = derivative_free.nelder_mead(
            self.problem,
            budget,
            width_scale=self.config.anneal_end,
            callback=self._recorder("nelder-mead", curve),
            callback_every=every,
        )
        curve.append(("nelder-mead", nm.draw_steps, nm.wall_time_s, self.validate(nm.gains)))
        summary = {
            "draw_steps": nm.draw_steps,
            "wall_time_s": round(nm.wall_time_s, 3),
            "evaluations": nm.evaluations,
        }
        return _record(nm.gains, curve, summary)


def _record(gains, curve: list, summary: dict) -> dict:
    """A tuner's run as JSON: its gains, its curve points ``(method, draw-steps, wall
    time, validation cost)`` and what it spent (``summary``)."""
    from fojax.controllers import gains_io

    return {"gains": gains_io.gains_to_dict(gains), "curve": [list(c) for c in curve],
            "summary": summary}  # fmt: skip


def run_tuners(args, study: _Study, start_cost: float) -> dict:
    """Each tuner's record, kept under its fingerprint in ``--out/runs`` (a study started
    again reuses the tuners that finished): the gradient tuner, then CMA-ES and
    Nelder-Mead with ``--df-budget-factor`` times its draw-steps."""
    settings = _common.settings(args, leave_out=("out", "update_doc", "quiet"))
    folder = args.out / "runs"
    gradient = records.cached(folder, "gradient", settings, lambda: study.gradient(start_cost))
    budget = int(args.df_budget_factor * gradient["summary"]["draw_steps"])
    es = records.cached(
        folder, "cma-es", settings | {"budget": budget}, lambda: study.cma_es(budget)
    )
    every = max(1, es["summary"]["popsize"])
    nm = records.cached(
        folder, "nelder-mead", settings | {"budget": budget, "every": every},
        lambda: study.nelder_mead(budget, every),
    )  # fmt: skip
    return {"gradient": gradient, "cma-es": es, "nelder-mead": nm}


def _cost_entry(costs, baseline) -> dict:
    """Held-out costs of one gain set: mean and 95 % interval, against the paper's
    gains' ``baseline`` costs on the same draws (None: the paper's), mean terms."""
    from fojax import statistics

    cost = statistics.mean_ci(costs.cost)
    if baseline is not None:
        cost["minus_paper"] = statistics.paired_difference(costs.cost, baseline)
        cost["better_than_paper_fraction"] = float(np.mean(np.asarray(costs.cost) < baseline))
    terms = np.where(costs.diverged[:, None], np.nan, costs.terms)
    return {
        "cost": cost,
        "terms_mean": np.mean(terms, 0).tolist(),
        "diverged": int(np.sum(costs.diverged)),
    }


def evaluate(args, study: _Study, gain_sets: dict) -> dict:
    """Every gain set on the held-out draws of the tuning scenario, of the unseen
    reference and of scenario 3, each at its full horizon (or ``--eval-horizon``)."""
    from fojax import scenarios
    from fojax.optimize import problem as problem_lib

    tuned_scenario = scenarios.get_scenario(args.scenario)
    settings = {
        f"scenario {args.scenario}": tuned_scenario,
        "unseen reference": dataclasses.replace(tuned_scenario, reference=unseen_reference),
        "scenario 3": scenarios.get_scenario(3),
    }
    keys = study.problem.heldout_keys(args.eval_draws)
    evaluation = {}
    for label, scenario in settings.items():
        horizon = args.eval_horizon or scenario.horizon
        t0 = time.perf_counter()
        costs = {
            name: problem_lib.evaluate(study.spec, gains, keys, horizon=horizon, scenario=scenario)
            for name, gains in gain_sets.items()
        }
        base = costs["paper"].cost
        evaluation[label] = {
            "horizon_s": horizon,
            "draws": args.eval_draws,
            "gains": {n: _cost_entry(c, None if n == "paper" else base) for n, c in costs.items()},
        }
        output.log(args.quiet, f"evaluated {label} ({time.perf_counter() - t0:.0f} s)")
    return evaluation


def reaches(curves: list) -> dict:
    """Where the gradient tuner first reaches each derivative-free tuner's best."""
    reach = {}
    gradient_curve = [(s, w, v) for m, s, w, v in curves if m == "gradient"]
    for method in ("cma-es", "nelder-mead"):
        points = [(s, w, v) for m, s, w, v in curves if m == method]
        best = min(v for _, _, v in points)
        first = next(((s, w) for s, w, v in gradient_curve if v <= best), None)
        reach[method] = {
            "best_validation_cost": best,
            "draw_steps_used": max(s for s, _, _ in points),
            "gradient_draw_steps_to_reach": first[0] if first else None,
            "gradient_wall_time_to_reach_s": first[1] if first else None,
        }
    return reach


def _write(args, results: dict, curves: list, references: dict) -> int:
    """``results.json``, ``table.md``, ``curves.csv``, ``tuning.png``; the document's
    block with ``--update-doc``."""
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "curves.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["method", "draw_steps", "wall_time_s", "validation_cost"])
        writer.writerows(curves)
    results["provenance"]["load_average_end"] = output.load_average()
    plot(curves, references, out / "tuning.png")
    doc_text = None
    if args.update_doc is not None:
        shutil.copyfile(out / "tuning.png", args.update_doc.parent / "tuning.png")
        doc_text = report(results)
    wrote = f", curves.csv, tuning.png ({results['total_wall_time_s']:.0f} s in all)"
    text = table(results)
    return _common.finish(out, results, text, args.update_doc, "tune-paper-gains", doc_text, wrote)


def main(argv=None) -> int:
    args = parse_args(argv)
    _common.enable_float64(args.dtype == "float64")
    from fojax.controllers import gains_io

    start_all = time.perf_counter()
    provenance = output.run_context(["python", "-m", "experiments.tune_paper_gains", *(argv or [])])
    study = _Study(args)
    compile_s = study.compile()
    output.log(args.quiet, f"compiled the tuning cost and its gradient ({compile_s:.0f} s)")
    references = {"paper": study.validate(study.paper), "naive": study.validate(study.naive)}
    output.log(
        args.quiet,
        f"validation cost: paper {references['paper']:.4g}, naive {references['naive']:.4g}",
    )
    records = run_tuners(args, study, references["naive"])
    study.curves += [(method, 0, 0.0, references["naive"]) for method in METHODS]
    study.curves += [tuple(c) for r in records.values() for c in r["curve"]]
    dtype = study.spec.jnp_dtype
    gain_sets = {"paper": study.paper, "naive": study.naive}
    gain_sets |= {
        name: gains_io.gains_from_dict("afonftsmc", r["gains"], name, dtype)
        for name, r in records.items()
    }
    evaluation = evaluate(args, study, gain_sets)
    validation = {"draws": args.validation_draws, "horizon_s": study.spec.horizon}
    results = {
        "problem": study.spec.as_dict(),
        "tuner": dataclasses.asdict(study.config),
        "validation": validation | {"switching": "sat", **references},
        "tuners": {name: r["summary"] for name, r in records.items()},
        "gradient_reaches": reaches(study.curves),
        "evaluation": evaluation,
        "gains": {name: gains_io.gains_to_dict(g) for name, g in gain_sets.items()},
        "compile_time_s": round(compile_s, 1),
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
        "provenance": provenance,
        "curves": [list(c) for c in study.curves],
    }
    return _write(args, results, study.curves, references)


def _minus_paper(cost: dict) -> str:
    diff, frac = cost["minus_paper"], cost["better_than_paper_fraction"]
    if diff["mean"] is None:
        return "n/a"
    if not diff["ci95"]:
        return f"{diff['mean']:+.3g}"
    low, high = diff["ci95"]
    return f"{diff['mean']:+.3g} [{low:+.3g}, {high:+.3g}], better on {100 * frac:.0f} %"


def table(results: dict) -> str:
    """Markdown tables: held-out costs per gain set, and the tuners' budgets."""
    evaluation = results["evaluation"]
    labels = list(evaluation)
    names = list(next(iter(evaluation.values()))["gains"])
    columns = " | ".join(f"{label} ({evaluation[label]['horizon_s']:g} s)" for label in labels)
    lines = _common.table_head(f"gains | {columns} | tuning draw-steps | tuning wall time (s)")
    tuners = results["tuners"]
    for name in names:
        cells = [_common.mean_cell(evaluation[label]["gains"][name], "div.") for label in labels]
        spent = tuners.get(name, {})
        lines.append(
            f"| {name} | "
            + " | ".join(cells)
            + f" | {spent.get('draw_steps', '-')} | {spent.get('wall_time_s', '-')} |"
        )
    columns = " | ".join(f"{label}: minus paper (95 % CI)" for label in labels)
    lines += ["", *_common.table_head(f"gains | {columns}")]
    for name in [n for n in names if n != "paper"]:
        cells = [_minus_paper(evaluation[label]["gains"][name]["cost"]) for label in labels]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _curve_at(points, limit, key):
    """The last curve point with ``key`` (0: draw-steps, 1: wall time) <= ``limit``."""
    inside = [p for p in points if p[key] <= limit]
    return inside[-1] if inside else None


def report(results: dict) -> str:
    """The generated part of docs/tuning.md's section: the run, the tables, the
    convergence and the cost terms."""

    p = results["provenance"]
    tuners = results["tuners"]
    g = tuners["gradient"]
    validation = results["validation"]
    lines = [
        f"Run: `{p['command']}`; commit {output.commit_label(p)}, JAX {p['jax']} / jaxlib "
        f"{p['jaxlib']}, {p.get('cpu_model')}, {p['cpu_count']} cores, load average "
        f"{p['load_average'][0] if p.get('load_average') else 'n/a'} at the start and "
        f"{p['load_average_end'][0] if p.get('load_average_end') else 'n/a'} at the end; "
        f"{results['total_wall_time_s']:.0f} s in all, of which {results['compile_time_s']:.0f} s "
        f"compiling the tuning cost and its gradient, {g['wall_time_s']:.0f} s gradient tuning "
        f"({g['method']}, its validation included), {tuners['cma-es']['wall_time_s']:.0f} s "
        f"CMA-ES, {tuners['nelder-mead']['wall_time_s']:.0f} s Nelder-Mead.",
        "",
        f"The gradient tuner returned the gains of step {g['returned_step']} of {g['steps']} "
        + (
            f"(validation cost {g['validation']['best']:.4g}; {g['validation']['initial']:.4g} "
            f"at the start, {g['validation']['final']:.4g} at the last step)."
            if g.get("validation")
            else "."
        ),
        "",
        "**Held-out cost** (mean ± 95 % half-width over "
        f"{next(iter(results['evaluation'].values()))['draws']} draws), paired differences "
        "against the paper's gains:",
        "",
        table(results),
        "",
    ]
    first = next(iter(results["evaluation"].values()))
    terms = ", ".join(
        f"{name} " + " / ".join(f"{t:.3g}" for t in entry["terms_mean"])
        for name, entry in first["gains"].items()
    )
    lines += [
        f"Mean terms on {next(iter(results['evaluation']))} "
        f"({first['horizon_s']:g} s), `P` / `A` / `E` / `C`: {terms}.",
        "",
    ]
    curves = results.get("curves", [])
    if curves:
        by_method = {}
        for method, steps, wall, value in curves:
            by_method.setdefault(method, []).append((steps, wall, value))
        budget = g["draw_steps"]
        lines += [
            f"**Convergence** (validation cost: {validation['draws']} held-out draws, "
            f"{validation['horizon_s']:g} s, `sat`; paper {validation['paper']:.4g}, naive "
            f"{validation['naive']:.4g}):",
            "",
            *_common.table_head(
                "method | at half the gradient's draw-steps | at the gradient's draw-steps | at "
                "the end | best point | at the gradient's wall time"
            ),
        ]
        for method, points in by_method.items():
            points.sort()
            cells = []
            for limit in (budget / 2, budget):
                at = _curve_at(points, limit, 0)
                cells.append("-" if at is None else f"{at[2]:.4g} ({at[0]:.2g})")
            cells.append(f"{points[-1][2]:.4g} ({points[-1][0]:.2g}, {points[-1][1]:.0f} s)")
            best = min(points, key=lambda q: q[2])
            cells.append(f"{best[2]:.4g} ({best[0]:.2g}, {best[1]:.0f} s)")
            at = _curve_at(sorted(points, key=lambda q: q[1]), g["wall_time_s"], 1)
            cells.append("-" if at is None else f"{at[2]:.4g} ({at[1]:.0f} s)")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        lines += ["", "(draw-steps and tuning wall time, compilation excluded, in parentheses.)"]
    return "\n".join(lines)


def plot(curves, references, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    colors = {"gradient": "C0", "cma-es": "C1", "nelder-mead": "C2"}
    for method, color in colors.items():
        points = sorted((s, w, v) for m, s, w, v in curves if m == method)
        if not points:
            continue
        s, w, v = (np.asarray(x, float) for x in zip(*points, strict=True))
        axes[0].plot(s, v, "o-", color=color, ms=3, label=method)
        axes[1].plot(w, v, "o-", color=color, ms=3, label=method)
    for ax in axes:
        ax.axhline(references["paper"], color="k", ls="--", lw=1, label="paper's gains")
        ax.axhline(references["naive"], color="gray", ls=":", lw=1, label="naive start")
        ax.grid(alpha=0.3)
    axes[0].set_xlabel("simulated draw-steps (forward)")
    axes[1].set_xlabel("tuning wall time (s)")
    axes[0].set_ylabel("held-out validation cost (mean)")
    axes[0].set_yscale("log")
    axes[1].legend(fontsize=8)
    fig.suptitle("AFONFTSMC tuned from a naive start: validation cost on held-out draws")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
