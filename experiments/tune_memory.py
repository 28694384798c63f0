"""Peak memory of the tuning gradient against the horizon (scenario 2, 256 draws).

    python -m experiments.tune_memory [--horizons 5 10 20 40 80] [--draws 256]
                                      [--execute-up-to 10] [--out results/tune_memory]

For each horizon, in a fresh process (``multiprocessing``'s ``spawn``): compile the
gradient of the mean tuning cost (:meth:`fojax.optimize.Objective.lower_gradient`: the
per-draw gradient of the fixed sample on one device, float32, AFONFTSMC, the paper's
gains) and read XLA's ``memory_analysis()`` (temporary buffers = the peak working set
the compiled program allocates besides its arguments and outputs); for horizons up to
``--execute-up-to`` s also run it once and record the process's peak resident memory
(``ru_maxrss``, which includes JAX itself and the compiler). Blocks of the rollout
(``save_every``) follow :func:`fojax.optimize.checkpoint_interval` (about ``0.75
sqrt(steps)`` steps) and, for comparison, a fixed 100 steps or one block over the whole
horizon (``--blocks auto 100 full``). Writes ``memory.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys

from experiments import _common
from fojax.cli import output


def _measure(horizon: float, draws: int, block: str, execute: bool) -> dict:
    """In a process of its own (its peak memory is the measurement): compile the
    gradient, read its memory analysis, and run it where ``execute``."""
    import resource
    import time

    import jax
    import jax.numpy as jnp

    from fojax import optimize
    from fojax.controllers.afonftsmc import paper_gains

    steps = round(horizon / 1e-3)
    save_every = None if block == "auto" else steps if block == "full" else int(block)
    spec = optimize.ProblemSpec(horizon=horizon, draws=draws, save_every=save_every)
    t0 = time.perf_counter()
    lowered, args = optimize.Objective(spec, paper_gains(jnp.float32)).lower_gradient()
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    memory = compiled.memory_analysis()
    out = {
        "horizon_s": horizon, "draws": draws, "steps": spec.steps, "save_every": spec.block,
        "blocks": spec.steps // spec.block, "temp_mb": memory.temp_size_in_bytes / 2**20,
        "argument_mb": memory.argument_size_in_bytes / 2**20, "compile_s": round(compile_s, 1),
        "executed": execute,
    }  # fmt: skip
    if execute:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        out["run_s"] = round(time.perf_counter() - t0, 1)
        out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def measure(horizon: float, draws: int, block: str, execute: bool) -> dict:
    """:func:`_measure` in a fresh process (``spawn``: nothing of this one carried over)."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(_measure, (horizon, draws, block, execute))


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("tune_memory")
    parser.add_argument("--horizons", type=float, nargs="+", default=[5, 10, 20, 40, 80])
    _common.add_numbers(parser, int, float, draws=256, execute_up_to=10.0)
    choices = (
        "block choices: auto (checkpoint_interval), a number of steps, or full "
        "(one block: no rematerialisation across the horizon)"
    )
    parser.add_argument("--blocks", nargs="+", default=["auto", "100"], help=choices)
    block = "markdown file whose tune-memory block to replace"
    _common.add_outputs(parser, "tune_memory", update_doc=block, smoke=False)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    rows = []
    for horizon in args.horizons:
        for block in args.blocks:
            if block.isdigit() and any(
                (r["horizon_s"], r["save_every"]) == (horizon, int(block)) for r in rows
            ):
                continue  # the same block size as an earlier choice of this horizon
            row = measure(horizon, args.draws, block, horizon <= args.execute_up_to)
            rows.append(row)
            print(
                f"  {row['horizon_s']:5g} s  save_every {row['save_every']:5d}  blocks "
                f"{row['blocks']:4d}  temp {row['temp_mb']:9.1f} MiB  args {row['argument_mb']:.1f}"
                f"  peak RSS {row.get('peak_rss_mb', float('nan')):8.0f} MiB  run "
                f"{row.get('run_s', '-')} s",
                flush=True,
            )
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "memory.json"
    previous = json.loads(path.read_text()) if path.exists() else []
    keep = {(r["horizon_s"], r["draws"], r["save_every"]) for r in rows}
    merged = [r for r in previous if (r["horizon_s"], r["draws"], r["save_every"]) not in keep]
    output.write_json(path, merged + rows)
    text = table(rows, args.draws)
    print(text)
    if args.update_doc is not None:
        output.splice(args.update_doc, text, name="tune-memory")
    return 0


def table(rows: list[dict], draws: int) -> str:
    """The block: per horizon and block size, the compiled gradient's working set, and
    where it ran, the process's peak resident memory and the run's time."""
    lines = [
        f"Gradient of the mean tuning cost over {draws} draws of scenario 2 (AFONFTSMC, "
        "float32, one device), XLA's `memory_analysis()` temporary buffers; executed runs: "
        "the process's peak resident memory (JAX and the compiler included).",
        "",
        *_common.table_head(
            "horizon (s) | steps | steps per block | working set (MiB) | compile (s) | "
            "peak RSS (MiB) | run (s)"
        ),
    ]
    for r in sorted(rows, key=lambda r: (r["horizon_s"], r["save_every"])):
        rss = "-" if r.get("peak_rss_mb") is None else f"{r['peak_rss_mb']:.0f}"
        lines.append(
            f"| {r['horizon_s']:g} | {r['steps']} | {r['save_every']} | {r['temp_mb']:.0f} | "
            f"{r['compile_s']:.0f} | {rss} | {r.get('run_s', '-')} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
