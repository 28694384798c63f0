"""docs/distributed.md's measurement: one process with two host devices against two
processes of one device each joined by ``jax.distributed`` on this machine.

    python -m experiments.distributed_timing [--out results/distributed] [--repeats 2]
        [--update-doc]

Runs :data:`COMMAND` (``fojax simulate``, compilation cache off) ``--repeats`` times
each way, alternating: one process with ``--xla_force_host_platform_device_count=2``,
then two processes of one device each on a free localhost port. Times each run as a
whole (for two processes: until both ended) and compares every per-draw array of
``draws.npz`` with the one-process run's, bit for bit. ``--update-doc`` writes the
table into the ``distributed`` block of docs/distributed.md.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _common
from fojax import sharding
from fojax.cli import output

DOC = Path(__file__).resolve().parents[1] / "docs" / "distributed.md"
COMMAND = (
    "simulate --scenario 2 --controller afonftsmc --draws 200 --horizon 20 --seed 3 "
    "--no-figures --no-compile-cache --quiet"
).split()


def run(processes: int, out: Path) -> float:
    """Wall time of :data:`COMMAND` as ``processes`` processes (one device each when
    several, two host devices when one), writing to ``out``."""
    shutil.rmtree(out, ignore_errors=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "SLURM_"))}
    devices = 2 if processes == 1 else 1
    env.update(XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu")
    base = [sys.executable, "-m", "fojax.cli", *COMMAND, "--out", str(out)]
    port = sharding.free_port()
    commands = [base] if processes == 1 else [
        base + ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(processes),
                "--process-id", str(index)]
        for index in range(processes)
    ]  # fmt: skip
    start = time.perf_counter()
    started = [subprocess.Popen(c, env=env, stderr=subprocess.PIPE, text=True) for c in commands]
    for process in started:
        _, err = process.communicate(timeout=1800)
        if process.returncode:
            raise SystemExit(f"{shlex.join(process.args)} failed:\n{err[-3000:]}")
    return time.perf_counter() - start


def equal_arrays(a: Path, b: Path) -> tuple[int, int]:
    """How many per-draw arrays of ``a/draws.npz`` equal ``b``'s bit for bit, of all."""
    with np.load(a / "draws.npz") as one, np.load(b / "draws.npz") as two:
        names = sorted(set(one.files) | set(two.files))
        same = sum(
            name in one.files and name in two.files and np.array_equal(one[name], two[name])
            for name in names
        )
    return same, len(names)


def main(argv=None) -> int:
    parser = _common.parser("distributed_timing")
    parser.add_argument("--out", type=Path, default=Path("results/distributed"))
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--update-doc", action="store_true")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    times = {1: [], 2: []}
    for index in range(args.repeats):
        for processes in (1, 2):
            seconds = run(processes, args.out / f"p{processes}_{index}")
            times[processes].append(seconds)
            print(f"{processes} process(es), run {index + 1}: {seconds:.1f} s", flush=True)
    same, total = equal_arrays(args.out / "p1_0", args.out / "p2_0")
    load = ", ".join(f"{x:g}" for x in output.load_average()) or "unknown"
    cell = {p: ", ".join(f"{s:.1f} s" for s in runs) for p, runs in times.items()}
    verdict = "equal to the one-process run's, bit for bit" if same == total else "differ"
    text = "\n".join([
        f"`fojax {' '.join(COMMAND)}`, {args.repeats} runs each way, alternating; load "
        f"average at the end {load}.",
        "",
        *_common.table_head("run | wall time | per-draw arrays"),
        f"| one process, 2 host devices | {cell[1]} | - |",
        f"| two processes on localhost (1 device each) | {cell[2]} | {verdict} ({same} of "
        f"{total} arrays) |",
    ])  # fmt: skip
    print(text)
    if args.update_doc:
        output.splice(DOC, text, name="distributed")
    return 0 if same == total else 1


if __name__ == "__main__":
    sys.exit(main())
