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

Lines are medians over the kept draws, bands their 5-95 % range, sampled at the
snapshot interval (0.1 s by default): inputs that switch every 1 ms step appear as a
wide band, not as a line. Input: ``{scenario id: {controller: MonteCarloResult}}``
with kept trajectories.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.figures import _band, _color, _pyplot

__all__ = ["FIGURE_NUMBERS", "plot_all"]

FIGURE_NUMBERS = {1: (5, 6, 7, 8), 2: (9, 10, 11, 12), 3: (13, 14, 15, 16)}
DPI = 80


def _kept(results: dict) -> dict:
    return {name: r for name, r in results.items() if r.trajectories is not None}


def _draw_count(results: dict) -> int:
    return min(r.trajectories.time.shape[0] for r in results.values())


def _reference_velocity(scenario_id: int, times: np.ndarray) -> np.ndarray:
    """``(T, 3)`` exact reference velocity at ``times`` (autodiff of the reference)."""
    import jax
    import jax.numpy as jnp

    from fojax import scenarios

    reference = scenarios.get_scenario(scenario_id).reference

    def velocity(t):
        return scenarios.reference_with_derivatives(reference, t)[1][:3]

    return np.asarray(jax.vmap(velocity)(jnp.asarray(times, jnp.float32)))


def _finish(fig, path: Path, title: str, results: dict, spread: str | None = None) -> Path:
    """Title, layout, and a PNG quantised to 128 colours (about a third of the size)."""
    import io

    from PIL import Image

    plt = _pyplot()
    spread = spread or f"median and 5-95 % band over {_draw_count(results)} Monte Carlo draws"
    fig.suptitle(f"{title}\n({spread})", fontsize=10)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=DPI, format="png")
    plt.close(fig)
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(colors=128).save(path, optimize=True)
    return path


def _legend(ax):
    ax.legend(fontsize=7, loc="best", ncol=2, framealpha=0.7)


