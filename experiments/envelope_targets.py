"""The flight envelope's targets: ``fojax tune --envelope`` with its defaults, from the
naive and the paper's start, judged against the paper's gains on held-out draws of
every case of the default envelope.

    python -m experiments.envelope_targets [--out results/envelope_targets]
        [--runs naive:0:paper,paper:0:paper,...] [--draws 64] [--update-doc docs/tuning.md]

1. **Tuning.** Each run ``INIT:SEED:SHARE`` is ``fojax tune --controller afonftsmc
   --envelope examples/envelopes/paper_and_manoeuvres.toml --init INIT --seed SEED
   --share SHARE --eval-draws 0`` in a process of its own, as a user runs it (its wall
   time as its gains file records it); a run whose ``gains.json`` is in ``--out/runs``
   is kept.
2. **Judgement.** The paper's gains and every run's on ``--draws`` held-out draws of
   every case (:func:`fojax.optimize.cases.evaluate_cases`, seed 0's held-out range,
   which no run tunes on), each over its full horizon at 1 ms, with ``sat`` and
   ``sign``; per run (:func:`targets`): diverged draws, the largest and the mean ratio
   of position RMSE to the paper's gains' over the cases and laws, the largest ratio of
   ``sat`` torque chattering, and whether it meets the targets (no diverged draw, RMSE
   at most the paper's in every case and at most :data:`RATIO` of it on average,
   chattering at most the paper's in every ``sat`` case).

Writes ``results.json`` and ``table.md`` to ``--out``; ``--update-doc`` replaces the
``envelope-targets`` block of docs/tuning.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from experiments import _common

ROOT = Path(__file__).resolve().parent.parent
ENVELOPE = "examples/envelopes/paper_and_manoeuvres.toml"
RATIO = 0.7
"""The largest mean ratio of position RMSE to the paper's gains' over the cases."""
RUNS = ",".join(f"{init}:{seed}:{share}" for share in ("paper", "none") for seed in (0, 1, 2)
                for init in ("naive", "paper"))  # fmt: skip
"""The issue's matrix: both starts, seeds 0-2, 33 and 66 parameters."""


def targets(evaluation: dict, label: str, reference: str = "paper") -> dict:
    """The targets of ``label`` against ``reference`` in an
    :func:`fojax.optimize.cases.evaluate_cases` result."""
    ratios, chatter, diverged, worse = [], [], 0, []
    for law, rows in evaluation["laws"].items():
        for case, row in rows.items():
            mine, ref = row[label], row[reference]
            diverged += mine["diverged"]
            if mine["position_rmse"] is None or ref["position_rmse"] is None:
                ratios.append(float("inf"))
                continue
            r = mine["position_rmse"] / ref["position_rmse"]
            ratios.append(r)
            if r > 1:
                worse.append(f"{law} {case}: RMSE x{r:.2f}")
            if law == "sat":
                c = mine["torque_chattering"] / ref["torque_chattering"]
                chatter.append(c)
                if c > 1:
                    worse.append(f"{law} {case}: chattering x{c:.2f}")
    met = diverged == 0 and max(ratios) <= 1 and float(np.mean(ratios)) <= RATIO
    return {
        "diverged": diverged,
        "largest_rmse_ratio": max(ratios),
        "mean_rmse_ratio": float(np.mean(ratios)),
        "largest_chattering_ratio": max(chatter) if chatter else None,
        "met": bool(met and (not chatter or max(chatter) <= 1)),
        "worse": worse,
    }


COST_DRAWS = 256
"""Held-out draws on which every run's gains are scored by one objective."""


def costs(out: Path, records: list[dict], gains: dict, draws: int) -> list[float]:
    """Every run's objective on the same ``draws`` held-out draws: the envelope's cost
    (CVaR over the draws, at the tuning horizon and step) with the case scales and
    bounds of the first run (each run computes its own from its seed's
    validation draws), so that runs of different seeds are scored alike."""
    from fojax import envelope, optimize

    first = out / "runs" / records[0]["label"] / "gains.json"
    problem = json.loads(first.read_text())["metadata"]["settings"]["objective"]["problem"]
    cost = optimize.CostConfig(**problem["cost"])
    out_costs = []
    for record in records:
        spec = optimize.ProblemSpec(
            controller="afonftsmc", scenario=None, envelope=envelope.load(ROOT / ENVELOPE),
            horizon=problem["horizon"], dt=problem["dt"], cost=cost, share=record["share"],
            case_scales=tuple(problem["case_scales"]),
            case_chattering=tuple(problem["case_chattering"]),
            case_tracking=tuple(problem["case_tracking"]),
            bound_excess=problem["bound_excess"],
        )  # fmt: skip
        objective = optimize.Objective(spec, gains["paper"])
        x = objective.vector(gains[record["label"]])
        _, summary, _ = objective.evaluate(x, objective.keys("heldout", draws))
        out_costs.append(float(summary["cost"]))
    return out_costs


