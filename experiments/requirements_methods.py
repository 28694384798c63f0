"""``fojax tune --requirements`` on docs/requirements.md's default case, once per method,
as a new user runs it.

    python -m experiments.requirements_methods [--out results/requirements_methods]
        [--methods auto,cma-es,adam] [--update-doc]

Each method runs ``fojax tune --scenario 2 --controller afonftsmc --requirements
examples/requirements/small_quadrotor.toml --objective effort --method M`` (the
defaults otherwise) in a fresh process with a fresh ``HOME`` and ``XDG_CACHE_HOME`` (no
compilation cache), one after another, timed as a whole; the table reads what each run
wrote (``gains.json``, ``history.csv``, ``evaluation.json``): the tuning's time, the
first validation at full yield, the selected step, the held-out yield and effort of the
start and of the tuned gains, and the forward draw-steps. Writes ``results.json`` and
``table.md`` to ``--out``; ``--update-doc`` replaces the ``requirements-methods`` block
of docs/requirements.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from experiments import _common
from fojax.cli import output
from fojax.optimize.strategies import METHODS

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "requirements.md"
REQUIREMENTS = "examples/requirements/small_quadrotor.toml"


def command(method: str, out: Path) -> list[str]:
    """The ``fojax tune`` command of ``method``, writing to ``out``."""
    return [
        *("fojax", "tune", "--scenario", "2", "--controller", "afonftsmc"),
        *("--requirements", REQUIREMENTS, "--objective", "effort", "--method", method),
        *("--quiet", "--out", str(out)),
    ]


def run_method(method: str, out: Path) -> dict:
    """Run ``method`` cold in a process of its own; its wall time and what it wrote."""
    if out.exists():
        shutil.rmtree(out)
    with _common.cold_environment("fojax-requirements-methods-") as env:
        load, start = output.load_average(), time.perf_counter()
        argv = [sys.executable, "-m", "fojax.cli", *command(method, out)[1:]]
        subprocess.run(argv, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
        seconds = time.perf_counter() - start
    metadata = json.loads((out / "gains.json").read_text())["metadata"]
    evaluation = json.loads((out / "evaluation.json").read_text())
    with open(out / "history.csv", newline="") as handle:
        history = list(csv.DictReader(handle))
    full = [row for row in history if row["validation"] and float(row["validation"]) == 1.0]
    return {
        "method": method,
        "command": " ".join(command(method, Path("DIR"))),
        "command_s": round(seconds, 1),
        "tuning_s": metadata["wall_time_s"],
        "first_full_validation": (
            {"step": int(full[0]["step"]), "wall_time_s": float(full[0]["wall_time_s"])}
            if full
            else None
        ),
        "validation_draws": (metadata["validation"] or {}).get("draws"),
        "returned_step": metadata["returned_step"],
        "draw_steps": metadata["draw_steps"],
        "heldout": {k: evaluation[k] for k in ("draws", "horizon_s", "initial", "tuned")},
        "load_before": load,
        "load_after": output.load_average(),
    }


def table(runs: list[dict]) -> str:
    first = runs[0]["heldout"]["initial"]
    rows = [
        "| `--method` | command (s) | tuning (s) | first validation at full yield: step, "
        f"time (s) | selected step | held-out yield, tuned (start {first['passed']}/"
        f"{first['draws']}) | effort, tuned (start {first['objective']:.3g}) | forward "
        "draw-steps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        full = run["first_full_validation"]
        when = f"{full['step']}, {full['wall_time_s']:.0f}" if full else "never"
        tuned = run["heldout"]["tuned"]
        name = f"`{run['method']}`" + (" (the default)" if run["method"] == "auto" else "")
        rows.append(
            f"| {name} | {run['command_s']:.0f} | {run['tuning_s']:.0f} | {when} | "
            f"{run['returned_step']} | {_common.yield_cell(tuned)} | {tuned['objective']:.3g} | "
            f"{run['draw_steps']:.3g} |"
        )
    heldout = runs[0]["heldout"]
    return (
        f"Each method's `{' '.join(command('M', Path('DIR')))}` in a "
        "fresh process with a fresh HOME and XDG_CACHE_HOME, one after another; the "
        f"held-out yield on {heldout['draws']} draws x {heldout['horizon_s']:g} s:\n\n"
        + "\n".join(rows)
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.requirements_methods")
    parser.add_argument("--out", type=Path, default=Path("results/requirements_methods"))
    parser.add_argument("--methods", default="auto,cma-es,adam")
    parser.add_argument("--update-doc", action="store_true")
    args = parser.parse_args(argv)
    methods = _common.listed(args.methods)
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        parser.error(f"--methods: {', '.join(unknown) or 'none given'}; choose from {METHODS}")
    runs = []
    for method in methods:
        print(f"{method}: {' '.join(command(method, args.out / method))}", flush=True)
        runs.append(run_method(method, args.out / method))
        print(f"  {runs[-1]['command_s']:.0f} s", flush=True)
    results = {"runs": runs, "command": output.invocation()}
    doc = DOC if args.update_doc else None
    return _common.finish(args.out, results, table(runs), doc, "requirements-methods")


if __name__ == "__main__":
    sys.exit(main())
