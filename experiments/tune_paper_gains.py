"""Reproduce the paper's gains: tune the AFONFTSMC from a naive guess with ``fojax
tune``'s default method, by gradient and by derivative-free baselines, all on the engine
(:mod:`fojax.optimize`), and compare against the paper's gains on held-out draws.

    python -m experiments.tune_paper_gains [--out results/tune_paper_gains]
                                           [--steps 50] [--draws 16] [--horizon 10] ...
                                           [--tiny]   (a seconds-long smoke run)

Protocol (every number in ``docs/tuning.md`` comes from this script):

1. Tuning problem (one :class:`fojax.optimize.Objective`, its programs compiled before
   any tuner runs: no tuner's wall time counts compilation): scenario ``--scenario``
   (2: drag uncertainty, disturbances (53), Gaussian disturbances), reference
   (54)-(55), ``--horizon`` seconds, the cost of :mod:`fojax.optimize.cost` with the CLI
   defaults, ``--draws`` draws per sample of seed ``--seed``; start:
   :func:`fojax.optimize.params.naive_gains`.
2. Tuners (:func:`fojax.optimize.strategies.make`), same problem, same start, each run
   by :func:`fojax.optimize.run`:
    * default (``auto``, ``fojax tune``'s: CMA-ES searches from several starts on fresh
      samples of their own, at the evaluation law; its plan in
      :data:`fojax.optimize.strategies.METHODS`), ``--default-steps`` generations at most,
      with its convergence stop;
   * gradient (``--gradient-method``: ``lbfgs``, quasi-Newton on the fixed sample;
     ``adam``, a fresh sample every step), ``--steps`` steps;
   * CMA-ES (each generation in one batched call, on fresh draws, at the evaluation
     law; its answer the distribution mean) and Nelder-Mead (the fixed sample; its
     answer the best vertex) with ``--df-budget-factor`` times the gradient tuner's
     simulated draw-steps (a gradient step simulates its draws once forward; its
     reverse pass costs a few forward passes more in wall time, which the wall-time
     axis shows).
   The default and the gradient tuner return their best validated answer (their own
   ``--tuner-validation-draws`` validation draws every ``--validate-every`` steps);
   CMA-ES and Nelder-Mead their last. After each run, every step's answer is scored on
   ``--validation-draws`` held-out draws at the tuning horizon (``sat``): not counted
   in any budget or wall time.
3. Evaluation of the paper's, the naive and the four tuned gain sets with the
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
deterministic; wall times aside). The float32 rounding of every rollout depends on the
code and on the instructions XLA picks for the CPU, and a tuner's path amplifies
rounding differences, so every tuned row is reproduced exactly only by the same commit
on the same kind of CPU; ``results.json`` records both.
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
from fojax.cli import output
from fojax.optimize.strategies import METHODS

__all__ = ["main", "unseen_reference"]

VALIDATION_OFFSET = 100_000  # the curves' draws: held-out indices from here on
TUNERS = ("default", "gradient", "cma-es", "nelder-mead")
LEFT_OUT = ("out", "update_doc", "quiet")  # the arguments that are no tuner setting
CELLS = ("{2:.4g} ({0:.2g})", "{2:.4g} ({0:.2g}, {1:.0f} s)", "{2:.4g} ({1:.0f} s)")
"""Convergence cells of a curve point ``(draw-steps, wall time, cost)``: the cost at a
number of draw-steps; at the end or the best, both; at a wall time."""


def unseen_reference(t):
    """A reference not used in tuning: a figure-eight with a climb and a varying yaw.

    ``x_r = 0.8 sin(pi t / 20)``, ``y_r = 0.4 sin(pi t / 10)``,
    ``z_r = 1.5 (1 - cos(pi t / 40))`` (m), ``psi_r = 0.3 + 0.2 sin(pi t / 20)`` (rad).
    Returns ``(4,)``.
    """
    import jax.numpy as jnp

    t = jnp.pi * jnp.asarray(t)
    s = jnp.sin(t / 20.0)
    return jnp.stack(
        [0.8 * s, 0.4 * jnp.sin(t / 10.0), 1.5 * (1.0 - jnp.cos(t / 40.0)), 0.3 + 0.2 * s]
    )


def parse_args(argv) -> argparse.Namespace:
    parser = _common.parser("tune_paper_gains")
    number = functools.partial(_common.add_numbers, parser, int, float)
    number(scenario=2, horizon=(10.0, "tuning horizon (s)"), draws=(16, "draws per sample"))
    number(steps=(50, "gradient steps"), default_steps=METHODS["auto"].steps)
    parser.add_argument("--gradient-method", choices=("lbfgs", "adam"), default="lbfgs")
    number(learning_rate=(None, "Adam's (the method's)"), tuner_validation_draws=32)
    number(max_step=(None, "L-BFGS's (the method's)"))
    number(seed=0)
    parser.add_argument("--dtype", default="float32")
    number(df_budget_factor=3.0, cma_sigma=(None, "CMA-ES's first step (the method's)"),
           validation_draws=32, validate_every=(5, "steps"))
    number(eval_draws=64, eval_horizon=(None, "s (default: each scenario's)"))
    _common.add_outputs(parser, "tune_paper_gains")
    # Cost weights (default: the fojax tune defaults).
    number(effort_weight=None, chattering_weight=None, attitude_weight=None)
    args = parser.parse_args(argv)
    if args.tiny:
        # The small problem of the tests (shares their compiled code).
        vars(args).update(
            horizon=0.3, draws=3, steps=2, default_steps=3, seed=5, dtype="float64",
            effort_weight=1e-3, chattering_weight=1e-3, attitude_weight=2.0,
            validation_draws=2, validate_every=1, eval_draws=2, tuner_validation_draws=2,
        )  # fmt: skip
        args.eval_horizon = args.eval_horizon or 0.3
        args.df_budget_factor = max(args.df_budget_factor, 40.0)
    return args


class _Study:
    """The tuning problem (compiled first), the draws its answers are scored on along
    the way, and the tuners' runs."""

    def __init__(self, args):
        import jax.numpy as jnp

        from fojax import optimize
        from fojax.controllers.afonftsmc import paper_gains

        self.args = args
        weights = ("effort_weight", "chattering_weight", "attitude_weight")
        overrides = {k: getattr(args, k) for k in weights if getattr(args, k) is not None}
        self.spec = optimize.ProblemSpec(
            "afonftsmc", args.scenario, args.horizon, draws=args.draws, seed=args.seed,
            cost=optimize.CostConfig(**overrides), dtype=args.dtype,
        )  # fmt: skip
        dtype = jnp.dtype(args.dtype)
        self.naive = optimize.naive_gains("afonftsmc", dtype)
        self.objective = optimize.Objective(self.spec, self.naive)
        paper = self.objective.vector(paper_gains(dtype))
        self.starts = {"paper": paper, "naive": self.objective.x0}
        self.validation_keys = optimize.draw_keys(
            args.seed, "heldout", args.validation_draws, VALIDATION_OFFSET
        )

    def validate(self, points) -> np.ndarray:
        return _common.mean_costs(self.objective, points, self.validation_keys)

    def compile(self) -> float:
        """Compile the objective's programs (the forward evaluation, the gradient) first,
        so that no tuner's wall time counts them; the seconds it took."""
        t0 = time.perf_counter()
        self.objective.compile("gradient", 1.0)
        self.validate([self.objective.x0])
        return time.perf_counter() - t0

    def run(self, name: str, budget: int | None = None) -> dict:
        """Tuner ``name`` (module docstring) from the naive start, within ``budget``
        draw-steps (the derivative-free tuners) or its steps: its record as JSON: its
        answer ``x`` and gains, its curve points ``(method, draw-steps, wall time,
        validation cost)`` and what it spent (``summary``)."""
        from fojax import optimize
        from fojax.controllers import gains_io
        from fojax.optimize import strategies

        args = self.args
        method, steps, validation_draws = {
            "default": ("auto", args.default_steps, args.tuner_validation_draws),
            "gradient": (args.gradient_method, args.steps, args.tuner_validation_draws),
        }.get(name, (name, None, 0))
        given = dict(sigma=args.cma_sigma, max_step=args.max_step, learning_rate=args.learning_rate)
        options = {k: v for k, v in given.items() if v is not None and k in METHODS[method].options}
        problem = strategies.Problem(self.objective, self.objective.x0, args.seed)
        strategy = strategies.make(method, problem, steps, **options)
        method_table = METHODS[method]
        patience = method_table.patience if validation_draws else None
        limit = optimize.Budget(steps=steps, draw_steps=budget, patience=patience,
                                tolerance=method_table.tolerance)  # fmt: skip
        spent = ", ".join(f"{v} {k}" for k, v in dataclasses.asdict(limit).items() if v)
        output.log(args.quiet, f"{name}: {spent}")
        result, record = _common.recorded_run(
            self.objective, strategy, limit, self.objective.x0, progress=not args.quiet,
            validation_draws=validation_draws, validate_every=args.validate_every,
        )  # fmt: skip
        costs = self.validate([answer for *_, answer in record])
        return {
            "x": np.asarray(result.x).tolist(),
            "gains": gains_io.gains_to_dict(self.objective.gains(result.x)),
            "curve": [
                [name, d, w, float(c)] for (_, w, d, _), c in zip(record, costs, strict=True)
            ],
            "summary": {
                "draw_steps": result.draw_steps,
                "wall_time_s": result.wall_time_s,
                "steps": result.steps,
                "evaluations": sum(row["points"] for row in result.history),
                "final_loss": result.history[-1]["loss"],
                "method": method,
                "returned_step": result.returned_step,
                "validation": result.validation,
            },
        }


