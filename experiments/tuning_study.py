"""The tuning study in wall time: gradient tuner, batched CMA-ES and Nelder-Mead.

    python -m experiments.tuning_study [--out results/tuning_study]
                                       [--update-doc docs/tuning.md] [--tiny]

Held-out cost against wall time (compilation included) and against simulated
draw-steps, for the gradient tuner (:mod:`fojax.optimize.tuner`), CMA-ES with every
generation evaluated in one batched, compiled call (:func:`fojax.optimize.derivative_free.cma_es`)
and Nelder-Mead (:func:`fojax.optimize.derivative_free.nelder_mead`), from the paper's gains
and from the naive start (:func:`fojax.optimize.params.naive_gains`), with 33 parameters
(``--share paper``) and 66 (``--share none``), over ``--seeds`` (the tuning draws'
seed, and CMA-ES's sampling seed).

Protocol (the defaults; every number of the study's section of ``docs/tuning.md``):

* Problem: scenario 2, 10 s, the default cost (:class:`fojax.optimize.cost.CostConfig`),
  mean objective, float32, seed ``s``.
* Gradient tuner: ``--gradient-method`` (``lbfgs``: quasi-Newton on one fixed sample
  of ``--gradient-draws`` draws at the final switching width; ``adam``: fresh
  minibatches, the ``fojax tune`` defaults), ``--gradient-steps`` evaluations of the
  objective and its gradient, its own validation (``--validation-draws`` validation
  draws, ``sat``, every ``--validate-every`` steps; it returns the best validated
  iterate), counted in its wall time.
* CMA-ES: ``--cma-generations`` generations of the ``cma`` package's default
  population, ``--df-draws`` fresh draws per generation shared by its candidates,
  step 0.5, the answer is the distribution mean; switching width x1.
* Nelder-Mead: ``--df-draws`` fixed draws, as many evaluations as CMA-ES's budget of
  draw-steps, the answer is the best point; initial simplex ``u0 + 0.5 e_i``.
* Held-out cost: each method's current answer (gradient: the best validated so far;
  CMA-ES: the mean; Nelder-Mead: the best point) on ``--heldout-draws`` held-out draws
  (indices ``2^31 + j`` of seed 0, the same for every run; never seen by any tuner),
  10 s, ``sat`` switching; not counted in any wall time.
* Wall time, compilation included: each method's functions are compiled once per
  parameter count, before its first run, and that compile time (first call minus a
  second call of the same function; for the gradient tuner, as the tuner schedules it:
  its gradient alone, then its validation compiled in a thread beside the next steps,
  counted as what it adds to those steps' wall time) is added to every one of its
  curves. XLA's
  persistent compilation cache is off. One process, one XLA device, runs one after
  another; the load average is recorded before and after each run.

Each finished run is kept in ``--out/runs/`` under its fingerprint, the settings it
depends on (:data:`BY_METHOD`; :func:`fojax.records.cached`): an interrupted study
continues where it stopped, a run is never reused for other settings, and variants of
one tuner share the other tuners' runs in one ``--out`` (``--gradient-draws 64`` reuses
the CMA-ES runs). ``results.json``, ``table.md`` and the figures ``tuning_wall.png`` and
``tuning_draw_steps.png`` summarise them. ``--update-doc FILE`` replaces the block
between ``<!-- tuning-study:begin -->`` and ``<!-- tuning-study:end -->`` of FILE and
copies the figures beside it.
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import sys
import time

import numpy as np

from experiments import _common, tuning_study_user
from experiments.tuning_study_report import METHODS, plot, summarize, table
from fojax import records as kept
from fojax.cli import arguments, output

__all__ = ["main", "summarize", "table"]


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("tuning_study")
    parser.add_argument("--scenario", type=int, choices=(1, 2, 3), default=2)
    _common.add_numbers(parser, horizon=10.0)
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated (0,1,2)")
    parser.add_argument("--shares", default="paper,none", help="comma-separated (paper,none)")
    parser.add_argument("--starts", default="paper,naive", help="comma-separated (paper,naive)")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--gradient-method", choices=("lbfgs", "adam"), default="lbfgs")
    _common.add_numbers(parser, gradient_steps=30, gradient_draws=16, learning_rate=0.1)
    _common.add_numbers(parser, max_step=1.0, validation_draws=32, validate_every=2)
    _common.add_numbers(parser, cma_generations=20, cma_sigma=0.5, df_draws=16, heldout_draws=64)
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument(
        "--compile", choices=("optimized", "fast"), default="optimized", help="tuning functions"
    )
    _common.add_outputs(parser, "tuning_study", smoke=False)
    parser.add_argument(
        "--report-only", action="store_true", help="summarise the stored runs, run nothing"
    )
    parser.add_argument(
        "--bench",
        type=arguments.nonnegative_int,
        default=0,
        metavar="N",
        help="also time N generations of CMA-ES evaluated in one batched call against one "
        "call per candidate (interleaved; medians), kept in --out/bench_<share>-*.json",
    )
    parser.add_argument(
        "--user-view",
        type=arguments.nonnegative_int,
        default=0,
        metavar="N",
        help="also run `fojax tune --scenario 2 --init paper` N times per --compile mode, "
        "each in a fresh process (compilation included), stored in --out/user_view/",
    )
    _common.add_numbers(parser, user_steps=6)
    _common.add_smoke(parser)
    return parser


def parse_args(argv) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.seeds = tuple(int(s) for s in args.seeds.split(",") if s.strip())
    except ValueError:
        parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
    args.shares, args.starts = _common.listed(args.shares), _common.listed(args.starts)
    args.methods = _common.listed(args.methods)
    for label, values, valid in (
        ("--shares", args.shares, ("paper", "none")),
        ("--starts", args.starts, ("paper", "naive")),
        ("--methods", args.methods, METHODS),
    ):
        if not values or any(v not in valid for v in values):
            parser.error(f"{label} must be among {', '.join(valid)}, got {','.join(values)}")
    if args.tiny:
        args.horizon, args.gradient_draws, args.df_draws = 0.3, 3, 3
        args.gradient_steps, args.cma_generations, args.heldout_draws = 4, 2, 4
        args.validation_draws, args.validate_every = 2, 2
        args.seeds, args.dtype = args.seeds[:1], "float64"
    return args


def _compile_time(fn) -> float:
    """The compile time of ``fn``: its first call less a second call."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return max(first - (time.perf_counter() - t0), 0.0)


