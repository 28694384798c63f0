"""``fojax reproduce``: the paper's Section V redone with Monte Carlo.

    fojax reproduce --out DIR [--draws N] [--seed S] [--switching sign|sat|tanh]
                    [--fractional soe|oustaloup|gl] [--scenarios 1,2,3] [--horizon T]
                    [--chunk N] [--keep N] [--dtype float32|float64] [--quiet]

All three scenarios, every registered controller (the AFONFTSMC and the four it is
compared with: ANFTSMC, FOBSMC, BSMC, FL), the same draws for every controller
(common random numbers: draw ``i`` of seed ``S`` is the same disturbance, drag and
mass/inertia sample for all of them). Writes to ``DIR``:

* ``report.md``: per scenario and controller each metric's mean and 95 % confidence
  interval, paired differences against the AFONFTSMC, and claim by claim whether the
  paper's Section V conclusions hold under this Monte Carlo;
* ``report.json``: the same numbers;
* ``figures/``: the paper's Figs. 5-16 redrawn from the data, Monte Carlo spread shaded;
* ``s1/``, ``s2/``, ``s3/``: each scenario's ``summary.json`` (every metric),
  ``draws.npz`` (per-draw metrics), ``trajectories.npz`` and ``chunks/`` (finished
  chunks: an interrupted run, started again with the same command, continues there).

The default size (``--draws``) is chosen to finish within 10 minutes on a 2-core CPU
(see ``DEFAULT_DRAWS``). Everything is validated before anything is compiled.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from experiments import arguments, simulate

__all__ = [
    "CLAIMS",
    "DEFAULT_DRAWS",
    "build_parser",
    "evaluate_claims",
    "main",
    "parse_args",
    "write_report",
]

DEFAULT_DRAWS = 100
"""Draws per scenario and controller by default, sized to finish within 10 minutes on
a 2-core CPU: 3 scenarios x 5 controllers x 100 draws took 196 s on the project's
2-core machine (float32, chunks of 50, load average about 1; about 100 s of it
compiling the 15 (scenario, controller) rollouts); the measured time of the committed
example is in ``docs/reproduction.md``."""

BASELINE = "afonftsmc"
CHATTER_THRESHOLD = 0.1
"""An input counts as chatter-free when its mean change per control step is below 10 %
of its RMS value. An input that switches at the step rate changes by about its own size
every step (a ratio near 1); a smooth one by a small fraction (a full-amplitude sinusoid
reaches 0.1 only at about 18 Hz with a 1 ms step)."""


def build_parser() -> argparse.ArgumentParser:
    from fojax import fractional
    from fojax.controllers import SWITCHING_FUNCTIONS

    parser = argparse.ArgumentParser(
        prog="fojax reproduce",
        description=(
            "The paper's Section V with Monte Carlo: 3 scenarios x 5 controllers on the same "
            "draws; report, JSON and Figs. 5-16."
        ),
    )
    parser.add_argument("--out", required=True, type=Path, metavar="DIR")
    parser.add_argument(
        "--draws",
        type=arguments.positive_int,
        default=DEFAULT_DRAWS,
        help=f"draws per scenario and controller (default {DEFAULT_DRAWS}: < 10 min on 2 cores)",
    )
    parser.add_argument("--seed", type=arguments.nonnegative_int, default=0)
    parser.add_argument(
        "--switching",
        choices=SWITCHING_FUNCTIONS,
        default="sign",
        help="switching function of the sliding-mode controllers (default sign, the paper's)",
    )
    parser.add_argument(
        "--fractional",
        choices=fractional.METHODS,
        default="soe",
        help="fractional operator method (default soe; oustaloup is the paper's CRONE)",
    )
    parser.add_argument(
        "--scenarios", type=arguments.scenario_ids, default=(1, 2, 3), help="subset, e.g. 1,3"
    )
    parser.add_argument(
        "--horizon",
        type=arguments.positive_float,
        help="simulated time (s) for every scenario (default: each scenario's, 80/80/50 s)",
    )
    parser.add_argument("--dt", type=arguments.positive_float, default=1e-3, help="step, s")
    parser.add_argument("--chunk", type=arguments.positive_int, default=50, help="draws per batch")
    parser.add_argument(
        "--keep",
        type=arguments.nonnegative_int,
        default=32,
        help="draws whose trajectories are kept for the figures (32)",
    )
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--no-figures", action="store_true", help="skip the figures")
    parser.add_argument(
        "--overwrite", action="store_true", help="discard finished chunks of an earlier run"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    return parser


def parse_args(argv) -> tuple[list[simulate.Study], argparse.Namespace]:
    """One validated :class:`experiments.simulate.Study` per scenario; exits on bad input."""
    from fojax import scenarios
    from fojax.controllers import registry

    parser = build_parser()
    args = parser.parse_args(argv)
    names = registry.controller_names()
    if BASELINE not in names:
        parser.error(f"the baseline controller {BASELINE!r} is not registered")
    if args.dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    studies = []
    for scenario_id in args.scenarios:
        scenario = scenarios.get_scenario(scenario_id)
        horizon = args.horizon if args.horizon is not None else scenario.horizon
        if args.dt > horizon:
            parser.error(f"--dt ({args.dt}) must not exceed the horizon ({horizon})")
        steps = horizon / args.dt
        if abs(steps - round(steps)) > 1e-6 * steps:
            parser.error(f"the horizon ({horizon} s) must be a whole number of steps of {args.dt}")
        steps = round(steps)
        studies.append(
            simulate.Study(
                scenario_id=scenario_id,
                controllers=(BASELINE,) + tuple(n for n in names if n != BASELINE),
                draws=args.draws,
                seed=args.seed,
                horizon=float(horizon),
                dt=float(args.dt),
                save_every=simulate.snapshot_interval(steps, args.dt),
                gains={},
                fractional=args.fractional,
                switching=args.switching,
                chunk=args.chunk,
                keep=min(args.keep, args.draws),
                dtype=args.dtype,
            )
        )
    for name in studies[0].controllers:
        try:
            registry.make_controller(
                name,
                dt=args.dt,
                horizon=studies[0].horizon,
                fractional_method=args.fractional,
                switching=args.switching,
            )
        except ValueError as error:
            parser.error(f"{name}: {error}")
    return studies, args


# ----------------------------------------------------------------------------- claims

AXES_XYZ = ("x", "y", "z")


def _metrics(prefix: str, axes=AXES_XYZ) -> list[str]:
    return [f"{prefix}_{axis}" for axis in axes]


# The paper's Section V conclusions, each mapped to metrics (every one lower-is-better)
# and to the scenarios it speaks about.
CLAIMS = [
    {
        "id": "S1-transient",
        "scenario": 1,
        "text": (
            "Scenario 1: 'the AFONFTSMC has better performances in terms of overshoot, "
            "settling/rising time, and steady-state error than other compared techniques'"
        ),
        "metrics": _metrics("overshoot") + _metrics("settling_time") + _metrics("itae"),
        "mapping": (
            "overshoot_x/y/z, settling_time_x/y/z (0.05 m band) and, for the steady-state "
            "error, itae_x/y/z (the time-weighted IAE, dominated by late errors). Rising "
            "time is not measured: the runs track a moving reference from a non-zero "
            "initial error, and the settling time stands for it."
        ),
    },
    {
        "id": "S1-robustness",
        "scenario": 1,
        "text": (
            "Scenario 1: 'better robustness performances relative to external disturbances "
            "and uncertainties'"
        ),
        "metrics": ["position_rmse", "attitude_rmse"] + _metrics("max_error"),
        "mapping": (
            "position_rmse, attitude_rmse and max_error_x/y/z under scenario 1's drag "
            "uncertainty and disturbances (53)."
        ),
    },
    {
        "id": "S2-convergence-tracking",
        "scenario": 2,
        "text": (
            "Scenario 2: 'better in terms of convergence speed, trajectory tracking, and "
            "rejection of the random disturbances'"
        ),
        "metrics": _metrics("settling_time") + ["position_rmse"] + _metrics("rmse"),
        "mapping": (
            "convergence speed: settling_time_x/y/z; trajectory tracking: position_rmse and "
            "rmse_x/y/z under scenario 2. Rejection of the random disturbances: see the "
            "next claim."
        ),
    },
    {
        "id": "S2-random-rejection",
        "scenario": 2,
        "text": "Scenario 2: 'rejection of the random disturbances'",
        "metrics": ["position_rmse", "attitude_rmse"],
        "delta_from": 1,
        "mapping": (
            "the increase of position_rmse and attitude_rmse from scenario 1 to scenario 2 "
            "on the same draw (same drag sample; scenario 2 adds only the Gaussian "
            "disturbances), compared between controllers (a difference of differences). "
            "Needs scenarios 1 and 2 in the run."
        ),
    },
    {
        "id": "S3-tracking-rejection",
        "scenario": 3,
        "text": (
            "Scenario 3: 'more accurate trajectory tracking, stronger random uncertainty and "
            "disturbances rejection'"
        ),
        "metrics": ["position_rmse"] + _metrics("rmse") + _metrics("max_error"),
        "mapping": (
            "position_rmse, rmse_x/y/z and max_error_x/y/z under scenario 3's 30 % mass and "
            "inertia uncertainty and disturbances (56)."
        ),
    },
]


def _pair_verdict(difference: dict) -> str:
    """``other - afonftsmc`` of a lower-is-better metric: 'better' when the whole 95 %
    interval is above 0 (the AFONFTSMC lower), 'worse' below 0, 'n.s.' otherwise."""
    ci = difference.get("ci95")
    if ci is None:
        return "n.s."
    if ci[0] > 0:
        return "better"
    if ci[1] < 0:
        return "worse"
    return "n.s."


def _verdict(counts: dict) -> str:
    if counts["worse"]:
        return "does not hold"
    if counts["better"] and not counts["n.s."]:
        return "holds"
    return "inconclusive"


def _difference_of_differences(results_by_scenario, metric, baseline, other):
    from fojax import statistics
    from fojax import study as monte_carlo

    s1, s2 = results_by_scenario[1], results_by_scenario[2]
    delta_base = (
        monte_carlo.metric_table(s2[baseline])[metric][0]
        - (monte_carlo.metric_table(s1[baseline])[metric][0])
    )
    delta_other = (
        monte_carlo.metric_table(s2[other])[metric][0]
        - (monte_carlo.metric_table(s1[other])[metric][0])
    )
    return statistics.paired_difference(delta_other, delta_base)


def evaluate_claims(summaries: dict, results_by_scenario: dict) -> list[dict]:
    """Each claim of :data:`CLAIMS` with its per-pair comparisons and its verdict.

    ``summaries``: scenario id -> the summary of :func:`experiments.simulate.write_outputs`
    (with ``paired_differences`` against the AFONFTSMC). ``results_by_scenario``:
    scenario id -> {controller: MonteCarloResult}, for the per-draw claims.
    """
    evaluated = []
    for claim in CLAIMS:
        entry = {k: claim[k] for k in ("id", "scenario", "text", "mapping", "metrics")}
        needed = {claim["scenario"], claim.get("delta_from", claim["scenario"])}
        if not needed <= set(summaries):
            entry.update(verdict="not run", comparisons=[], counts={})
            evaluated.append(entry)
            continue
        summary = summaries[claim["scenario"]]
        paired = summary["paired_differences"]["minus_baseline"]
        comparisons = []
        for other, differences in paired.items():
            for metric in claim["metrics"]:
                if "delta_from" in claim:
                    difference = _difference_of_differences(
                        results_by_scenario, metric, BASELINE, other
                    )
                else:
                    difference = differences[metric]
                comparisons.append(
                    {
                        "controller": other,
                        "metric": metric,
                        "difference": difference,
                        "result": _pair_verdict(difference),
                    }
                )
        counts = {
            k: sum(c["result"] == k for c in comparisons) for k in ("better", "worse", "n.s.")
        }
        entry.update(verdict=_verdict(counts), comparisons=comparisons, counts=counts)
        evaluated.append(entry)
    evaluated.append(_chatter_claim(summaries))
    evaluated.append(_finite_time_claim(summaries, results_by_scenario))
    return evaluated


def _chatter_claim(summaries: dict) -> dict:
    """Remark 2: 'chatter-free control inputs'. Per input, the mean change per step
    (total variation / steps) relative to the input's RMS, for every controller."""
    from fojax import metrics as metrics_module

    rows = []
    free_everywhere = True
    for scenario_id, summary in summaries.items():
        steps = round(summary["horizon_s"] / summary["dt_s"])
        for name, entry in summary["controllers"].items():
            ratios = {}
            for channel in metrics_module.INPUTS:
                tv = entry["metrics"][f"chattering_{channel}"]["mean"]
                rms = entry["metrics"][f"control_effort_{channel}"]["mean"]
                ratios[channel] = None if tv is None or not rms else tv / steps / rms
            chatter_free = all(r is not None and r < CHATTER_THRESHOLD for r in ratios.values())
            if name == BASELINE:
                free_everywhere &= chatter_free
            rows.append(
                {
                    "scenario": scenario_id,
                    "controller": name,
                    "change_per_step_over_rms": ratios,
                    "chatter_free": chatter_free,
                }
            )
    return {
        "id": "R2-chatter-free",
        "scenario": None,
        "text": "Remark 2 and conclusions: 'chatter-free control inputs'",
        "mapping": (
            "chattering_<input> (total variation) / steps / control_effort_<input> (RMS) "
            f"below {CHATTER_THRESHOLD:g} for u_F, tau_x, tau_y, tau_z, in every scenario."
        ),
        "metrics": [f"chattering_{c}" for c in metrics_module.INPUTS],
        "rows": rows,
        "verdict": "holds" if free_everywhere else "does not hold",
    }


