"""The tables and the figure of :mod:`experiments.remark3_inverted`: the residuals per
gain set and objective, the weights, the requirement set found, the gains against the
paper's field by field, and the quantities."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments import _common
from experiments.remark3 import table_row

__all__ = ["SURROGATES", "figure", "table"]

SURROGATES = ("settling_time", "rotor_saturation")
"""Piecewise-constant metrics whose derivative is a smooth surrogate's
(:mod:`fojax.requirements`): their finite difference is 0 or a jump, not compared."""


MARKERS = {
    "naive": ("o", 9, "none"),
    "tuned from naive": ("o", 3.5, None),
    "tuned from paper": ("D", 4, None),
}
"""Panel (c)'s ``(marker, size, face)`` per gain set: the naive start a large hollow circle,
so that a tuned-from-naive dot left where it started shows inside it."""


def _fmt_set(entry: dict) -> str:  # the bounds with a multiplier > 0
    return ", ".join(f"{n} ({w:.3g})" for n, w in entry["set"].items() if w > 0) or "-"


def _residual_lines(results: dict) -> list[str]:
    """The residuals by requirement set (size, objective, gain set) and weighted sum."""
    lines = [
        "Residual `r` (0: stationary, 1: no bound helps) of the best requirement set of each "
        "size, multipliers in brackets:",
        "",
        *_common.table_head("gains | objective | 1 bound | 2 bounds | 3 bounds | every candidate"),
    ]
    for point, analysis in results["analysis"].items():
        for objective in ("tracking", "effort"):
            cells = [
                f"{e['residual']:.3f}" + (f": {_fmt_set(e)}" if point == "paper" else "")
                for e in analysis[objective]["subsets"]
            ]
            lines.append(table_row(point, objective, *cells))
    columns = "gains | fojax tune's weights (1e-5, 1e-5) | best `(w_E, w_C)` | its residual"
    lines += ["", "Weighted sum `P + A + w_E E + w_C C`: residual at `w = 0` is 1.", ""]
    lines += _common.table_head(columns)
    for point, analysis in results["analysis"].items():
        default, best = analysis["weights"]["fojax_tune_default"], analysis["weights"]["best"]
        cells = f"{default['residual']:.3f}", f"({best['w_E']:.3g}, {best['w_C']:.3g})"
        lines.append(table_row(point, *cells, f"{best['residual']:.3f}"))
    return lines


def table(results: dict) -> str:
    """Markdown: the residuals per point and objective, the weights, the requirement set
    found, the tuned gains against the paper's field by field, the quantities."""
    s = results["setting"]
    worst = max(results["finite_difference_check"].items(), key=lambda i: i[1]["relative_error"])
    lines = [
        f"Setting: scenario {s['scenario']}, {s['drag']}, {s['horizon_s']:g} s, {s['switching']}, "
        f"{s['actuators']} actuators, {s['dtype']}, {s['parameters']} parameters `u`. "
        f"Jacobian of {len(results['quantities'])} quantities against a central finite "
        "difference along a random direction: largest relative error "
        f"{worst[1]['relative_error']:.1g} "
        f"(`{worst[0]}`; {' and '.join(SURROGATES)} carry a smooth surrogate's derivative, "
        "not compared).",
        "",
        *_residual_lines(results),
    ]
    names = list(results["gains"])
    head = "Quantities of each gain set (the requirement set found: bounds at the paper's values):"
    lines += ["", head, "", *_common.table_head("quantity | bound | " + " | ".join(names))]
    bounds = {r["metric"]: r["max"] for r in results["requirements_found"]["requirements"]}
    for i, q in enumerate(results["quantities"]):
        bound = f"<= {bounds[q]:.4g}" if q in bounds else ""
        lines.append(table_row(q, bound, *(f"{results['values'][n][i]:.4g}" for n in names)))
    lines += ["", "Gains field by field (`log10(gain / paper)` in brackets):", ""]
    lines += _common.table_head("parameter | " + " | ".join(names))
    distances = results["distance_to_paper"]
    for label in distances["paper"]["values"]:
        cells = [
            f"{distances[n]['values'][label]:.4g}"
            + ("" if n == "paper" else f" ({distances[n]['log10_ratio'][label]:+.2f})")
            for n in names
        ]
        lines.append(table_row(label, *cells))
    medians = [f"{distances[n]['median_abs_log10']:.2f}" for n in names]
    within = [f"{distances[n]['within_factor_2']}/{distances[n]['parameters']}" for n in names]
    for title, cells in (("median abs log10", medians), ("within a factor 2", within)):
        lines.append(table_row(f"**{title}**", *cells))
    tuning = results["requirement_tuning"]
    t = results["times_s"]
    runs = "; ".join(
        f"from {start}: selected step {r['selected'].get('step')}, meets "
        f"{r['selected'].get('passed', '?')}/1 ({r['wall_time_s']:.0f} s)"
        for start, r in tuning.items()
    )
    lines += [
        "",
        f"Requirement tuning (objective effort; the second start reuses the first's "
        f"compiled programs): {runs}; the paper's gains meet "
        f"{tuning['paper']['paper']['passed']}/1. Jacobian: {t['jacobian']:.1f} s (first, "
        f"with compilation, {t['first_jacobian_with_compile']:.0f} s); {t['total']:.0f} s in "
        f"all, load average at the end {results['load_average']}.",
    ]
    return "\n".join(lines)


