"""The tuning race in wall time: ``fojax tune``'s default method against L-BFGS, CMA-ES
and Nelder-Mead, every one on the engine (:mod:`fojax.optimize`).

    python -m experiments.tuning_study [--out results/tuning_study]
                                       [--update-doc docs/tuning.md] [--tiny]

Held-out cost against wall time (compilation included, as a user waits) and against
simulated draw-steps, from the paper's gains and from the naive start
(:func:`fojax.optimize.params.naive_gains`), with 33 parameters (``--share paper``) and
66 (``--share none``), over ``--seeds`` (the tuning draws' seed, and CMA-ES's
sampling seed).

Protocol (the defaults; every number of the study's section of ``docs/tuning.md``):

* Problem: the AFONFTSMC on scenario 2, 10 s, the default cost
  (:class:`fojax.optimize.CostConfig`), mean objective, ``--draws`` 16 draws per
  sample, float32, seed ``s``, the tuners at the simulator's 1 ms step (``--dt`` another;
  held-out costs stay at 1 ms).
* Methods (:func:`fojax.optimize.strategies.make`, the rows): ``default`` (``auto``, the
  ``fojax tune`` default: CMA-ES on small fresh samples, ``--default-steps``
  generations), ``lbfgs``
  (``--gradient-steps`` steps on the fixed sample), ``cma-es`` (``--cma-generations``
  generations of ``4 + floor(3 ln d)`` candidates on fresh draws, step
  ``--cma-sigma``) and ``nelder-mead`` (CMA-ES's budget of draw-steps, at least the
  initial simplex and one generation more).
* Each run builds a fresh :class:`fojax.optimize.Objective`, so its wall time includes
  the compilation of its own programs exactly as a user waits (XLA's persistent
  compilation cache, and with it fojax's export cache, is off), and runs the driver
  (:func:`fojax.optimize.run`): ``--validation-draws`` validation draws as the driver
  schedules them (by the work since the last validation; ``--validate-every``: every so
  many steps), its answer the best validated one.
* Curve: the driver's callback records every step's ``(step, wall time, draw-steps,
  answer)``; after the run (nothing runs beside it) the held-out cost of each distinct
  answer: ``--heldout-draws`` held-out draws (indices ``2^31 + j`` of seed 0, the same
  for every run, never seen by a tuner), 10 s, ``sat``, on an objective of its own
  compiled once per share. The final held-out cost is that of the run's returned
  (best validated) answer.
* Target: per (share, start, seed), whether the default (and L-BFGS) reaches CMA-ES's
  best held-out cost (the minimum over CMA-ES's curve) within half of CMA-ES's wall
  time, and whether its final held-out cost is at or below it
  (:func:`experiments.tuning_study_report.summarize`).

One process, one XLA device per core (``fojax tune`` runs on one device whose kernels
are threaded over the cores; the user view measures the command as it runs), its lanes
per device fitted to each method's requests (:func:`fojax.optimize.strategies.lanes`), runs one
after another; the load average is recorded before and after each run. ``--tiny`` (a
smoke run) keeps the caller's compilation cache and shares each seed's objective between
the runs of a share (its wall times mean nothing).

Each finished run is kept in ``--out/runs/`` under its fingerprint, the settings it
depends on (:data:`BY_METHOD`; :func:`experiments._common.cached`): an interrupted study
continues where it stopped, a run is never reused for other settings, and variants of
one method share the other methods' runs in one ``--out``. ``results.json``,
``table.md`` and the figures ``tuning_wall.png`` and ``tuning_draw_steps.png``
summarise them. ``--update-doc FILE`` replaces the block between
``<!-- tuning-study:begin -->`` and ``<!-- tuning-study:end -->`` of FILE and copies the
figures beside it.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import shutil
import sys
import time

import numpy as np

from experiments import _common, tuning_study_user
from experiments.tuning_study_report import METHODS, plot, summarize, table
from fojax.cli import arguments, output
from fojax.optimize.strategies import DEFAULT_STEPS

__all__ = ["METHODS", "main", "summarize", "table"]


CHOICES = {"shares": ("paper", "none"), "starts": ("paper", "naive"), "methods": METHODS}


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("tuning_study")
    parser.add_argument("--scenario", type=int, choices=(1, 2, 3), default=2)
    step = (1e-3, "the tuners' step (s); held-out costs stay at 1 ms")
    _common.add_numbers(parser, horizon=10.0, draws=16, dt=step)
    for name, default in (("seeds", "0,1,2"), ("shares", "paper,none"), ("starts", "paper,naive")):
        parser.add_argument(f"--{name}", default=default, help=f"comma-separated ({default})")
    parser.add_argument("--methods", default=",".join(METHODS))
    _common.add_numbers(parser, default_steps=DEFAULT_STEPS["auto"], switch=30)
    _common.add_numbers(parser, gradient_steps=30, max_step=1.0, cma_generations=20)
    _common.add_numbers(parser, cma_sigma=0.5, validation_draws=32)
    every = (None, "steps between validations (default: the driver's, by the work since the last)")
    _common.add_numbers(parser, real=arguments.positive_int, validate_every=every)
    _common.add_numbers(parser, heldout_draws=64)
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument(
        "--compile", choices=("optimized", "fast"), default="optimized", help="the gradient"
    )
    _common.add_outputs(parser, "tuning_study", smoke=False)
    parser.add_argument(
        "--report-only", action="store_true", help="summarise the stored runs, run nothing"
    )
    parser.add_argument(
        "--bench", type=arguments.nonnegative_int, default=0, metavar="N",
        help="also time N CMA-ES generations evaluated in one batched call against one call "
        "per candidate (interleaved; medians), kept in --out/bench_<share>-*.json",
    )  # fmt: skip
    parser.add_argument(
        "--user-view", type=arguments.nonnegative_int, default=0, metavar="N",
        help="also run `fojax tune` as a user does N times per command (naive start: the "
        "default and --method cma-es; the paper's gains: the default), each in a fresh "
        "process with an empty cache, stored in --out/user_view/",
    )  # fmt: skip
    _common.add_smoke(parser)
    return parser


def parse_args(argv) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.seeds = tuple(int(s) for s in args.seeds.split(",") if s.strip())
    except ValueError:
        parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
    for name, valid in CHOICES.items():
        values = _common.listed(getattr(args, name))
        setattr(args, name, values)
        if not values or any(v not in valid for v in values):
            parser.error(f"--{name} must be among {', '.join(valid)}, got {','.join(values)}")
    if args.tiny:
        args.horizon, args.draws, args.heldout_draws, args.validation_draws = 0.3, 3, 4, 2
        args.default_steps, args.switch, args.gradient_steps, args.cma_generations = 4, 2, 4, 2
        args.seeds, args.dtype, args.compile = args.seeds[:1], "float64", "fast"
    return args


class _Setup:
    """One parameter count: the runs' objectives (fresh ones, or with ``--tiny`` one per
    seed) and the held-out objective, compiled once."""

    def __init__(self, args, share: str):
        import jax.numpy as jnp

        from fojax import optimize
        from fojax.controllers.afonftsmc import paper_gains

        self.args, self.share, self._kept = args, share, {}
        dtype = jnp.dtype(args.dtype)
        self.naive = optimize.naive_gains("afonftsmc", dtype)
        self.starts = {"paper": paper_gains(dtype), "naive": self.naive}
        self.heldout_keys = optimize.draw_keys(0, "heldout", args.heldout_draws)
        self.heldout_objective = self.objective(0)
        self.heldout([self.heldout_objective.x0])  # compiled here, not counted

    def objective(self, seed: int, strategy=None, dt: float = 1e-3):
        """The problem of ``seed`` at step ``dt``: a fresh objective over every device, its
        lanes fitted to ``strategy``'s requests (kept per seed with ``--tiny``)."""
        import jax

        from fojax import optimize, sharding
        from fojax.optimize import strategies

        args = self.args
        if (seed, dt) in self._kept:
            return self._kept[seed, dt]
        mesh = sharding.draw_mesh(jax.devices())
        size = optimize.make_parameter_map("afonftsmc", None, self.share).size
        lanes = 128
        if strategy is not None:
            lanes = strategies.lanes(strategy, size, args.draws, int(mesh.devices.size))
        tiny = {"effort_weight": 1e-3, "chattering_weight": 1e-3, "attitude_weight": 2.0}
        cost = optimize.CostConfig(**(tiny if args.tiny else {}))
        same = {k: getattr(args, k) for k in ("scenario", "horizon", "draws", "dtype", "compile")}
        spec = optimize.ProblemSpec(
            controller="afonftsmc", dt=dt, seed=seed, cost=cost, share=self.share, **same
        )
        objective = optimize.Objective(spec, self.naive, mesh=mesh, lanes=lanes)
        if args.tiny:
            self._kept[seed, dt] = objective
        return objective

    @property
    def popsize(self) -> int:
        return 4 + int(3 * math.log(self.heldout_objective.size))

    def heldout(self, points) -> np.ndarray:
        return _common.mean_costs(self.heldout_objective, points, self.heldout_keys)

    def strategy(self, method: str, seed: int):
        """``(strategy, budget)`` of ``method`` (module docstring)."""
        from fojax import optimize
        from fojax.optimize import strategies

        args = self.args
        settings = dict(seed=seed, switch=args.switch, sigma=args.cma_sigma, max_step=args.max_step)
        if method == "nelder-mead":
            size = self.heldout_objective.size
            per_point = args.draws * self.heldout_objective.spec.steps
            points = max(args.cma_generations * self.popsize, size + 1 + self.popsize)
            return strategies.make(method), optimize.Budget(draw_steps=points * per_point)
        steps = {"default": args.default_steps, "lbfgs": args.gradient_steps}
        steps = steps.get(method, args.cma_generations)
        name = "auto" if method == "default" else method
        return strategies.make(name, steps, **settings), optimize.Budget(steps=steps)


