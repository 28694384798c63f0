"""The tuning methods as a user runs them: ``fojax tune`` in a fresh process with an
empty cache, every method of :data:`fojax.optimize.strategies.METHODS` at its defaults.

    python -m experiments.tuning_study [--out results/tuning_study] [--reference]
                                       [--carry METHODS] [--update-doc docs/tuning.md]
                                       [--tiny]

Protocol (the defaults; every number of the study's section of ``docs/tuning.md``):

* Problem: the AFONFTSMC on scenario 2, ``fojax tune``'s defaults (10 s, the default
  cost, mean objective, float32, the evaluation law ``sat``), 33 parameters
  (``--share paper``) and 66 (``--share none``), from the paper's gains and from the
  naive start, the tuning draws' seed ``s`` in ``--seeds`` for the default method and
  ``--baseline-seeds`` for the others.
* Runs: each the command ``fojax tune --scenario 2 --controller afonftsmc --init START
  --share SHARE --seed S [--method M] --quiet --out DIR`` in a process of its own with
  an empty compilation cache (``experiments._common.cold_environment``), timed as a
  whole (its wall time is the user's, start-up, compilation, the run, its held-out
  evaluation and its figure included), one after another, the load average recorded
  before and after.
* Scores: the returned gains (``gains.json``) on 64 held-out draws of seed 0 (indices
  ``2^31 + j``, the same for every run and never seen by a tuner; 10 s, ``sat``), and
  over the full horizon on 64 unseen draws (seed ``--unseen-seed``) of scenarios 2 and 3
  (``sat``): position RMSE and roll and pitch torque chattering. The validation curve
  of every run (``history.csv``: the validated cost of the answer at each validation,
  against the run's wall time) for the figures and the times to a cost.
* Reference (``--reference``): long runs, each named with its command
  (:data:`REFERENCE`), whose lowest held-out cost per parameter count, with every
  study run's, is the best-known cost the targets are measured against.
* Targets (the tuning issue's): the default within 2 % of the best-known cost in at
  least 5 of 6 runs and within 5 % in 6 of 6 per start, each run in at most 120 s;
  its seeds within 1 % of each other.

Each finished run is kept in ``--out/runs/`` under its fingerprint (its command, the
scoring's settings and the digest of fojax's source, :func:`fojax.records.cached`; not
of the studies' code, whose report can change without running anything again): an
interrupted study continues where it stopped. ``results.json``, ``table.md`` and the
figure ``tuning_methods.png`` summarise them;
``--update-doc FILE`` replaces the blocks ``tuning-reference`` (with ``--reference``)
and ``tuning-study`` of FILE and copies the figure beside it.
"""

from __future__ import annotations

import argparse
import csv
import functools
import itertools
import json
import shutil
import subprocess
import sys
import time

from experiments import _common
from experiments.tuning_study_report import plot, reference_table, summarize, table
from fojax import records
from fojax.cli import arguments, output
from fojax.optimize.strategies import METHODS

__all__ = ["REFERENCE", "command", "main"]

CHOICES = {"shares": ("paper", "none"), "starts": ("naive", "paper"), "methods": tuple(METHODS)}
REFERENCE = {"long": ("naive", 0, ["--steps", "1500", "--patience", "0"])}
"""The reference runs per parameter count: ``(start, seed, options)``, the default
method far past its convergence stop."""
UNSEEN = (2, 3)
"""The scenarios the returned gains are scored on over their full horizon."""


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("tuning_study")
    for name, default in (("seeds", "0,1,2"), ("baseline_seeds", "0"), ("shares", "paper,none"),
                          ("starts", "naive,paper")):  # fmt: skip
        flag = "--" + name.replace("_", "-")
        parser.add_argument(flag, default=default, help=f"comma-separated ({default})")
    parser.add_argument("--methods", default=",".join(METHODS))
    _common.add_numbers(parser, heldout_draws=64, unseen_draws=64)
    parser.add_argument("--unseen-seed", type=arguments.seed, default=7)
    parser.add_argument(
        "--carry", default="",
        help="comma-separated methods whose stored runs are kept though fojax's code changed, "
             "once a rerun of the quickest of them returns its stored gains bit for bit; a run "
             "with none stored runs (none)",
    )  # fmt: skip
    parser.add_argument("--reference", action="store_true",
                        help="also run the long reference runs (REFERENCE)")  # fmt: skip
    _common.add_outputs(parser, "tuning_study", smoke=False)
    parser.add_argument(
        "--report-only", action="store_true", help="summarise the stored runs, run nothing"
    )
    _common.add_smoke(parser)
    return parser


def parse_args(argv) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("seeds", "baseline_seeds"):
        try:
            setattr(args, name, tuple(int(s) for s in _common.listed(getattr(args, name))))
        except ValueError:
            parser.error(f"--{name.replace('_', '-')} must be comma-separated integers")
    for name, valid in CHOICES.items():
        values = _common.listed(getattr(args, name))
        setattr(args, name, values)
        if not values or any(v not in valid for v in values):
            parser.error(f"--{name} must be among {', '.join(valid)}, got {','.join(values)}")
    args.carry = _common.listed(args.carry) if args.carry else ()
    if any(m not in CHOICES["methods"] for m in args.carry):
        parser.error(f"--carry must be among {', '.join(CHOICES['methods'])}")
    if args.tiny:
        args.heldout_draws, args.unseen_draws = 4, 2
        args.seeds, args.baseline_seeds = args.seeds[:1], args.baseline_seeds[:1]
    return args


