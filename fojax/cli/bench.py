"""``fojax bench``: throughput, compile time and gradient cost of the closed loop.

Standard workload: scenario 2, AFONFTSMC with the default fractional method (sum of
exponentials), RK4, 1 ms, float32. Measured in one run, on every device JAX sees
(draws sharded with :mod:`fojax.sharding`):

* forward rollouts at several draw counts: draw-steps per second (median of
  ``--repeats`` runs) and compile time, apart; batches larger than ``--chunk`` draws
  run as consecutive calls of ``--chunk`` draws each (as the Monte Carlo layer runs
  them; one call of a big batch streams the fractional memory from DRAM every step),
  and are also timed as one call for comparison;
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

Big batches run a shorter horizon (``--long-horizon`` for at most ``--long-max-draws``
draws, ``--short-horizon`` above): cost is linear in the horizon (``--scaling``
measures it), and the horizon used is printed and stored with each figure. On a CPU
the default spreads the draws over one XLA host device per core
(``--xla_force_host_platform_device_count``; set before JAX starts, ``--devices``
changes it). Progress goes to stderr; ``--json FILE`` writes every figure with its
units.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import resource
import sys
import time

from fojax.cli import arguments
from fojax.cli import study as study_layer

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
    return arguments._listed(text, _horizon, "0.25,1")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fojax bench",
        description=(
            "Throughput of the standard workload (scenario 2, AFONFTSMC, SOE, RK4, 1 ms, "
            "float32): forward, gradient, NumPy reference. Defaults finish in a few "
            "minutes on a 2-core CPU."
        ),
    )
    parser.add_argument(
        "--json",
        type=arguments.output_file,
        metavar="FILE",
        help="write every figure, with units and provenance, here (checked before running)",
    )
    parser.add_argument(
        "--draws", type=arguments.positive_ints, default=DEFAULT_DRAWS, help="forward draw counts"
    )
    parser.add_argument(
        "--long-horizon", type=_horizon, default=4.0, help="horizon (s), small batches"
    )
    parser.add_argument(
        "--short-horizon", type=_horizon, default=1.0, help="horizon (s), big batches"
    )
    parser.add_argument(
        "--long-max-draws",
        type=arguments.positive_int,
        default=64,
        help="batches up to this size run the long horizon",
    )
    parser.add_argument(
        "--repeats", type=arguments.positive_int, default=3, help="timed runs (median)"
    )
    parser.add_argument(
        "--chunk",
        type=arguments.positive_int,
        default=DEFAULT_CHUNK,
        help="draws per compiled call for bigger forward batches (Monte Carlo chunks)",
    )
    parser.add_argument(
        "--gradient-draws",
        type=arguments.positive_ints,
        default=(64, 256),
        help="draw counts of the gradient runs (comma-separated; default 64,256)",
    )
    parser.add_argument(
        "--gradient-horizons",
        type=_horizons,
        default=(0.25, 1.0, 4.0),
        help="horizons (s) of the gradient runs (memory against horizon)",
    )
    parser.add_argument(
        "--numpy-draws",
        type=arguments.positive_ints,
        default=None,
        help="draw counts of the NumPy reference (default: the forward ones)",
    )
    parser.add_argument("--numpy-horizon", type=_horizon, default=0.25, help="NumPy horizon (s)")
    parser.add_argument(
        "--scaling",
        action="store_true",
        help="also measure forward cost against draws and horizon (linearity)",
    )
    parser.add_argument(
        "--devices",
        type=arguments.positive_int,
        default=None,
        help="CPU only: XLA host devices to split the draws over (default: CPU cores)",
    )
    parser.add_argument(
        "--small",
        action="store_true",
        help="tiny sizes for a smoke test (seconds, not minutes; figures meaningless); it "
        "sets --draws, the horizons, --repeats and the gradient and NumPy sizes itself",
    )
    return parser


# ----------------------------------------------------------------------------- pieces


class _Workload:
    """The standard workload, built for a given horizon."""

    def __init__(self, horizon: float, switching: str = "sat", save_every: int | None = None):
        from fojax import plant, scenarios, simulator
        from fojax.controllers import make_controller, paper_gains

        self.dt = 1e-3
        steps = int(round(horizon / self.dt))
        if save_every is None:
            save_every = _block_size(steps)
        self.scenario = scenarios.get_scenario(2)
        self.config = simulator.SimulationConfig(dt=self.dt, horizon=horizon, save_every=save_every)
        # The fractional memory is sized for the scenario's 80 s, whatever the horizon.
        self.controller = make_controller(
            "afonftsmc", dt=self.dt, horizon=80.0, switching=switching
        )
        self.gains = paper_gains("float32")
        self.model = plant.nominal_params("float32")

    def draws(self, count: int):
        import jax

        from fojax import scenarios

        keys = scenarios.draw_keys(0, range(count))
        return jax.vmap(lambda k: scenarios.sample_draw(self.scenario, k, self.dt, "float32"))(keys)

    def run_draws(self, gains, draws, observer=None, per_draw_gains=False):
        """The rollout of a batch of draws (``draws`` batch first, as :meth:`draws` makes
        them), run with the batch last; results batch first. ``per_draw_gains``: one
        copy of the gains per draw, so that under ``grad`` their cotangents stay per
        draw inside the time loop and are summed once, after it."""
        import jax
        import jax.numpy as jnp

        from fojax import scenarios, simulator

        draws = scenarios.batch_last(draws)
        if per_draw_gains:
            n = draws.params.mass.shape[-1]
            gains = jax.tree.map(lambda g: jnp.broadcast_to(g[..., None], g.shape + (n,)), gains)
        result = simulator.rollout(
            self.controller, gains, self.model, self.scenario, draws, self.config, observer
        )
        return scenarios.batch_first(result)


def _block_size(steps: int) -> int:
    """The divisor of ``steps`` nearest ``sqrt(steps)``: checkpointed blocks of that many
    steps keep reverse-mode memory ``O(sqrt(steps))``."""
    from fojax import simulator

    return simulator.divisor_near(steps, math.sqrt(steps))


def _median_time(fn, repeats: int) -> tuple[float, list[float]]:
    import jax

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    times.sort()
    return times[len(times) // 2], times


def _padded_count(count: int, devices: int) -> int:
    return count if count % devices == 0 else count + (-count % devices)


def _compile(fn, *args):
    start = time.perf_counter()
    compiled = fn.lower(*args).compile()
    return compiled, time.perf_counter() - start


def _memory(compiled) -> dict:
    try:
        stats = compiled.memory_analysis()
    except Exception:  # not every backend reports it
        return {}
    if stats is None:
        return {}
    fields = (
        "temp_size_in_bytes",
        "argument_size_in_bytes",
        "output_size_in_bytes",
        "generated_code_size_in_bytes",
    )
    out = {name.replace("_in_bytes", "_bytes"): int(getattr(stats, name, 0)) for name in fields}
    out["peak_bytes"] = (
        out["temp_size_bytes"] + out["argument_size_bytes"] + out["output_size_bytes"]
    )
    return out


def measure_forward(
    count: int, horizon: float, repeats: int, mesh, chunk: int | None = None
) -> dict:
    """Forward rollouts of ``count`` draws over ``horizon`` seconds.

    With ``chunk`` smaller than ``count``, the draws run as consecutive calls of
    ``chunk`` draws each (one compiled function), the way :mod:`fojax.study` runs
    them; the batch is also timed as one call (``one_call_*``).
    """
    import jax

    from fojax import sharding

    work = _Workload(horizon)
    devices = mesh.devices.size
    chunk = count if chunk is None or chunk >= count else chunk
    padded_chunk = _padded_count(chunk, devices)
    n_chunks = math.ceil(count / chunk)
    all_draws = work.draws(n_chunks * padded_chunk)
    gains = sharding.replicate(work.gains, mesh)
    run = sharding.sharded_batch(work.run_draws, mesh, batched=(False, True))

    def place(first, size):
        return sharding.shard_draws(
            jax.tree.map(lambda x: x[first : first + size], all_draws), mesh
        )

    chunks = [place(i * padded_chunk, padded_chunk) for i in range(n_chunks)]
    compiled, compile_s = _compile(run, gains, chunks[0])
    jax.block_until_ready(compiled(gains, chunks[0]))  # warm

    def run_all():
        return [compiled(gains, c) for c in chunks]

    run_s, times = _median_time(run_all, repeats)
    steps = work.config.steps
    entry = {
        "draws": count,
        "draws_computed": n_chunks * padded_chunk,
        "chunk": chunk,
        "calls": n_chunks,
        "horizon_s": horizon,
        "steps": steps,
        "compile_s": compile_s,
        "run_s": run_s,
        "run_s_all": times,
        "draw_steps_per_s": count * steps / run_s,
    }
    if n_chunks > 1:
        padded = _padded_count(count, devices)
        whole = place(0, padded)
        one_call, one_compile_s = _compile(run, gains, whole)
        jax.block_until_ready(one_call(gains, whole))
        one_s, _ = _median_time(lambda: one_call(gains, whole), repeats)
        entry.update(
            one_call_compile_s=one_compile_s,
            one_call_run_s=one_s,
            one_call_draw_steps_per_s=count * steps / one_s,
        )
    return entry


def measure_gradient(count: int, horizon: float, repeats: int, mesh) -> dict:
    """Reverse-mode gradient of the mean rollout cost w.r.t. the gains (tanh switching)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from fojax import observers, sharding

    work = _Workload(horizon, switching="tanh")
    devices = mesh.devices.size
    padded = _padded_count(count, devices)
    draws = sharding.shard_draws(work.draws(padded), mesh)
    gains = sharding.replicate(work.gains, mesh)

    cost = observers.TrackingISE(work.dt)

    def costs(gains, draws):
        # One copy of the gains per draw: their cotangents stay per draw inside the time
        # loop and are summed once, after it (see the module docstring).
        return work.run_draws(gains, draws, cost, per_draw_gains=True).outputs

    per_device = sharding.sharded_batch(costs, mesh, batched=(False, True))

    def forward(gains, draws):
        return jnp.mean(per_device(gains, draws))

    forward_jit = jax.jit(forward)
    gradient_jit = jax.jit(jax.grad(forward))
    forward_c, forward_compile_s = _compile(forward_jit, gains, draws)
    gradient_c, gradient_compile_s = _compile(gradient_jit, gains, draws)
    jax.block_until_ready(forward_c(gains, draws))
    jax.block_until_ready(gradient_c(gains, draws))
    # Interleaved, so that a load that comes and goes falls on both alike; the ratio is
    # the median of the per-round ratios.
    forward_all, gradient_all, cpu_forward, cpu_gradient = [], [], [], []
    for _ in range(repeats):
        for fn, wall, cpu in (
            (forward_c, forward_all, cpu_forward),
            (gradient_c, gradient_all, cpu_gradient),
        ):
            start, start_cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(gains, draws))
            wall.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
    forward_s, gradient_s = float(np.median(forward_all)), float(np.median(gradient_all))
    ratios = [g / f for f, g in zip(forward_all, gradient_all, strict=True)]
    cpu_ratios = [g / f for f, g in zip(cpu_forward, cpu_gradient, strict=True)]
    steps = work.config.steps
    return {
        "draws": count,
        "draws_computed": padded,
        "horizon_s": horizon,
        "steps": steps,
        "save_every": work.config.save_every,
        "forward_s": forward_s,
        "gradient_s": gradient_s,
        "gradient_over_forward": float(np.median(ratios)),
        "gradient_over_forward_all": ratios,
        "gradient_over_forward_cpu_time": float(np.median(cpu_ratios)),
        "gradient_draw_steps_per_s": count * steps / gradient_s,
        "forward_compile_s": forward_compile_s,
        "gradient_compile_s": gradient_compile_s,
        "gradient_memory": _memory(gradient_c),
        "forward_memory": _memory(forward_c),
    }


