"""The tables and figures of :mod:`experiments.tuning_study`: the per-run records
summarised (median and spread over seeds), the Markdown table of the study's section of
``docs/tuning.md``, and the held-out cost against wall time or draw-steps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments import _common

__all__ = ["METHODS", "plot", "summarize", "table", "user_table"]

METHODS = ("gradient", "cma-es", "nelder-mead")
COLORS = {"gradient": "#0072B2", "cma-es": "#D55E00", "nelder-mead": "#009E73"}
LABELS = {"gradient": "gradient tuner", "cma-es": "CMA-ES (batched)", "nelder-mead": "Nelder-Mead"}
USER_MODES = ("optimized", "fast")


def _reach(curve, level, compile_s):
    """(wall time incl. compile, draw-steps) at which ``curve`` first reaches ``level``."""
    for draw_steps, wall, cost in curve:
        if cost <= level:
            return wall + compile_s, draw_steps
    return None, None


def summarize(records: list[dict]) -> dict:
    """Per (share, start): per method the held-out costs and times over the seeds, and,
    per seed, where the gradient tuner reaches CMA-ES's best held-out cost."""
    groups: dict = {}
    for r in records:
        groups.setdefault((r["share"], r["start"]), {}).setdefault(r["method"], {})[r["seed"]] = r
    out = {}
    for (share, start), methods in sorted(groups.items()):
        entry = {"methods": {}, "target": []}
        for method, by_seed in methods.items():
            runs = list(by_seed.values())
            entry["methods"][method] = {
                "parameters": runs[0]["parameters"],
                "seeds": sorted(by_seed),
                "initial": runs[0]["initial_heldout"],
                "final": [r["final_heldout"] for r in runs],
                "best": [min(c for _, _, c in r["curve"]) for r in runs],
                "wall_time_s": [r["wall_time_s"] + r["compile_s"] for r in runs],
                "compile_s": runs[0]["compile_s"],
                "draw_steps": [r["draw_steps"] for r in runs],
            }
        if "gradient" in methods and "cma-es" in methods:
            for seed, cma in sorted(methods["cma-es"].items()):
                gradient = methods["gradient"].get(seed)
                if gradient is None:
                    continue
                level = min(c for _, _, c in cma["curve"])
                cma_total = cma["wall_time_s"] + cma["compile_s"]
                cma_at, _ = _reach(cma["curve"], level, cma["compile_s"])
                wall, steps = _reach(gradient["curve"], level, gradient["compile_s"])
                entry["target"].append(
                    {
                        "seed": seed,
                        "cma_best": level,
                        "cma_wall_time_s": cma_total,
                        "cma_reached_at_s": cma_at,
                        "gradient_reached_at_s": wall,
                        "gradient_draw_steps": steps,
                        "ratio_to_cma_wall_time": None if wall is None else wall / cma_total,
                        "ratio_without_compilation": None
                        if wall is None
                        else (wall - gradient["compile_s"]) / cma["wall_time_s"],
                        "met": wall is not None and wall <= 0.5 * cma_total,
                        "gradient_best": min(c for _, _, c in gradient["curve"]),
                    }
                )
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
    "best held-out cost on the curve | wall time incl. compile (s) | compile (s) | draw-steps"
)


def _method_rows(summary: dict):
    for share, start, entry in _entries(summary):
        for m, label in ((entry["methods"].get(k), LABELS[k]) for k in METHODS):
            if m is not None:
                yield (
                    f"| {m['parameters']} (`--share {share}`) | {start} | {label} | "
                    f"{m['initial']:.4g} | {_spread(m['final'], '.4g')} | "
                    f"{_spread(m['best'], '.4g')} | {_spread(m['wall_time_s'], '.0f')} | "
                    f"{m['compile_s']:.0f} | {_spread(m['draw_steps'], '.3g')} |"
                )


TARGET_COLUMNS = (
    "parameters | start | seed | CMA-ES best | CMA-ES wall time (s) (reached its best at) | "
    "gradient reached it at (s) | ratio | met | ratio without compilation | gradient's best"
)