def _finite_time_claim(summaries: dict, results_by_scenario: dict) -> dict:
    """Conclusions: 'fast finite-time convergence'. Holds when, in every valid draw of
    every scenario and on every axis, the AFONFTSMC's sliding variable reaches
    |S| <= 0.01 and stays there from before half the run on (reaching_time < T / 2);
    the eq. (34) bound is shown next to it; 'fast' is judged by the settling times."""
    from fojax import metrics as metrics_module

    rows = []
    kept_everywhere = True
    for scenario_id, summary in summaries.items():
        entry = summary["controllers"][BASELINE]["metrics"]
        result = results_by_scenario[scenario_id][BASELINE]
        reaching = np.asarray(result.per_draw["reaching_time"], dtype=float)[result.valid]
        half = 0.5 * summary["horizon_s"]
        for j, axis in enumerate(metrics_module.AXES):
            times = reaching[:, j]
            early = int(np.sum(times < half))
            kept_everywhere &= times.size > 0 and early == times.size
            rows.append(
                {
                    "scenario": scenario_id,
                    "axis": axis,
                    "valid_draws": int(times.size),
                    "kept_from_first_half": early,
                    "never_reached": int(np.sum(~np.isfinite(times))),
                    "mean_reaching_time_s": entry[f"reaching_time_{axis}"]["mean"],
                    "mean_bound_34_s": entry.get(f"reaching_time_bound_{axis}", {}).get("mean"),
                }
            )
    return {
        "id": "C-finite-time",
        "scenario": None,
        "text": "Conclusions: 'fast finite-time convergence'",
        "mapping": (
            "reaching_time_<axis> of the AFONFTSMC (the time after which |S| <= 0.01 holds "
            "to the end of the run): the claim holds when it is below half the horizon in "
            "every draw and axis, i.e. the sliding mode is reached and then kept despite "
            "the disturbances; the eq. (34) bound is shown next to it. The 'fast' part is "
            "the settling-time comparison of the scenario claims."
        ),
        "metrics": [f"reaching_time_{a}" for a in metrics_module.AXES],
        "rows": rows,
        "verdict": "holds" if kept_everywhere else "does not hold",
    }


