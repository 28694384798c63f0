"""``fojax tune``: tune a controller's gains over Monte Carlo draws of a scenario.

The objective (the weighted-sum cost's mean or CVaR, or a requirement set with what is
minimised under it) and the method are independent choices, both run on the engine
(:mod:`fojax.optimize`): an :class:`~fojax.optimize.Objective`, a strategy (inside the
augmented Lagrangian with ``--requirements``) and :func:`fojax.optimize.run`.

Writes to ``DIR``: ``gains.json`` (what ``fojax simulate --gains`` reads: the best
validated gains, the start's on a tie, with the run's settings, the step they come from
and the validation scores), ``history.csv`` (one row per step), ``checkpoint.npz`` (an
interrupted run continues with the same command and ``--resume``, to the result the
uninterrupted run gives), ``evaluation.json`` (the initial and the tuned gains on
``--eval-draws`` held-out draws: cost, or yield with its interval), ``convergence.png``
(and ``.pdf``) and ``run.json`` (the initial gains and, per session, the command line,
versions, backend and devices).

Each option is declared once in :data:`OPTIONS`, with its default and what it applies
to; a method's options, their defaults and the methods they apply to come from the
method table (:data:`fojax.optimize.strategies.METHODS`), and so does every number of the
help about a method (summary, steps, convergence test, option defaults, own draws).
argv is parsed once and every option is checked before anything is compiled or written.
An option that would change nothing (another method's, the other objective's, a law's
option for a controller without it, ...) is an error naming what it applies to.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from fojax import records
from fojax.cli import arguments, figures, output, style
from fojax.cli import requirements as requirements_cli
from fojax.optimize import spec as optimize_spec
from fojax.optimize.strategies import METHODS, words

__all__ = ["METHODS", "OPTIONS", "Run", "build_parser", "main", "parse_args"]

WEIGHTED, CONSTRAINED = ("mean", "cvar"), ("effort", "tracking")
TERMS = ("position", "attitude", "effort", "chattering")
GRADIENT = tuple(name for name, method in METHODS.items() if method.gradient)
BUILT_IN = {"paper": "defaults", "naive": "naive"}
DEFAULT = next(iter(METHODS))
"""The default method: the method table's first."""


class Option(NamedTuple):
    """One option: its flag, argparse keywords (no default: ``None`` means not given),
    its default (a value, or a function of the parsed arguments) and what it applies to
    (``applies(args)``: ``None``, or why it changes nothing)."""

    flag: str
    kwargs: dict
    default: Any = None
    applies: Callable | None = None

    @property
    def dest(self) -> str:
        return self.flag[2:].replace("-", "_")


def _methods(*names) -> Callable:
    def applies(a):
        if a.method not in names:
            return f"applies to --method {' or '.join(names)} only, not to --method {a.method}"

    return applies


def _option_of(name: str) -> tuple[Callable, Callable]:
    """``(default, applies)`` of the method option ``name``: its default and the
    methods it applies to, both from the method table (:data:`METHODS`)."""
    names = tuple(m for m, method in METHODS.items() if name in method.options)

    def default(a):
        return METHODS[a.method].defaults(a.requirements is not None).get(name)

    return default, _methods(*names)


def _defaults_of(name: str) -> str:
    """The method option ``name``'s defaults in words, from the method table: ``(0.5)``,
    or per method and with requirements where they differ."""
    found = {}
    for method_name, method in METHODS.items():
        if name in method.options:
            for constrained, label in ((False, ""), (True, " with --requirements")):
                value = words(name, method.defaults(constrained)[name])
                found.setdefault(value, []).append(f"{method_name}{label}")
    if len(found) == 1:
        return f"({next(iter(found))})"
    return "(" + "; ".join(f"{value}: {', '.join(where)}" for value, where in found.items()) + ")"


def _own_draws(name: str) -> str:
    """The draws per point of method ``name``'s own samples, phase by phase: ``4 then 8``."""
    return " then ".join(map(str, METHODS[name].own_draws()))


OWN = tuple(name for name, method in METHODS.items() if not method.draws)
"""The methods that sample draws of their own without a requirement set, not ``--draws``."""


def _draws(a):
    if a.requirements is None and not METHODS[a.method].draws:
        return (
            f"does not apply to --method {a.method}, which scores every point on fresh "
            f"samples of its own ({_own_draws(a.method)} draws per point)"
        )


def _requirements(a):
    if a.requirements is None:
        return "applies with --requirements FILE only (tuning to requirements)"


def _weighted(a):
    if a.requirements is not None or a.objective not in (None, *WEIGHTED):
        return "applies to the weighted-sum objective only (not with --requirements)"


def _every(*checks) -> Callable:
    return lambda a: next((r for r in (c(a) for c in checks) if r), None)


