"""``report.md`` and ``report.json`` of ``fojax reproduce``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fojax.cli import output
from fojax.cli.reproduce import claims as rule
from fojax.cli.reproduce.claims import BASELINE, CHATTER_THRESHOLD, per_axis
from fojax.records import atomic_write

__all__ = ["TABLE_METRICS", "write_report"]

TABLE_METRICS = (
    ["position_rmse", "attitude_rmse"]
    + per_axis("rmse")
    + per_axis("overshoot")
    + per_axis("settling_time")
    + per_axis("itae")
    + per_axis("max_error")
    + ["chattering_thrust", "chattering_tau_x", "control_effort_thrust", "actuator_saturation"]
)

MARK = {"better": "**better**", "worse": "**worse**", "equivalent": "equiv.", "inconclusive": "?"}


def format_number(value, digits: int = 3) -> str:
    """``value`` to ``digits`` significant digits; ``n/a`` for None, ``0`` for zero."""
    if value is None:
        return "n/a"
    if value == 0:
        return "0"
    if not math.isfinite(value):
        return str(value)
    return f"{value:.{digits}g}"


_fmt = format_number


def _row(cells) -> str:
    """A Markdown table row."""
    return "| " + " | ".join(cells) + " |"


def _head(columns) -> list[str]:
    """A Markdown table's header row and rule."""
    return [_row(columns), "|" + "---|" * len(columns)]


def _cell(stats: dict) -> str:
    if stats.get("mean") is None:
        return "n/a"
    ci = stats.get("ci95")
    if ci is None:
        return _fmt(stats["mean"])
    return f"{_fmt(stats['mean'])} [{_fmt(ci[0])}, {_fmt(ci[1])}]"


def _rule_lines(settings: dict) -> list[str]:
    floors, alpha = rule.MARGIN_FLOORS, rule.ALPHA
    return [
        "### The verdict rule",
        "",
        f"*Comparisons.* For each claim, every (compared controller X, mapped metric) pair "
        f"is one comparison of the per-draw difference d = metric(X) - metric({BASELINE}) "
        "over the draws where neither diverged. Every mapped metric is lower-is-better, so "
        f"d > 0 means the {BASELINE} is better.",
        "",
        f"*Margin of practical relevance* per comparison: delta = max(floor, "
        f"{rule.RELATIVE_MARGIN * 100:g} % of the {BASELINE}'s mean of the metric), with the "
        f"floors {floors['m']:g} m, {floors['rad']:g} rad, {floors['s']:g} s, "
        f"{floors['1']:g} for a fraction of the run; for an integral of the error the "
        f"integral of a constant error at the floor over the run (floor T for IAE, "
        "floor T^2/2 for ITAE: 3.2 m s^2 over 80 s); forces and torques relative only. "
        "Each comparison's delta is listed with it.",
        "",
        "*Three questions* per comparison, each a one-sample t-test on d: **better** "
        "(mean d > delta), **worse** (mean d < -delta), **equivalent** (-delta < mean d "
        "< delta, two one-sided tests). *Multiplicity*: the 3 k p-values of a claim's k "
        f"comparisons are Holm-adjusted as one family; an answer is yes when its "
        f"adjusted p-value is below {alpha:g}, so that all the yes answers of a claim are "
        f"right together with probability at least {(1 - alpha) * 100:g} %. A comparison is "
        "*better*, *worse* or *equivalent* by its yes answer (at most one can be yes), "
        "*inconclusive* when none is.",
        "",
        "*Claim verdicts*: **holds** when the AFONFTSMC is better beyond the margin in "
        "every comparison; **does not hold** when it is worse beyond the margin in at "
        "least one; **equivalent within the margin** when it is never worse and every "
        "comparison where it is not better is equivalent (no practical disadvantage, but "
        "the claimed advantage is not of practical size everywhere); **inconclusive** "
        "otherwise. The last column of the table above applies the earlier rule (any 95 % "
        "interval of d excluding 0 decides, no margin, no multiplicity control) to the "
        "same draws.",
        "",
        "*Chatter-free* (Remark 2): every input of the AFONFTSMC changes per control step by "
        f"less than {CHATTER_THRESHOLD:g} of its RMS value on average "
        "(total variation / steps / RMS), in every scenario.",
        "",
        "*Finite-time convergence*: the AFONFTSMC's sliding variable of each axis enters "
        "|S| <= band and stays there from before half the run to its end, in every draw, "
        f"axis and scenario, with band = {rule.REACHING_BAND_FACTOR:g} (h1 + mu) "
        f"dt per axis ({_band_text(settings)}). Switching at a fixed step moves S by about "
        "(h1 + mu) dt per step, so `sgn` leaves S chattering in a band of that width "
        "however well the surface is held: a smaller band cannot be kept by construction.",
        "",
    ]


