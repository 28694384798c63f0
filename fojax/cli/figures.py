"""Figures of Monte Carlo runs: tracking, errors, inputs, paths, adaptive estimates;
a tuning run's convergence (:func:`plot_convergence`, ``fojax tune``) and the yield of
a requirement set (:func:`plot_yield`, ``fojax simulate --requirements``).

Each function takes ``{controller name: MonteCarloResult}`` (results with kept
trajectories) and writes one PNG and a PDF beside it (:func:`fojax.cli.style.save`).
Lines are the median over the kept draws that did not diverge, the shaded band their
5-95 % range; the reference is dashed black, on top. Inputs are drawn as the range the
command covers at full rate within each saved block (``inputs_low``/``inputs_high``),
not as samples: a command that chatters at every step fills its band. Each controller
has one colour in every figure (:data:`fojax.cli.style.CONTROLLER_COLORS`).
"""

from __future__ import annotations

import csv
import itertools
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fojax.cli import style

__all__ = [
    "block_length",
    "controller_handles",
    "estimate_handles",
    "finish",
    "inputs_envelope",
    "kept_valid",
    "label_axes",
    "path_figure",
    "plot_adaptive",
    "plot_all",
    "plot_convergence",
    "plot_errors",
    "plot_inputs",
    "plot_path",
    "plot_tracking",
    "plot_yield",
    "six_bands",
    "six_panels",
    "time_grid",
    "times",
    "tracking_grid",
]

INPUTS = ("u_F (N)", "tau_x (N m)", "tau_y (N m)", "tau_z (N m)")


def times(result) -> np.ndarray:
    """``(T,)`` snapshot times of ``result``'s trajectories, s."""
    return np.asarray(result.trajectories.time[0])


def kept_valid(result, array) -> np.ndarray:
    """``array`` of the kept draws that did not diverge."""
    return np.asarray(array)[style.valid_kept(result)]


def time_grid(rows, cols, size):
    """``(fig, axes)``: a ``(rows, cols)`` grid of time plots sharing their time axis."""
    fig = style.pyplot().figure(figsize=size, layout="constrained")
    return fig, fig.subplots(rows, cols, sharex=True, squeeze=False)


def label_axes(axes, ylabels=()) -> None:
    """``t (s)`` under the last row of ``axes``, ``ylabels`` on the panels of a 3 x 2
    grid (:func:`six_panels`), a light grid in every one."""
    for ax, text in zip(six_panels(axes), ylabels, strict=False):
        ax.set_ylabel(text)
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    for ax in axes.flat:
        ax.grid(alpha=0.3)


def six_panels(axes):
    """The six panels of a 3 x 2 grid in axis order: ``x, y, z`` left, ``phi, theta,
    psi`` right."""
    return axes.T.flat


def six_bands(axes, results: dict, values) -> None:
    """Per controller of ``results``, in its colour, the band (:func:`fojax.cli.style.band`)
    of ``values(result)`` ``(kept, T, 6)`` over its kept draws that did not diverge, on
    the panels of :func:`six_panels`."""
    for i, (name, result) in enumerate(results.items()):
        data = kept_valid(result, values(result))
        for axis, ax in enumerate(six_panels(axes)):
            style.band(ax, times(result), data[:, :, axis], style.color(name, i))


def tracking_grid(results: dict, reference):
    """``(fig, axes, line)``: a 3 x 2 :func:`time_grid` of the states ``x, y, z, phi,
    theta, psi`` (:func:`six_bands`) and ``reference`` ``(T, 4)`` (``x, y, z, psi``)
    dashed over them; ``line``: the reference's."""
    fig, axes = time_grid(3, 2, (11, 8))
    six_bands(axes, results, lambda result: result.trajectories.state)
    t = times(next(iter(results.values())))
    for k, ax in enumerate([*axes[:, 0], axes[2, 1]]):
        line = style.reference(ax, t, reference[:, k])
    return fig, axes, line


def finish(fig, path, title, caption, handles=(), axes=None, ylabels=(), quantize=False):
    """:func:`label_axes` of ``axes`` (a grid of time plots, when given), the title and
    ``caption``, the legend of ``handles`` below (when any) and the files
    (:func:`fojax.cli.style.save`); returns ``path``."""
    if axes is not None:
        label_axes(axes, ylabels)
    style.suptitle(fig, title, caption)
    if handles:
        style.legend_below(fig, handles)
    return style.save(fig, path, quantize=quantize)