def _tuner_compile_time(step, validation) -> float:
    """The gradient tuner's compile time, scheduled as :func:`fojax.optimize.tuner.tune`
    schedules it: the gradient compiles alone (its first call less a second), then the
    validation run compiles in a thread beside the next steps. What that thread adds is
    the wall time of the steps run beside it less the same number of steps alone and
    one validation run."""
    import threading

    import jax

    first = _compile_time(step)
    thread = threading.Thread(target=lambda: jax.block_until_ready(validation()))
    t0 = time.perf_counter()
    thread.start()
    steps = 0
    while thread.is_alive():
        jax.block_until_ready(step())
        steps += 1
    thread.join()
    beside = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(steps):
        jax.block_until_ready(step())
    jax.block_until_ready(validation())
    return first + max(beside - (time.perf_counter() - t0), 0.0)


class _Setup:
    """One parameter count: the problem, compiled once, and each method's compile time."""

    def __init__(self, args, share: str):
        import jax.numpy as jnp

        from fojax.optimize import cost as cost_lib
        from fojax.optimize import draw_keys
        from fojax.optimize import params as params_lib
        from fojax.optimize import problem as problem_lib

        self.args = args
        tiny = {"effort_weight": 1e-3, "chattering_weight": 1e-3, "attitude_weight": 2.0}
        cost = cost_lib.CostConfig(**(tiny if args.tiny else {}))
        self.spec = problem_lib.ProblemSpec(
            controller="afonftsmc",
            scenario=args.scenario,
            horizon=args.horizon,
            draws=args.gradient_draws,
            seed=0,
            cost=cost,
            share=share,
            dtype=args.dtype,
            compile=args.compile,
        )
        dtype = jnp.dtype(args.dtype)
        self.naive = params_lib.naive_gains("afonftsmc", dtype)
        self.problem = problem_lib.TuningProblem(self.spec, self.naive)
        self.heldout_keys = draw_keys(0, "heldout", args.heldout_draws)
        self.compile_s: dict[str, float] = {}

        problem = self.problem
        params = problem.initial_params()
        grad_keys = problem.minibatch_keys(0, args.gradient_draws)
        df_keys = problem.minibatch_keys(0, args.df_draws)
        validation_keys = problem.validation_keys(args.validation_draws)
        vectors = np.repeat(problem.vector(params)[None], self.popsize, axis=0)
        if "gradient" in args.methods:
            self.compile_s["gradient"] = _tuner_compile_time(
                lambda: problem.value_and_grad(params, 1.0, grad_keys).objective,
                lambda: problem_lib.evaluate(self.spec, self.naive, validation_keys).cost,
            )
        if "cma-es" in args.methods:
            self.compile_s["cma-es"] = _compile_time(
                lambda: problem.batch_value(vectors, 1.0, df_keys)[0]
            )
        if "nelder-mead" in args.methods:
            self.compile_s["nelder-mead"] = _compile_time(
                lambda: problem.value(params, 1.0, df_keys).objective
            )
        self.heldout(self.naive)  # compiles the held-out evaluation (not counted)

    @property
    def popsize(self) -> int:
        return 4 + int(3 * np.log(self.problem.param_map.size))

    def heldout(self, gains) -> float:
        from fojax.optimize import problem as problem_lib

        costs = problem_lib.evaluate(self.spec, gains, self.heldout_keys)
        return float(np.mean(np.asarray(costs.cost, np.float64)))

    def start(self, name: str):
        import jax.numpy as jnp

        from fojax.controllers.afonftsmc import paper_gains

        return paper_gains(jnp.dtype(self.args.dtype)) if name == "paper" else self.naive