def _law(option: str, name: str) -> Callable:
    def applies(a):
        from fojax.controllers import registry

        if name not in registry.controller_options(a.controller):
            return f"does not apply to {a.controller}, which takes no {option}"

    return applies


def _smoothing(a):
    from fojax.controllers import registry

    if not registry.get_controller_class(a.controller).GAINS.with_role("smoothing"):
        return f"does not apply to {a.controller}, which has no boundary layer to anneal"


_EXCESS = next(f.default for f in dataclasses.fields(optimize_spec.ProblemSpec)
               if f.name == "bound_excess")
ENVELOPE_HORIZON, ENVELOPE_DT = 20.0, 2e-3
"""The tuning horizon and step over a flight envelope (docs/tuning.md): 20 s see (53)'s
disturbances act and two-thirds of a manoeuvre, at the cost of 10 s at 1 ms."""

count, real, whole = arguments.positive_int, arguments.positive_float, arguments.nonnegative_int
OPTIONS = (
    # what is tuned, on which draws
    Option("--scenario", dict(type=int, choices=(1, 2, 3), help="the paper's scenario (or "
           "--envelope)")),
    Option("--envelope", dict(type=arguments.envelope_file, metavar="FILE", help="envelope file "
           "(TOML, docs/tuning.md; e.g. examples/envelopes/paper_and_manoeuvres.toml): tune over "
           "its cases (the paper's scenarios, random manoeuvres, reference files) in place of "
           "--scenario"), None,
           lambda a: None if a.scenario is None and a.reference is None
           else "holds the cases flown: give it without --scenario and --reference"),
    Option("--controller", dict(required=True, help="a registered controller")),
    Option("--init", dict(metavar="paper|naive|FILE", help="initial gains: the controller's "
           "defaults, a knowledge-free guess (positive gains 1, p/q 1.5, orders 0.5), or a "
           "gains file (paper)"), "paper"),
    Option("--draws", dict(type=count, help="draws per sample (16; 8 with --requirements); "
           "without --requirements " + "; ".join(f"{m} takes its own ({_own_draws(m)})"
           for m in OWN)), lambda a: 8 if a.requirements else 16, _draws),
    Option("--horizon", dict(type=real, help="tuning horizon, s (10; 20 with --envelope)"),
           lambda a: ENVELOPE_HORIZON if a.envelope is not None else 10.0),
    Option("--dt", dict(type=real, help="step, s (1e-3; 2e-3 with --envelope)"),
           lambda a: ENVELOPE_DT if a.envelope is not None else 1e-3),
    Option("--seed", dict(type=arguments.seed, help="the draws' seed (0)"), 0),
    Option("--fields", dict(help="comma-separated gain fields; 'default' (every bounded design "
           "gain); 'all'"), "default"),
    Option("--share", dict(choices=("paper", "none"), help="axis sharing (paper)"), "paper"),
    Option("--vehicle", dict(type=arguments.vehicle_file, metavar="FILE", help="vehicle file "
           "(TOML, docs/model.md); default the paper's quadrotor; its rotor limit, if any, "
           "makes the actuators rotor-limited")),
    Option("--reference", dict(type=arguments.reference_file, metavar="FILE", help="reference "
           "file (TOML, docs/model.md: timed waypoints or a built-in) flown in place of the "
           "scenario's; its last waypoint within --horizon")),
    Option("--allow-infeasible-reference", dict(action="store_const", const=True, help="fly a "
           "--reference that asks for more thrust or tilt than the vehicle has (refused by "
           "default)"), False,
           lambda a: None if a.reference is not None else "applies with --reference only"),
    # the objective
    Option("--objective", dict(choices=WEIGHTED + CONSTRAINED, help="mean or cvar of the "
           "weighted-sum cost (mean; cvar with --envelope); with --requirements what is "
           "minimised under them: effort (default) or tracking"),
           lambda a: "effort" if a.requirements else "cvar" if a.envelope else "mean"),
    Option("--cvar-fraction", dict(type=real, help="worst share averaged by cvar (0.25)"), 0.25,
           lambda a: None if a.objective == "cvar" else "applies to --objective cvar only"),
    Option("--error", dict(choices=("ise", "itae"), help="tracking error measure (ise)"), "ise",
           _weighted),
    Option("--case-scale", dict(choices=("default", "none"), help="with --envelope: each case's "
           "cost in units of the controller's default gains' on that case (default), or as it "
           "is (none)"), "default",
           lambda a: None if a.envelope is not None and not a.requirements
           else "applies with --envelope (without --requirements) only"),
    Option("--chattering-bound", dict(choices=("default", "none"), help="with --envelope: "
           "a draw whose torques vary more than the controller's default gains' median on its "
           "case pays the excess (default), or not (none)"), "default",
           lambda a: None if a.envelope is not None and not a.requirements
           else "applies with --envelope (without --requirements) only"),
    Option("--tracking-bound", dict(choices=("default", "none"), help="with --envelope: "
           "a draw whose position RMSE passes the controller's default gains' median on its "
           "case pays the excess (default), or not (none)"), "default",
           lambda a: None if a.envelope is not None and not a.requirements
           else "applies with --envelope (without --requirements) only"),
    Option("--bound-excess", dict(type=arguments.nonnegative_float, help="the weight of "
           f"a draw's excess over its case's bounds ({_EXCESS:g})"), _EXCESS,
           lambda a: None if a.envelope is not None and not a.requirements
           else "applies with --envelope (without --requirements) only"),
    *(Option(f"--{t}-weight", dict(type=arguments.nonnegative_float, help=f"({w:g})"), w, _weighted)
      for t, w in zip(TERMS, (1.0, 1.0, 1e-5, 1e-5), strict=True)),
    Option("--requirements", dict(type=requirements_cli.requirements_file, metavar="FILE",
           help="requirement file (TOML or JSON, docs/requirements.md)")),
    Option("--rotor-limit", dict(type=requirements_cli.thrust_to_weight, metavar="T",
           help="rotor-limited actuators at thrust-to-weight T (replaces the file's)"),
           None, _requirements),
    Option("--outer-steps", dict(type=count, help="multiplier updates (10)"), 10, _requirements),
    Option("--inner-steps", dict(type=count, help="method steps per multiplier update (10)"), 10,
           _requirements),
    Option("--formulation", dict(choices=("mean", "chance"), help="constraint per requirement: "
           "mean hinge (every draw) or chance (at most 5 %% violating) (mean)"), "mean",
           _requirements),
    Option("--margin", dict(type=arguments.nonnegative_float, help="share of each bound a "
           "draw must beat it by (0.05)"), 0.05, _requirements),
    # the method
    Option("--method", dict(choices=tuple(METHODS), help="; ".join(
           f"{name}: {m.summary}" for name, m in METHODS.items()) + f" ({DEFAULT})"), DEFAULT),
    Option("--steps", dict(type=count, help="steps (generations for CMA-ES), a cap where the "
           "method stops once converged: " + ", ".join(
           f"{m} {n.steps}" for m, n in METHODS.items())), lambda a: METHODS[a.method].steps,
           lambda a: "is set by --outer-steps and --inner-steps with --requirements"
           if a.requirements else None),
    Option("--seconds", dict(type=real, help="stop after this wall time (none)")),
    Option("--patience", dict(type=whole, help="stop once the best validated cost improved by "
           "less than the method's tolerance over this many steps (" + ", ".join(
           f"{m} {n.patience}, tolerance {n.tolerance * 100:g} %%" for m, n in METHODS.items()
           if n.patience) + "; 0: never)"),
           lambda a: METHODS[a.method].patience or 0,
           lambda a: "does not apply with --requirements" if a.requirements else (
               "applies with validation draws only" if a.validation_draws == 0 else None)),
    Option("--switch", dict(type=count, help="CMA-ES generations before L-BFGS "
           + _defaults_of("switch")), *_option_of("switch")),
    Option("--sigma", dict(type=real, help="CMA-ES's initial step " + _defaults_of("sigma")),
           *_option_of("sigma")),
    Option("--popsize", dict(type=count, help="CMA-ES's candidates " + _defaults_of("popsize")),
           *_option_of("popsize")),
    Option("--learning-rate", dict(type=real, help="Adam's step "
           + _defaults_of("learning_rate")), *_option_of("learning_rate")),
    Option("--clip-norm", dict(type=real, help="Adam's gradient clip "
           + _defaults_of("clip_norm")), *_option_of("clip_norm")),
    Option("--anneal-start", dict(type=real, help="Adam's first width scale "
           + _defaults_of("anneal_start")),
           _option_of("anneal_start")[0], _every(_option_of("anneal_start")[1], _smoothing)),
    Option("--anneal-end", dict(type=real, help="the gradient's (last) width scale "
           + _defaults_of("anneal_end")),
           _option_of("anneal_end")[0], _every(_option_of("anneal_end")[1], _smoothing)),
    Option("--max-step", dict(type=real, help="L-BFGS's largest change of a parameter "
           + _defaults_of("max_step")), *_option_of("max_step")),
    # validation, held-out draws
    Option("--validation-draws", dict(type=whole, help="draws scoring the answer; the best "
           "validated gains are returned (32; 0: the last)"), 32),
    Option("--validate-every", dict(type=count, help="steps between validations (default: "
           "once the work since the last is 8 times a validation's; with --requirements every "
           "multiplier update)"), lambda a: a.inner_steps + 1 if a.requirements else None,
           lambda a: "applies with validation draws only" if a.validation_draws == 0 else None),
    Option("--eval-draws", dict(type=whole, help="held-out draws (32; 128 with --requirements; "
           "0: none)"), lambda a: 128 if a.requirements else 32),
    Option("--eval-horizon", dict(type=real, help="s (the tuning horizon)"), None,
           lambda a: "applies with held-out draws only (--eval-draws is 0)"
           if a.eval_draws == 0 else _weighted(a)),
    Option("--eval-switching", dict(choices=("sat", "tanh", "sign"), help="the evaluation law "
           "(sat)"), "sat", _law("switching function", "switching")),
    # how it computes, where it writes
    Option("--fractional", dict(choices=("soe", "oustaloup", "gl"), help="fractional method "
           "(soe)"), "soe", _law("fractional operator", "fractional_method")),
    Option("--dtype", dict(choices=("float32", "float64"), help="(float32)"), "float32"),
    Option("--compile", dict(choices=("optimized", "fast"), help="the gradient without LLVM's "
           "optimisation passes: faster to compile, slower to run (optimized)"), "optimized",
           _methods(*GRADIENT)),
    Option("--device-batch", dict(type=count, metavar="N", help="draws per device and call of "
           "the gradient (the sample)"), None, _methods(*GRADIENT)),
    Option("--checkpoint-every", dict(type=count, help="steps between checkpoints (10)"), 10),
    Option("--out", dict(type=arguments.output_directory, required=True, metavar="DIR")),
)  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fojax tune", description="Tune a controller's gains over Monte Carlo draws."
    )
    for option in OPTIONS:
        parser.add_argument(option.flag, **option.kwargs)
    parser.add_argument("--resume", action="store_true", help="continue the run in DIR")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    arguments.add_runtime_options(parser)
    return parser


