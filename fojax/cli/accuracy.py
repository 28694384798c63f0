"""Accuracy and cost of every fractional method against exact Riemann-Liouville results.

For each method and order, the worst relative error over the horizon (default 80 s at
1 ms) on test signals with exact differintegrals (sin, cos, step, ramp, t^2 and the
Mittag-Leffler relaxation), the cost per step (modes, flops, state) and the measured
wall time per channel-step. Writes ``accuracy.json``, ``accuracy.md`` (the table of
``docs/fractional.md``) and ``accuracy.png`` (and ``accuracy.pdf``) to ``--out``;
``accuracy.json`` also records the command line, versions and devices
(:func:`fojax.cli.study.provenance`).

    fojax accuracy --out results/fractional
    (or python -m fojax.cli.accuracy --out results/fractional)
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import timeit

import jax
import jax.numpy as jnp
import numpy as np

from fojax import fractional, settings
from fojax.cli import arguments, require_extra, style
from fojax.cli import study as study_layer
from fojax.records import atomic_write

EXTRA_MODULES = ("mpmath", "pymittagleffler")
"""What the exact references (:mod:`fojax.cli.references`) need: the ``[experiments]``
extra, imported only when the command runs."""

ORDERS = (0.01, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99)

METHODS = {
    "soe": ("soe", {}),
    "oustaloup (paper: N=5, 0.01-100 rad/s)": ("oustaloup", {}),
    "oustaloup N=10": ("oustaloup", {"order": 10}),
    "refined oustaloup N=5": ("oustaloup", {"refined": True}),
    "gl full memory": ("gl", {}),
    "gl short memory 1 s": ("gl", {"memory": 1000}),
}

SMOOTH = ("sin(1.7t)", "ramp", "t^2")
"""The smooth test signals: the main table and the figure show the worst over these."""


SIGNALS = {
    "sin(1.7t)": (lambda t: np.sin(1.7 * t), "sine", 1.7),
    "cos(0.4t)": (lambda t: np.cos(0.4 * t), "cosine", 0.4),
    "step": (np.ones_like, "power", 0.0),
    "ramp": (lambda t: t, "power", 1.0),
    "t^2": (lambda t: t**2, "power", 2.0),
}
"""The test signals: ``(signal of t, exact differintegral)``, the latter a function of
:mod:`fojax.cli.references` and its parameter (the frequency, or the power of t)."""


def relative_error(y: np.ndarray, exact: np.ndarray, skip: int = 1) -> float:
    """Worst |error| over t >= skip*dt relative to the largest |exact| there."""
    return float(np.max(np.abs(y[skip:] - exact[skip:])) / np.max(np.abs(exact[skip:])))


def _time_per_step(method: str, options: dict, dt: float, steps: int, channels: int = 64) -> float:
    """Median wall time (ns) per channel-step of ``fractional.run`` (init/step scan)."""
    op = fractional.make_operator(method, dt, steps * dt, **options)
    u = jnp.asarray(np.random.default_rng(0).normal(size=(steps, channels)), jnp.float32)
    runner = jax.jit(lambda u, a: fractional.run(op, a, u))
    runner(u, -0.5).block_until_ready()
    times = timeit.repeat(lambda: runner(u, -0.5).block_until_ready(), number=1, repeat=3)
    return float(np.median(times) / (steps * channels) * 1e9)


def evaluate(horizon: float = 80.0, dt: float = 1e-3, orders=ORDERS, methods=None) -> dict:
    from fojax.cli import references

    methods = methods or METHODS
    steps = int(round(horizon / dt)) + 1
    t = np.arange(steps) * dt
    u = jnp.asarray(np.stack([signal(t) for signal, _, _ in SIGNALS.values()], axis=1))
    alphas = [-o for o in orders] + list(orders)
    results = {"horizon_s": horizon, "dt_s": dt, "orders": list(orders), "methods": {}}
    for label, (method, options) in methods.items():
        print(f"  {label} ...", flush=True)
        apply = jax.jit(
            jax.vmap(lambda a, m=method, o=options: fractional.differintegrate(u, a, dt, m, **o))
        )
        y_all = np.asarray(apply(jnp.asarray(alphas)))
        errors = {}
        for i, alpha in enumerate(alphas):
            # Derivatives of the step are unbounded at t = 0 and O(1/dt^a) at t = dt.
            per_signal = {
                name: relative_error(y_all[i][:, j], getattr(references, exact)(t, x, alpha))
                for j, (name, (_, exact, x)) in enumerate(SIGNALS.items())
            }
            # Relaxation E_a(-t^a): I^a E = 1 - E (integral orders only).
            if alpha < 0:
                relax = references.mittag_leffler(-(t**-alpha), -alpha)
                y_relax = np.asarray(
                    fractional.differintegrate(relax, alpha, dt, method, **options)
                )
                for key, skip in (("relaxation", 1), ("relaxation, t>=1s", round(1.0 / dt))):
                    per_signal[key] = relative_error(y_relax, 1.0 - relax, skip)
            errors[f"{alpha:+.2f}"] = per_signal
        cost = fractional.make_operator(method, dt, horizon, **options).cost()
        cost["ns_per_channel_step"] = _time_per_step(method, options, dt, min(steps, 20_001))
        results["methods"][label] = {
            "method": method,
            "options": options,
            "errors": errors,
            "worst_smooth_signals": max(errors[a][s] for a in errors for s in SMOOTH),
            "worst_all_signals": max(max(v.values()) for v in errors.values()),
            "cost": cost,
        }
    return results


def _worst_smooth(result: dict, sign: int, orders) -> list[float]:
    """A method's worst error over :data:`SMOOTH` at each order: integrals (``sign``
    -1) or derivatives (1)."""
    return [max(result["errors"][f"{sign * o:+.2f}"][s] for s in SMOOTH) for o in orders]


COST_COLUMNS = ("modes", "flops/step", "state floats", "ns/channel-step")


def _row(cells) -> str:
    """A row of a Markdown table."""
    return "| " + " | ".join(map(str, cells)) + " |"


def markdown(results: dict) -> str:
    orders = results["orders"]
    lines = [
        f"Worst relative error over {results['horizon_s']:g} s at dt = {results['dt_s']:g} s "
        "(max |error| / max |exact|, t >= dt), worst over sin(1.7t), ramp and t^2; "
        "I = integral, D = derivative of the order in the column.",
        "",
        _row(["method", *(f"{k} {o:g}" for k in "ID" for o in orders), *COST_COLUMNS]),
        "|---" * (2 * len(orders) + 5) + "|",
    ]
    for label, r in results["methods"].items():
        cells = [f"{e:.1e}" for sign in (-1, 1) for e in _worst_smooth(r, sign, orders)]
        c = r["cost"]
        cost = [c[key] for key in ("modes", "flops_per_step", "state_floats")]
        lines.append(_row([label, *cells, *cost, f"{c['ns_per_channel_step']:.1f}"]))
    lines += [
        "",
        "Non-smooth signals (worst over orders): step and cos (derivative singular at t = 0), "
        "relaxation E_a(-t^a) (behaves like 1 - t^a/Gamma(1+a) at t = 0).",
        "",
        "| method | step | cos(0.4t) | relaxation | relaxation, t >= 1 s |",
        "|---|---|---|---|---|",
    ]
    non_smooth = ("step", "cos(0.4t)", "relaxation", "relaxation, t>=1s")
    for label, r in results["methods"].items():
        worst = [max(v[name] for v in r["errors"].values() if name in v) for name in non_smooth]
        lines.append(_row([label, *(f"{w:.1e}" for w in worst)]))
    return "\n".join(lines) + "\n"


def plot(results: dict, path: pathlib.Path) -> pathlib.Path:
    plt = style.pyplot()
    orders = results["orders"]
    fig = plt.figure(figsize=(11, 4.6), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    for ax, sign in zip(axes, (-1, 1), strict=True):
        markers = ("o", "s", "^", "D", "v", "P", "X")
        for index, (label, r) in enumerate(results["methods"].items()):
            # Hollow markers shrinking with the index: methods whose errors coincide
            # (e.g. full and short GL memory at short horizons) stay visible.
            ax.semilogy(
                orders, _worst_smooth(r, sign, orders), marker=markers[index % len(markers)],
                ms=10 - index, mfc="none", mew=1.3, lw=1.2, label=label,
            )  # fmt: skip
        ax.axhline(1e-4, color="k", ls="--", lw=0.8, label="1e-4")
        ax.set(xlabel="order a", title=f"{'integral' if sign < 0 else 'derivative'} of order a")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"worst relative error over {results['horizon_s']:g} s")
    style.legend_below(fig, *axes[0].get_legend_handles_labels(), ncol=4)
    return style.save(fig, path)


MAX_STEPS = 1_000_000
"""The full-memory Grunwald-Letnikov reference costs steps^2: beyond this it would not
finish (80 s at 1 ms, the default, is 80,000)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fojax accuracy", description=__doc__.splitlines()[0])
    real = arguments.positive_float
    # fmt: off
    arguments.add_options(
        parser,
        ("--out", dict(type=arguments.output_directory, default=pathlib.Path("results/fractional"),
                       metavar="DIR", help="output folder (results/fractional)")),
        ("--horizon", dict(type=real, default=80.0, help="seconds (default 80)")),
        ("--dt", dict(type=real, default=1e-3, help="step in seconds (default 1e-3)")),
    )
    # fmt: on
    return parser