def measure_numpy(count: int, horizon: float) -> dict:
    """The NumPy reference (float32, like the JAX workload), one timed run."""
    import numpy as np

    from fojax.cli import numpy_reference

    work = _Workload(horizon)
    prepared = numpy_reference.prepare(
        work.controller, work.gains, work.model, work.draws(count), np.float32
    )
    start = time.perf_counter()
    numpy_reference.simulate(prepared, work.scenario, work.config)
    run_s = time.perf_counter() - start
    steps = work.config.steps
    return {
        "draws": count,
        "horizon_s": horizon,
        "steps": steps,
        "run_s": run_s,
        "draw_steps_per_s": count * steps / run_s,
    }


def measure_crazyflow(count: int, steps: int) -> dict:
    """crazyflow's simulator (attitude control, analytical physics) at ``count`` worlds."""
    import numpy as np
    from crazyflow.control import Control
    from crazyflow.sim import Physics, Sim

    sim = Sim(
        n_worlds=count,
        n_drones=1,
        physics=Physics.analytical,
        control=Control.attitude,
        device="cpu",
    )
    sim.reset()
    cmd = np.zeros((count, 1, 4))
    cmd[..., 0] = 0.3
    sim.attitude_control(cmd)
    sim.step(10)  # compile
    start = time.perf_counter()
    sim.step(steps)
    run_s = time.perf_counter() - start
    return {
        "worlds": count,
        "steps": steps,
        "run_s": run_s,
        "drone_steps_per_s": count * steps / run_s,
    }