def controller_handles(results: dict):
    """Legend handles: one line per controller of ``results``, in its colour and label."""
    from matplotlib.lines import Line2D

    return [
        Line2D([], [], color=style.color(name, i), lw=2, label=style.label(name, result))
        for i, (name, result) in enumerate(results.items())
    ]


def estimate_handles(labels) -> list:
    """Legend handles of the adaptive estimates: a grey line in each style of
    :data:`fojax.cli.style.ESTIMATE_STYLES`, labelled ``labels`` in turn."""
    from matplotlib.lines import Line2D

    return [
        Line2D([], [], color="0.3", ls=ls, lw=1.1, label=text)
        for ls, text in zip(style.ESTIMATE_STYLES, labels, strict=False)
    ]


def plot_tracking(results: dict, path: Path, title: str = "Tracking") -> Path:
    """Position ``x, y, z`` and attitude ``phi, theta, psi`` against their references."""
    ref = np.asarray(next(iter(results.values())).trajectories.reference)
    fig, axes, line = tracking_grid(results, np.median(ref[:, :, :4], 0))
    labels = ["x (m)", "y (m)", "z (m)", "phi (rad)", "theta (rad)", "psi (rad)"]
    axes[0, 1].set_title(
        "phi, theta: no reference drawn (each controller commands its own)", fontsize=8
    )
    caption = style.draws_caption(results)
    handles = controller_handles(results) + [line]
    return finish(fig, path, title, caption, handles, axes, labels)


def plot_errors(results: dict, path: Path, title: str = "Tracking errors") -> Path:
    """Position errors ``e = X - X_r`` and attitude errors against the commanded attitude."""
    fig, axes = time_grid(3, 2, (11, 8))
    labels = ["e_x (m)", "e_y (m)", "e_z (m)", "e_phi (rad)", "e_theta (rad)", "e_psi (rad)"]
    for ax in axes.flat:
        ax.axhline(0.0, color="0.4", lw=0.6, zorder=1)

    def errors(result):
        tr = result.trajectories
        position_error = np.asarray(tr.state)[:, :, :3] - np.asarray(tr.reference)[:, :, :3]
        attitude_error = np.asarray(tr.state)[:, :, 3:6] - np.asarray(tr.info.attitude_reference)
        return np.concatenate([position_error, attitude_error], axis=-1)

    six_bands(axes, results, errors)
    caption = style.draws_caption(results)
    return finish(fig, path, title, caption, controller_handles(results), axes, labels)


def inputs_envelope(result):
    """``(low, high)`` ``(draws, blocks, 4)`` of the kept draws that did not diverge;
    the samples themselves where a store predates the envelope."""
    tr = result.trajectories
    low, high = getattr(tr, "inputs_low", None), getattr(tr, "inputs_high", None)
    if low is None or high is None:
        low = high = tr.inputs
    return kept_valid(result, low), kept_valid(result, high)


def plot_inputs(results: dict, path: Path, title: str = "Control inputs") -> Path:
    """Thrust ``u_F`` and torques ``tau_x, tau_y, tau_z``, one column per controller:
    the range each command covers at full rate within every saved block (median over
    draws of its low and high edges). A command that switches at every step fills its
    band; one that does not is a line."""
    plt = style.pyplot()
    n = len(results)
    fig = plt.figure(figsize=(max(10.0, 2.6 * n + 1.5), 8), layout="constrained")
    axes = fig.subplots(4, n, sharex=True, sharey="row", squeeze=False)
    for i, (name, result) in enumerate(results.items()):
        low, high = inputs_envelope(result)
        color = style.color(name, i)
        axes[0, i].set_title(style.label(name, result), color=color, fontsize=10)
        if low.shape[0] == 0:
            continue
        for channel in range(4):
            style.envelope(
                axes[channel, i], times(result), low[:, :, channel], high[:, :, channel], color
            )
    for channel in range(4):
        axes[channel, 0].set_ylabel(INPUTS[channel])
    block = block_length(times(next(iter(results.values()))))
    curves = f"band: each command's range (min to max over every step) within each {block:g} s"
    caption = style.draws_caption(results, curves + " block, median")
    return finish(fig, path, title, caption, axes=axes)


def block_length(t) -> float:
    """The snapshot interval of the times ``t``, s (NaN for a single snapshot)."""
    return float(t[1] - t[0]) if t.size > 1 else float("nan")