def tune(init: str, seed: int, share: str, out: Path) -> None:
    argv = ["fojax", "tune", "--controller", "afonftsmc", "--envelope", ENVELOPE, "--init", init,
            "--seed", str(seed), "--share", share, "--eval-draws", "0", "--quiet",
            "--out", str(out)]  # fmt: skip
    print(" ".join(argv), flush=True)
    subprocess.run(argv, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def table(results: dict) -> str:
    lines = [
        f"Every run: `fojax tune --controller afonftsmc --envelope {ENVELOPE} --init INIT "
        "--seed SEED --share SHARE` (its defaults: 20 s at 2 ms, CVaR, the chattering and "
        f"tracking bounds per case), judged on {results['draws']} held-out draws of every "
        "case, each over its full horizon at 1 ms, against the paper's gains. Ratios: the "
        "run's position RMSE (chattering) over the paper's gains', per case and law; the "
        f"targets: no diverged draw, every RMSE ratio <= 1, their mean <= {RATIO}, every `sat` "
        "chattering ratio <= 1.",
        "",
        f"Cost: the envelope's objective on {COST_DRAWS} held-out draws at the tuning "
        "horizon and step, every run scored with the first run's case scales and bounds; "
        "above best: over the lowest of the table.",
        "",
        "| start | seed | parameters | tuning (s) | cost | above best | diverged | RMSE ratio, "
        "largest | RMSE ratio, mean | chattering ratio, largest | met | where it loses |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in results["runs"]:
        t = run["targets"]
        lines.append(
            f"| {run['init']} | {run['seed']} | {run['parameters']} | {run['tuning_s']:.0f} | "
            f"{run['cost']:.4g} | {100 * run['above_best']:.1f} % | {t['diverged']} | "
            f"{t['largest_rmse_ratio']:.3g} | {t['mean_rmse_ratio']:.3g} | "
            f"{t['largest_chattering_ratio']:.3g} | {'yes' if t['met'] else 'no'} | "
            f"{'; '.join(t['worse']) or '-'} |"
        )
    paper = results["evaluation"]["laws"]
    lines += ["", "The paper's gains on the same draws (position RMSE, m; `sat` chattering, "
              "N m/s):", "", "| case | `sat` RMSE | `sign` RMSE | `sat` chattering |",
              "|---|---|---|---|"]  # fmt: skip
    for case in results["evaluation"]["cases"]:
        sat, sign = paper["sat"][case]["paper"], paper["sign"][case]["paper"]
        lines.append(f"| {case} | {sat['position_rmse']:.3g} | {sign['position_rmse']:.3g} | "
                     f"{sat['torque_chattering']:.3g} |")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "envelope_targets")
    parser.add_argument("--runs", default=RUNS, help="INIT:SEED:SHARE, comma-separated")
    parser.add_argument("--draws", type=int, default=64)
    parser.add_argument("--update-doc", type=Path)
    args = parser.parse_args(argv)
    runs = []
    for entry in args.runs.split(","):
        init, seed, share = entry.split(":")
        if init not in ("naive", "paper") or share not in ("paper", "none"):
            parser.error(f"--runs: {entry!r} is not naive|paper:SEED:paper|none")
        runs.append((init, int(seed), share))
    for init, seed, share in runs:
        out = args.out / "runs" / f"{init}-{seed}-{share}"
        if not (out / "gains.json").is_file():
            tune(init, seed, share, out)

    import jax.numpy as jnp

    from fojax import envelope, optimize
    from fojax.controllers import gains_io, registry
    from fojax.optimize import cases

    spec = optimize.ProblemSpec(controller="afonftsmc", scenario=None,
                                envelope=envelope.load(ROOT / ENVELOPE))  # fmt: skip
    gains = {"paper": registry.get_controller_class("afonftsmc").default_gains(jnp.float32)}
    records = []
    for init, seed, share in runs:
        path = args.out / "runs" / f"{init}-{seed}-{share}" / "gains.json"
        _, tuned, metadata = gains_io.load_gains(path, jnp.float32)
        label = f"{init}-{seed}-{share}"
        gains[label] = tuned
        records.append({"init": init, "seed": seed, "share": share, "label": label,
                        "parameters": 33 if share == "paper" else 66,
                        "tuning_s": metadata["wall_time_s"]})  # fmt: skip
    print(f"judging {len(gains)} sets of gains on {args.draws} held-out draws per case",
          flush=True)  # fmt: skip
    evaluation = cases.evaluate_cases(spec, gains, args.draws)
    for record in records:
        record["targets"] = targets(evaluation, record["label"])
    for record, cost in zip(records, costs(args.out, records, gains, COST_DRAWS), strict=True):
        record["cost"] = cost
    best = min(r["cost"] for r in records)
    for record in records:
        record["above_best"] = record["cost"] / best - 1.0
    results = {"envelope": ENVELOPE, "draws": args.draws, "runs": records,
               "evaluation": evaluation}  # fmt: skip
    (args.out).mkdir(parents=True, exist_ok=True)
    doc = None if args.update_doc is None else args.update_doc
    return _common.finish(args.out, json.loads(json.dumps(results)), table(results), doc,
                          "envelope-targets", wrote="")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