def figure(results: dict, path: Path) -> None:
    """(a) The best residual by number of bounds, per gain set and objective; (b) the
    residual of ``P + A + w_E E`` over ``w_E``; (c) ``log10(gain / paper)`` per
    parameter of the other gain sets."""
    from fojax.cli import style

    plt = style.pyplot()
    fig, (sizes, sweep, fields) = plt.subplots(
        1, 3, figsize=(15, 4.8), gridspec_kw={"width_ratios": [1, 1, 1.9]}
    )
    colors = {name: f"C{i}" for i, name in enumerate(results["analysis"])}
    for name, analysis in results["analysis"].items():
        # the naive start wide and light: tuned-from-naive's lines may lie on it
        wide = {"lw": 5, "alpha": 0.4} if name == "naive" else {}
        for objective, style_ in (("effort", "-o"), ("tracking", "--s")):
            rows = analysis[objective]["subsets"]
            sizes.plot(
                range(1, len(rows) + 1), [e["residual"] for e in rows], style_,
                ms=9 if wide else 4, color=colors[name], label=f"{name}, {objective}", **wide,
            )  # fmt: skip
        w = analysis["weights"]
        sweep.loglog(w["sweep_w_E"], w["sweep_residual"], color=colors[name], label=name, **wide)
    count = len(results["analysis"]["paper"]["effort"]["subsets"])
    sizes.set_xticks(range(1, count + 1), [*map(str, range(1, count)), "all"])
    sizes.set(xlabel="bounds (the best set of each size)", ylim=(0, 1.02))
    sizes.set_ylabel("residual r (0: stationary, 1: no bound helps)")
    sizes.set_title("(a) min objective s.t. bounds at these gains' values", fontsize=10)
    sizes.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    sweep.axhline(1, color="0.5", lw=0.8)
    sweep.axvline(1e-5, color="0.5", ls=":", lw=1)
    where = sweep.get_xaxis_transform()
    sweep.text(1e-5, 0.97, " fojax tune's w_E", transform=where, va="top", color="0.4", fontsize=8)
    sweep.set(xlabel="effort weight w_E", ylabel="r = |grad(P + A + w_E E)| / |grad(P + A)|")
    sweep.set_title(
        "(b) the weighted sum P + A + w_E E\n(a wide light line: the naive start's)", fontsize=10
    )
    sweep.legend(fontsize=8)
    distances = results["distance_to_paper"]
    labels = list(distances["paper"]["log10_ratio"])
    xs = np.arange(len(labels))
    fields.axhspan(-np.log10(2), np.log10(2), color="0.88", zorder=0, label="within a factor 2")
    fields.axhline(0, color="k", lw=0.8)
    for name, entry in distances.items():
        if name == "paper":
            continue
        ys = [entry["log10_ratio"][label] for label in labels]
        text = f"{name} (median |.| {entry['median_abs_log10']:.2f})"
        marker, size, face = MARKERS.get(name, ("o", 4, None))
        fields.plot(xs, ys, marker, ms=size, mfc=face, color=colors[name], label=text)
    fields.set_xticks(xs, labels, rotation=90, fontsize=7)
    fields.set_ylabel("log10(gain / paper's gain)")
    note = "(a dot inside a hollow circle: a gain the tuner left at its naive start)"
    fields.set_title(f"(c) each gain set against the paper's, field by field\n{note}", fontsize=10)
    fields.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