# ------------------------------------------------------------------------------ main


UNITS = {
    "draw_steps_per_s": "draw-steps per second (draws x plant/controller steps / wall time)",
    "gradient_draw_steps_per_s": "draw-steps per second of the reverse-mode gradient",
    "drone_steps_per_s": "drone-steps per second (crazyflow)",
    "compile_s": "seconds, lowering + XLA compilation",
    "run_s": "seconds of wall time, median of the timed runs",
    "horizon_s": "simulated seconds",
    "steps": "steps of 1 ms",
    "*_bytes": "bytes (XLA buffer assignment of the compiled program, all devices' share)",
    "gradient_over_forward": "gradient wall time / forward wall time, same draws and horizon",
    "chunk": "draws per compiled call (bigger batches run as consecutive calls)",
    "jax_over_numpy": "JAX draw-steps/s / NumPy draw-steps/s at the same draw count",
}


SMALL_SETS = (
    "draws",
    "long_horizon",
    "short_horizon",
    "repeats",
    "gradient_draws",
    "gradient_horizons",
    "numpy_draws",
    "numpy_horizon",
)
"""The options ``--small`` sets itself (giving one of them with it is an error)."""


def _given(argv: list[str]) -> set[str]:
    """The destinations of the options given on the command line (not defaulted)."""
    probe = build_parser()
    for action in probe._actions:
        action.default = argparse.SUPPRESS
    return set(vars(probe.parse_known_args(argv)[0]))


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.small:
        clashing = sorted(_given(argv) & set(SMALL_SETS))
        if clashing:
            flags = ", ".join("--" + name.replace("_", "-") for name in clashing)
            parser.error(f"--small sets the sizes itself; leave {flags} out or drop --small")
        args.draws = (min(args.draws[0], 4),)
        args.long_horizon = args.short_horizon = 0.02
        args.repeats = 1
        args.gradient_draws = (min(args.gradient_draws[0], 4),)
        args.gradient_horizons = (0.02,)
        args.numpy_draws = args.draws
        args.numpy_horizon = 0.02
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
            "device_count": int(mesh.devices.size),
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "processor": platform.processor(),
            "jax": jax.__version__,
            "numpy": np.__version__,
        },
        "provenance": study_layer.provenance(["fojax", "bench", *argv]),
        "units": UNITS,
        "forward": [],
        "gradient": [],
        "numpy": [],
        "comparison": [],
        "scaling": {},
        "crazyflow": None,
    }

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

    forward_by_draws = {e["draws"]: e for e in result["forward"]}
    for entry in result["numpy"]:
        jax_entry = forward_by_draws.get(entry["draws"])
        if jax_entry is not None:
            ratio = jax_entry["draw_steps_per_s"] / entry["draw_steps_per_s"]
            result["comparison"].append({"draws": entry["draws"], "jax_over_numpy": ratio})

    for count in args.gradient_draws:
        for horizon in args.gradient_horizons:
            _log(f"gradient: {count} draws x {horizon} s ...")
            entry = measure_gradient(count, horizon, args.repeats, mesh)
            result["gradient"].append(entry)
            _log_gradient(entry)

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

    import importlib.util

    if importlib.util.find_spec("crazyflow") is not None:
        _log("crazyflow ...")
        try:
            result["crazyflow"] = [measure_crazyflow(c, 1000) for c in args.draws]
        except Exception as error:  # report, do not fail the whole benchmark
            result["crazyflow"] = {"error": f"{type(error).__name__}: {error}"}
    else:
        result["crazyflow"] = {"skipped": "crazyflow is not installed"}

    result["process_max_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    _print_summary(result)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        study_layer.write_json(args.json, result)
        _log(f"wrote {args.json}")
    return result


def _log_gradient(entry: dict) -> None:
    memory = entry["gradient_memory"].get("peak_bytes")
    _log(
        f"  {entry['gradient_draw_steps_per_s']:.3g} draw-steps/s, "
        f"{entry['gradient_over_forward']:.2f}x forward "
        f"({entry['gradient_over_forward_cpu_time']:.2f}x in CPU time), "
        f"peak {memory / 2**20 if memory else float('nan'):.1f} MiB, "
        f"compile {entry['gradient_compile_s']:.1f} s"
    )


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