def bench_batched(setup: _Setup, repeats: int) -> dict:
    """Wall time of one CMA-ES generation (the population on the same draws): one
    batched call against one call per candidate, interleaved, ``repeats`` times each;
    and the largest relative difference of their costs."""
    import jax

    args = setup.args
    problem = setup.problem
    rng = np.random.default_rng(0)
    start = problem.vector(problem.initial_params())
    candidates = start + 0.5 * rng.normal(size=(setup.popsize, start.size))
    keys = problem.minibatch_keys(0, args.df_draws)
    jax.block_until_ready(problem.batch_value(candidates, 1.0, keys))  # compiled first
    jax.block_until_ready(problem.value(problem.unravel(candidates[0]), 1.0, keys))
    batched, alone = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        together = np.asarray(jax.block_until_ready(problem.batch_value(candidates, 1.0, keys)[0]))
        batched.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        separate = np.asarray(
            [float(problem.value(problem.unravel(x), 1.0, keys).objective) for x in candidates]
        )
        alone.append(time.perf_counter() - t0)
    return {
        "share": setup.spec.share,
        "parameters": problem.param_map.size,
        "population": setup.popsize,
        "draws": args.df_draws,
        "horizon_s": args.horizon,
        "batched_s": batched,
        "one_at_a_time_s": alone,
        "median_batched_s": float(np.median(batched)),
        "median_one_at_a_time_s": float(np.median(alone)),
        "largest_relative_difference": float(np.max(np.abs(together - separate) / separate)),
        "load": output.load_average(),
    }


def run_one(setup: _Setup, start: str, seed: int, method: str) -> dict:
    """One tuning run; returns its curve (draw-steps, wall time without compilation,
    held-out cost of the current answer) and totals."""
    import copy
    import dataclasses

    problem = copy.copy(setup.problem)  # the same compiled functions, another seed
    problem.spec = dataclasses.replace(setup.spec, seed=seed)
    init = setup.start(start)
    x0 = problem.params_of(init)
    curve = [(0, 0.0, setup.heldout(init))]
    load_before = output.load_average()
    t0 = time.perf_counter()
    if method == "gradient":
        totals, gains = _run_gradient(setup, problem, init, start, curve)
    else:
        totals, gains = _run_derivative_free(setup, problem, method, seed, x0, curve)
    final = setup.heldout(gains)
    if curve[-1][0] != totals["draw_steps"] or curve[-1][2] != final:
        curve.append((totals["draw_steps"], totals["wall_time_s"], final))
    return {
        "start": start,
        "seed": seed,
        "method": method,
        "share": setup.spec.share,
        "parameters": setup.problem.param_map.size,
        "compile_s": round(setup.compile_s[method], 2),
        "curve": [[int(s), round(float(w), 3), float(c)] for s, w, c in curve],
        "final_heldout": final,
        "initial_heldout": curve[0][2],
        "load_before": load_before,
        "load_after": output.load_average(),
        "elapsed_s": round(time.perf_counter() - t0, 1),
        "git_commit": output.commit_label(full=True),
        **totals,
    }