def bench_batched(setup: _Setup, repeats: int) -> dict:
    """Wall time of one CMA-ES generation (the population on the same draws): one
    batched call against one call per candidate (on an objective of ``--draws`` lanes
    per call: no padding), interleaved, ``repeats`` times each; and the largest
    relative difference of their costs."""
    from fojax import optimize

    args, objective = setup.args, setup.objective(0)
    alone = optimize.Objective(objective.spec, setup.naive, lanes=args.draws)
    rng = np.random.default_rng(0)
    candidates = objective.x0 + 0.5 * rng.normal(size=(setup.popsize, objective.size))
    keys = objective.sample(0)

    def together():
        return objective.loss.values(objective.forward(candidates, keys))

    def separate():
        return np.asarray([alone.loss.values(alone.forward(x[None], keys))[0] for x in candidates])

    together(), separate()  # compiled first
    times, values = {"batched": [], "one_at_a_time": []}, {}
    for _ in range(repeats):
        for name, call in (("batched", together), ("one_at_a_time", separate)):
            t0 = time.perf_counter()
            values[name] = call()
            times[name].append(time.perf_counter() - t0)
    single = values["one_at_a_time"]
    difference = np.abs(values["batched"] - single) / np.abs(single)
    return {
        "share": setup.share,
        "parameters": objective.size,
        "population": setup.popsize,
        "draws": args.draws,
        "horizon_s": args.horizon,
        **{f"{name}_s": kept for name, kept in times.items()},
        **{f"median_{name}_s": float(np.median(kept)) for name, kept in times.items()},
        "largest_relative_difference": float(np.max(difference)),
        "load": output.load_average(),
    }