def parse_args(argv) -> argparse.Namespace:
    """Parse and check (the extra's modules installed, a horizon the table can use);
    exits with a message before anything is computed."""
    parser = build_parser()
    args = parser.parse_args(argv)
    require_extra("accuracy", "experiments", EXTRA_MODULES)
    if args.dt >= args.horizon:
        parser.error(f"--dt ({args.dt:g} s) must be smaller than --horizon ({args.horizon:g} s)")
    steps = round(args.horizon / args.dt)
    if steps < round(1.0 / args.dt):
        parser.error(
            f"--horizon ({args.horizon:g} s) must be at least 1 s: the table's "
            "'relaxation, t >= 1 s' column reads the samples from 1 s on"
        )
    if steps > MAX_STEPS:
        parser.error(
            f"--horizon / --dt is {steps} steps; at most {MAX_STEPS} (the full-memory "
            "reference costs steps^2): use a shorter --horizon or a larger --dt"
        )
    return args


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    settings.enable_float64()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    print(f"fractional accuracy: {args.horizon:g} s at dt = {args.dt:g} s (float64)", flush=True)
    results = evaluate(args.horizon, args.dt)
    results["provenance"] = study_layer.provenance(["fojax", "accuracy", *argv])
    study_layer.write_json(out / "accuracy.json", results)
    table = markdown(results)
    atomic_write(out / "accuracy.md", table)
    print(table)
    written = ["accuracy.json", "accuracy.md"]
    if style.attempt("accuracy.png", plot, results, out / "accuracy.png") is not None:
        written.append("accuracy.png (+ .pdf)")
    print(f"wrote {out}/: {', '.join(written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