# ----------------------------------------------------------------------------- report

TABLE_METRICS = (
    ["position_rmse", "attitude_rmse"]
    + _metrics("rmse")
    + _metrics("overshoot")
    + _metrics("settling_time")
    + _metrics("itae")
    + _metrics("max_error")
    + ["chattering_thrust", "chattering_tau_x", "control_effort_thrust", "actuator_saturation"]
)


def _fmt(value) -> str:
    if value is None:
        return "n/a"
    if value == 0:
        return "0"
    if not math.isfinite(value):
        return str(value)
    return f"{value:.3g}"


def _cell(stats: dict) -> str:
    if stats.get("mean") is None:
        return "n/a"
    ci = stats.get("ci95")
    if ci is None:
        return _fmt(stats["mean"])
    return f"{_fmt(stats['mean'])} [{_fmt(ci[0])}, {_fmt(ci[1])}]"


def _scenario_section(summary: dict) -> list[str]:
    names = list(summary["controllers"])
    lines = [
        f"### Scenario {summary['scenario']}",
        "",
        f"{summary['draws']} draws, seed {summary['seed']}, {summary['horizon_s']:g} s at "
        f"dt = {summary['dt_s']:g} s, switching `{summary['switching']}`, fractional "
        f"method `{summary['fractional_method']}`, {summary['dtype']}.",
        "",
        "Mean and 95 % confidence interval over the draws that did not diverge:",
        "",
        "| metric | unit | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    first = summary["controllers"][names[0]]["metrics"]
    for metric in TABLE_METRICS:
        cells = [_cell(summary["controllers"][n]["metrics"][metric]) for n in names]
        lines.append(f"| {metric} | {first[metric]['unit']} | " + " | ".join(cells) + " |")
    diverged = [str(summary["controllers"][n]["diverged"]) for n in names]
    lines.append("| diverged draws | | " + " | ".join(diverged) + " |")
    wall = [f"{summary['controllers'][n].get('wall_time_s', float('nan')):.0f}" for n in names]
    lines.append("| wall time | s | " + " | ".join(wall) + " |")
    paired = summary["paired_differences"]["minus_baseline"]
    others = list(paired)
    lines += [
        "",
        f"Paired differences, controller minus {BASELINE} on the same draw (mean [95 % CI]); "
        f"**better**: the {BASELINE} is lower with the whole interval above 0, **worse**: "
        "lower for the other controller, n.s.: the interval contains 0:",
        "",
        "| metric | " + " | ".join(others) + " |",
        "|---|" + "---|" * len(others),
    ]
    for metric in TABLE_METRICS:
        cells = []
        for other in others:
            difference = paired[other][metric]
            verdict = _pair_verdict(difference)
            mark = f"**{verdict}**" if verdict != "n.s." else verdict
            cells.append(f"{_cell(difference)} {mark}")
        lines.append(f"| {metric} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines


def _claim_section(claim: dict) -> list[str]:
    lines = [f"### {claim['text']}", "", f"**Verdict: {claim['verdict']}.**", ""]
    lines += [f"Metrics: {claim['mapping']}", ""]
    if "counts" in claim and claim["counts"]:
        c = claim["counts"]
        lines.append(
            f"Of {sum(c.values())} paired comparisons (4 controllers x "
            f"{len(claim['metrics'])} metrics) the {BASELINE} is significantly better in "
            f"{c['better']}, significantly worse in {c['worse']}, not significantly "
            f"different in {c['n.s.']}."
        )
        worse = [x for x in claim["comparisons"] if x["result"] == "worse"]
        if worse:
            items = ", ".join(
                f"{x['metric']} vs {x['controller']} ({_cell(x['difference'])})" for x in worse
            )
            lines.append(f"Worse: {items}.")
        lines.append("")
        if claim.get("delta_from"):
            lines += [
                "| controller | metric | (S2 - S1) minus the AFONFTSMC's (S2 - S1) | result |",
                "|---|---|---|---|",
            ]
            for x in claim["comparisons"]:
                lines.append(
                    f"| {x['controller']} | {x['metric']} | {_cell(x['difference'])} | "
                    f"{x['result']} |"
                )
            lines.append("")
    if claim["id"] == "R2-chatter-free":
        lines += [
            "Mean change per 1 ms step relative to the input's RMS "
            f"(chatter-free below {CHATTER_THRESHOLD:g}):",
            "",
            "| scenario | controller | u_F | tau_x | tau_y | tau_z | chatter-free |",
            "|---|---|---|---|---|---|---|",
        ]
        for row in claim["rows"]:
            r = row["change_per_step_over_rms"]
            cells = " | ".join(_fmt(r[k]) for k in ("thrust", "tau_x", "tau_y", "tau_z"))
            lines.append(
                f"| {row['scenario']} | {row['controller']} | {cells} | "
                f"{'yes' if row['chatter_free'] else 'no'} |"
            )
        lines.append("")
    if claim["id"] == "C-finite-time":
        lines += [
            f"The {BASELINE}'s sliding variables: in how many draws |S| <= 0.01 holds from "
            "before half the run to its end, in how many it never holds at the last "
            "sample, the mean reaching time (over the draws where it is finite; close to "
            "the horizon means |S| left the band until the last samples) and the mean "
            "eq. (34) bound (from S(0), which is near 0 here: the fractional terms start "
            "at 0 and the initial velocity error is small):",
            "",
            "| scenario | axis | kept from the first half | never | mean reaching time (s) "
            "| mean eq. (34) bound (s) |",
            "|---|---|---|---|---|---|",
        ]
        for row in claim["rows"]:
            lines.append(
                f"| {row['scenario']} | {row['axis']} | "
                f"{row['kept_from_first_half']}/{row['valid_draws']} | "
                f"{row['never_reached']} | {_fmt(row['mean_reaching_time_s'])} | "
                f"{_fmt(row['mean_bound_34_s'])} |"
            )
        lines.append("")
    return lines


def write_report(
    out: Path,
    summaries: dict,
    claims: list[dict],
    settings: dict,
    figures: list[Path],
    wall_time: float,
) -> tuple[Path, Path]:
    """``report.md`` and ``report.json`` in ``out``; returns their paths."""
    lines = [
        "# Labbadi & Cherkaoui, Section V, redone with Monte Carlo",
        "",
        "Generated by `fojax reproduce`. Every controller flies the same draws (common random "
        "numbers); differences are paired by draw. Controllers, their sources and default "
        "gains: `docs/model.md`, section *Compared controllers*. The paper's baseline gains "
        "are unpublished: the ANFTSMC uses its own paper's Table 2, the FL, BSMC and FOBSMC "
        "gains are ours (matched to the AFONFTSMC's surface slopes and switching gains), so "
        "every verdict below is for these gains.",
        "",
        f"Settings: {settings['draws']} draws per scenario and controller, seed "
        f"{settings['seed']}, switching `{settings['switching']}` "
        f"({'the paper' if settings['switching'] == 'sign' else 'not the paper'}'s sgn), "
        f"fractional method `{settings['fractional']}`, dt = {settings['dt']:g} s, "
        f"{settings['dtype']}. Wall time of this invocation {wall_time:.0f} s (chunks finished "
        "by an earlier invocation are loaded, not recomputed).",
        "",
        "## Verdicts",
        "",
        "| claim | verdict |",
        "|---|---|",
    ]
    for claim in claims:
        lines.append(f"| {claim['text']} | **{claim['verdict']}** |")
    lines += [
        "",
        "A scenario claim *holds* when the AFONFTSMC is significantly better (95 % paired "
        "interval excluding 0) on every mapped metric against every compared controller, "
        "*does not hold* when it is significantly worse on at least one, and is "
        "*inconclusive* otherwise.",
        "",
        "Reading the metrics: errors are `actual - reference`; roll and pitch errors (in "
        "`attitude_rmse`) are measured against the attitude reference each controller's "
        "attitude loop tracks, its position loop's command of eq. (13) after the command "
        "filter; how much that command chatters shows in `chattering_*` and "
        "`actuator_saturation`. Settling times use a 0.05 m band; `chattering_*` is the "
        "total variation of an input over the run. Definitions: `docs/model.md`, *Metrics*.",
        "",
        "## Claims",
        "",
    ]
    for claim in claims:
        lines += _claim_section(claim)
    if figures:
        lines += ["## Figures (the paper's Figs. 5-16, redrawn)", ""]
        for path in figures:
            rel = path.relative_to(out) if path.is_relative_to(out) else path
            lines += [f"![{path.stem}]({rel.as_posix()})", ""]
    lines += ["## Metrics by scenario", ""]
    for scenario_id in sorted(summaries):
        lines += _scenario_section(summaries[scenario_id])
    report_md = out / "report.md"
    report_md.write_text("\n".join(lines) + "\n")

    def scalar_tables(summary):
        return {
            name: {m: entry["metrics"][m] for m in TABLE_METRICS}
            | {"diverged": entry["diverged"], "wall_time_s": entry.get("wall_time_s")}
            for name, entry in summary["controllers"].items()
        }

    document = {
        "settings": settings,
        "wall_time_s": round(wall_time, 1),
        "baseline": BASELINE,
        "claims": claims,
        "scenarios": {
            str(sid): {
                "metrics": scalar_tables(summary),
                "paired_differences": {
                    other: {m: diffs[m] for m in TABLE_METRICS}
                    for other, diffs in summary["paired_differences"]["minus_baseline"].items()
                },
            }
            for sid, summary in summaries.items()
        },
        "figures": [p.name for p in figures],
    }
    report_json = out / "report.json"
    report_json.write_text(json.dumps(document, indent=1, default=_json_default) + "\n")
    return report_md, report_json


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


# ------------------------------------------------------------------------------- main


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    studies, args = parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.quiet
    start = time.perf_counter()
    results_by_scenario, summaries = {}, {}
    try:
        for index, study in enumerate(studies):
            if progress:
                print(
                    f"scenario {study.scenario_id} ({index + 1}/{len(studies)}): "
                    f"{len(study.controllers)} controllers x {study.draws} draws, "
                    f"{study.horizon:g} s; {time.perf_counter() - start:.0f} s so far",
                    file=sys.stderr,
                    flush=True,
                )
            directory = out / f"s{study.scenario_id}"
            results = simulate.run_study(study, directory, progress, args.overwrite)
            results_by_scenario[study.scenario_id] = results
            summaries[study.scenario_id] = simulate.write_outputs(
                study, results, directory, figures=False
            )
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: finished chunks are kept under {out}/s*/chunks; run the same "
            "command again to continue",
            file=sys.stderr,
        )
        return 130
    except ValueError as error:
        print(f"fojax reproduce: error: {error}", file=sys.stderr)
        return 2
    figures = []
    if not args.no_figures:
        from experiments import paper_figures

        if progress:
            print("figures ...", file=sys.stderr, flush=True)
        figures = paper_figures.plot_all(results_by_scenario, out / "figures")
    claims = evaluate_claims(summaries, results_by_scenario)
    settings = {
        "draws": args.draws,
        "seed": args.seed,
        "scenarios": list(args.scenarios),
        "switching": args.switching,
        "fractional": args.fractional,
        "dt": args.dt,
        "dtype": args.dtype,
        "horizons_s": {str(s.scenario_id): s.horizon for s in studies},
        "controllers": list(studies[0].controllers),
    }
    wall = time.perf_counter() - start
    report_md, _ = write_report(out, summaries, claims, settings, figures, wall)
    print(f"wrote {report_md}, report.json, figures/ and s*/ in {wall:.0f} s")
    for claim in claims:
        print(f"  {claim['verdict']:>14}: {claim['text']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
