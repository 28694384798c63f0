"""``fojax bench``: throughput, compile time and gradient cost of the closed loop.

Standard workload: scenario 2, AFONFTSMC with the default fractional method (sum of
exponentials), RK4, 1 ms, float32. Measured in one run, on every device JAX sees
(draws sharded with :mod:`fojax.sharding`):

* forward rollouts at several draw counts: draw-steps per second (median of
  ``--repeats`` runs) and compile time, apart; batches larger than ``--chunk`` draws
  run as consecutive calls of ``--chunk`` draws each (one call of a big batch streams
  the fractional memory from DRAM every step), and are also timed as one call for
  comparison. ``fojax simulate`` and ``fojax reproduce`` run their draws in blocks of
  ``--device-batch`` draws per device and call instead (:mod:`fojax.study`);
* reverse-mode gradient of the rollout cost with respect to the gains (``tanh``
  switching) at several horizons: draw-steps per second, its cost relative to the
  forward pass of the same rollout, compile time, and peak memory (XLA's buffer
  assignment: arguments + outputs + temporaries of the compiled program). The gains
  are broadcast to one copy per draw before the rollout, so the sum of the draws'
  gradients happens once, after the time loop (with shared gains it happened at every
  step, an all-reduce across devices each step on a mesh: 20-100x slower);
* the same closed loop in plain NumPy vectorised over draws
  (:mod:`fojax.cli.numpy_reference`) and the ratio JAX / NumPy;
* crazyflow's simulator at the same world counts, where it is installed.

Each compile time is also given by phase (tracing, lowering, XLA), and each compiled
program's kernels per iteration of its innermost loops (the time loop's step; one per
pass of the gradient): on XLA's CPU backend a step's cost follows its kernel count.
The machine (CPU model, cores, devices and their kind, load average at the start and
the end) is recorded with the provenance, so that a report of the JSON can be labelled
from it alone (``experiments/bench_report.py``).

Big batches run a shorter horizon (``--long-horizon`` for at most ``--long-max-draws``
draws, ``--short-horizon`` above): cost is linear in the horizon (``--scaling``
measures it), and the horizon used is printed and stored with each figure. On a CPU
the default spreads the draws over one XLA host device per core
(:func:`fojax.settings.use_host_devices`; set before JAX starts, ``--devices``
changes it). Progress goes to stderr; ``--json FILE`` writes every figure with its
units.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import resource
import sys

from fojax.cli import arguments, output
from fojax.cli import study as study_layer
from fojax.cli.bench_measure import (
    measure_crazyflow,
    measure_forward,
    measure_gradient,
    measure_numpy,
)

DEFAULT_DRAWS = (1, 64, 1024, 4096)
DEFAULT_CHUNK = 1024  # draws per call: 512 per core keeps each core's modes in its L2


def _log(message: str) -> None:
    print(f"[bench] {message}", file=sys.stderr, flush=True)


def _horizon(text: str) -> float:
    """Seconds > 0, a whole number of the workload's 1 ms steps."""
    try:
        value = arguments.positive_float(text)
    except argparse.ArgumentTypeError as error:
        raise argparse.ArgumentTypeError(f"{error} (a positive number of seconds)") from None
    steps = value / 1e-3
    if round(steps) < 1 or abs(steps - round(steps)) > 1e-6 * steps:
        raise argparse.ArgumentTypeError(
            f"expected a positive horizon, a whole number of 1 ms steps (e.g. 0.25), got {text}"
        )
    return value


def _horizons(text: str) -> tuple[float, ...]:
    return arguments.listed(text, _horizon, "0.25,1")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fojax bench",
        description="Throughput of the standard workload (scenario 2, AFONFTSMC, SOE, RK4, 1 ms, "
        "float32): forward, gradient, NumPy reference. Defaults finish in a few minutes on a "
        "2-core CPU.",
    )
    count, counts = arguments.positive_int, arguments.positive_ints
    # fmt: off
    arguments.add_options(
        parser,
        ("--json", dict(type=arguments.output_file, metavar="FILE", help="write every figure, "
                        "with units and provenance, here (checked before running)")),
        ("--draws", dict(type=counts, default=DEFAULT_DRAWS, help="forward draw counts")),
        ("--long-horizon", dict(type=_horizon, default=4.0, help="horizon (s), small batches")),
        ("--short-horizon", dict(type=_horizon, default=1.0, help="horizon (s), big batches")),
        ("--long-max-draws", dict(type=count, default=64,
                                  help="batches up to this size run the long horizon")),
        ("--repeats", dict(type=count, default=3, help="timed runs (median)")),
        ("--chunk", dict(type=count, default=DEFAULT_CHUNK, help="draws per compiled call for "
                         "bigger forward batches (simulate and reproduce: --device-batch)")),
        ("--gradient-draws", dict(type=counts, default=(64, 256), help="draw counts of the "
                                  "gradient runs (comma-separated; default 64,256)")),
        ("--gradient-horizons", dict(type=_horizons, default=(0.25, 1.0, 4.0), help="horizons "
                                     "(s) of the gradient runs (memory against horizon)")),
        ("--numpy-draws", dict(type=counts, default=None, help="draw counts of the NumPy "
                               "reference (default: the forward ones)")),
        ("--numpy-horizon", dict(type=_horizon, default=0.25, help="NumPy horizon (s)")),
        ("--scaling", dict(action="store_true", help="also measure forward cost against draws "
                           "and horizon (linearity)")),
        ("--devices", dict(type=count, default=None, help="CPU only: XLA host devices to split "
                           "the draws over (default: CPU cores)")),
        ("--small", dict(action="store_true", help="tiny sizes for a smoke test (seconds, not "
                         "minutes; figures meaningless); it sets --draws, the horizons, "
                         "--repeats and the gradient and NumPy sizes itself")),
    )
    # fmt: on
    return parser


