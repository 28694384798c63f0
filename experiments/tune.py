"""``fojax tune``: gradient-based gain tuning through the batched simulator.

    fojax tune --scenario {1,2,3} --controller NAME --draws N --steps K
               [--horizon T] [--init paper|naive|FILE] [--objective mean|cvar]
               [--resume] --out DIR      (fojax tune --help lists every option)

Each step draws a fresh minibatch of ``N`` Monte Carlo draws of the scenario (seed
``--seed``), simulates ``T`` seconds (default 10 s, a tuning horizon; the scenario's
own horizon is 80 s or 50 s) with the controller's switching smoothed to ``tanh``
(annealed towards the evaluation boundary layer), and takes one clipped Adam step on
the gradient of the mean (or CVaR) cost. Writes to ``DIR``:

* ``gains.json``: the tuned gains, the format ``fojax simulate --gains`` reads;
* ``history.csv``: one row per step (objective, gradient norm, learning rate,
  boundary-layer scale, diverged draws, simulated draw-steps, wall time);
* ``checkpoint.npz``: the state every ``--checkpoint-every`` steps. After an
  interruption, the same command with ``--resume`` continues and gives the result the
  uninterrupted run would have given;
* ``evaluation.json``: the cost of the initial and the tuned gains on
  ``--eval-draws`` held-out draws (never used in tuning), with ``--eval-switching``.

Every input is checked before anything is compiled or written; an existing
checkpoint is never overwritten.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from experiments import arguments

__all__ = ["build_parser", "main", "parse_args"]


def build_parser() -> argparse.ArgumentParser:
    from fojax import fractional, scenarios
    from fojax.controllers import SWITCHING_FUNCTIONS, registry
    from optimize import cost, params
    from optimize.tuner import TunerConfig

    defaults = cost.CostConfig()
    tuner = TunerConfig()
    parser = argparse.ArgumentParser(
        prog="fojax tune",
        description="Tune a controller's gains by gradient over Monte Carlo draws of a scenario.",
    )
    parser.add_argument("--scenario", type=int, required=True, choices=scenarios.SCENARIO_IDS)
    parser.add_argument(
        "--controller", required=True, help=f"one of {', '.join(registry.controller_names())}"
    )
    parser.add_argument(
        "--draws", type=arguments.positive_int, required=True, help="draws per step"
    )
    parser.add_argument(
        "--steps", type=arguments.positive_int, required=True, help="optimisation steps"
    )
    parser.add_argument(
        "--horizon", type=arguments.positive_float, default=10.0, help="tuning horizon, s (10)"
    )
    parser.add_argument("--dt", type=arguments.positive_float, default=1e-3, help="step, s (1e-3)")
    parser.add_argument(
        "--init",
        default="paper",
        metavar="paper|naive|FILE",
        help="initial gains: the controller's defaults (paper), a knowledge-free guess "
        "(naive: positive gains 1, p/q = 1.5, orders 0.5), or a gains file (paper)",
    )
    parser.add_argument("--objective", choices=cost.OBJECTIVES, default=defaults.objective)
    parser.add_argument(
        "--cvar-fraction",
        type=arguments.positive_float,
        default=defaults.cvar_fraction,
        help=f"worst fraction of draws averaged by --objective cvar ({defaults.cvar_fraction})",
    )
    parser.add_argument("--error", choices=cost.ERRORS, default=defaults.error)
    for name in ("position", "attitude", "effort", "chattering"):
        value = getattr(defaults, f"{name}_weight")
        parser.add_argument(
            f"--{name}-weight", type=arguments.nonnegative_float, default=value, help=f"({value:g})"
        )
    parser.add_argument("--seed", type=arguments.nonnegative_int, default=0, help="draws' seed (0)")
    parser.add_argument(
        "--fields",
        default="default",
        help="comma-separated gain fields to tune; 'default': every bounded field except "
        "the constant and smoothing ones (mu, boundary_layer); 'all': every field",
    )
    parser.add_argument("--share", choices=tuple(params.SHARING), default="paper")
    parser.add_argument(
        "--learning-rate",
        type=arguments.positive_float,
        default=tuner.learning_rate,
        help="Adam step",
    )
    parser.add_argument(
        "--clip-norm",
        type=arguments.positive_float,
        default=tuner.clip_norm,
        help="gradient-norm clip",
    )
    parser.add_argument("--anneal-start", type=arguments.positive_float, default=tuner.anneal_start)
    parser.add_argument("--anneal-end", type=arguments.positive_float, default=tuner.anneal_end)
    parser.add_argument(
        "--checkpoint-every", type=arguments.positive_int, default=tuner.checkpoint_every
    )
    parser.add_argument("--fractional", choices=fractional.METHODS, default="soe")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument(
        "--eval-draws",
        type=arguments.nonnegative_int,
        default=32,
        help="held-out draws (32; 0: none)",
    )
    parser.add_argument(
        "--eval-horizon", type=arguments.positive_float, help="s (default: the tuning horizon)"
    )
    parser.add_argument("--eval-switching", choices=SWITCHING_FUNCTIONS, default="sat")
    parser.add_argument("--resume", action="store_true", help="continue the run in DIR")
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR")
    return parser


def _initial_gains(parser, args, dtype):
    from fojax.controllers import gains_io, registry
    from optimize import params

    if args.init == "paper":
        return registry.get_controller_class(args.controller).default_gains(dtype), "paper"
    if args.init == "naive":
        return params.naive_gains(args.controller, dtype), "naive"
    try:
        name, gains, _ = gains_io.load_gains(args.init, dtype)
    except ValueError as error:
        parser.error(f"--init: {error}")
    if name != args.controller:
        parser.error(f"--init {args.init} holds gains of {name!r}, not of {args.controller!r}")
    return gains, str(Path(args.init).resolve())


def parse_args(argv):
    """Parse and validate; returns ``(PreparedRun, args)``. Raises ``SystemExit`` with
    a message on bad input, before anything is compiled or written."""
    from fojax.controllers import registry
    from optimize import cost, params, problem, tuner

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.controller not in registry.controller_names():
        parser.error(
            f"unknown controller {args.controller!r}; choose one of "
            f"{', '.join(registry.controller_names())}"
        )
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
    try:
        cost_config = cost.CostConfig(
            error=args.error,
            position_weight=args.position_weight,
            attitude_weight=args.attitude_weight,
            effort_weight=args.effort_weight,
            chattering_weight=args.chattering_weight,
            objective=args.objective,
            cvar_fraction=args.cvar_fraction,
        )
        spec = problem.ProblemSpec(
            controller=args.controller,
            scenario=args.scenario,
            horizon=float(args.horizon),
            dt=float(args.dt),
            draws=args.draws,
            seed=args.seed,
            cost=cost_config,
            fields=fields,
            share=args.share,
            fractional=args.fractional,
            dtype=args.dtype,
        )
        config = tuner.TunerConfig(
            steps=args.steps,
            learning_rate=args.learning_rate,
            clip_norm=args.clip_norm,
            anneal_start=args.anneal_start,
            anneal_end=args.anneal_end,
            checkpoint_every=args.checkpoint_every,
        )
        if args.eval_horizon is not None:
            steps = args.eval_horizon / args.dt
            if abs(steps - round(steps)) > 1e-6 * steps:
                raise ValueError(
                    f"--eval-horizon ({args.eval_horizon} s) must be a whole number of steps "
                    f"of {args.dt} s"
                )
        params.make_parameter_map(args.controller, fields, args.share)
    except ValueError as error:
        parser.error(str(error))
    gains, label = _initial_gains(parser, args, dtype)
    try:
        run = tuner.prepare(spec, config, gains, label, args.out, resume=args.resume)
    except ValueError as error:
        parser.error(str(error))
    return run, args


def _evaluate(run, result, args) -> dict:
    import numpy as np

    from optimize import problem as problem_lib

    horizon = args.eval_horizon or run.spec.horizon
    keys = result.problem.heldout_keys(args.eval_draws)
    out = {
        "draws": args.eval_draws,
        "horizon_s": horizon,
        "switching": args.eval_switching,
        "draw_indices": f"{problem_lib.HELDOUT_OFFSET} + [0, {args.eval_draws})",
    }
    for label, gains in (("initial", run.init_gains), ("tuned", result.gains)):
        costs = problem_lib.evaluate(
            run.spec, gains, keys, horizon=horizon, switching=args.eval_switching
        )
        out[label] = {
            "mean_cost": float(np.mean(costs.cost)),
            "std_cost": float(np.std(costs.cost, ddof=1)) if args.eval_draws > 1 else None,
            "mean_terms": dict(
                zip(
                    ("position", "attitude", "effort", "chattering"),
                    np.mean(costs.terms, 0).tolist(),
                    strict=True,
                )
            ),
            "diverged": int(np.sum(costs.diverged)),
        }
    return out


def main(argv=None) -> int:
    from optimize import tuner

    argv = list(sys.argv[1:] if argv is None else argv)
    run, args = parse_args(argv)
    start = time.perf_counter()
    try:
        result = tuner.tune(run, progress=not args.quiet)
    except KeyboardInterrupt:
        return 130
    print(
        f"tuned {run.spec.controller} on scenario {run.spec.scenario}: {result.completed} "
        f"steps x {run.spec.draws} draws x {run.spec.horizon:g} s, final objective "
        f"{result.history[-1]['objective']:.5g} ({time.perf_counter() - start:.0f} s)"
    )
    if args.eval_draws > 0:
        evaluation = _evaluate(run, result, args)
        (args.out / "evaluation.json").write_text(json.dumps(evaluation, indent=1) + "\n")
        print(
            f"held-out cost ({evaluation['draws']} draws, {evaluation['horizon_s']:g} s, "
            f"{evaluation['switching']}): initial {evaluation['initial']['mean_cost']:.5g}, "
            f"tuned {evaluation['tuned']['mean_cost']:.5g}"
        )
    print(f"wrote {args.out}/gains.json and history.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