class Run(NamedTuple):
    """``fojax tune``'s arguments, checked: the objective, the strategy, the budget, the
    start, the run's fingerprint and what it writes."""

    args: argparse.Namespace
    objective: Any
    strategy: Any
    budget: Any
    x0: Any
    init_label: str
    init_gains: Any
    fingerprint: dict


def parse_args(argv) -> Run:
    """Parse and check; every error exits with status 2 before anything is compiled or
    written."""
    from fojax.controllers import registry

    parser = build_parser()
    args = parser.parse_args(argv)
    try:  # a registered name, 'package.module:Class' or an entry point
        args.controller = registry.get_controller_class(args.controller).name
    except (TypeError, ValueError) as error:
        parser.error(str(error))
    if args.requirements is None and args.objective in CONSTRAINED:
        parser.error(f"--objective {args.objective} applies with --requirements FILE only")
    if args.requirements is not None and args.objective in WEIGHTED:
        parser.error(
            f"--objective {args.objective} is the weighted-sum objective's; with "
            f"--requirements choose {' or '.join(CONSTRAINED)}"
        )
    given = {o.dest for o in OPTIONS if getattr(args, o.dest) is not None}
    for option in OPTIONS:  # defaults first: an option's check may read another's value
        if option.dest not in given:
            default = option.default
            setattr(args, option.dest, default(args) if callable(default) else default)
    for option in OPTIONS:
        reason = option.applies(args) if option.applies and option.dest in given else None
        if reason:
            parser.error(f"{option.flag} {reason}; leave it out")
    if args.scenario is None and args.envelope is None:
        parser.error("give --scenario N (the paper's) or --envelope FILE (several cases)")
    args.reference_peaks = arguments.check_reference(parser, args.reference, args.horizon)
    try:
        return _build(parser, args)
    except ValueError as error:
        parser.error(str(error))