TINY = ["--horizon", "0.3", "--validation-draws", "2", "--eval-draws", "2", "--steps", "3"]
"""A seconds-long run (``--tiny``), in the default float32 as the scorer's evaluation is."""


def command(args, share: str, start: str, seed: int, method: str, extra=()) -> list[str]:
    """The ``fojax tune`` command of one run (``--out`` last, added by the caller)."""
    words = ["fojax", "tune", "--scenario", "2", "--controller", "afonftsmc", "--init", start,
             "--share", share, "--seed", str(seed)]  # fmt: skip
    if method != "auto":
        words += ["--method", method]
    words += list(extra)
    if args.tiny:
        words += TINY + (["--draws", "3"] if METHODS[method].draws else [])
        if method == "cma-lbfgs":
            words += ["--switch", "2"]
    return words


def _key(args, name: str, words: list[str]) -> tuple:
    """``(folder, stem, fingerprint)`` of a run (:func:`fojax.records.cached`)."""
    scoring = {k: getattr(args, k) for k in ("heldout_draws", "unseen_draws", "unseen_seed")}
    return args.out / "runs", name, {"command": words, "cache": "empty", "scoring": scoring}


def _run(args, name: str, words: list[str]) -> dict:
    """One run: ``words`` in a fresh process with an empty cache, timed as a whole, and
    what it wrote."""
    run_dir = args.out / "runs" / name
    if run_dir.exists():
        shutil.rmtree(run_dir)
    with _common.cold_environment("fojax-tuning-study-") as env:
        load, t0 = output.load_average(), time.perf_counter()
        argv = [sys.executable, "-m", "fojax.cli", *words[1:], "--quiet", "--out", str(run_dir)]
        subprocess.run(argv, check=True, env=env, stdout=subprocess.DEVNULL)
        total = time.perf_counter() - t0
    gains = json.loads((run_dir / "gains.json").read_text())
    with open(run_dir / "history.csv", newline="") as handle:
        history = list(csv.DictReader(handle))
    curve = [[int(r["step"]), float(r["wall_time_s"]), float(r["validation"])]
             for r in history if r["validation"]]  # fmt: skip
    meta = gains["metadata"]
    return {
        "name": name,
        "command": " ".join(words),
        "wall_s": round(total, 1),
        "tuning_s": float(history[-1]["wall_time_s"]) if history else 0.0,
        "steps": meta["steps"],
        "returned_step": meta["returned_step"],
        "draw_steps": meta["draw_steps"],
        "validation": meta["validation"],
        "curve": curve,
        "kept_search": int(float(history[-1]["search"])) if history and history[-1].get("search")
        else None,
        "gains": gains["gains"],
        "load_before": load,
        "load_after": output.load_average(),
        "git_commit": output.commit_label(full=True),
    }


def runs(args) -> list[tuple[str, list[str], dict]]:
    """``(name, command, case)`` of every run of these settings, the reference runs
    with ``--reference``."""
    found = []
    for share, start, method in itertools.product(args.shares, args.starts, args.methods):
        for seed in args.seeds if method == "auto" else args.baseline_seeds:
            case = dict(share=share, start=start, method=method, seed=seed, kind="study")
            name = f"{share}_{start}_{method}_{seed}"
            found.append((name, command(args, share, start, seed, method), case))
    if args.reference:
        for share, (label, (start, seed, extra)) in itertools.product(
            args.shares, REFERENCE.items()
        ):
            words = command(args, share, start, seed, "auto", [] if args.tiny else extra)
            case = dict(share=share, start=start, method="auto", seed=seed, kind="reference",
                        label=label)  # fmt: skip
            found.append((f"{share}_reference_{label}", words, case))
    return found