RESULT_FIELDS = ("wall_time_s", "draw_steps", "steps", "best_step", "validation")
"""What a run keeps of :func:`fojax.optimize.run`'s result."""


def run_one(setup: _Setup, start: str, seed: int, method: str) -> dict:
    """One run on a fresh objective; its curve ``[step, wall time (s), draw-steps,
    held-out cost of the answer]`` (the start first) and totals."""
    load_before, t0 = output.load_average(), time.perf_counter()
    strategy, budget = setup.strategy(method, seed)
    objective = setup.objective(seed, strategy, setup.args.dt)
    x0 = objective.vector(setup.starts[start])
    result, steps = _common.recorded_run(
        objective, strategy, budget, x0, validation_draws=setup.args.validation_draws,
        validate_every=setup.args.validate_every, progress=False,
    )  # fmt: skip
    costs = setup.heldout([x0, result.x] + [answer for *_, answer in steps])
    curve = [[0, 0.0, 0, float(costs[0])]]
    curve += [[s, w, int(d), float(c)] for (s, w, d, _), c in zip(steps, costs[2:], strict=True)]
    return {
        "start": start,
        "seed": seed,
        "method": method,
        "share": setup.share,
        "parameters": objective.size,
        "curve": curve,
        "initial_heldout": float(costs[0]),
        "final_heldout": float(costs[1]),
        **{k: getattr(result, k) for k in RESULT_FIELDS},
        "load_before": load_before,
        "load_after": output.load_average(),
        "elapsed_s": round(time.perf_counter() - t0, 1),
        "git_commit": output.commit_label(full=True),
    }


COMMON = (
    "scenario horizon dt draws dtype compile tiny heldout_draws validation_draws validate_every"
).split()
BY_METHOD = {
    "default": ("default_steps", "cma_sigma"),
    "lbfgs": ("gradient_steps", "max_step"),
    "cma-es": ("cma_generations", "cma_sigma"),
    "nelder-mead": ("cma_generations",),
}
"""The settings a run depends on (its fingerprint), besides its share, start and seed."""


