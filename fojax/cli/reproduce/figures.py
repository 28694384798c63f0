"""The paper's Figs. 5-16 redrawn from Monte Carlo data, the spread shaded.

Per scenario ``k`` (1, 2, 3) four figures, numbered as in the paper
(``4 k + 1 ... 4 k + 4``):

* Fig. 5 / 9 / 13, "Path following performance": (a) position ``x, y, z`` against the
  reference, (b) attitude ``phi, theta, psi`` (``psi`` against ``psi_r``);
* Fig. 6 / 10 / 14, "Control inputs & tracking errors": (a) ``u_F, tau_x, tau_y,
  tau_z``, (b) position errors ``e = X - X_r`` and the velocity error ``|X' - X_r'|``;
* Fig. 7 / 11 / 15, "Path following performance": (a) 3-D path, (b) 2-D path (top
  view), the reference dashed;
* Fig. 8 / 12 / 16, "Parameters estimation": the adaptive estimates ``b0, b1, b2`` of
  the AFONFTSMC (solid) and ``a0, a1, a2`` of the ANFTSMC (dashed), (a) position axes,
  (b) attitude axes.

Lines are medians over the kept draws that did not diverge, bands their 5-95 % range;
each title says how many draws that is and how many the tables use. States are
sampled at the snapshot interval (0.1 s by default); the control inputs are drawn as
the range each command covers at full rate within every snapshot block
(``inputs_low``/``inputs_high``), so a command switching at every 1 ms step fills a
band instead of aliasing into spikes. Each controller has one colour in every figure
(:data:`fojax.cli.style.CONTROLLER_COLORS`); the reference is dashed black, on top.
Each figure is a PNG (:data:`fojax.cli.style.DPI`) with a PDF beside it. Input:
``{scenario id: {controller: MonteCarloResult}}`` with kept trajectories.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fojax.cli import style
from fojax.cli.figures import (
    INPUTS,
    block_length,
    controller_handles,
    estimate_handles,
    finish,
    inputs_envelope,
    kept_valid,
    path_figure,
    six_panels,
    time_grid,
    times,
    tracking_grid,
)

__all__ = ["FIGURE_NUMBERS", "plot_all"]

FIGURE_NUMBERS = {1: (5, 6, 7, 8), 2: (9, 10, 11, 12), 3: (13, 14, 15, 16)}


def _reference_velocity(scenario_id: int, times: np.ndarray) -> np.ndarray:
    """``(T, 3)`` exact reference velocity at ``times`` (autodiff of the reference)."""
    import jax
    import jax.numpy as jnp

    from fojax import scenarios

    reference = scenarios.get_scenario(scenario_id).reference

    def velocity(t):
        return scenarios.reference_with_derivatives(reference, t)[1][:3]

    return np.asarray(jax.vmap(velocity)(jnp.asarray(times, jnp.float32)))


def _handles(results: dict) -> list:
    """The legend: the controllers of ``results`` and the reference."""
    from matplotlib.lines import Line2D

    reference = Line2D([], [], color=style.REFERENCE_COLOR, ls="--", lw=1.2, label="reference")
    return controller_handles(results) + [reference]


def _finish(fig, path: Path, title: str, results: dict, handles, *curves, **grid):
    """:func:`fojax.cli.figures.finish` (``grid``: its ``axes`` and ``ylabels``) with the
    true draw counts in the caption (:func:`fojax.cli.style.draws_caption`, of ``curves``
    when given), the PNG quantized."""
    caption = style.draws_caption(results, *curves, statistics="the tables")
    return finish(fig, path, title, caption, handles, quantize=True, **grid)


def plot_tracking(results: dict, path: Path, number: int, scenario_id: int) -> Path:
    """Fig. 5/9/13: (a) position tracking, (b) attitude tracking."""
    reference = np.asarray(next(iter(results.values())).trajectories.reference[0])
    fig, axes, _ = tracking_grid(results, reference)
    labels = ["x (m)", "y (m)", "z (m)", "phi (rad)", "theta (rad)", "psi (rad)"]
    axes[0, 0].set_title("(a) Position tracking", fontsize=9)
    axes[0, 1].set_title("(b) Attitude tracking (phi, theta sampled every snapshot)", fontsize=9)
    title = f"Fig. {number}: Path following performance in Scenario {scenario_id}"
    return _finish(fig, path, title, results, _handles(results), axes=axes, ylabels=labels)


def plot_inputs_errors(results: dict, path: Path, number: int, scenario_id: int) -> Path:
    """Fig. 6/10/14: (a) control inputs, (b) position and velocity tracking errors."""
    fig, axes = time_grid(4, 2, (11, 9))
    t = times(next(iter(results.values())))
    reference_velocity = _reference_velocity(scenario_id, t)
    colors = {name: style.color(name, i) for i, name in enumerate(results)}
    envelopes = {name: inputs_envelope(result) for name, result in results.items()}
    for channel in range(4):

        def width(name, channel=channel):
            low, high = envelopes[name]
            return float(np.nanmean(high[..., channel] - low[..., channel])) if low.size else 0.0

        # The widest bands first: narrower ones stay visible over them.
        for name in sorted(results, key=width, reverse=True):
            low, high = envelopes[name]
            if low.shape[0]:
                style.envelope(
                    axes[channel, 0], t, low[:, :, channel], high[:, :, channel],
                    colors[name], alpha=0.12,
                )  # fmt: skip
    for name, result in results.items():
        tr = result.trajectories
        position_error = kept_valid(result, np.asarray(tr.state)[:, :, :3] - tr.reference[:, :, :3])
        for axis in range(3):
            style.band(axes[axis, 1], t, position_error[:, :, axis], colors[name])
        velocity = kept_valid(result, tr.state)[:, :, 6:9]
        velocity_error = np.linalg.norm(velocity - reference_velocity[None], axis=-1)
        style.band(axes[3, 1], t, velocity_error, colors[name])
    errors = ["e_x (m)", "e_y (m)", "e_z (m)", "|e_v| (m/s)"]
    for row in range(4):
        axes[row, 0].set_ylabel(INPUTS[row])
        axes[row, 1].set_ylabel(errors[row])
        axes[row, 1].axhline(0.0, color="0.4", lw=0.6, zorder=1)
    axes[0, 0].set_title(
        f"(a) Control inputs: each command's range within every {block_length(t):g} s block "
        "(median over draws)",
        fontsize=9,
    )
    axes[0, 1].set_title("(b) Tracking errors (position; velocity error norm)", fontsize=9)
    title = f"Fig. {number}: Control inputs & tracking errors in Scenario {scenario_id}"
    return _finish(fig, path, title, results, controller_handles(results), axes=axes)


def plot_paths(results: dict, path: Path, number: int, scenario_id: int, faint: int = 3) -> Path:
    """Fig. 7/11/15: (a) 3-D path, (b) 2-D path; median path bold, a few draws faint."""
    fig, ax3, ax2 = path_figure(6)
    ref = np.asarray(next(iter(results.values())).trajectories.reference[0])
    for i, (name, result) in enumerate(results.items()):
        state = kept_valid(result, result.trajectories.state)
        if state.shape[0] == 0:
            continue
        color = style.color(name, i)
        median = np.median(state[:, :, :3], axis=0)
        ax3.plot(median[:, 0], median[:, 1], median[:, 2], color=color, lw=1.1)
        ax2.plot(median[:, 0], median[:, 1], color=color, lw=1.1, zorder=3)
        for d in range(min(faint, state.shape[0])):
            ax2.plot(state[d, :, 0], state[d, :, 1], color=color, lw=0.5, alpha=0.3, zorder=2)
    ax3.plot(ref[:, 0], ref[:, 1], ref[:, 2], color=style.REFERENCE_COLOR, ls="--", lw=1.2)
    style.reference(ax2, ref[:, 0], ref[:, 1])
    ax3.set_title("(a) 3-D trajectory tracking", fontsize=9)
    ax2.set_title(f"(b) 2-D trajectory tracking (faint: {faint} single draws)", fontsize=9)
    title = f"Fig. {number}: Path following performance in Scenario {scenario_id}"
    return _finish(fig, path, title, results, _handles(results), "median path")


ADAPTIVE = {"afonftsmc": ("b0", "b1", "b2"), "anftsmc": ("a0", "a1", "a2")}


def plot_parameters(results: dict, path: Path, number: int, scenario_id: int) -> Path:
    """Fig. 8/12/16: adaptive estimates, (a) position axes, (b) attitude axes: each
    controller in its colour, one line style per estimate (solid b0/a0, dashed b1/a1,
    dotted b2/a2)."""
    fig, axes = time_grid(3, 2, (11, 8))
    t = times(next(iter(results.values())))
    shown = {}
    for index, (name, result) in enumerate(results.items()):
        if name not in ADAPTIVE:
            continue
        symbols = ADAPTIVE[name]
        adaptive = kept_valid(result, result.trajectories.info.adaptive)  # (draws, T, 6, 3)
        if adaptive.shape[0] == 0:
            continue
        color = style.color(name, index)
        shown[name] = result
        for axis, ax in enumerate(six_panels(axes)):
            for j, ls in enumerate(style.ESTIMATE_STYLES[: len(symbols)]):
                values = adaptive[:, :, axis, j]
                low, mid, high = np.percentile(values, style.BAND_PERCENTILES, axis=0)
                ax.plot(t, mid, ls=ls, color=color, lw=1.1, zorder=3)
                if values.shape[0] > 1 and name == "afonftsmc":
                    ax.fill_between(t, low, high, color=color, alpha=0.12, lw=0, zorder=2)
    axes[0, 0].set_title("(a) Parameters position", fontsize=9)
    axes[0, 1].set_title("(b) Parameters attitude", fontsize=9)
    styles = estimate_handles(" / ".join(s[j] for s in ADAPTIVE.values()) for j in range(3))
    title = (
        f"Fig. {number}: Parameters estimation in Scenario {scenario_id} "
        "(AFONFTSMC b-hat, ANFTSMC a-hat; band: AFONFTSMC 5-95 %)"
    )
    handles = controller_handles(shown or results) + styles
    labels = [f"{axis} estimates" for axis in ("x", "y", "z", "phi", "theta", "psi")]
    return _finish(fig, path, title, shown or results, handles, axes=axes, ylabels=labels)


def plot_all(results_by_scenario: dict, directory: Path) -> list[Path]:
    """Figs. 5-16 (those of the scenarios present) into ``directory``; the PNGs' paths
    (a PDF beside each). A figure that fails is a warning naming it; the others are
    still drawn."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    makers = (
        (plot_tracking, "path_following"),
        (plot_inputs_errors, "inputs_errors"),
        (plot_paths, "paths"),
        (plot_parameters, "parameters"),
    )
    for scenario_id in sorted(results_by_scenario):
        results = results_by_scenario[scenario_id]
        results = {name: r for name, r in results.items() if r.trajectories is not None}
        if not results:
            continue
        for (maker, stem), number in zip(makers, FIGURE_NUMBERS[scenario_id], strict=True):
            path = directory / f"fig{number:02d}_s{scenario_id}_{stem}.png"
            if style.attempt(path.name, maker, results, path, number, scenario_id) is not None:
                paths.append(path)
    return paths