class _Scorer:
    """The held-out cost and the full-horizon metrics of gains, one compiled evaluator
    per parameter count and scenario."""

    def __init__(self, args):
        self.args, self._objectives = args, {}

    def _objective(self, share: str):
        from fojax import optimize
        from fojax.controllers.afonftsmc import paper_gains

        if share not in self._objectives:
            tiny = {"horizon": 0.3} if self.args.tiny else {}
            spec = optimize.ProblemSpec(share=share, **tiny)
            self._objectives[share] = optimize.Objective(spec, paper_gains())
        return self._objectives[share]

    def heldout(self, share: str, gains) -> float:
        from fojax.optimize import draw_keys

        objective = self._objective(share)
        keys = draw_keys(0, "heldout", self.args.heldout_draws)
        return float(_common.mean_costs(objective, [objective.vector(gains)], keys)[0])

    def full_horizon(self, gains) -> dict:
        """Per scenario of :data:`UNSEEN`: position RMSE (m) and roll and pitch torque
        chattering (N m), means over the unseen draws, and the diverged draws."""
        import fojax
        from fojax import study

        out = {}
        for scenario_id in UNSEEN:
            scenario = fojax.get_scenario(scenario_id)
            horizon = 0.3 if self.args.tiny else scenario.horizon
            config = fojax.SimulationConfig(dt=1e-3, horizon=horizon)
            controller = fojax.make_controller("afonftsmc", dt=1e-3, horizon=horizon,
                                               switching="sat")  # fmt: skip
            result = fojax.run_monte_carlo(controller, gains, scenario, config,
                                           draws=self.args.unseen_draws,
                                           seed=self.args.unseen_seed, progress=False)  # fmt: skip
            summary = study.summarize(result)
            metrics = summary["metrics"]
            out[str(scenario_id)] = {
                "position_rmse": metrics["position_rmse"]["mean"],
                "torque_chattering": [
                    metrics[f"chattering_{axis}"]["mean"] for axis in ("tau_x", "tau_y")
                ],
                "diverged": summary["diverged"],
            }
        return out


def _scored(scorer: _Scorer, run, case: dict) -> dict:
    """``run()``'s record with the scores of its gains and its case."""
    from fojax.controllers import gains_io

    record = run()
    gains = gains_io.gains_from_dict("afonftsmc", record["gains"])
    return {**record, **case, "heldout": scorer.heldout(case["share"], gains),
            "full_horizon": scorer.full_horizon(gains)}  # fmt: skip


def _carried(args, scorer, found) -> tuple[dict, dict | None]:
    """The stored runs of ``--carry``'s methods made by other code, by name, once a
    rerun of the quickest of them at this code returned the same gains bit for bit (that
    rerun in their place), and what was checked; ``SystemExit`` where the rerun differs.
    A run of those methods with no stored run is not carried: it runs."""
    stale, record_file = {}, args.out / "carried.json"
    for name, words, case in found:
        key = _key(args, name, words)
        if case["method"] not in args.carry or records.stored(*key) is not None:
            continue
        record = records.stored(*key, any_code=True)
        if record is not None:  # none stored (a fresh clone): it runs at this code
            stale[name] = record
    if not stale:
        return {}, None
    done = json.loads(record_file.read_text()) if record_file.is_file() else {}
    if done.get("code") == records.code_digest() and done.get("carried") == sorted(stale):
        done.pop("code")  # these checked at this code already: the rerun is stored, not stale
        return stale, done
    if args.report_only:
        raise SystemExit("--carry: the carried runs were not checked at this code: run the "
                         "study without --report-only")  # fmt: skip
    check = min(stale, key=lambda name: stale[name]["wall_s"])
    words, case = next((w, c) for n, w, c in found if n == check)
    compute = functools.partial(_scored, scorer, functools.partial(_run, args, check, words))
    rerun = records.cached(*_key(args, check, words), lambda: compute(case))
    if rerun["gains"] != stale[check]["gains"]:
        raise SystemExit(
            f"--carry: {check} rerun at this code returned other gains than its stored run "
            f"(commit {stale[check]['git_commit'][:7]}): run it without --carry"
        )
    kept = sorted(name for name in stale if name != check)
    checked = {"methods": list(args.carry), "rerun": check, "carried": kept,
               "from": sorted({stale[name]["git_commit"] for name in kept})}
    records.write_json(record_file, {**checked, "code": records.code_digest()})
    return {**stale, check: rerun}, checked


def report(args, records: list[dict], started: float, carried=None) -> int:
    results = {
        "settings": _common.settings(args),
        "summary": summarize(records),
        "runs": records,
        "git_commit": ", ".join(sorted({r["git_commit"] for r in records})),
        "this_invocation_s": round(time.perf_counter() - started, 1),
        "runs_s": round(sum(r["wall_s"] for r in records), 1),
        "carried": carried,
    }
    figure = plot(records, args.out / "tuning_methods.png")
    if args.update_doc is not None:
        shutil.copyfile(figure, args.update_doc.parent / figure.name)
        if args.reference:
            output.splice(args.update_doc, reference_table(results), name="tuning-reference")
    return _common.finish(
        args.out, results, table(results), args.update_doc, "tuning-study", None,
        ", tuning_methods.png",
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    started, scorer, found = time.perf_counter(), _Scorer(args), []
    carried, checked = _carried(args, scorer, runs(args))
    for name, words, case in runs(args):
        key = _key(args, name, words)
        if name in carried:
            record = carried[name]
        elif args.report_only:
            record = records.stored(*key, records.code_digest())
            if record is None:
                continue
        else:
            compute = functools.partial(_scored, scorer, functools.partial(_run, args, name, words))
            record = records.cached(*key, lambda compute=compute, case=case: compute(case))
            output.log(args.quiet, f"  {name}: {record['wall_s']:.0f} s, held-out "
                                   f"{record['heldout']:.4g}")  # fmt: skip
        found.append(record)
    if not found:
        raise SystemExit(f"{args.out / 'runs'} holds no run of these settings")
    return report(args, found, started, checked)


if __name__ == "__main__":
    sys.exit(main())