def path_figure(height: float):
    """``(fig, ax3, ax2)``: a 3-D path's axes (left) and its top view's (right), labelled."""
    fig = style.pyplot().figure(figsize=(12, height), layout="constrained")
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    ax3.set(xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    ax2.set(xlabel="x (m)", ylabel="y (m)")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.grid(alpha=0.3)
    return fig, ax3, ax2


def plot_path(results: dict, path: Path, title: str = "Path", draws: int = 8) -> Path:
    """3-D path (left) and its top view (right): the reference and a few draws."""
    fig, ax3, ax2 = path_figure(5.8)
    first = next(iter(results.values()))
    ref = np.asarray(first.trajectories.reference[0])
    shown = 0
    for i, (name, result) in enumerate(results.items()):
        state = kept_valid(result, result.trajectories.state)
        color = style.color(name, i)
        shown = max(shown, min(draws, state.shape[0]))
        for d in range(min(draws, state.shape[0])):
            ax3.plot(state[d, :, 0], state[d, :, 1], state[d, :, 2], color=color, lw=0.7, alpha=0.7)
            ax2.plot(state[d, :, 0], state[d, :, 1], color=color, lw=0.7, alpha=0.7, zorder=3)
    line = style.reference(ax2, ref[:, 0], ref[:, 1])
    ax3.plot(
        ref[:, 0], ref[:, 1], ref[:, 2], color=style.REFERENCE_COLOR, ls="--", lw=1.3, zorder=10
    )
    caption = (
        f"one line per draw: the first {shown} of {first.draws} draws per controller "
        "(diverged draws left out)"
    )
    return finish(fig, path, title, caption, controller_handles(results) + [line])


def plot_adaptive(results: dict, path: Path, title: str = "Adaptive estimates") -> Path:
    """Adaptive bound estimates ``b0, b1, b2`` per axis, for controllers that adapt:
    the controller's colour, one line style per estimate (solid b0, dashed b1, dotted
    b2), median over draws."""
    from matplotlib.lines import Line2D

    fig, axes = time_grid(3, 2, (11, 8))
    handles = []
    for i, (name, result) in enumerate(results.items()):
        adaptive = kept_valid(result, result.trajectories.info.adaptive)  # (draws, time, 6, 3)
        if adaptive.shape[0] == 0 or not np.any(adaptive):
            continue
        color, t = style.color(name, i), times(result)
        handles.append(Line2D([], [], color=color, lw=2, label=style.label(name, result)))
        for axis, ax in enumerate(six_panels(axes)):
            for j, ls in enumerate(style.ESTIMATE_STYLES):
                ax.plot(t, np.median(adaptive[:, :, axis, j], 0), ls=ls, color=color, lw=1.1)
    handles += estimate_handles(f"b{j}" for j in range(3))
    labels = [f"{text}: b0, b1, b2" for text in ("x", "y", "z", "phi", "theta", "psi")]
    caption = style.draws_caption(results, "median")
    return finish(fig, path, title, caption, handles, axes, labels)


FIGURES = (
    ("tracking", plot_tracking, "Tracking"),
    ("errors", plot_errors, "Tracking errors"),
    ("inputs", plot_inputs, "Control inputs"),
    ("path3d", plot_path, "Path"),
    ("adaptive", plot_adaptive, "Adaptive estimates"),
)


def plot_all(results: dict, directory: Path, prefix: str = "", context: str = "") -> list[Path]:
    """All figures above into ``directory``; returns the paths of the PNGs drawn.

    ``context``: appended to each title (e.g. the scenario and switching). A figure
    that fails is reported as a warning naming it (:func:`style.attempt`); the others
    are still drawn.
    """
    directory = Path(directory)
    results = {k: r for k, r in results.items() if r.trajectories is not None}
    if not results:
        return []
    adapts = any(np.any(np.asarray(r.trajectories.info.adaptive)) for r in results.values())
    paths = []
    for stem, maker, title in FIGURES:
        if stem == "adaptive" and not adapts:
            continue  # no controller here adapts: nothing to draw
        path = directory / f"{prefix}{stem}.png"
        title = f"{title}: {context}" if context else title
        if style.attempt(path.name, maker, results, path, title) is not None:
            paths.append(path)
    return paths


def _read_history(path: Path) -> dict[str, list[float]]:
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    columns = {key: [] for key in (rows[0] if rows else {})}
    for row in rows:
        for key, value in row.items():
            try:
                columns[key].append(float(value))
            except (TypeError, ValueError):
                columns[key].append(math.nan)
    return columns


class _Progress(NamedTuple):
    """What a tuning run's ``history.csv`` shows, read for :func:`plot_convergence`."""

    history: dict[str, list[float]]
    step: np.ndarray
    wall: np.ndarray
    validation: np.ndarray  # NaN where a step has none
    start: float | None  # the validation score at the start (step 0)
    yields: bool  # the validation score is a yield (a right axis from 0 to 1)
    lower: list[str]  # the columns of the lower panels: grad_norm and/or sigma
    show_mean: bool  # the sample's mean target differs from the loss
    diverged: np.ndarray  # steps with diverged draws
    switch: int | None  # the index of the first step of a strategy's second phase


def _read_progress(history_csv: Path, evaluation: dict | None, start: float | None,
                   yields: bool) -> _Progress:  # fmt: skip
    h = _read_history(history_csv)
    if not h.get("step"):
        raise ValueError(f"{history_csv} holds no step")
    step, wall = np.asarray(h["step"]), np.asarray(h["wall_time_s"])
    validation = np.asarray(h.get("validation", [math.nan] * len(step)))
    if evaluation is not None and "initial" in evaluation:
        yields = evaluation["initial"]["kind"] == "yield"
    lower = [k for k in ("grad_norm", "sigma") if np.isfinite(h.get(k, [math.nan])).any()]
    show_mean = not np.allclose(h["loss"], h["mean_target"], rtol=1e-6, equal_nan=True)
    diverged = np.asarray(h.get("diverged", [0] * len(step))) > 0
    with open(history_csv, newline="") as handle:
        phases = [row.get("phase") for row in csv.DictReader(handle)]
    switch = next((i for i, (a, b) in enumerate(itertools.pairwise(phases)) if a != b), None)
    switch = None if switch is None else switch + 1
    return _Progress(h, step, wall, validation, start, yields, lower, show_mean, diverged, switch)


# Colours of plot_convergence (Okabe-Ito).
_DARK, _BLUE, _RED, _ORANGE, _GREEN = "#333333", "#0072B2", "#D55E00", "#E69F00", "#009E73"
_LOOK = {
    "loss": dict(color=_DARK, lw=1.4, marker="o", ms=2.5),
    "mean": dict(color=_BLUE, lw=0.9),
    "worst": dict(color=_BLUE, lw=0.8, ls=":"),
    "validation": dict(color=_ORANGE, lw=1.2, marker="s", ms=4),
    "diverged": dict(ls="none", marker="x", color=_RED),
    "held": dict(ls="none", marker="D", ms=7, mfc="white", mec=_GREEN, mew=2),
    "lower": dict(lw=1.2, marker="o", ms=2.5),  # coloured _DARK, then _GREEN
}
"""The look of each line of :func:`plot_convergence`, in its axes and in its legend."""


def _draw_progress(top, bottom, col: int, x: np.ndarray, p: _Progress, evaluation) -> None:
    """One column of :func:`plot_convergence`: the run against ``x`` (step or wall time)."""
    h = p.history
    top.plot(x, h["loss"], **_LOOK["loss"], zorder=4)
    if p.show_mean:
        top.plot(x, h["mean_target"], **_LOOK["mean"])
    top.plot(x, h["max_target"], **_LOOK["worst"])
    if p.diverged.any():
        top.scatter(x[p.diverged], np.asarray(h["loss"])[p.diverged], **_LOOK["diverged"], zorder=5)
    right = top.twinx() if p.yields else top
    known = np.isfinite(p.validation)
    vx, vy = x[known], p.validation[known]
    if p.start is not None:
        vx, vy = np.concatenate([[0.0], vx]), np.concatenate([[p.start], vy])
    if vy.size:
        # a validation holds until the next one: steps in both panels
        right.plot(vx, vy, **_LOOK["validation"], zorder=5, drawstyle="steps-post")
    if evaluation and "initial" in evaluation:
        held = [_held_number(evaluation[k]) for k in ("initial", "tuned")]
        where = [0, x[-1]] if col == 0 else [x[-1]]
        right.plot(where, held if col == 0 else held[1:], **_LOOK["held"], zorder=6)
    if p.yields:
        right.set_ylim(-0.02, 1.02)
        right.set_ylabel("yield (validation, held-out)" if col else "")
    for key, color in zip(p.lower, (_DARK, _GREEN), strict=False):
        bottom.plot(x, h[key], color=color, **_LOOK["lower"])
    if p.switch is not None:  # a strategy's second phase (e.g. auto's, at the full step)
        for ax in (top, bottom):
            ax.axvline(x[p.switch], color="0.5", lw=0.9, ls="--")


_LOWER_NAMES = {"grad_norm": "gradient norm", "sigma": "CMA-ES step size"}


def _progress_handles(p: _Progress, evaluation) -> list:
    """The legend of :func:`plot_convergence`."""
    from matplotlib.lines import Line2D

    best = p.history.get("returned_step", [math.nan])[-1]
    validation = f"validation {'yield' if p.yields else 'cost'} (returned: step {best:.0f})"
    rows = [("loss", "loss (best point)"), ("mean", "sample mean target")][: 1 + p.show_mean]
    rows += [("worst", "sample worst target"), ("validation", validation)]
    if p.diverged.any():
        rows.append(("diverged", "diverged draws"))
    if evaluation and "initial" in evaluation:
        held = f"held-out, initial and tuned ({evaluation['draws']} draws, "
        rows.append(("held", held + f"{evaluation['switching']}, {evaluation['horizon_s']:g} s)"))
    handles = [Line2D([], [], **_LOOK[key], label=label) for key, label in rows]
    if p.switch is not None:
        handles.append(Line2D([], [], color="0.5", lw=0.9, ls="--", label="second phase begins"))
    return handles + [
        Line2D([], [], color=color, **_LOOK["lower"], label=_LOWER_NAMES[key])
        for key, color in zip(p.lower, (_DARK, _GREEN), strict=False)
    ]


def plot_convergence(
    history_csv: Path,
    path: Path,
    evaluation: dict | None = None,
    title: str = "fojax tune: convergence",
    validation_start: float | None = None,
    yields: bool = False,
) -> Path:
    """A tuning run's progress from ``history.csv`` (:mod:`fojax.optimize.driver`'s
    columns, any method): top, the loss of each step's best point, the sample's mean
    and worst target, and the validation score (cost, or yield on a right axis) with the
    start as step 0; bottom, the gradient norm (gradient steps) or CMA-ES's step size;
    against step (left) and wall time (right). Steps with diverged draws are marked; the
    held-out score of the initial and the tuned gains is drawn where ``evaluation`` has
    it; a dashed line marks where a strategy's second phase begins (``history.csv``'s
    ``phase`` column). ``yields``: the validation score is a yield (without
    ``evaluation``, which says so itself)."""
    p = _read_progress(history_csv, evaluation, validation_start, yields)
    h, lower = p.history, p.lower
    fig = style.pyplot().figure(figsize=(11, 7), layout="constrained")
    axes = fig.subplots(2, 2, sharex="col", sharey="row")
    for col, x in enumerate((p.step, p.wall)):
        _draw_progress(axes[0, col], axes[1, col], col, x, p, evaluation)
    for ax in axes.flat:
        ax.grid(alpha=0.3, which="both")
    loss = np.asarray(h["loss"])
    loss = loss[np.isfinite(loss)]
    scores = np.concatenate([loss, p.validation[np.isfinite(p.validation)],
                             [] if p.start is None else [p.start]])  # fmt: skip
    if not p.yields and scores.size and np.all(scores > 0) and scores.max() > 3 * scores.min():
        axes[0, 0].set_yscale("log")
    axes[0, 0].set_ylabel("loss, cost")
    if lower and max(np.nanmax(h[k]) for k in lower) > 30 * min(np.nanmin(h[k]) for k in lower):
        axes[1, 0].set_yscale("log")
    axes[1, 0].set_ylabel(" and ".join(_LOWER_NAMES[k] for k in lower))
    axes[1, 0].set_xlabel("step")
    axes[1, 1].set_xlabel(f"wall time (s); step 1 ended at {p.wall[0]:.1f} s, compilation included")
    fig.suptitle(title, fontsize=10)
    style.legend_below(fig, _progress_handles(p, evaluation), ncol=3)
    return style.save(fig, path)


def _held_number(summary: dict) -> float:
    return summary["score"]


def _bar_axes(ax, labels, right_end: float, xlabel: str, title: str) -> None:
    """Axes of horizontal bars: one row per label, top down; x from 0 to ``right_end``."""
    ax.set_yticks(np.arange(len(labels)), labels)
    ax.invert_yaxis()
    ax.set_xlim(0, right_end)
    ax.set_xlabel(xlabel)
    ax.set_title(title, fontsize=9)
    ax.grid(axis="x", alpha=0.3)


def plot_yield(results: dict, path: Path, title: str) -> Path:
    """Left: the yield per controller with its 95 % Clopper-Pearson interval. Right: the
    share of draws failing each requirement, per controller."""
    plt = style.pyplot()
    names = list(results)
    requirements = list(results[names[0]].names)
    size = (10.5, 0.5 + 0.45 * max(4, len(requirements) * len(names) ** 0.5))
    fig, (left, right) = plt.subplots(
        1, 2, figsize=size, layout="constrained", gridspec_kw={"width_ratios": [1, 1.6]}
    )
    height = 0.8 / len(names)
    rows = np.arange(len(requirements))
    for i, (name, result) in enumerate(results.items()):
        (low, high), value, color = result.interval, result.yield_, style.color(name, i)
        left.barh(i, 100 * value, color=color, alpha=0.35, height=0.6)
        xerr = [[100 * (value - low)], [100 * (high - value)]]
        left.errorbar(100 * value, i, xerr=xerr, fmt="o", color=color, capsize=4)
        text = f"{value:.0%} ({result.passed}/{result.draws})"
        left.annotate(text, (100 * high, i), xytext=(4, 0), textcoords="offset points",
                      va="center", fontsize=8)  # fmt: skip
        share = 100 * np.asarray(result.failures) / result.draws
        offset = (i - (len(names) - 1) / 2) * height
        right.barh(rows + offset, share, height=height, color=color, label=name)
    _bar_axes(left, names, 125, "yield (%), 95 % Clopper-Pearson interval",
              "draws meeting every requirement")  # fmt: skip
    left.set_xticks([0, 25, 50, 75, 100])
    _bar_axes(right, requirements, 100, "draws failing the requirement (%)",
              "failures per requirement")  # fmt: skip
    if len(names) > 1:
        right.legend(fontsize=8, loc="best")
    style.suptitle(fig, title, "a diverged draw fails every requirement")
    return style.save(fig, path)


def plot_cases(evaluation: dict, path: Path, title: str) -> Path:
    """Held-out gains case by case (:func:`fojax.optimize.cases.evaluate_cases`): per law
    (a column), position RMSE (top) and torque chattering (bottom), both on log scales
    (cases apart by orders of magnitude: millimetres on a steady reference, decimetres
    in a transient), of each case, a bar per set of gains, a diverged case marked; the
    diverged draws written beside a bar."""
    plt = style.pyplot()
    laws = list(evaluation["laws"])
    cases = evaluation["cases"]
    labels = list(next(iter(evaluation["laws"][laws[0]].values())))
    fig, axes = plt.subplots(2, len(laws), figsize=(4.8 * len(laws) + 1.5, 6.5),
                             layout="constrained", squeeze=False)  # fmt: skip
    height = 0.8 / len(labels)
    rows = np.arange(len(cases))
    for col, law in enumerate(laws):
        table = evaluation["laws"][law]
        for row, (key, unit, log) in enumerate((("position_rmse", "m", True),
                                                ("torque_chattering", "N m/s", True))):  # fmt: skip
            ax = axes[row, col]
            for i, label in enumerate(labels):
                values = [table[c][label][key] for c in cases]
                bars = [np.nan if v is None else v for v in values]
                y = rows + (i - (len(labels) - 1) / 2) * height
                ax.barh(y, bars, height=height, color=style.color(label, i), label=label)
                for yy, c in zip(y, cases, strict=True):
                    lost = table[c][label]["diverged"]
                    if lost:
                        ax.annotate(f"{lost} diverged", (0, yy), xytext=(2, 0), va="center",
                                    textcoords="offset points", fontsize=7)  # fmt: skip
            ax.set_yticks(rows, cases)
            ax.invert_yaxis()
            if log:
                ax.set_xscale("log")
                ax.xaxis.set_minor_formatter(plt.NullFormatter())
            ax.set_xlabel(f"{key.replace('_', ' ')} ({unit})")
            ax.set_title(f"{law} switching" if law != "none" else "no switching", fontsize=9)
            ax.grid(axis="x", alpha=0.3, which="both")
    axes[0, 0].legend(fontsize=8, loc="best")
    style.suptitle(fig, title, f"{evaluation['draws']} held-out draws per case, each over its "
                   "own horizon; RMSE mean and chattering median over the draws kept")  # fmt: skip
    return style.save(fig, path)
