"""The tables and figures of :mod:`experiments.tuning_study`: the per-run records
summarised (median and spread over seeds), the Markdown table of the study's section of
``docs/tuning.md``, and the held-out cost against wall time or draw-steps."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from experiments import _common

__all__ = ["CHALLENGERS", "METHODS", "USER_MODES", "plot", "summarize", "table", "user_table"]

METHODS = ("default", "lbfgs", "cma-es", "nelder-mead")
CHALLENGERS = ("default", "lbfgs")
"""The methods checked against CMA-ES's best held-out cost (the target)."""
COLORS = {"default": "#CC79A7", "lbfgs": "#0072B2", "cma-es": "#D55E00", "nelder-mead": "#009E73"}
LABELS = {
    "default": "default (CMA-ES on 8 fresh draws)",
    "lbfgs": "L-BFGS",
    "cma-es": "CMA-ES (batched)",
    "nelder-mead": "Nelder-Mead",
}
USER_MODES = ("naive-default", "naive-cma-es", "paper-default")
"""The user view's commands: ``<start>-<method>`` (``default``: no ``--method``)."""


def _reach(curve, level):
    """(wall time, draw-steps) at which ``curve`` (rows ``[step, wall time, draw-steps,
    held-out cost]``) first reaches ``level``."""
    for _, wall, draw_steps, cost in curve:
        if cost <= level:
            return wall, draw_steps
    return None, None


def _best(run: dict) -> float:
    return min(point[3] for point in run["curve"])


def _method_entry(runs: list[dict]) -> dict:
    return {
        "parameters": runs[0]["parameters"],
        "seeds": sorted(r["seed"] for r in runs),
        "initial": runs[0]["initial_heldout"],
        "final": [r["final_heldout"] for r in runs],
        "best": [_best(r) for r in runs],
        "wall_time_s": [r["wall_time_s"] for r in runs],
        "first_step_s": [r["curve"][1][1] for r in runs if len(r["curve"]) > 1],
        "draw_steps": [r["draw_steps"] for r in runs],
    }


def _against(run: dict, level: float, cma_wall: float) -> dict:
    """Where ``run`` reaches CMA-ES's best ``level``, against CMA-ES's wall time."""
    wall, steps = _reach(run["curve"], level)
    return {
        "reached_at_s": wall,
        "draw_steps": steps,
        "ratio_to_cma_wall_time": None if wall is None else wall / cma_wall,
        "met": wall is not None and wall <= 0.5 * cma_wall,
        "final": run["final_heldout"],
        "final_at_or_below": run["final_heldout"] <= level,
        "best": _best(run),
    }


def summarize(runs: list[dict]) -> dict:
    """Per (share, start): per method the held-out costs and times over the seeds, and,
    per seed, where each of :data:`CHALLENGERS` reaches CMA-ES's best held-out cost."""
    groups: dict = {}
    for r in runs:
        groups.setdefault((r["share"], r["start"]), {}).setdefault(r["method"], {})[r["seed"]] = r
    out = {}
    for (share, start), methods in sorted(groups.items()):
        entry = {"methods": {}, "target": []}
        for method, by_seed in methods.items():
            entry["methods"][method] = _method_entry(list(by_seed.values()))
        for seed, cma in sorted(methods.get("cma-es", {}).items()):
            level = _best(cma)
            row = {"seed": seed, "cma_best": level, "cma_wall_time_s": cma["wall_time_s"]}
            row["cma_reached_at_s"] = _reach(cma["curve"], level)[0]
            for method in CHALLENGERS:
                if seed in methods.get(method, {}):
                    row[method] = _against(methods[method][seed], level, cma["wall_time_s"])
            entry["target"].append(row)
        out[f"{share}/{start}"] = entry
    return out


def _spread(values, fmt=".3g") -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    median = float(np.median(values))
    if len(values) == 1:
        return format(median, fmt)
    return f"{median:{fmt}} [{min(values):{fmt}}, {max(values):{fmt}}]"


def _entries(summary: dict):
    """``(share, start, entry)`` per entry of :func:`summarize`'s summary."""
    for key, entry in summary.items():
        share, start = key.split("/")
        yield share, start, entry


def _number(value, fmt: str, missing: str = "-") -> str:
    return missing if value is None else format(value, fmt)


METHOD_COLUMNS = (
    "parameters | start | method | held-out cost at the start | final held-out cost | "
    "best held-out cost on the curve | wall time incl. compilation (s) | first step done at "
    "(s) | draw-steps"
)