def _target_rows(summary: dict):
    for _, start, entry in _entries(summary):
        size = next(iter(entry["methods"].values()))["parameters"]
        for t in entry["target"]:
            reached = _number(t["gradient_reached_at_s"], ".0f", "not reached")
            ratio = _number(t["ratio_to_cma_wall_time"], ".2f")
            bare = _number(t.get("ratio_without_compilation"), ".2f")
            yield (
                f"| {size} | {start} | {t['seed']} | {t['cma_best']:.4g} | "
                f"{t['cma_wall_time_s']:.0f} ({t['cma_reached_at_s']:.0f}) | {reached} | "
                f"{ratio} | {'yes' if t['met'] else 'no'} | {bare} | {t['gradient_best']:.4g} |"
            )


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
    "gradient_method gradient_steps gradient_draws validation_draws validate_every "
    "cma_generations df_draws heldout_draws horizon dtype"
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
        "Target: the gradient tuner reaches CMA-ES's best held-out cost (over CMA-ES's whole "
        "budget) in at most half of CMA-ES's wall time (both with compilation):",
        "",
        *_common.table_head(TARGET_COLUMNS),
        *_target_rows(results["summary"]),
    ]
    for bench in results.get("bench", []):
        lines += ["", _bench_line(bench)]
    if results.get("user_view"):
        lines += ["", "The user's view, `fojax tune` from the paper's gains:", ""]
        lines.append(user_table(results["user_view"]))
    lines += ["", "Settings: " + ", ".join(f"{k} {settings[k]}" for k in SETTINGS) + "."]
    return "\n".join(lines)


def plot(records: list[dict], path: Path, axis: str) -> Path:
    """Held-out cost against wall time (compile included) or draw-steps: one panel
    per (parameter count, start), one colour per method, one line per seed."""
    from matplotlib.lines import Line2D

    from fojax.cli import style

    plt = style.pyplot()
    panels = sorted({(r["parameters"], r["share"], r["start"]) for r in records})
    cols = len({p[2] for p in panels}) or 1
    rows = max(1, len(panels) // cols)
    fig = plt.figure(figsize=(5.2 * cols, 3.6 * rows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).reshape(rows, cols)
    for index, (size, share, start) in enumerate(panels):
        ax = axes.flat[index]
        initial = None
        for r in records:
            if (r["parameters"], r["share"], r["start"]) != (size, share, start):
                continue
            curve = np.asarray(r["curve"], float)
            if axis == "wall":  # the start, then nothing until compilation ends
                x = np.concatenate([[0.0], curve[:, 1] + r["compile_s"]])
                y = np.concatenate([[curve[0, 2]], curve[:, 2]])
            else:
                x, y = curve[:, 0], curve[:, 2]
            ax.step(x, y, where="post", color=COLORS[r["method"]], lw=1.2, alpha=0.85)
            initial = r["initial_heldout"]
        if initial is not None:
            ax.axhline(initial, color="0.4", ls=":", lw=1)
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
    style.legend_below(fig, handles, ncol=len(handles))
    fig.suptitle(
        "AFONFTSMC, scenario 2, 10 s: held-out cost of each tuner's current answer "
        "(one line per seed)",
        fontsize=10,
    )
    return style.save(fig, path)


def user_table(records: list[dict]) -> str:
    lines = _common.table_head(
        "`--compile` | runs | command wall time (s), compilation included | tuning loop (s) "
        "| validation cost first at half the start's, at (s of the loop) | held-out cost: "
        "paper's -> returned | returned step | held-out halved"
    )
    for mode in USER_MODES:
        runs = [r for r in records if r["mode"] == mode]
        if not runs:
            continue
        halved = sum(r["heldout_tuned"] <= 0.5 * r["heldout_initial"] for r in runs)
        lines.append(
            f"| {mode} | {len(runs)} | {_spread([r['total_s'] for r in runs], '.0f')} | "
            f"{_spread([r['tuning_s'] for r in runs], '.0f')} | "
            f"{_spread([r['validation_halved_at_s'] for r in runs], '.0f')} | "
            f"{runs[0]['heldout_initial']:.4g} -> "
            f"{_spread([r['heldout_tuned'] for r in runs], '.4g')} | "
            f"{', '.join(str(r['selected_step']) for r in runs)} | {halved}/{len(runs)} |"
        )
    loads = [x for r in records for x in (r["load_before"][:1] + r["load_after"][:1])]
    if loads:
        lines += ["", f"(1-minute load average {min(loads):.1f}-{max(loads):.1f}; command: "
                  f"`{records[0]['command'].replace(' --compile optimized', '')}` "
                  "with `--compile fast` or not.)"]  # fmt: skip
    return "\n".join(lines)