def _run_gradient(setup: _Setup, problem, init, start: str, curve: list):
    """The gradient tuner from ``init``; appends its answers' held-out costs to
    ``curve``; returns its totals and gains."""
    from fojax.optimize import tuner as tuner_lib

    args = setup.args
    config = _common.tuner_config(
        args, args.gradient_steps, args.validation_draws, checkpoint_every=10**6
    )
    run = tuner_lib.prepare(problem.spec, config, init, start, None)

    def on_step(step, params, row):
        if row["validation_cost"] is not None:
            best = row["best_step"] == step
            cost = setup.heldout(problem.gains(params)) if best else curve[-1][2]
            curve.append((row["draw_steps"], row["wall_time_s"], cost))

    result = tuner_lib.tune(run, progress=False, callback=on_step, problem=problem)
    last = result.history[-1]
    totals = {
        "draw_steps": last["draw_steps"],
        "wall_time_s": last["wall_time_s"],
        "steps": result.completed,
        "best_step": result.best_step,
        "validation": result.validation,
    }
    return totals, result.gains


def _run_derivative_free(setup: _Setup, problem, method: str, seed: int, x0, curve: list):
    """CMA-ES or Nelder-Mead from ``x0`` with the study's budget of draw-steps; appends
    its answers' held-out costs to ``curve``; returns its totals and gains."""
    from fojax.optimize import derivative_free

    args = setup.args
    every = {"n": 0}

    def record(draw_steps, params, row):
        every["n"] += 1
        if method == "nelder-mead" or every["n"] % 2 == 0:
            curve.append((draw_steps, row["wall_time_s"], setup.heldout(problem.gains(params))))

    per_evaluation = args.df_draws * problem.spec.steps
    budget = args.cma_generations * setup.popsize * per_evaluation
    if method == "cma-es":
        result = derivative_free.cma_es(
            problem,
            budget,
            draws_per_candidate=args.df_draws,
            sigma0=args.cma_sigma,
            seed=seed,
            callback=record,
            x0=x0,
        )
    else:  # at least the initial simplex and one generation more
        budget = max(budget, (problem.param_map.size + 1 + setup.popsize) * per_evaluation)
        result = derivative_free.nelder_mead(
            problem,
            budget,
            draws=args.df_draws,
            callback=record,
            callback_every=setup.popsize,
            x0=x0,
        )
    totals = {
        "draw_steps": result.draw_steps,
        "wall_time_s": round(result.wall_time_s, 3),
        "evaluations": result.evaluations,
    }
    return totals, result.gains


COMMON = ("scenario", "horizon", "dtype", "compile", "tiny", "heldout_draws", "validation_draws")
BY_METHOD = {
    "gradient": ("gradient_method", "gradient_steps", "gradient_draws", "learning_rate",
                 "max_step", "validate_every"),
    "cma-es": ("cma_generations", "cma_sigma", "df_draws"),
    "nelder-mead": ("cma_generations", "df_draws"),
}  # fmt: skip
"""The settings a run depends on (its fingerprint), besides its share, start and seed."""


COMPILE_ACCOUNTING = {"gradient": "validation compiled beside the steps"}
"""How a method's compile time is counted, where it has changed (part of its runs'
fingerprints: runs counted the earlier way are not reused)."""


def run_fingerprint(args, share: str, start: str, seed: int, method: str) -> dict:
    names = COMMON + BY_METHOD[method]
    fingerprint = {k: getattr(args, k) for k in names} | dict(share=share, start=start, seed=seed)
    if method in COMPILE_ACCOUNTING:
        fingerprint["compile_accounting"] = COMPILE_ACCOUNTING[method]
    return fingerprint


def _bench_fingerprint(args, share: str) -> dict:
    """What the batched-generation bench depends on (not how many generations it times)."""
    return {k: getattr(args, k) for k in COMMON + BY_METHOD["cma-es"]} | {"share": share}


