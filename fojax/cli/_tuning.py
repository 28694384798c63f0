"""What ``fojax tune``'s two tuners share: the weighted-sum tuner (:mod:`fojax.cli.tune`)
and the requirement tuner (``--requirements``, :mod:`fojax.cli._requirement_tuning`).

The checks of ``--fractional`` and ``--eval-switching`` against the controller, the
dtype and the gain fields, the initial gains (``--init``), the tuning problem's
:class:`fojax.optimize.problem.ProblemSpec`, the record of the initial gains in
``run.json`` and ``gains.json``, and ``evaluation.json``'s held-out evaluation.
"""

from __future__ import annotations

from pathlib import Path

from fojax.cli import arguments

BUILT_IN_INIT = {"paper": "defaults", "naive": "naive"}
"""``--init`` without a file: its label -> the ``source`` recorded for the gains."""


def check_law_options(args) -> None:
    """``ValueError`` when ``--fractional`` or ``--eval-switching`` is given for a
    controller whose law does not take it (:func:`fojax.cli.arguments.controller_flags`)."""
    arguments.controller_flags(
        [args.controller],
        {
            "--fractional": ("fractional_method", args.fractional),
            "--eval-switching": ("switching", args.eval_switching),
        },
    )


def dtype_and_fields(args):
    """``(dtype, fields)``: ``--dtype`` (float64 turns JAX's 64-bit mode on) and the gain
    fields ``--fields`` names (None: the default ones; ``all``: every field)."""
    import jax.numpy as jnp

    from fojax.controllers import registry

    arguments.enable_dtype(args.dtype)
    if args.fields == "default":
        fields = None
    elif args.fields == "all":
        fields = registry.get_controller_class(args.controller).GAINS.names
    else:
        fields = tuple(f.strip() for f in args.fields.split(",") if f.strip())
    return jnp.dtype(args.dtype), fields


def initial_gains(parser, args, dtype):
    """``(gains, label)`` of ``--init``: the controller's defaults (``paper``), the naive
    guess (``naive``) or a gains file (its absolute path); a bad file is a ``parser.error``."""
    from fojax.controllers import gains_io, registry
    from fojax.optimize import params

    if args.init == "paper":
        return registry.get_controller_class(args.controller).default_gains(dtype), "paper"
    if args.init == "naive":
        return params.naive_gains(args.controller, dtype), "naive"
    try:
        path = arguments.check_input_file(args.init, "gains file")
    except ValueError as error:
        parser.error(f"--init: {error}; give paper, naive or a gains file (JSON)")
    try:
        name, gains, _ = gains_io.load_gains(path, dtype)
    except ValueError as error:
        message = str(error)
        parser.error(f"--init: {message}" if str(path) in message else f"--init {path}: {message}")
    if name != args.controller:
        parser.error(f"--init {args.init} holds gains of {name!r}, not of {args.controller!r}")
    return gains, str(Path(args.init).resolve())


def problem_spec(args, fields, **settings):
    """The tuning problem of the options (``settings``: further fields, e.g. ``cost``)."""
    from fojax.optimize import problem

    return problem.ProblemSpec(
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
        **settings,
    )


def init_record(gains, label: str) -> dict:
    """The initial gains' values and their source: the file, or ``defaults`` (``--init
    paper``) or ``naive``."""
    from fojax.cli import study as study_layer

    record = study_layer.gains_record(gains, None if label in BUILT_IN_INIT else label)
    if label in BUILT_IN_INIT:
        record["source"] = BUILT_IN_INIT[label]
    return record


def heldout_evaluation(draws, horizon, switching, score, gains, before=(), after=()) -> dict:
    """``evaluation.json``: ``score(g)`` of ``gains`` (``{"initial": g0, "tuned": g1}``)
    on the ``draws`` held-out draws (never used in tuning), with what each tuner adds
    before the scores (``before``) and after them (``after``)."""
    from fojax.optimize import problem

    return {
        "draws": draws,
        "horizon_s": horizon,
        "switching": switching,
        "draw_indices": f"{problem.HELDOUT_OFFSET} + [0, {draws})",
        **dict(before),
        **{label: score(value) for label, value in gains.items()},
        **dict(after),
    }