def _build(parser, args) -> Run:
    """The objective, strategy, budget and fingerprint of checked arguments."""
    import jax

    from fojax import optimize, sharding
    from fojax.controllers import registry
    from fojax.optimize import strategies as st

    arguments.enable_dtype(args.dtype)
    fields = {"default": None, "all": registry.get_controller_class(args.controller).GAINS.names}
    fields = fields.get(args.fields, tuple(f.strip() for f in args.fields.split(",") if f.strip()))
    weights = {f"{t}_weight": getattr(args, f"{t}_weight") for t in TERMS}
    reduction = args.objective if args.objective in WEIGHTED else "mean"
    cost = optimize.CostConfig(args.error, objective=reduction,
                               cvar_fraction=args.cvar_fraction, **weights)  # fmt: skip
    take = ("controller", "scenario", "horizon", "dt", "draws", "seed", "share", "fractional",
            "dtype", "compile", "vehicle", "reference", "envelope")  # fmt: skip
    spec = optimize.ProblemSpec(cost=cost, fields=fields, **{k: getattr(args, k) for k in take})
    cases = len(spec.scenario_object().members)
    if cases > 1:  # every sample holds each case equally often
        rounded = {name: optimize.objective.stratified(getattr(args, name), cases)
                   for name in ("draws", "validation_draws")}  # fmt: skip
        changed = {n: v for n, v in rounded.items() if v != getattr(args, n)}
        if changed and not args.quiet:
            given = " and ".join("--" + n.replace("_", "-") + f" {getattr(args, n)}"
                                 for n in changed)  # fmt: skip
            print(f"{given} rounded up to {' and '.join(map(str, changed.values()))}, a "
                  f"multiple of the {cases} cases")  # fmt: skip
        for name, value in changed.items():
            setattr(args, name, value)
        spec = dataclasses.replace(spec, draws=args.draws)
    if args.eval_horizon is not None:  # a ValueError unless a whole number of steps
        dataclasses.replace(spec, horizon=args.eval_horizon)
    gains, label = _initial_gains(parser, args)
    reqs, limit = requirements_cli.resolve_requirements(args)
    args.requirement_set, args.rotor_speed_limit = reqs, limit
    arguments.check_flight(parser, args, limit, requirements_cli.limit_source(args))
    # With requirements the method's steps are one outer step's: the augmented Lagrangian
    # restarts its inner strategy (optimiser and schedule) after every multiplier update.
    steps = args.inner_steps if reqs is not None else args.steps
    mesh = sharding.draw_mesh(jax.devices())
    target = args.objective if reqs is not None else "cost"

    def objective_with(lanes):
        return optimize.Objective(spec, gains, reqs, target, rotor_speed_limit=limit,
                                  switching=args.eval_switching, mesh=mesh,
                                  device_batch=args.device_batch, lanes=lanes)  # fmt: skip

    method = st.METHODS[args.method]
    probe = objective_with(optimize.objective.LANES)
    if spec.envelope is not None and reqs is None and (
        args.case_scale == "default" or args.chattering_bound == "default"
        or args.tracking_bound == "default"
    ):
        scales, chattering, tracking = _case_scales(spec, args, limit, mesh, gains)
        spec = dataclasses.replace(
            spec,
            case_scales=scales if args.case_scale == "default" else None,
            case_chattering=chattering if args.chattering_bound == "default" else None,
            case_tracking=tracking if args.tracking_bound == "default" else None,
            bound_excess=args.bound_excess,
        )
        probe = objective_with(optimize.objective.LANES)
    x0 = probe.vector(gains)
    options = {name: getattr(args, name) for name in method.options}  # each an option
    outer = args.outer_steps if reqs is not None else 1
    problem = st.Problem(probe, x0, args.seed, reqs is not None, outer)
    strategy = method.make(problem, steps, **options)
    lanes = st.lanes(strategy, probe.size, args.draws, int(mesh.devices.size))
    objective = objective_with(lanes)
    steps = args.steps
    if reqs is not None:
        share = 0.05 if args.formulation == "chance" else 0.0
        strategy = st.AugmentedLagrangian(strategy, len(reqs), args.outer_steps, args.inner_steps,
                                          formulation=args.formulation, margin=args.margin,
                                          allowed_share=share)  # fmt: skip
        steps = strategy.requests
    patience = None if reqs is not None or not args.patience else args.patience
    budget = optimize.Budget(steps=steps, seconds=args.seconds, patience=patience,
                             tolerance=method.tolerance)  # fmt: skip
    fingerprint = optimize.describe(
        objective, strategy, budget, x0, args.validation_draws, args.validate_every
    )
    fingerprint["init"] = label
    optimize.check_resume(args.out, records.canonical(fingerprint), args.resume)
    return Run(args, objective, strategy, budget, x0, label, gains, fingerprint)