def run_tuners(args, study: _Study) -> dict:
    """Each tuner's record, kept under its fingerprint in ``--out/runs`` (a study started
    again reuses the tuners that finished): the gradient tuner and the default, then
    CMA-ES and Nelder-Mead with ``--df-budget-factor`` times the gradient's draw-steps."""
    fingerprint = _common.settings(args, leave_out=LEFT_OUT) | {"engine": "fojax.optimize"}
    found, budget = {}, None
    for name in ("gradient", "default", "cma-es", "nelder-mead"):
        if name == "cma-es":
            budget = int(args.df_budget_factor * found["gradient"]["summary"]["draw_steps"])
            fingerprint = fingerprint | {"budget": budget}
        run = functools.partial(study.run, name, budget)
        found[name] = _common.cached(args.out / "runs", name, fingerprint, run)
    return {name: found[name] for name in TUNERS}


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


def evaluate(args, study: _Study, points: dict) -> dict:
    """Every gain set (``points``: name -> parameters) on the held-out draws of the
    tuning scenario, of the unseen reference and of scenario 3, each at its full horizon
    (or ``--eval-horizon``)."""
    from fojax import scenarios

    tuned_scenario = scenarios.get_scenario(args.scenario)
    settings = {
        f"scenario {args.scenario}": None,  # the objective's own
        "unseen reference": dataclasses.replace(tuned_scenario, reference=unseen_reference),
        "scenario 3": scenarios.get_scenario(3),
    }
    keys = study.objective.keys("heldout", args.eval_draws)
    evaluation = {}
    for label, scenario in settings.items():
        horizon = args.eval_horizon or (scenario or tuned_scenario).horizon
        t0 = time.perf_counter()
        costs = {
            name: _common.draw_costs(study.objective, x, keys, horizon, scenario)
            for name, x in points.items()
        }
        base = costs["paper"].cost
        evaluation[label] = {
            "horizon_s": horizon,
            "draws": args.eval_draws,
            "gains": {n: _cost_entry(c, None if n == "paper" else base) for n, c in costs.items()},
        }
        output.log(args.quiet, f"evaluated {label} ({time.perf_counter() - t0:.0f} s)")
    return evaluation