def _method_rows(summary: dict):
    for share, start, entry in _entries(summary):
        for m, label in ((entry["methods"].get(k), LABELS[k]) for k in METHODS):
            if m is not None:
                yield (
                    f"| {m['parameters']} (`--share {share}`) | {start} | {label} | "
                    f"{m['initial']:.4g} | {_spread(m['final'], '.4g')} | "
                    f"{_spread(m['best'], '.4g')} | {_spread(m['wall_time_s'], '.0f')} | "
                    f"{_spread(m['first_step_s'], '.0f')} | {_spread(m['draw_steps'], '.3g')} |"
                )


TARGET_COLUMNS = "parameters | start | seed | CMA-ES best | CMA-ES wall time (s) (best at) | " + (
    " | ".join(
        f"{LABELS[m].split(' (')[0]} {c}"
        for m in CHALLENGERS
        for c in ("reached it at (s) (ratio)", "in half", "final (at or below)")
    )
)


def _challenger_cells(t: dict | None) -> str:
    if t is None:
        return "- | - | -"
    reached = _number(t["reached_at_s"], ".0f", "not reached")
    ratio = _number(t["ratio_to_cma_wall_time"], ".2f")
    final = f"{t['final']:.4g} ({'yes' if t['final_at_or_below'] else 'no'})"
    return f"{reached} ({ratio}) | {'yes' if t['met'] else 'no'} | {final}"


def _target_rows(summary: dict):
    for _, start, entry in _entries(summary):
        size = next(iter(entry["methods"].values()))["parameters"]
        for t in entry["target"]:
            cells = " | ".join(_challenger_cells(t.get(m)) for m in CHALLENGERS)
            yield (
                f"| {size} | {start} | {t['seed']} | {t['cma_best']:.4g} | "
                f"{t['cma_wall_time_s']:.0f} ({_number(t['cma_reached_at_s'], '.0f')}) | {cells} |"
            )


def _tallies(summary: dict) -> list[str]:
    """Per challenger and start: runs reaching CMA-ES's best in half its time, and
    ending at or below it."""
    lines = []
    for method, start in itertools.product(CHALLENGERS, ("paper", "naive")):
        entries = [entry for _, s, entry in _entries(summary) if s == start]
        rows = [t[method] for entry in entries for t in entry["target"] if method in t]
        if rows:
            met, below = (sum(r[k] for r in rows) for k in ("met", "final_at_or_below"))
            lines.append(
                f"- {LABELS[method]}, from the {start} start: reaches it in half of "
                f"CMA-ES's wall time in {met}/{len(rows)} runs, ends at or below it in "
                f"{below}/{len(rows)}."
            )
    return lines


def _bench_line(bench: dict) -> str:
    return (
        f"One CMA-ES generation, {bench['parameters']} parameters: {bench['population']} "
        f"candidates x {bench['draws']} draws x {bench['horizon_s']:g} s in one batched "
        f"call {bench['median_batched_s']:.2f} s, one call per candidate "
        f"{bench['median_one_at_a_time_s']:.2f} s (medians of {len(bench['batched_s'])}, "
        f"interleaved; {bench['median_one_at_a_time_s'] / bench['median_batched_s']:.1f}x); "
        f"costs equal to {bench['largest_relative_difference']:.1g} relative (float32 "
        "rounding depends on the batch)."
    )


SETTINGS = (
    "default_steps switch gradient_steps cma_generations draws validation_draws "
    "validate_every heldout_draws horizon dt dtype"
).split()
"""The settings the table's last line states."""


def table(results: dict) -> str:
    """Markdown: per parameter count and start, each method's held-out costs and times
    (median [min, max] over the seeds), and the target check per seed."""
    settings = results["settings"]
    runs = results["runs"]
    loads = [x for r in runs for x in (r["load_before"][:1] + r["load_after"][:1])]
    lines = [
        f"Runs: {len(runs)}, {results['runs_elapsed_s']:.0f} s in all (held-out evaluation "
        f"included); commit {results['git_commit']}; 1-minute load average "
        + (f"{min(loads):.1f}-{max(loads):.1f}" if loads else "n/a")
        + " over the runs (2 cores).",
        "",
        *_common.table_head(METHOD_COLUMNS),
        *_method_rows(results["summary"]),
        "",
        "Target: the default (and L-BFGS) reaches CMA-ES's best held-out cost (the lowest on "
        "CMA-ES's curve) in at most half of CMA-ES's wall time (both with compilation), and "
        "its final held-out cost is at or below it:",
        "",
        *_common.table_head(TARGET_COLUMNS),
        *_target_rows(results["summary"]),
        "",
        *_tallies(results["summary"]),
    ]
    for bench in results.get("bench", []):
        lines += ["", _bench_line(bench)]
    if results.get("user_view"):
        lines += ["", "The user's view, `fojax tune` in a fresh process with an empty cache:", ""]
        lines.append(user_table(results["user_view"]))
    lines += ["", "Settings: " + ", ".join(f"{k} {settings[k]}" for k in SETTINGS) + "."]
    return "\n".join(lines)