CASE_SCALE_DRAWS = 32
"""Draws per case on which the reference gains set each case's scales (validation draws)."""


def _case_scales(spec, args, limit, mesh, start) -> tuple:
    """Each case's scale, chattering bound and tracking bound: the median cost, torque
    variation and position term ``P`` of the controller's default gains on
    :data:`CASE_SCALE_DRAWS` validation draws of the case, at the tuning horizon and the
    evaluation law
    (:func:`fojax.optimize.cost.case_scales`); on a case where they diverge on every
    draw (another vehicle's, say), the start's."""
    import jax.numpy as jnp
    import numpy as np

    from fojax import optimize
    from fojax.controllers import registry

    defaults = registry.get_controller_class(spec.controller).default_gains(jnp.dtype(spec.dtype))
    runs = []
    for gains in (defaults, start):
        reference = optimize.Objective(spec, gains, rotor_speed_limit=limit,
                                       switching=args.eval_switching, mesh=mesh)  # fmt: skip
        cases = max(1, reference.members)
        keys = reference.keys("validation", CASE_SCALE_DRAWS * cases)
        members = np.arange(len(keys)) % cases
        out = reference.forward(reference.x0[None], keys)
        runs.append((out.values[0, :, 0], out.metrics["torque_variation"][0],
                     out.terms[0, :, 0], out.status[0]))
        kept = out.valid[0]
        lost = [c for c in range(cases) if not np.any(kept[members == c])]
        if not lost:
            break
        if len(runs) == 1:
            names = [n for n, _ in spec.envelope.cases(spec.vehicle)]
            print("the default gains diverge on every reference draw of "
                  f"{', '.join(names[c] for c in lost)}: the start sets their scales")  # fmt: skip
    if len(runs) == 2:  # the start's draws in the cases the defaults lost
        swap = np.isin(members, lost)
        runs = [tuple(np.where(swap, b, a) for a, b in zip(*runs, strict=True))]
    values, variation, tracking, status = runs[0]
    return tuple(optimize.cost.case_scales(v, status, members, cases)
                 for v in (values, variation, tracking))  # fmt: skip