# ------------------------------------------------------------------------------ main


UNITS = {
    "draw_steps_per_s": "draw-steps per second (draws x plant/controller steps / wall time)",
    "gradient_draw_steps_per_s": "draw-steps per second of the reverse-mode gradient",
    "drone_steps_per_s": "drone-steps per second (crazyflow)",
    "compile_s": "seconds, tracing + lowering + XLA compilation",
    "*_phases_s": "the compile time by phase: trace_s (to a jaxpr), lower_s (to StableHLO), "
    "xla_s (XLA's optimisation and code generation), seconds",
    "*loop_kernels": "kernels per iteration of each innermost loop of the compiled program "
    "(optimised HLO), largest first: the time loop's step, one per pass under grad",
    "load_average": "1, 5 and 15-minute load averages at the start (load_average_end: at the end)",
    "run_s": "seconds of wall time, median of the timed runs",
    "horizon_s": "simulated seconds",
    "steps": "steps of 1 ms",
    "*_bytes": "bytes (XLA buffer assignment of the compiled program, all devices' share)",
    "gradient_over_forward": "gradient wall time / forward wall time, same draws and horizon",
    "chunk": "draws per compiled call (bigger batches run as consecutive calls)",
    "jax_over_numpy": "JAX draw-steps/s / NumPy draw-steps/s at the same draw count",
}


