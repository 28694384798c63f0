"""The throughput blocks of docs/performance.md: a ``fojax bench`` JSON as tables.

    python -m experiments.bench_report [--json FILE] [--name NAME] [--update-doc DOC]
                                       [fojax bench options ...]
    python -m experiments.bench_report --from FILE [--commit HASH] [--name NAME]
                                       [--update-doc DOC]

Without ``--from`` it runs ``fojax bench --json FILE`` (default
``results/bench/bench.json``) with the other options given (none: ``fojax bench``'s
default sizes), in a process of its own, and renders what it wrote. With ``--from
FILE`` it runs nothing and renders an existing JSON, measured elsewhere (a GPU
machine). The block holds the forward throughput (draws, horizon, draw-steps per
second, compile time by phase, kernels per step), the reverse-mode gradient (draws,
horizon, draw-steps per second, ratio to the forward, compile time, kernels per step
of each pass, peak memory), the NumPy reference side by side, and crazyflow's figures
where the JSON has them; every figure present in the JSON is shown, whatever its draw
counts and horizons.

The block's label (:func:`fojax.cli.output.format_label`, as every block's) is built from
the JSON alone: its provenance (commit and whether the tree had uncommitted changes,
the versions of Python, jax, jaxlib, optax and NumPy) and its machine (CPU model,
cores, load average at the start, devices and their kind), not from the machine
rendering it; its command is this command, or with ``--from`` the command that made
the JSON. ``--commit HASH`` names the commit of a clean tree for a JSON made where the
checkout had no git metadata (the label says so). ``--update-doc DOC`` replaces the
block ``<!-- NAME:begin -->`` ... ``<!-- NAME:end -->`` of DOC (``--name``, default
``bench``); without it the block is printed.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

from experiments import _common
from fojax.cli import output

__all__ = ["build_parser", "label_record", "main", "parse_args", "render", "step_loops"]

DEFAULT_JSON = Path("results/bench/bench.json")


# ----------------------------------------------------------------------------- label


def label_record(result: dict, command: str, commit: str | None = None) -> dict:
    """The label's record of a bench ``result`` (its JSON): ``command``, the commit and
    whether the tree was dirty (from the provenance; ``commit``: the commit of a clean
    tree, for a JSON that records none), the CPU model, cores and load average at the
    start (from its machine), the versions, and the backend, device count and kind."""
    provenance, machine = result.get("provenance") or {}, result.get("machine") or {}
    git = provenance.get("fojax_git") or {}
    record = {
        "command": command,
        "commit": git.get("commit"),
        "dirty": git.get("dirty"),
        "cpu": machine.get("cpu_model") or machine.get("processor") or machine.get("platform"),
        "cores": machine.get("cores") or machine.get("cpu_count"),
        "load": machine.get("load_average") or [],
        **{name: provenance.get(name) for name in ("python", *output.VERSIONED)},
        **{name: machine.get(name) for name in ("backend", "device_count", "device_kind")},
        "load_when": "at the start",
    }
    if commit is not None:
        if record["commit"] is not None and not record["commit"].startswith(commit):
            raise ValueError(f"--commit {commit}: the JSON records commit {record['commit']}")
        record.update(commit=record["commit"] or commit, dirty=False, commit_given=True)
    return record


# ---------------------------------------------------------------------------- tables


def _number(x: float) -> str:
    """Three significant digits, ``2.98e6`` from 1,000 on."""
    if abs(x) < 1e3:
        return f"{x:.3g}"
    mantissa, exponent = f"{x:.2e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def step_loops(counts: list[int] | None) -> list[int]:
    """The step-level loops of :func:`fojax.cli.bench_measure.loop_kernels`' counts:
    those with at least a quarter of the largest one's kernels (the others are small
    loops of the set-up, a matrix exponential or a search)."""
    counts = list(counts or [])
    return [c for c in counts if counts and 4 * c >= counts[0]]


def _compiled(e: dict, prefix: str = "") -> str:
    """The compile cell (total, then trace + lower + XLA) and the kernels-per-step cell
    (:func:`step_loops`) of an entry's forward pass (``prefix`` ``""``) or gradient pass
    (``"gradient_"``)."""
    text, phases = f"{e[prefix + 'compile_s']:.1f} s", e.get(prefix + "compile_phases_s")
    if phases:
        parts = (phases.get(k, float("nan")) for k in ("trace_s", "lower_s", "xla_s"))
        text += " (" + " + ".join(f"{p:.1f}" for p in parts) + ")"
    loops = step_loops(e.get(prefix + "loop_kernels"))
    return f"{text} | {' + '.join(str(c) for c in loops) if loops else 'n/a'}"


def _forward(result: dict) -> list[str]:
    lines = _common.table_head(
        "draws | horizon | draw-steps/s | compile (trace + lower + XLA) | kernels per step"
    )
    for e in result["forward"]:
        rate = _number(e["draw_steps_per_s"])
        if e.get("calls", 1) > 1:
            rate += f" ({e['calls']} calls of {e['chunk']}"
            if "one_call_draw_steps_per_s" in e:
                rate += f"; as one call {_number(e['one_call_draw_steps_per_s'])}"
            rate += ")"
        lines.append(f"| {e['draws']} | {e['horizon_s']:g} s | {rate} | {_compiled(e)} |")
    return lines


def _gradient(result: dict) -> list[str]:
    lines = _common.table_head(
        "draws | horizon | draw-steps/s | gradient / forward (CPU time) | "
        "compile (trace + lower + XLA) | kernels per step, each pass | peak memory"
    )
    for e in result["gradient"]:
        cpu = e.get("gradient_over_forward_cpu_time")
        ratio = f"{e['gradient_over_forward']:.2f}x" + (f" ({cpu:.2f}x)" if cpu else "")
        peak = (e.get("gradient_memory") or {}).get("peak_bytes")
        memory = f"{peak / 2**20:.1f} MiB" if peak else "n/a"
        lines.append(
            f"| {e['draws']} | {e['horizon_s']:g} s | {_number(e['gradient_draw_steps_per_s'])} "
            f"| {ratio} | {_compiled(e, 'gradient_')} | {memory} |"
        )
    return lines


def _numpy(result: dict) -> list[str]:
    forward = {e["draws"]: e for e in result["forward"]}
    lines = _common.table_head(
        "draws | NumPy: draw-steps/s (horizon) | JAX: draw-steps/s (horizon) | JAX / NumPy"
    )
    for e in result["numpy"]:
        jax_entry = forward.get(e["draws"])
        jax_cell, ratio = "n/a", "n/a"
        if jax_entry is not None:
            jax_cell = f"{_number(jax_entry['draw_steps_per_s'])} ({jax_entry['horizon_s']:g} s)"
            ratio = f"{jax_entry['draw_steps_per_s'] / e['draw_steps_per_s']:.1f}x"
        numpy_cell = f"{_number(e['draw_steps_per_s'])} ({e['horizon_s']:g} s)"
        lines.append(f"| {e['draws']} | {numpy_cell} | {jax_cell} | {ratio} |")
    return lines


def render(result: dict, source: str | None = None) -> str:
    """The block's text (below its label) for a bench ``result``; ``source``: the
    command that rendered it from a stored JSON, stated first."""
    workload, machine = result.get("workload") or {}, result.get("machine") or {}
    provenance = result.get("provenance") or {}
    repeats = {len(e.get("run_s_all") or [None]) for e in result["forward"]}
    head = []
    if "--small" in str(provenance.get("command") or "").split():
        head.append("**Made with `fojax bench --small`, a smoke test: its figures mean nothing.**")
    if source is not None:
        created = provenance.get("created_utc")
        head.append(f"Rendered by `{source}`" + (f"; measured {created}." if created else "."))
    integrator = str(workload.get("integrator", "rk4")).upper()
    devices = f"{machine.get('device_count')} {machine.get('backend')} device(s)"
    if machine.get("device_kind") and machine.get("backend") != "cpu":
        devices += f" ({machine['device_kind']})"
    line = (
        f"Workload: scenario {workload.get('scenario', 2)}, AFONFTSMC "
        f"({workload.get('fractional_method', 'soe')}), {integrator}, "
        f"{workload.get('dt_s', 1e-3) * 1e3:g} ms, {workload.get('dtype', 'float32')}; {devices}"
    )
    if end := machine.get("load_average_end"):
        line += f"; load average at the end {', '.join(f'{x:g}' for x in end)}"
    head.append(line + ".")
    paragraphs = [
        " ".join(head),
        f"Forward rollouts (`{workload.get('switching_forward', 'sat')}` switching; median of "
        f"{'/'.join(str(r) for r in sorted(repeats))} timed runs after a warm call; a batch "
        "larger than `--chunk` runs as consecutive calls of `--chunk` draws):",
        "\n".join(_forward(result)),
        "Reverse-mode gradient of the mean tracking cost with respect to the gains "
        f"(`{workload.get('switching_gradient', 'tanh')}` switching, one copy of the gains per "
        "draw; forward and gradient calls interleaved, the ratio the median of their ratios; "
        "kernels per step of each pass: the loops with at least a quarter of the largest "
        "one's kernels; peak memory: XLA's buffer assignment):",
        "\n".join(_gradient(result)),
        "The same closed loop in NumPy, vectorised over the draws (float32, one run; "
        "`fojax/cli/numpy_reference.py`), against the forward rollouts above:",
        "\n".join(_numpy(result)),
    ]
    crazyflow = result.get("crazyflow")
    if isinstance(crazyflow, list) and crazyflow:
        rates = (f"{e['worlds']} worlds {_number(e['drone_steps_per_s'])}" for e in crazyflow)
        paragraphs.append(
            f"crazyflow (analytical physics, attitude control), drone-steps/s: {', '.join(rates)}."
        )
    return "\n\n".join(paragraphs) + "\n"


# ---------------------------------------------------------------------------- writing


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser(
        "bench_report",
        description="Run fojax bench (or read its JSON with --from) and write its block.",
    )
    parser.add_argument("--from", dest="source", type=Path, metavar="FILE",
                        help="render this bench JSON; run nothing")  # fmt: skip
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON, metavar="FILE",
                        help=f"where fojax bench writes (default {DEFAULT_JSON})")  # fmt: skip
    parser.add_argument("--commit", metavar="HASH",
                        help="with --from: the commit of the clean tree the JSON was "
                        "made from, where it records none")  # fmt: skip
    parser.add_argument("--name", default="bench", help="the block's name (default bench)")
    parser.add_argument("--update-doc", type=Path, metavar="DOC",
                        help="the Markdown file whose block to replace (else: print)")  # fmt: skip
    return parser


def parse_args(argv) -> tuple[argparse.Namespace, list[str]]:
    """``(options, fojax bench's options)``: the options it does not know are passed on to
    ``fojax bench`` and checked by its parser (none with ``--from``); exits with a
    message on bad input, before anything runs."""
    from fojax.cli import bench

    parser = build_parser()
    args, bench_options = parser.parse_known_args(argv)
    if args.source is None:
        if args.commit is not None:
            parser.error("--commit is for --from: a run here records its own commit")
        bench.parse_args(["--json", str(args.json), *bench_options])
    elif bench_options:
        parser.error(f"--from runs nothing: {' '.join(bench_options)} not used")
    return args, bench_options


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args, bench_options = parse_args(argv)
    parser = build_parser()  # the errors found later, in its name
    if args.source is None:
        bench = [sys.executable, "-m", "fojax.cli", "bench", "--json", str(args.json)]
        status = subprocess.run([*bench, *bench_options]).returncode
        if status:
            return status
    elif not args.source.is_file():
        parser.error(f"--from {args.source}: no such file (make it with fojax bench --json FILE)")
    result = json.loads((args.source or args.json).read_text())
    invocation = shlex.join(["python", "-m", "experiments.bench_report", *argv])
    source = None if args.source is None else invocation
    recorded = (result.get("provenance") or {}).get("command") or "unknown"
    command = invocation if source is None else recorded
    body = render(result, source)
    try:
        record = label_record(result, command, args.commit)
    except ValueError as error:
        parser.error(str(error))
    if args.update_doc is None:
        print(f"{output.format_label(record)}\n\n{body}")
    else:
        output.splice(args.update_doc, body.rstrip(), name=args.name, label=record)
        output.log(False, f"wrote the {args.name} block of {args.update_doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