def _initial_gains(parser, args):
    """``(gains, label)`` of ``--init``; a bad file is a ``parser.error``."""
    import jax.numpy as jnp

    from fojax.controllers import gains_io, registry
    from fojax.optimize import params

    dtype = jnp.dtype(args.dtype)
    if args.init == "paper":
        return registry.get_controller_class(args.controller).default_gains(dtype), "paper"
    if args.init == "naive":
        return params.naive_gains(args.controller, dtype, args.envelope is not None), "naive"
    try:
        path = arguments.check_input_file(args.init, "gains file")
        name, gains, _ = gains_io.load_gains(path, dtype)
    except ValueError as error:
        text = str(error)
        if not Path(args.init).exists():
            text += "; give paper, naive or a gains file"
        parser.error(f"--init: {text}" if args.init in text else f"--init {args.init}: {text}")
    if name != args.controller:
        parser.error(f"--init {args.init} holds gains of {name!r}, not of {args.controller!r}")
    if args.envelope is not None:  # within the envelope's search bounds
        spec = registry.get_controller_class(name).GAINS
        for field, bounds in spec.search_bounds(True).items():
            value = jnp.asarray(getattr(gains, field))
            if bounds != spec.bounds[field] and bool(jnp.any(value >= bounds.high)):
                print(f"--init: {field} brought below {bounds.high:g}, the largest value a "
                      "tuner over a flight envelope searches (docs/tuning.md)")  # fmt: skip
                gains = gains._replace(**{field: jnp.minimum(value, 0.999 * bounds.high)})
    return gains, str(Path(args.init).resolve())


# ----------------------------------------------------------------------------- run


def main(argv=None) -> int:
    from fojax import optimize

    argv = list(sys.argv[1:] if argv is None else argv)
    runtime = arguments.setup_runtime(argv, "fojax tune")
    run = parse_args(argv)
    args, objective = run.args, run.objective
    lead = runtime["process_index"] == 0
    out = Path(args.out) if lead else _private_copy(Path(args.out), args.resume)
    session = output.provenance(["fojax", "tune", *argv])
    session["device_batch"] = args.device_batch or args.draws
    record = _record_session(run, out, session) if lead else None
    earlier = out / "gains.json"  # a finished run resumed keeps it as it was
    earlier = earlier.read_text() if args.resume and earlier.is_file() else None
    if not args.quiet and lead:
        print(_announce(run), file=sys.stderr, flush=True)
    start = time.perf_counter()
    try:
        result = optimize.run(
            objective, run.strategy, run.budget, run.x0, validation_draws=args.validation_draws,
            validate_every=args.validate_every, checkpoint_every=args.checkpoint_every, out=out,
            fingerprint=run.fingerprint, resume=args.resume, progress=not args.quiet and lead,
        )  # fmt: skip
    except KeyboardInterrupt:
        return 130
    if not lead:
        shutil.rmtree(out, ignore_errors=True)
        return 0
    print(_summary(run, result, time.perf_counter() - start))
    _save_gains(run, result, record, earlier)
    files = ["gains.json", "history.csv", "run.json"]
    evaluation = None
    if args.eval_draws > 0:
        evaluation = _heldout(run, result, session)
        output.write_json(out / "evaluation.json", evaluation)
        files.append("evaluation.json")
    if _figure(run, result, evaluation) is not None:
        files.append("convergence.png (+ .pdf)")
    if evaluation is not None and "cases" in evaluation and _cases_figure(run, evaluation):
        files.append("cases.png (+ .pdf)")
    print(f"wrote {out}/: {', '.join(files)}")
    return 0