def _by_method(curves) -> dict:
    """The points ``(draw-steps, wall time, validation cost)`` of each method's curve
    (``curves``: rows ``(method, draw-steps, wall time, validation cost)``), in order."""
    by_method = {}
    for method, *point in curves:
        by_method.setdefault(method, []).append(tuple(point))
    return by_method


def reaches(curves: list, challenger: str = "gradient") -> dict:
    """Where ``challenger`` first reaches each derivative-free tuner's best."""
    by_method = _by_method(curves)
    reach = {}
    for method in ("cma-es", "nelder-mead"):
        best = min(v for _, _, v in by_method[method])
        first = next(((s, w) for s, w, v in by_method[challenger] if v <= best), (None, None))
        reach[method] = {
            "best_validation_cost": best,
            "draw_steps_used": max(s for s, _, _ in by_method[method]),
            f"{challenger}_draw_steps_to_reach": first[0],
            f"{challenger}_wall_time_to_reach_s": first[1],
        }
    return reach


def main(argv=None) -> int:
    """Tune, evaluate and write ``results.json``, ``table.md``, ``curves.csv``,
    ``tuning.png``; the document's block with ``--update-doc``."""
    args = parse_args(argv)
    _common.enable_float64(args.dtype == "float64")
    from fojax.controllers import gains_io

    start_all = time.perf_counter()
    provenance = output.run_context(["python", "-m", "experiments.tune_paper_gains", *(argv or [])])
    study = _Study(args)
    compile_s = study.compile()
    output.log(args.quiet, f"compiled the tuning cost and its gradient ({compile_s:.0f} s)")
    paper, naive = study.validate([study.starts["paper"], study.starts["naive"]])
    references = {"paper": float(paper), "naive": float(naive)}
    output.log(args.quiet, f"validation cost: paper {paper:.4g}, naive {naive:.4g}")
    tuners = run_tuners(args, study)
    curves = [[method, 0, 0.0, references["naive"]] for method in TUNERS]
    curves += [c for r in tuners.values() for c in r["curve"]]
    points = dict(study.starts) | {name: np.asarray(r["x"]) for name, r in tuners.items()}
    evaluation = evaluate(args, study, points)
    validation = {"draws": args.validation_draws, "horizon_s": study.spec.horizon}
    gains = {"paper": gains_io.gains_to_dict(study.objective.gains(study.starts["paper"]))}
    gains["naive"] = gains_io.gains_to_dict(study.naive)
    results = {
        "problem": study.spec.as_dict(),
        "tuner_settings": _common.settings(args, leave_out=LEFT_OUT),
        "validation": validation | {"switching": "sat", **references},
        "tuners": {name: r["summary"] for name, r in tuners.items()},
        "gradient_reaches": reaches(curves),
        "default_reaches": reaches(curves, "default"),
        "evaluation": evaluation,
        "gains": gains | {name: r["gains"] for name, r in tuners.items()},
        "compile_time_s": round(compile_s, 1),
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
        "provenance": provenance,
        "curves": curves,
    }
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "curves.csv", "w", newline="") as handle:
        header = ("method", "draw_steps", "wall_time_s", "validation_cost")
        csv.writer(handle).writerows([header, *curves])
    results["provenance"]["load_average_end"] = output.load_average()
    plot(curves, references, out / "tuning.png")
    doc_text = None
    if args.update_doc is not None:
        shutil.copyfile(out / "tuning.png", args.update_doc.parent / "tuning.png")
        doc_text = report(results)
    wrote = f", curves.csv, tuning.png ({results['total_wall_time_s']:.0f} s in all)"
    text = table(results)
    return _common.finish(out, results, text, args.update_doc, "tune-paper-gains", doc_text, wrote)