def _band_text(settings: dict) -> str:
    band = settings.get("reaching_band")
    if not band:
        return "not recorded"
    return (
        f"{_fmt(band[0])} x/y, {_fmt(band[2])} z, {_fmt(band[3])} attitude at dt = "
        f"{settings['dt']:g} s"
    )


def _applied(summary: dict, option: str) -> str:
    """`` (AFONFTSMC, ...)``: the controllers a shared option applied to, when not all
    of them (the FL has no switching function; only two have fractional operators)."""
    users = summary.get("options_applied_to", {}).get(option)
    if users is None or len(users) == len(summary["controllers"]):
        return ""
    return f" ({', '.join(name.upper() for name in users) or 'none'})"


def _scenario_section(summary: dict, table: dict | None) -> list[str]:
    controllers = summary["controllers"]
    names = list(controllers)
    lines = [
        f"### Scenario {summary['scenario']}",
        "",
        f"{summary['draws']} draws, seed {summary['seed']}, {summary['horizon_s']:g} s at "
        f"dt = {summary['dt_s']:g} s, switching `{summary['switching']}`"
        f"{_applied(summary, 'switching')}, fractional method "
        f"`{summary['fractional_method']}`{_applied(summary, 'fractional_method')}, "
        f"{summary['dtype']}.",
        "",
        "Mean and 95 % confidence interval over the draws that did not diverge:",
        "",
        *_head(["metric", "unit", *names]),
    ]
    for metric in TABLE_METRICS:
        cells = [_cell(controllers[n]["metrics"][metric]) for n in names]
        lines.append(_row([metric, controllers[names[0]]["metrics"][metric]["unit"], *cells]))
    diverged = [str(controllers[n]["diverged"]) for n in names]
    lines.append("| diverged draws | | " + " | ".join(diverged) + " |")
    wall = [f"{controllers[n].get('wall_time_s', float('nan')):.0f}" for n in names]
    lines.append("| wall time | s | " + " | ".join(wall) + " |")
    if not table:
        return lines + [""]
    return lines + [
        "",
        f"Paired differences, controller minus {BASELINE} on the same draw (mean [95 % CI]), "
        "against the margin delta, each comparison decided on its own (no multiplicity "
        f"control; the claims' verdicts adjust): **better**: the {BASELINE} lower by more "
        "than delta, **worse**: higher by more than delta, equiv.: within +-delta, ?: "
        "undecided:",
        "",
        *_differences(TABLE_METRICS, table),
        "",
    ]


def _differences(metrics, table: dict) -> list[str]:
    """A table of paired differences: per metric its margin and, per controller of
    ``table`` (controller -> metric -> comparison), the difference and its outcome."""
    lines = _head(["metric", "delta", *table])
    for metric in metrics:
        row = [by_metric[metric] for by_metric in table.values()]
        cells = [f"{_cell(c['difference'])} {MARK[c['outcome']]}" for c in row]
        lines.append(_row([metric, _fmt(row[0]["margin"]), *cells]))
    return lines