def _private_copy(out: Path, resume: bool) -> Path:
    """Processes other than 0 write into a private folder (process 0 writes the outputs),
    holding a copy of the checkpoint to resume from."""
    from fojax.optimize import CHECKPOINT

    folder = Path(tempfile.mkdtemp(prefix="fojax-tune-"))
    if resume and (out / CHECKPOINT).is_file():
        shutil.copy2(out / CHECKPOINT, folder / CHECKPOINT)
    return folder


def _record_session(run: Run, out: Path, session: dict) -> dict:
    """``run.json``: the initial gains (their values and source: the file, ``defaults`` or
    ``naive``), the settings and one provenance entry per session."""
    from fojax.cli import study as study_layer

    path, label = out / "run.json", run.init_label
    record = json.loads(path.read_text()) if run.args.resume and path.is_file() else {}
    init_gains = study_layer.gains_record(run.init_gains, None if label in BUILT_IN else label)
    if label in BUILT_IN:
        init_gains["source"] = BUILT_IN[label]
    record.update(controller=run.args.controller, init=label, init_gains=init_gains,
                  settings=run.fingerprint)  # fmt: skip
    record["sessions"] = list(record.get("sessions", [])) + [session]
    out.mkdir(parents=True, exist_ok=True)
    output.write_json(path, record)
    return record


def _announce(run: Run) -> str:
    args, spec, reqs = run.args, run.objective.spec, run.args.requirement_set
    what = "the weighted-sum cost"
    if reqs is not None:
        what = f"{args.objective} under {len(reqs)} requirements ({', '.join(reqs.names)})"
    lines = [
        f"tuning {spec.controller} on {spec.describe_cases()}: {what}, {args.method}, "
        f"{spec.draws} draws x {spec.horizon:g} s, {run.objective.size} parameters"
    ]
    if spec.vehicle is not None or args.rotor_speed_limit is not None:
        lines.append(arguments.describe_vehicle(spec.vehicle, args.rotor_speed_limit))
    if spec.reference is not None:
        lines.append(arguments.describe_reference(spec.reference, args.reference_peaks))
    plan = _plan(run)
    if plan is not None:
        lines.append(f"plan: {plan}")
    return "\n".join(lines)


def _plan(run: Run) -> str | None:
    """The method's plan for ``--steps`` in words, where its strategy states one
    (``auto``'s phases: :meth:`fojax.optimize.strategies.MultiStart.plan`)."""
    plan = getattr(run.strategy, "plan", None)
    return None if plan is None else plan(run.budget.steps, run.objective.size)


def _cut(run: Run) -> bool:
    """Whether ``--steps`` end within the method's first phase (its plan says so)."""
    search = getattr(run.strategy, "search", None)
    return search is not None and run.budget.steps <= search


def _summary(run: Run, result, wall: float) -> str:
    """What the run did and which gains it returned."""
    from fojax.optimize.driver import headline

    args, v = run.args, result.validation
    text = (
        f"tuned {args.controller} on {run.objective.spec.describe_cases()} ({args.method}): "
        f"{result.steps} "
        f"steps, {result.draw_steps:.3g} draw-steps ({wall:.0f} s)"
    )
    if _cut(run):  # stated whatever --quiet: the run was not the method's whole plan
        text += f"\nplan: {_plan(run)}"
    if v is not None and v["best"] is not None:
        step = result.returned_step
        chosen = "the start's (no answer validated better)" if step == 0 else f"step {step}'s"
        text += (
            f"\nreturned {chosen} gains: validation {headline(v['best'])} against "
            f"{headline(v['initial'])} at the start and {headline(v['final'])} at the last "
            f"step ({v['draws']} validation draws, {v['switching']}, {v['horizon_s']:g} s)"
        )
    return text


def _save_gains(run: Run, result, record: dict, earlier: str | None) -> None:
    """``gains.json``: the returned gains and the run's record (a finished run resumed
    keeps its file as it was)."""
    from fojax.controllers import gains_io

    args, path = run.args, Path(run.args.out) / "gains.json"
    if earlier is not None and result.steps == json.loads(earlier)["metadata"].get("steps"):
        records.atomic_write(path, earlier)
        return
    metadata = {
        "tuned_by": "fojax tune",
        "method": args.method,
        "init": run.init_label,
        "steps": result.steps,
        "returned_step": result.returned_step,
        "selected_by": "validation" if result.validation else "last step",
        "validation": result.validation,
        "draw_steps": result.draw_steps,
        "wall_time_s": result.wall_time_s,
        "settings": run.fingerprint,
        "vehicle": arguments.vehicle_record(run.objective.spec.vehicle, args.rotor_speed_limit),
        "init_gains": record["init_gains"],
        "provenance": record["sessions"][-1],
    }
    if args.requirement_set is not None:
        metadata.update(
            tuned_to="requirements",
            objective=args.objective,
            requirements=args.requirement_set.to_dict(),
            actuators=requirements_cli.actuators_record(args.rotor_speed_limit, args),
        )
    gains_io.save_gains(path, args.controller, run.objective.gains(result.x), metadata)