def _run_key(args, share: str, start: str, seed: int, method: str) -> tuple:
    """``(folder, stem, fingerprint)`` of a run (:func:`experiments._common.cached`)."""
    import jax

    names = COMMON + list(BY_METHOD[method])
    cases = dict(share=share, start=start, seed=seed, method=method, engine="fojax.optimize")
    fingerprint = {k: getattr(args, k) for k in names} | cases | {"devices": jax.device_count()}
    return args.out / "runs", f"{share}_{start}_{seed}_{method}", fingerprint


def _bench_key(args, share: str) -> tuple:
    """``(folder, stem, fingerprint)`` of the batched-generation bench: it depends on
    these settings, not on how many generations it times."""
    fingerprint = {k: getattr(args, k) for k in COMMON + ["cma_generations"]} | {"share": share}
    return args.out, f"bench_{share}", fingerprint


def _stored_run(args, share, start, seed, method) -> dict | None:
    return _common.stored(*_run_key(args, share, start, seed, method))


def run_share(args, share: str, settings: dict) -> None:
    """The runs (and the bench) of one parameter count that are not stored yet (each
    kept under its fingerprint: :func:`experiments._common.cached`)."""
    cases = itertools.product(args.starts, args.seeds, args.methods)
    pending = [case for case in cases if _stored_run(args, share, *case) is None]
    bench_done = _common.stored(*_bench_key(args, share)) is not None
    if not pending and (not args.bench or bench_done):
        return
    t0 = time.perf_counter()
    setup = _Setup(args, share)
    output.log(
        args.quiet,
        f"share={share}: {setup.heldout_objective.size} parameters, held-out evaluation "
        f"compiled in {time.perf_counter() - t0:.0f} s",
    )
    if args.bench and not bench_done:
        bench = _common.cached(*_bench_key(args, share), lambda: bench_batched(setup, args.bench))
        output.log(
            args.quiet,
            f"  batched generation {bench['median_batched_s']:.2f} s, one at a "
            f"time {bench['median_one_at_a_time_s']:.2f} s (medians)",
        )
    for start, seed, method in pending:
        record = _common.cached(
            *_run_key(args, share, start, seed, method),
            lambda case=(start, seed, method): run_one(setup, *case) | {"settings": settings},
        )
        output.log(
            args.quiet,
            f"  {share} {start} seed {seed} {method}: held-out "
            f"{record['initial_heldout']:.4g} -> {record['final_heldout']:.4g}, "
            f"{record['wall_time_s']:.0f} s (compilation included), "
            f"load {record['load_before']} -> {record['load_after']}",
        )


def report(args, settings: dict, start_all: float) -> int:
    """``results.json``, ``table.md`` and the figures from the stored runs of the
    selected shares, starts, seeds and methods; the document's block with ``--update-doc``."""
    out = args.out
    users = tuning_study_user.records(args, out, run=not args.report_only)
    cases = itertools.product(args.shares, args.starts, args.seeds, args.methods)
    runs = [r for r in (_stored_run(args, *case) for case in cases) if r is not None]
    if not runs:
        raise SystemExit(
            f"{out / 'runs'} holds no run made with these settings (runs are kept under the "
            "settings they depend on); run without --report-only, or give the settings "
            "the runs were made with"
        )
    benches = (_common.stored(*_bench_key(args, share)) for share in args.shares)
    results = {
        "user_view": users,
        "bench": [bench for bench in benches if bench is not None],
        "settings": settings,
        "summary": summarize(runs),
        "runs": runs,
        # The commit that ran the runs (a --report-only later may stand elsewhere).
        "git_commit": ", ".join(sorted({r.get("git_commit", "unknown") for r in runs}))
        or output.commit_label(full=True),
        "this_invocation_s": round(time.perf_counter() - start_all, 1),
        "runs_elapsed_s": round(sum(r["elapsed_s"] for r in runs), 1),
    }
    for axis in ("wall", "draw_steps"):
        figure = plot(runs, out / f"tuning_{axis}.png", axis)
        if args.update_doc is not None:
            shutil.copyfile(figure, args.update_doc.parent / figure.name)
    wrote = ", tuning_wall.png, tuning_draw_steps.png"
    return _common.finish(
        out, results, table(results), args.update_doc, "tuning-study", None, wrote
    )


def main(argv=None) -> int:
    from fojax import settings as process_settings

    process_settings.use_host_devices()  # one XLA device per core, as fojax tune runs
    args = parse_args(argv)
    _common.enable_float64(args.dtype == "float64")
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    start_all = time.perf_counter()
    settings = _common.settings(args)
    # Every run compiles its own programs, as a user's first run does (--tiny: reused).
    with contextlib.nullcontext() if args.tiny else process_settings.without_compile_cache():
        if not args.report_only:
            for share in args.shares:
                run_share(args, share, settings)
        return report(args, settings, start_all)


if __name__ == "__main__":
    sys.exit(main())