def _claim_section(claim: dict) -> list[str]:
    lines = [f"### {claim['text']}", "", f"**Verdict: {claim['verdict']}.**", ""]
    lines += [f"Metrics: {claim['mapping']}", ""]
    if claim.get("counts"):
        c = claim["counts"]
        controllers = len(claim["comparisons"]) // len(claim["metrics"])
        lines.append(
            f"Of {sum(c.values())} comparisons ({controllers} controllers x "
            f"{len(claim['metrics'])} metrics) the {BASELINE} is better beyond "
            f"the margin in {c['better']}, worse beyond it in {c['worse']}, equivalent within "
            f"it in {c['equivalent']}, undecided in {c['inconclusive']}. Without margin or "
            f"correction the verdict would be: {claim['verdict_without_margin']}."
        )
        worse = [x for x in claim["comparisons"] if x["outcome"] == "worse"]
        if worse:
            items = ", ".join(
                f"{x['metric']} vs {x['controller']} ({_cell(x['difference'])}, delta "
                f"{_fmt(x['margin'])})"
                for x in worse
            )
            lines.append(f"Worse: {items}.")
        table = {}
        for x in claim["comparisons"]:
            table.setdefault(x["controller"], {})[x["metric"]] = x
        head = "(S2 - S1) difference" if claim.get("delta_from") else "difference"
        lines += [
            "",
            f"Per comparison: {head}, controller minus {BASELINE} (mean [95 % CI]), and its "
            "outcome (Holm-adjusted over the claim):",
            "",
            *_differences(claim["metrics"], table),
            "",
        ]
    if claim["id"] == "R2-chatter-free":
        lines += [
            "Mean change per control step relative to the input's RMS "
            f"(chatter-free below {CHATTER_THRESHOLD:g}):",
            "",
            *_head(["scenario", "controller", "u_F", "tau_x", "tau_y", "tau_z", "chatter-free"]),
        ]
        for row in claim["rows"]:
            r = row["change_per_step_over_rms"]
            cells = [_fmt(r[k]) for k in ("thrust", "tau_x", "tau_y", "tau_z")]
            free = "yes" if row["chatter_free"] else "no"
            lines.append(_row([str(row["scenario"]), row["controller"], *cells, free]))
        lines.append("")
    if claim["id"] == "C-finite-time":
        head = ["scenario", "axis", "band", "reached", "kept from the first half"]
        lines += [
            f"The {BASELINE}'s sliding variables, per scenario and axis: the band; in how "
            "many draws |S| is in the band at the end of the run (reached) and in it from "
            "before half the run to its end (kept); the reaching time, the time after "
            "which |S| stays in the band (mean [95 % CI] over the draws that reach it); the "
            "eq. (34) bound from S(0) (mean over the draws):",
            "",
            *_head([*head, "reaching time (s)", "eq. (34) bound (s)"]),
        ]
        for row in claim["rows"]:
            valid = row["valid_draws"]
            counts = [f"{row['reached']}/{valid}", f"{row['kept_from_first_half']}/{valid}"]
            cells = [str(row["scenario"]), row["axis"], _fmt(row["band"]), *counts]
            cells += [_cell(row["reaching_time_s"]), _fmt(row["bound_34_s"]["mean"])]
            lines.append(_row(cells))
        lines.append("")
    return lines


def write_report(
    out: Path,
    summaries: dict,
    claims: list[dict],
    settings: dict,
    figures: list[Path],
    wall_time: float,
    tables: dict | None = None,
) -> tuple[Path, Path]:
    """``report.md`` and ``report.json`` in ``out``; returns their paths.

    ``tables``: :func:`fojax.cli.reproduce.claims.paired_tables` (scenario id ->
    controller -> metric -> comparison) for the per-scenario difference tables.
    """
    tables = tables or {}
    report_md, report_json = out / "report.md", out / "report.json"
    lines = _markdown(out, summaries, claims, settings, figures, wall_time, tables)
    atomic_write(report_md, "\n".join(lines) + "\n")
    document = _document(summaries, claims, settings, figures, wall_time, tables)
    output.write_json(report_json, document, default=_json_default)
    return report_md, report_json


def _markdown(out, summaries, claims, settings, figures, wall_time, tables) -> list[str]:
    """The lines of ``report.md``: settings, verdicts, rule, claims, figures, metrics."""
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
        "| claim | verdict | better / worse / equivalent / undecided | without margin "
        "or correction |",
        "|---|---|---|---|",
    ]
    for claim in claims:
        c = claim.get("counts")
        tally = " / ".join(str(c[k]) for k in rule.OUTCOMES) if c else ""
        without = claim.get("verdict_without_margin", claim["verdict"])
        lines.append(_row([claim["text"], f"**{claim['verdict']}**", tally, without]))
    lines += [""] + _rule_lines(settings)
    lines += [
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
        lines += _scenario_section(summaries[scenario_id], tables.get(scenario_id))
    return lines


def _document(summaries, claims, settings, figures, wall_time, tables) -> dict:
    """``report.json``: the settings, the rule, the claims, each scenario's tables."""
    return {
        "settings": settings,
        "wall_time_s": round(wall_time, 1),
        "baseline": BASELINE,
        "rule": {
            "alpha": rule.ALPHA,
            "relative_margin": rule.RELATIVE_MARGIN,
            "margin_floors": rule.MARGIN_FLOORS,
            "multiplicity": "Holm over the 3 p-values of each of a claim's comparisons",
            "reaching_band_factor": rule.REACHING_BAND_FACTOR,
            "chatter_threshold": CHATTER_THRESHOLD,
        },
        "claims": claims,
        "scenarios": {
            str(sid): {
                "metrics": {
                    name: {m: entry["metrics"][m] for m in TABLE_METRICS}
                    | {"diverged": entry["diverged"], "wall_time_s": entry.get("wall_time_s")}
                    for name, entry in summary["controllers"].items()
                },
                "paired_differences": {
                    other: {m: row[m] for m in TABLE_METRICS}
                    for other, row in tables.get(sid, {}).items()
                },
            }
            for sid, summary in summaries.items()
        },
        "figures": [p.name for p in figures],
    }


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
