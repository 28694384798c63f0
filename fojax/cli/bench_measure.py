"""The measurements of ``fojax bench`` (:mod:`fojax.cli.bench`): the standard workload
(scenario 2, AFONFTSMC, RK4, 1 ms, float32), its forward rollouts in chunks of draws,
the reverse-mode gradient of its cost with respect to the gains, the NumPy reference
and crazyflow, each timed apart from its compilation."""

from __future__ import annotations

import functools
import math
import re
import time


class _Workload:
    """The standard workload, built for a given horizon."""

    def __init__(self, horizon: float, switching: str = "sat"):
        from fojax import plant, scenarios, simulator
        from fojax.controllers import make_controller, paper_gains

        self.dt = 1e-3
        steps = int(round(horizon / self.dt))
        # Checkpointed blocks of the divisor of ``steps`` nearest ``sqrt(steps)`` keep
        # reverse-mode memory ``O(sqrt(steps))``.
        save_every = simulator.divisor_near(steps, math.sqrt(steps))
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


def _timed(fn) -> tuple[float, float]:
    """Wall and CPU seconds of one call of ``fn``, up to its results being ready."""
    import jax

    start, start_cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn())
    return time.perf_counter() - start, time.process_time() - start_cpu


def _median_time(fn, repeats: int) -> tuple[float, list[float]]:
    """The median wall time of ``repeats`` calls of ``fn``, and all of them, sorted."""
    times = sorted(_timed(fn)[0] for _ in range(repeats))
    return times[len(times) // 2], times


def _padded_count(count: int, devices: int) -> int:
    return count + (-count % devices)


def _compile(fn, *args) -> tuple:
    """``fn`` compiled for ``args``, its compile time (s) and that time by phase:
    ``{"trace_s", "lower_s", "xla_s"}`` (tracing to a jaxpr, lowering to StableHLO,
    XLA's optimisation and code generation). The compiled ``fn`` has run once on
    ``args`` (untimed warm-up)."""
    import jax

    stage, phases = fn, {}
    for phase, advance in (
        ("trace_s", lambda jitted: jitted.trace(*args)),
        ("lower_s", lambda traced: traced.lower()),
        ("xla_s", lambda lowered: lowered.compile()),
    ):
        start = time.perf_counter()
        stage = advance(stage)
        phases[phase] = time.perf_counter() - start
    jax.block_until_ready(stage(*args))
    return stage, sum(phases.values()), phases


_NOT_KERNELS = frozenset({"parameter", "get-tuple-element", "tuple", "constant", "bitcast"})
_INSTRUCTION = re.compile(r"=\s*(?:\([^=]*?\)|\S+)\s+([a-z][\w-]*)\(")
_WHILE_BODY = re.compile(r"\swhile\(.*?body=%?([\w.-]+)")


def loop_kernels(compiled) -> list[int]:
    """The kernels in the body of each innermost loop of ``compiled``'s optimised HLO,
    largest first: the instructions of the loop's body other than parameters, tuples,
    their elements, constants and bitcasts (each remaining instruction, a fusion, copy,
    library call or collective, runs as one kernel per iteration). The time loop's step
    is the largest; a reverse-mode program has one per pass (sweep, rematerialisation,
    backward step). ``[]`` where the backend gives no HLO text."""
    try:
        text = compiled.as_text()
    except Exception:  # not every backend gives it
        return []
    bodies: dict[str, list[str]] = {}
    name = None
    for line in text.splitlines():
        if line.endswith("{") and not line.startswith(" "):
            name = line.removeprefix("ENTRY ").split()[0].lstrip("%")
            bodies[name] = []
        elif line.startswith("}"):
            name = None
        elif name is not None and (found := _INSTRUCTION.search(line)):
            bodies[name].append(found.group(1))
    loops = (bodies.get(body, []) for body in set(_WHILE_BODY.findall(text)))
    innermost = [ops for ops in loops if ops and "while" not in ops]
    return sorted((sum(op not in _NOT_KERNELS for op in ops) for ops in innermost), reverse=True)


def _memory(compiled) -> dict:
    try:
        stats = compiled.memory_analysis()
    except Exception:  # not every backend reports it
        return {}
    if stats is None:
        return {}
    parts = ("temp", "argument", "output", "generated_code")
    out = {f"{k}_size_bytes": int(getattr(stats, f"{k}_size_in_bytes", 0)) for k in parts}
    out["peak_bytes"] = sum(out[f"{k}_size_bytes"] for k in parts[:3])
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
    compiled, compile_s, phases = _compile(run, gains, chunks[0])
    run_s, times = _median_time(lambda: [compiled(gains, c) for c in chunks], repeats)
    steps = work.config.steps
    entry = {
        "draws": count,
        "draws_computed": n_chunks * padded_chunk,
        "chunk": chunk,
        "calls": n_chunks,
        "horizon_s": horizon,
        "steps": steps,
        "compile_s": compile_s,
        "compile_phases_s": phases,
        "loop_kernels": loop_kernels(compiled),
        "run_s": run_s,
        "run_s_all": times,
        "draw_steps_per_s": count * steps / run_s,
    }
    if n_chunks > 1:
        whole = place(0, _padded_count(count, devices))
        one_call, one_compile_s, _ = _compile(run, gains, whole)
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
        # loop and are summed once, after it (see :meth:`_Workload.run_draws`).
        return work.run_draws(gains, draws, cost, per_draw_gains=True).outputs

    per_device = sharding.sharded_batch(costs, mesh, batched=(False, True))

    def forward(gains, draws):
        return jnp.mean(per_device(gains, draws))

    forward_c, forward_compile_s, forward_phases = _compile(jax.jit(forward), gains, draws)
    gradient_c, gradient_compile_s, gradient_phases = _compile(
        jax.jit(jax.grad(forward)), gains, draws
    )
    # Interleaved, so that a load that comes and goes falls on both alike; the ratio is
    # the median of the per-round ratios. Each round: ((wall, cpu) forward, gradient).
    rounds = [
        [_timed(functools.partial(fn, gains, draws)) for fn in (forward_c, gradient_c)]
        for _ in range(repeats)
    ]
    forward_s, gradient_s = (float(np.median([r[i][0] for r in rounds])) for i in (0, 1))
    ratios, cpu_ratios = ([g[i] / f[i] for f, g in rounds] for i in (0, 1))
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
        "forward_compile_phases_s": forward_phases,
        "gradient_compile_phases_s": gradient_phases,
        "forward_loop_kernels": loop_kernels(forward_c),
        "gradient_loop_kernels": loop_kernels(gradient_c),
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
    rate = count * steps / run_s
    return dict(draws=count, horizon_s=horizon, steps=steps, run_s=run_s, draw_steps_per_s=rate)


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
    return dict(worlds=count, steps=steps, run_s=run_s, drone_steps_per_s=count * steps / run_s)