def plot(runs: list[dict], path: Path, axis: str) -> Path:
    """Held-out cost against wall time (compilation included) or draw-steps: one panel
    per (parameter count, start), one colour per method, one line per seed."""
    from matplotlib.lines import Line2D

    from fojax.cli import style

    plt = style.pyplot()
    panels = sorted({(r["parameters"], r["share"], r["start"]) for r in runs})
    cols = len({p[2] for p in panels}) or 1
    rows = max(1, len(panels) // cols)
    fig = plt.figure(figsize=(5.2 * max(cols, 2), 3.6 * rows + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).reshape(rows, cols)
    column = 1 if axis == "wall" else 2
    for index, (size, share, start) in enumerate(panels):
        ax = axes.flat[index]
        chosen = [r for r in runs if (r["parameters"], r["share"], r["start"]) == panels[index]]
        for r in chosen:  # the start at 0, then nothing until the first step
            curve = np.asarray(r["curve"], float)
            ax.step(curve[:, column], curve[:, 3], where="post", color=COLORS[r["method"]],
                    lw=1.2, alpha=0.85)  # fmt: skip
        if chosen:
            ax.axhline(chosen[0]["initial_heldout"], color="0.4", ls=":", lw=1)
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
        origin = "the paper's gains" if start == "paper" else "the naive start"
        ax.set_title(f"{size} parameters (--share {share}), from {origin}", fontsize=9)
        ax.set_xlabel(
            "wall time, compilation included (s)" if axis == "wall" else "simulated draw-steps"
        )
        if index % cols == 0:
            ax.set_ylabel("held-out cost of the current answer")
    handles = [Line2D([], [], color=COLORS[m], lw=1.4, label=LABELS[m]) for m in METHODS]
    handles.append(Line2D([], [], color="0.4", ls=":", lw=1, label="the start's held-out cost"))
    style.legend_below(fig, handles, ncol=3)
    fig.suptitle(
        "AFONFTSMC, scenario 2, 10 s: held-out cost of each tuner's current answer "
        "(one line per seed)",
        fontsize=10,
    )
    return style.save(fig, path)


USER_COLUMNS = ("total_s", "tuning_s", "heldout_tuned")
"""The user view's columns that are spread over the runs of a command."""


def user_table(runs: list[dict]) -> str:
    """The user view: per command, its wall time and held-out costs; whether the default
    from the naive start ends at or below ``--method cma-es`` in at most its wall time,
    and whether from the paper's gains it halves the held-out cost."""
    lines = _common.table_head(
        "command | runs | wall time (s), compilation included | tuning loop (s) | held-out "
        "cost: start -> returned | returned step"
    )
    by_mode = {mode: [r for r in runs if r["mode"] == mode] for mode in USER_MODES}
    for chosen in filter(None, by_mode.values()):
        total, tuning, tuned = ([r[k] for r in chosen] for k in USER_COLUMNS)
        lines.append(
            f"| `{chosen[0]['command']}` | {len(chosen)} | {_spread(total, '.0f')} | "
            f"{_spread(tuning, '.0f')} | {chosen[0]['heldout_initial']:.4g} -> "
            f"{_spread(tuned, '.4g')} | {', '.join(str(r['selected_step']) for r in chosen)} |"
        )
    pairs = list(zip(by_mode["naive-default"], by_mode["naive-cma-es"], strict=False))
    wins = sum(
        a["heldout_tuned"] <= b["heldout_tuned"] and a["total_s"] <= b["total_s"] for a, b in pairs
    )
    halved = [r["heldout_tuned"] <= 0.5 * r["heldout_initial"] for r in by_mode["paper-default"]]
    loads = [x for r in runs for x in (r["load_before"][:1] + r["load_after"][:1])]
    lines += [
        "",
        f"From the naive start the default ends at or below `--method cma-es`'s held-out "
        f"cost in at most its wall time in {wins}/{len(pairs)} pairs of runs; from the "
        f"paper's gains it halves the held-out cost in {sum(halved)}/{len(halved)} runs "
        f"(1-minute load average {min(loads, default=0):.1f}-{max(loads, default=0):.1f}).",
    ]
    return "\n".join(lines)