SMALL = {
    "draws": (1,),
    "long_horizon": 0.02,
    "short_horizon": 0.02,
    "repeats": 1,
    "gradient_draws": (4,),
    "gradient_horizons": (0.02,),
    "numpy_draws": (1,),
    "numpy_horizon": 0.02,
}
"""The sizes ``--small`` sets itself (giving one of these options with it is an error)."""


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The options, with ``--small``'s sizes applied (an error when one is also given)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.small:
        probe = build_parser()  # without defaults: the options given on the command line
        for action in probe._actions:
            action.default = argparse.SUPPRESS
        clashing = sorted(set(vars(probe.parse_known_args(argv)[0])) & set(SMALL))
        if clashing:
            flags = ", ".join("--" + name.replace("_", "-") for name in clashing)
            parser.error(f"--small sets the sizes itself; leave {flags} out or drop --small")
        vars(args).update(SMALL)
    return args


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    requested_devices = arguments.use_host_devices(args.devices)
    if args.devices is not None and requested_devices is None:
        _log(
            f"--devices {args.devices} ignored: XLA_FLAGS already sets the host device "
            "count, or JAX had started"
        )

    import jax
    import numpy as np

    from fojax import sharding

    mesh = sharding.draw_mesh()
    backend = jax.default_backend()
    _log(
        f"backend {backend}, {mesh.devices.size} device(s)"
        + (f" (asked for {requested_devices} host devices)" if requested_devices else "")
    )
    result: dict = {
        "workload": {
            "scenario": 2,
            "controller": "afonftsmc",
            "fractional_method": "soe",
            "integrator": "rk4",
            "dt_s": 1e-3,
            "dtype": "float32",
            "switching_forward": "sat",
            "switching_gradient": "tanh",
        },
        "machine": {
            "backend": backend,
            "devices": [str(d) for d in mesh.devices.flat],
            "device_kind": mesh.devices.flat[0].device_kind,
            "device_count": int(mesh.devices.size),
            "cpu_model": output.cpu_model(),
            "cpu_count": os.cpu_count(),
            "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "load_average": output.load_average(),
            "platform": platform.platform(),
            "processor": platform.processor(),
            "jax": jax.__version__,
            "numpy": np.__version__,
        },
        "provenance": study_layer.provenance(["fojax", "bench", *argv]),
        "units": UNITS,
        **{section: [] for section in ("forward", "gradient", "numpy", "comparison")},
        "scaling": {},
        "crazyflow": None,
    }
    _measure(args, result, mesh)
    result["machine"]["load_average_end"] = output.load_average()
    result["process_max_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    _print_summary(result)
    if args.json is not None:
        study_layer.write_json(args.json, result)
        _log(f"wrote {args.json}")
    return result


def _measure(args, result: dict, mesh) -> None:
    """Every measurement the options ask for, into ``result``, logged as it finishes."""
    for count in args.draws:
        horizon = args.long_horizon if count <= args.long_max_draws else args.short_horizon
        _log(f"forward: {count} draws x {horizon} s ...")
        entry = measure_forward(count, horizon, args.repeats, mesh, args.chunk)
        result["forward"].append(entry)
        _log(
            f"  {entry['draw_steps_per_s']:.3g} draw-steps/s "
            f"(run {entry['run_s']:.3f} s in {entry['calls']} call(s), "
            f"compile {entry['compile_s']:.1f} s)"
            + (
                f"; as one call {entry['one_call_draw_steps_per_s']:.3g}"
                if "one_call_draw_steps_per_s" in entry
                else ""
            )
        )

    for count in args.numpy_draws or args.draws:
        _log(f"numpy reference: {count} draws x {args.numpy_horizon} s ...")
        entry = measure_numpy(count, args.numpy_horizon)
        result["numpy"].append(entry)
        _log(f"  {entry['draw_steps_per_s']:.3g} draw-steps/s")

    forward_rates = {e["draws"]: e["draw_steps_per_s"] for e in result["forward"]}
    result["comparison"] = [
        {"draws": e["draws"], "jax_over_numpy": forward_rates[e["draws"]] / e["draw_steps_per_s"]}
        for e in result["numpy"]
        if e["draws"] in forward_rates
    ]

    for count in args.gradient_draws:
        for horizon in args.gradient_horizons:
            _log(f"gradient: {count} draws x {horizon} s ...")
            entry = measure_gradient(count, horizon, args.repeats, mesh)
            result["gradient"].append(entry)
            memory = entry["gradient_memory"].get("peak_bytes")
            _log(
                f"  {entry['gradient_draw_steps_per_s']:.3g} draw-steps/s, "
                f"{entry['gradient_over_forward']:.2f}x forward "
                f"({entry['gradient_over_forward_cpu_time']:.2f}x in CPU time), "
                f"peak {memory / 2**20 if memory else float('nan'):.1f} MiB, "
                f"compile {entry['gradient_compile_s']:.1f} s"
            )

    if args.scaling:
        base_draws = 8 if args.small else 256
        _log("scaling: cost against draws and horizon ...")
        result["scaling"]["draws"] = [
            measure_forward(base_draws * m, args.short_horizon, args.repeats, mesh, args.chunk)
            for m in (1, 4, 16)
        ]
        result["scaling"]["horizon"] = [
            measure_forward(base_draws * 4, args.short_horizon * m, args.repeats, mesh, args.chunk)
            for m in (0.5, 1, 2)
        ]
        for kind, entries in result["scaling"].items():
            for e in entries:
                _log(f"  {kind}: {e['draws']} x {e['horizon_s']} s: run {e['run_s']:.3f} s")

    if importlib.util.find_spec("crazyflow") is not None:
        _log("crazyflow ...")
        try:
            result["crazyflow"] = [measure_crazyflow(c, 1000) for c in args.draws]
        except Exception as error:  # report, do not fail the whole benchmark
            result["crazyflow"] = {"error": f"{type(error).__name__}: {error}"}
    else:
        result["crazyflow"] = {"skipped": "crazyflow is not installed"}


def _print_summary(result: dict) -> None:
    machine = result["machine"]
    print(
        f"fojax bench: scenario 2, AFONFTSMC (soe), RK4, 1 ms, float32; "
        f"{machine['backend']} x {machine['device_count']} device(s)"
    )
    print("forward:")
    for e in result["forward"]:
        print(
            f"  {e['draws']:6d} draws x {e['horizon_s']:g} s: "
            f"{e['draw_steps_per_s']:10.3g} draw-steps/s   compile {e['compile_s']:5.1f} s"
            + (
                f"   ({e['calls']} calls of {e['chunk']}; one call: "
                f"{e['one_call_draw_steps_per_s']:.3g})"
                if "one_call_draw_steps_per_s" in e
                else ""
            )
        )
    print("numpy reference:")
    for e in result["numpy"]:
        print(f"  {e['draws']:6d} draws x {e['horizon_s']:g} s: {e['draw_steps_per_s']:10.3g}")
    for e in result["comparison"]:
        print(f"  JAX / NumPy at {e['draws']} draws: {e['jax_over_numpy']:.2f}x")
    print("gradient (reverse mode, cost w.r.t. gains, tanh):")
    for e in result["gradient"]:
        memory = e["gradient_memory"].get("peak_bytes")
        print(
            f"  {e['draws']} draws x {e['horizon_s']:g} s (blocks of {e['save_every']}): "
            f"{e['gradient_draw_steps_per_s']:10.3g} draw-steps/s, "
            f"{e['gradient_over_forward']:.2f}x forward "
            f"({e['gradient_over_forward_cpu_time']:.2f}x in CPU time), "
            f"compile {e['gradient_compile_s']:.1f} s, peak "
            + (f"{memory / 2**20:.1f} MiB" if memory else "n/a")
        )
    if isinstance(result["crazyflow"], list):
        for e in result["crazyflow"]:
            print(f"crazyflow {e['worlds']} worlds: {e['drone_steps_per_s']:.3g} drone-steps/s")
    else:
        print(f"crazyflow: {result['crazyflow']}")


if __name__ == "__main__":
    main()