def _minus_paper(cost: dict) -> str:
    share = f", better on {100 * cost['better_than_paper_fraction']:.0f} %"
    return _common.difference_cell(cost["minus_paper"], lambda low, high: share)


def table(results: dict) -> str:
    """Markdown tables: held-out costs per gain set, and the tuners' budgets."""
    evaluation = results["evaluation"]
    labels = list(evaluation)
    gains = [evaluation[label]["gains"] for label in labels]
    names = list(gains[0])
    columns = " | ".join(f"{label} ({evaluation[label]['horizon_s']:g} s)" for label in labels)
    lines = _common.table_head(f"gains | {columns} | tuning draw-steps | tuning wall time (s)")
    for name in names:
        cells = [_common.mean_cell(g[name], "div.") for g in gains]
        spent = results["tuners"].get(name, {})
        cells += [spent.get(key, "-") for key in ("draw_steps", "wall_time_s")]
        lines.append(f"| {name} | " + " | ".join(map(str, cells)) + " |")
    columns = " | ".join(f"{label}: minus paper (95 % CI)" for label in labels)
    lines += ["", *_common.table_head(f"gains | {columns}")]
    for name in [n for n in names if n != "paper"]:
        cells = [_minus_paper(g[name]["cost"]) for g in gains]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _curve_at(points, limit, key):
    """The last curve point with ``key`` (0: draw-steps, 1: wall time) <= ``limit``."""
    inside = [p for p in points if p[key] <= limit]
    return inside[-1] if inside else None