def _heldout(run: Run, result, session: dict) -> dict:
    """``evaluation.json``: the initial and the tuned gains on the held-out draws."""
    from fojax.optimize import HELDOUT_OFFSET
    from fojax.optimize.driver import headline

    args, objective = run.args, run.objective
    horizon = args.eval_horizon or objective.spec.horizon
    draws = objective.stratified(args.eval_draws)  # each case equally often
    keys = objective.keys("heldout", draws)
    document = {
        "draws": draws,
        "horizon_s": horizon,
        "switching": args.eval_switching,
        "draw_indices": f"{HELDOUT_OFFSET} + [0, {draws})",
        "returned_step": result.returned_step,
    }
    for label, x in (("initial", run.x0), ("tuned", result.x)):
        document[label] = objective.evaluate(x, keys, horizon=horizon)[1]
    document["provenance"] = session
    print(
        f"held-out ({draws} draws, {horizon:g} s, {args.eval_switching}): initial "
        f"{headline(document['initial'])}, tuned {headline(document['tuned'])}"
    )
    if objective.spec.envelope is not None:
        document["cases"] = _cases(run, result)
    return document


def _cases(run: Run, result) -> dict:
    """The start's and the tuned gains on held-out draws of every case of the envelope,
    each over its own horizon, with each switching law (:mod:`fojax.optimize.cases`);
    printed with where the tuned gains do worse."""

    from fojax import simulator
    from fojax.controllers import registry
    from fojax.optimize import cases

    args, objective = run.args, run.objective
    gains = {"start": objective.gains(run.x0), "tuned": objective.gains(result.x)}
    default = registry.get_controller_class(objective.spec.controller).default_gains(
        objective.dtype)
    if run.init_label != "paper":  # the controller's default (the paper's) gains beside them
        gains["default"] = objective.base_gains._replace(
            **{n: getattr(default, n) for n in objective.param_map.names})
    # judged at the step the simulator flies (the tuning may take a coarser one)
    flown = dataclasses.replace(objective.spec, dt=simulator.SimulationConfig.dt)
    found = cases.evaluate_cases(flown, gains, args.eval_draws,
                                 objective.rotor_speed_limit)  # fmt: skip
    found["dt"] = flown.dt
    found["tuned_worse"] = cases.losses(found, "tuned", "start")
    if "default" in gains:
        found["tuned_worse_than_default"] = cases.losses(found, "tuned", "default")
    print(f"held-out, case by case ({args.eval_draws} draws each, its own horizon, dt "
          f"{flown.dt:g} s):")
    print(cases.table(found, tuple(gains)))
    if "default" in gains:
        worse = found["tuned_worse_than_default"]
        print("the tuned gains do worse than the default gains: " + "; ".join(worse) if worse
              else "the tuned gains do no worse than the default gains in any case")
    worse = found["tuned_worse"]
    print("the tuned gains do worse than the start: " + "; ".join(worse) if worse
          else "the tuned gains do no worse than the start in any case")  # fmt: skip
    return found


def _cases_figure(run: Run, evaluation: dict):
    """``cases.png`` (and ``.pdf``): the held-out evaluation case by case."""
    spec = run.objective.spec
    labels = ("the start's, the tuned and the default gains"
              if "tuned_worse_than_default" in evaluation["cases"]
              else "the start's and the tuned gains")  # fmt: skip
    return style.attempt(
        "cases.png", figures.plot_cases, evaluation["cases"], Path(run.args.out) / "cases.png",
        f"fojax tune: {spec.controller}, {labels} case by case",
    )


def _figure(run: Run, result, evaluation):
    """``convergence.png`` (and ``.pdf``); ``None`` (a warning) when it cannot be drawn."""
    args, spec = run.args, run.objective.spec
    start = result.validation["initial"] if result.validation else None
    own = args.requirement_set is None and not METHODS[args.method].draws
    sample = f"{_own_draws(args.method)}-draw samples" if own else f"{spec.draws} draws"
    return style.attempt(
        "convergence.png",
        figures.plot_convergence,
        Path(args.out) / "history.csv",
        Path(args.out) / "convergence.png",
        evaluation,
        f"fojax tune: {spec.controller}, {spec.describe_cases()}, {args.method}, "
        f"{sample} x {spec.horizon:g} s, {args.objective}",
        None if start is None else start["score"],
        start is not None and start["kind"] == "yield",
    )


if __name__ == "__main__":
    sys.exit(main())
