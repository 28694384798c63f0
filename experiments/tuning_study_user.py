"""The tuning study's user view (:mod:`experiments.tuning_study`): ``fojax tune`` as a
new user runs it, in a fresh process with an empty cache, timed as a whole, each run
kept under its fingerprint (:func:`experiments._common.cached`). The commands
(:data:`experiments.tuning_study_report.USER_MODES`): from the naive start the default
method and ``--method cma-es`` (does the default end at or below CMA-ES's held-out cost
in at most its wall time?), and from the paper's gains the default (does it halve the
held-out cost?)."""

from __future__ import annotations

import csv
import functools
import itertools
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from experiments import _common
from experiments.tuning_study_report import USER_MODES
from fojax.cli import output


def records(args, out: Path, run: bool = True) -> list[dict]:
    """The user-view records of these settings: where ``run``, each command run (or read
    back) ``args.user_view`` times, interleaving the commands (:func:`_run`); else those
    already stored under ``out/user_view`` for these settings and this code
    (:func:`experiments._common.stored`), run by run."""
    if run and args.user_view:
        return [
            _common.cached(
                *_key(args, out, mode, index), functools.partial(_run, args, out, mode, index)
            )
            for index, mode in itertools.product(range(args.user_view), USER_MODES)
        ]
    found = []
    for index in itertools.count():
        kept = [_common.stored(*_key(args, out, mode, index)) for mode in USER_MODES]
        if not any(kept):
            return found
        found += [record for record in kept if record is not None]


def _key(args, out: Path, mode: str, index: int) -> tuple:
    """``(folder, stem, fingerprint)`` of a user-view run (:func:`experiments._common.cached`)."""
    return out / "user_view", f"{mode}_{index}", user_fingerprint(args, mode, index)


def user_command(args, mode: str, out: Path) -> list[str]:
    """The ``fojax tune`` command of ``mode`` (``<start>-<method>``: scenario 2, the
    default cost; ``default`` leaves ``--method`` out)."""
    start, method = mode.split("-", 1)
    command = ["fojax", "tune", "--scenario", str(args.scenario), "--controller", "afonftsmc",
               "--init", start]  # fmt: skip
    if method != "default":
        command += ["--method", method]
    if args.tiny:
        command += ["--horizon", str(args.horizon), "--dtype", "float64", "--draws", "3"]
        command += ["--validation-draws", "2", "--eval-draws", "4", "--steps", "2"]
    return command + ["--out", str(out)]


def user_fingerprint(args, mode: str, index: int) -> dict:
    """What one user-view run depends on: its command (``DIR`` for the output folder)
    and the empty cache it starts from."""
    return {"command": user_command(args, mode, Path("DIR")), "run": index, "cache": "empty"}


def _run(args, out: Path, mode: str, index: int) -> dict:
    """One user-view run: the command in a fresh process with an empty cache (its own
    ``XDG_CACHE_HOME``, the folder of ``fojax``'s persistent and export caches), timed
    as a whole, and what it wrote (kept under its fingerprint by :func:`records`)."""
    run_dir = out / "user_view" / f"{mode}_{index}"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    command = user_command(args, mode, run_dir)
    with _common.cold_environment("fojax-user-view-") as env:
        load, t0 = output.load_average(), time.perf_counter()
        argv = [sys.executable, "-m", "fojax.cli", *command[1:], "--quiet"]
        subprocess.run(argv, check=True, env=env, stdout=subprocess.DEVNULL)
        total = time.perf_counter() - t0
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    gains = json.loads((run_dir / "gains.json").read_text())["metadata"]
    with open(run_dir / "history.csv", newline="") as handle:
        history = list(csv.DictReader(handle))
    record = {
        "mode": mode,
        "run": index,
        "command": " ".join(command[:-2]),
        "total_s": round(total, 1),
        "tuning_s": float(history[-1]["wall_time_s"]),
        "heldout_initial": evaluation["initial"]["cost"],
        "heldout_tuned": evaluation["tuned"]["cost"],
        "heldout_draws": evaluation["draws"],
        "returned_step": gains["returned_step"],
        "validation": gains["validation"],
        "load_before": load,
        "load_after": output.load_average(),
    }
    output.log(
        args.quiet,
        f"  user view ({mode}, run {index}): {total:.0f} s in all, held-out "
        f"{record['heldout_initial']:.4g} -> {record['heldout_tuned']:.4g}",
    )
    return record