def plot_tracking(results: dict, path: Path, number: int, scenario_id: int) -> Path:
    """Fig. 5/9/13: (a) position tracking, (b) attitude tracking."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 2, figsize=(11, 7.5), sharex=True)
    first = next(iter(results.values())).trajectories
    t = np.asarray(first.time[0])
    for i, (name, result) in enumerate(results.items()):
        tr = result.trajectories
        for axis in range(6):
            _band(axes[axis % 3, axis // 3], t, tr.state[:, :, axis], _color(name, i), name)
    for axis in range(3):
        axes[axis, 0].plot(t, first.reference[0, :, axis], "k--", lw=1, label="reference")
    axes[2, 1].plot(t, first.reference[0, :, 3], "k--", lw=1, label="reference")
    labels = ["x (m)", "y (m)", "z (m)", "phi (rad)", "theta (rad)", "psi (rad)"]
    for axis, label in enumerate(labels):
        ax = axes[axis % 3, axis // 3]
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0, 0].set_title("(a) Position tracking", fontsize=9)
    axes[0, 1].set_title("(b) Attitude tracking", fontsize=9)
    _legend(axes[0, 0])
    for ax in axes[2]:
        ax.set_xlabel("t (s)")
    title = f"Fig. {number}: Path following performance in Scenario {scenario_id}"
    return _finish(fig, path, title, results)


def plot_inputs_errors(results: dict, path: Path, number: int, scenario_id: int) -> Path:
    """Fig. 6/10/14: (a) control inputs, (b) position and velocity tracking errors."""
    plt = _pyplot()
    fig, axes = plt.subplots(4, 2, figsize=(11, 8.5), sharex=True)
    first = next(iter(results.values())).trajectories
    t = np.asarray(first.time[0])
    reference_velocity = _reference_velocity(scenario_id, t)
    for i, (name, result) in enumerate(results.items()):
        tr = result.trajectories
        color = _color(name, i)
        for channel in range(4):
            _band(axes[channel, 0], t, tr.inputs[:, :, channel], color, name)
        position_error = tr.state[:, :, :3] - tr.reference[:, :, :3]
        for axis in range(3):
            _band(axes[axis, 1], t, position_error[:, :, axis], color, name)
        velocity_error = np.linalg.norm(tr.state[:, :, 6:9] - reference_velocity[None], axis=-1)
        _band(axes[3, 1], t, velocity_error, color, name)
    inputs = ["u_F (N)", "tau_x (N m)", "tau_y (N m)", "tau_z (N m)"]
    errors = ["e_x (m)", "e_y (m)", "e_z (m)", "|e_v| (m/s)"]
    for row in range(4):
        axes[row, 0].set_ylabel(inputs[row])
        axes[row, 1].set_ylabel(errors[row])
        for ax in axes[row]:
            ax.grid(alpha=0.3)
        axes[row, 1].axhline(0.0, color="k", lw=0.5)
    axes[0, 0].set_title("(a) Control inputs", fontsize=9)
    axes[0, 1].set_title("(b) Tracking errors (position; velocity error norm)", fontsize=9)
    _legend(axes[0, 0])
    for ax in axes[3]:
        ax.set_xlabel("t (s)")
    title = f"Fig. {number}: Control inputs & tracking errors in Scenario {scenario_id}"
    return _finish(fig, path, title, results)


def plot_paths(results: dict, path: Path, number: int, scenario_id: int, faint: int = 3) -> Path:
    """Fig. 7/11/15: (a) 3-D path, (b) 2-D path; median path bold, a few draws faint."""
    plt = _pyplot()
    fig = plt.figure(figsize=(12, 5.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    first = next(iter(results.values())).trajectories
    ref = first.reference[0]
    ax3.plot(ref[:, 0], ref[:, 1], ref[:, 2], "k--", lw=1.2, label="reference")
    ax2.plot(ref[:, 0], ref[:, 1], "k--", lw=1.2, label="reference")
    for i, (name, result) in enumerate(results.items()):
        state = np.asarray(result.trajectories.state)
        color = _color(name, i)
        median = np.median(state[:, :, :3], axis=0)
        ax3.plot(median[:, 0], median[:, 1], median[:, 2], color=color, lw=1.1, label=name)
        ax2.plot(median[:, 0], median[:, 1], color=color, lw=1.1, label=name)
        for d in range(min(faint, state.shape[0])):
            ax2.plot(state[d, :, 0], state[d, :, 1], color=color, lw=0.5, alpha=0.3)
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax3.set_title("(a) 3-D trajectory tracking", fontsize=9)
    ax2.set_xlabel("x (m)")
    ax2.set_ylabel("y (m)")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.grid(alpha=0.3)
    ax2.set_title(f"(b) 2-D trajectory tracking (faint: {faint} single draws)", fontsize=9)
    _legend(ax2)
    title = f"Fig. {number}: Path following performance in Scenario {scenario_id}"
    spread = f"median path over {_draw_count(results)} Monte Carlo draws"
    return _finish(fig, path, title, results, spread)


ADAPTIVE = {"afonftsmc": ("b0", "b1", "b2"), "anftsmc": ("a0", "a1", "a2")}


def plot_parameters(results: dict, path: Path, number: int, scenario_id: int) -> Path:
    """Fig. 8/12/16: adaptive estimates, (a) position axes, (b) attitude axes."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 2, figsize=(11, 7.5), sharex=True)
    first = next(iter(results.values())).trajectories
    t = np.asarray(first.time[0])
    shades = ("tab:red", "tab:blue", "tab:green")
    for name, symbols in ADAPTIVE.items():
        if name not in results:
            continue
        adaptive = np.asarray(results[name].trajectories.info.adaptive)  # (draws, T, 6, 3)
        style = "-" if name == "afonftsmc" else "--"
        for axis in range(6):
            ax = axes[axis % 3, axis // 3]
            for j, symbol in enumerate(symbols):
                values = adaptive[:, :, axis, j]
                low, mid, high = np.percentile(values, [5, 50, 95], axis=0)
                ax.plot(t, mid, style, color=shades[j], lw=1.1, label=f"{name} {symbol}")
                if values.shape[0] > 1 and name == "afonftsmc":
                    ax.fill_between(t, low, high, color=shades[j], alpha=0.2, lw=0)
    labels = ["x", "y", "z", "phi", "theta", "psi"]
    for axis, label in enumerate(labels):
        ax = axes[axis % 3, axis // 3]
        ax.set_ylabel(f"{label} estimates")
        ax.grid(alpha=0.3)
    axes[0, 0].set_title("(a) Parameters position", fontsize=9)
    axes[0, 1].set_title("(b) Parameters attitude", fontsize=9)
    _legend(axes[0, 0])
    for ax in axes[2]:
        ax.set_xlabel("t (s)")
    title = (
        f"Fig. {number}: Parameters estimation in Scenario {scenario_id} "
        "(AFONFTSMC b-hat solid, ANFTSMC a-hat dashed)"
    )
    return _finish(fig, path, title, results)


def plot_all(results_by_scenario: dict, directory: Path) -> list[Path]:
    """Figs. 5-16 (those of the scenarios present) into ``directory``; their paths."""
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
        results = _kept(results_by_scenario[scenario_id])
        if not results:
            continue
        for (maker, stem), number in zip(makers, FIGURE_NUMBERS[scenario_id], strict=True):
            path = directory / f"fig{number:02d}_s{scenario_id}_{stem}.png"
            paths.append(maker(results, path, number, scenario_id))
    return paths