def _convergence(method: str, points: list, budget, wall_time) -> str:
    """The convergence table's row of ``method`` (``points``: its curve, sorted): at half
    and all of the gradient's draw-steps ``budget``, at the end, at its best point and at
    the gradient's ``wall_time``."""
    by_wall = sorted(points, key=lambda q: q[1])
    at = (
        (_curve_at(points, budget / 2, 0), CELLS[0]),
        (_curve_at(points, budget, 0), CELLS[0]),
        (points[-1], CELLS[1]),
        (min(points, key=lambda q: q[2]), CELLS[1]),
        (_curve_at(by_wall, wall_time, 1), CELLS[2]),
    )
    cells = ("-" if point is None else text.format(*point) for point, text in at)
    return f"| {method} | " + " | ".join(cells) + " |"


def report(results: dict) -> str:
    """The generated part of docs/tuning.md's section: the run, the tables, the
    convergence and the cost terms."""
    p = results["provenance"]
    tuners = results["tuners"]
    validation = results["validation"]
    label, first = next(iter(results["evaluation"].items()))
    start, end = (p[k][0] if p.get(k) else "n/a" for k in ("load_average", "load_average_end"))
    terms = ", ".join(
        f"{name} " + " / ".join(f"{t:.3g}" for t in entry["terms_mean"])
        for name, entry in first["gains"].items()
    )
    g = tuners["gradient"]
    convergence = [
        _convergence(method, sorted(points), g["draw_steps"], g["wall_time_s"])
        for method, points in _by_method(results["curves"]).items()
    ]
    return "\n".join(
        [
            f"Run: `{p['command']}`; commit {output.commit_label(p)}, JAX {p['jax']} / jaxlib "
            f"{p['jaxlib']}, {p.get('cpu_model')}, {p['cpu_count']} cores, load average "
            f"{start} at the start and {end} at the end; {results['total_wall_time_s']:.0f} s "
            f"in all, of which {results['compile_time_s']:.0f} s compiling the tuning cost and "
            "its gradient. Each tuner's wall time as it ran (validation included; a tuner kept "
            "in `--out/runs` with the same settings is reused, not run again): "
            + ", ".join(
                f"{tuners[n]['wall_time_s']:.0f} s {n} ({tuners[n]['method']})" for n in TUNERS
            )
            + ".",
            "",
            *(
                f"The {name} tuner returned the gains of step {tuners[name]['returned_step']} of "
                f"{tuners[name]['steps']} (validation cost {v['best']['cost']:.4g}; "
                f"{v['initial']['cost']:.4g} at the start, {v['final']['cost']:.4g} at the last "
                "step)."
                for name in ("default", "gradient")
                if (v := tuners[name].get("validation"))
            ),
            "",
            f"**Held-out cost** (mean ± 95 % half-width over {first['draws']} draws), paired "
            "differences against the paper's gains:",
            "",
            table(results),
            "",
            f"Mean terms on {label} ({first['horizon_s']:g} s), `P` / `A` / `E` / `C`: {terms}.",
            "",
            f"**Convergence** (validation cost: {validation['draws']} held-out draws, "
            f"{validation['horizon_s']:g} s, `sat`; paper {validation['paper']:.4g}, naive "
            f"{validation['naive']:.4g}):",
            "",
            *_common.table_head(
                "method | at half the gradient's draw-steps | at the gradient's draw-steps | at "
                "the end | best point | at the gradient's wall time"
            ),
            *convergence,
            "",
            "(draw-steps and tuning wall time, compilation excluded, in parentheses.)",
        ]
    )


def plot(curves, references, path: Path) -> None:
    from fojax.cli import style

    plt = style.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    colors = dict(zip(TUNERS, ("C3", "C0", "C1", "C2"), strict=True))
    for method, points in _by_method(curves).items():
        s, w, v = (np.asarray(x, float) for x in zip(*sorted(points), strict=True))
        for ax, x in zip(axes, (s, w), strict=True):
            ax.plot(x, v, "o-", color=colors[method], ms=3, label=method)
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