def _stored_run(args, share, start, seed, method) -> dict | None:
    fingerprint = run_fingerprint(args, share, start, seed, method)
    return kept.stored(args.out / "runs", f"{share}_{start}_{seed}_{method}", fingerprint)


def run_share(args, share: str, settings: dict) -> None:
    """The runs (and the bench) of one parameter count that are not stored yet (each
    kept under its fingerprint: :func:`fojax.records.cached`)."""
    cases = itertools.product(args.starts, args.seeds, args.methods)
    pending = [case for case in cases if _stored_run(args, share, *case) is None]
    bench_fingerprint = _bench_fingerprint(args, share)
    bench_done = kept.stored(args.out, f"bench_{share}", bench_fingerprint) is not None
    if not pending and (not args.bench or bench_done):
        return
    t0 = time.perf_counter()
    setup = _Setup(args, share)
    output.log(
        args.quiet,
        f"share={share}: {setup.problem.param_map.size} parameters, compiled in "
        f"{time.perf_counter() - t0:.0f} s ({setup.compile_s})",
    )
    if args.bench and not bench_done:
        bench = kept.cached(
            args.out, f"bench_{share}", bench_fingerprint, lambda: bench_batched(setup, args.bench)
        )
        output.log(
            args.quiet,
            f"  batched generation {bench['median_batched_s']:.2f} s, one at a "
            f"time {bench['median_one_at_a_time_s']:.2f} s (medians)",
        )
    for start, seed, method in pending:
        fingerprint = run_fingerprint(args, share, start, seed, method)
        record = kept.cached(
            args.out / "runs", f"{share}_{start}_{seed}_{method}", fingerprint,
            lambda case=(start, seed, method): run_one(setup, *case) | {"settings": settings},
        )  # fmt: skip
        output.log(
            args.quiet,
            f"  {share} {start} seed {seed} {method}: held-out "
            f"{record['initial_heldout']:.4g} -> {record['final_heldout']:.4g}, "
            f"{record['wall_time_s']:.0f} s + {record['compile_s']:.0f} s compile, "
            f"load {record['load_before']} -> {record['load_after']}",
        )


def report(args, settings: dict, start_all: float) -> int:
    """``results.json``, ``table.md`` and the figures from the stored runs of the
    selected shares, starts, seeds and methods; the document's block with ``--update-doc``."""
    out = args.out
    users = tuning_study_user.records(args, out, run=not args.report_only)
    cases = itertools.product(args.shares, args.starts, args.seeds, args.methods)
    records = [r for r in (_stored_run(args, *case) for case in cases) if r is not None]
    if not records:
        raise SystemExit(
            f"{out / 'runs'} holds no run made with these settings (runs are kept under the "
            "settings they depend on); run without --report-only, or give the settings "
            "the runs were made with"
        )
    benches = [kept.stored(out, f"bench_{s}", _bench_fingerprint(args, s)) for s in args.shares]
    results = {
        "user_view": users,
        "bench": [bench for bench in benches if bench is not None],
        "settings": settings,
        "summary": summarize(records),
        "runs": records,
        # The commit that ran the runs (a --report-only later may stand elsewhere).
        "git_commit": ", ".join(sorted({r.get("git_commit", "unknown") for r in records}))
        or output.commit_label(full=True),
        "this_invocation_s": round(time.perf_counter() - start_all, 1),
        "runs_elapsed_s": round(sum(r["elapsed_s"] for r in records), 1),
    }
    figures = [
        plot(records, out / "tuning_wall.png", "wall"),
        plot(records, out / "tuning_draw_steps.png", "draw_steps"),
    ]
    if args.update_doc is not None:
        for figure in figures:
            shutil.copyfile(figure, args.update_doc.parent / figure.name)
    wrote = ", tuning_wall.png, tuning_draw_steps.png"
    return _common.finish(
        out, results, table(results), args.update_doc, "tuning-study", None, wrote
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    _common.enable_float64(args.dtype == "float64")
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    start_all = time.perf_counter()
    settings = _common.settings(args)
    if not args.report_only:
        for share in args.shares:
            run_share(args, share, settings)
    return report(args, settings, start_all)


if __name__ == "__main__":
    sys.exit(main())
