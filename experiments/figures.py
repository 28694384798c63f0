"""Figures of Monte Carlo runs: tracking, errors, inputs and paths, spread shaded.

Each function takes ``{controller name: MonteCarloResult}`` (results with kept
trajectories) and writes one PNG. Lines are the median over the kept draws, the shaded
band their 5-95 % range; the reference is drawn in black.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_all", "plot_errors", "plot_inputs", "plot_path", "plot_tracking"]

COLORS = {
    "afonftsmc": "tab:red",
    "anftsmc": "tab:blue",
    "fobsmc": "tab:green",
    "bsmc": "tab:purple",
    "fl": "tab:orange",
}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _color(name: str, index: int) -> str:
    return COLORS.get(name, f"C{index % 10}")


def _band(ax, t, values, color, label):
    """Median line and 5-95 % band of ``values`` ``(draws, time)``."""
    values = np.asarray(values, dtype=float)
    low, mid, high = np.nanpercentile(values, [5, 50, 95], axis=0)
    ax.plot(t, mid, color=color, lw=1.2, label=label)
    if values.shape[0] > 1:
        ax.fill_between(t, low, high, color=color, alpha=0.25, lw=0)


def _series(result):
    tr = result.trajectories
    t = np.asarray(tr.time[0])
    return tr, t


def _title(fig, title, results):
    kept = min(r.trajectories.time.shape[0] for r in results.values())
    fig.suptitle(f"{title} (median, 5-95 % band over {kept} draws)", fontsize=10)


def plot_tracking(results: dict, path: Path, title: str = "Tracking") -> Path:
    """Position ``x, y, z`` and attitude ``phi, theta, psi`` against their references."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex=True)
    labels = ["x (m)", "y (m)", "z (m)", "phi (rad)", "theta (rad)", "psi (rad)"]
    first = next(iter(results.values()))
    tr0, t0 = _series(first)
    for i, (name, result) in enumerate(results.items()):
        tr, t = _series(result)
        for axis in range(6):
            ax = axes[axis % 3, axis // 3]
            _band(ax, t, tr.state[:, :, axis], _color(name, i), name)
    for axis in range(3):
        axes[axis, 0].plot(t0, np.median(tr0.reference[:, :, axis], 0), "k--", lw=1, label="ref")
    axes[2, 1].plot(t0, np.median(tr0.reference[:, :, 3], 0), "k--", lw=1, label="ref")
    for axis, label in enumerate(labels):
        ax = axes[axis % 3, axis // 3]
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    axes[2, 0].set_xlabel("t (s)")
    axes[2, 1].set_xlabel("t (s)")
    _title(fig, title, results)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_errors(results: dict, path: Path, title: str = "Tracking errors") -> Path:
    """Position errors ``e = X - X_r`` and attitude errors against the commanded attitude."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex=True)
    labels = ["e_x (m)", "e_y (m)", "e_z (m)", "e_phi (rad)", "e_theta (rad)", "e_psi (rad)"]
    for i, (name, result) in enumerate(results.items()):
        tr, t = _series(result)
        position_error = tr.state[:, :, :3] - tr.reference[:, :, :3]
        attitude_error = tr.state[:, :, 3:6] - tr.info.attitude_reference
        errors = np.concatenate([position_error, attitude_error], axis=-1)
        for axis in range(6):
            _band(axes[axis % 3, axis // 3], t, errors[:, :, axis], _color(name, i), name)
    for axis, label in enumerate(labels):
        ax = axes[axis % 3, axis // 3]
        ax.set_ylabel(label)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    axes[2, 0].set_xlabel("t (s)")
    axes[2, 1].set_xlabel("t (s)")
    _title(fig, title, results)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_inputs(results: dict, path: Path, title: str = "Control inputs") -> Path:
    """Thrust ``u_F`` and torques ``tau_x, tau_y, tau_z`` (sampled at the snapshots)."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
    labels = ["u_F (N)", "tau_x (N m)", "tau_y (N m)", "tau_z (N m)"]
    for i, (name, result) in enumerate(results.items()):
        tr, t = _series(result)
        for channel in range(4):
            _band(axes.flat[channel], t, tr.inputs[:, :, channel], _color(name, i), name)
    for channel, label in enumerate(labels):
        axes.flat[channel].set_ylabel(label)
        axes.flat[channel].grid(alpha=0.3)
    axes.flat[0].legend(fontsize=8, loc="best")
    axes[1, 0].set_xlabel("t (s)")
    axes[1, 1].set_xlabel("t (s)")
    _title(fig, title, results)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_path(results: dict, path: Path, title: str = "Path", draws: int = 8) -> Path:
    """3-D path (left) and its top view (right): the reference and a few draws."""
    plt = _pyplot()
    fig = plt.figure(figsize=(12, 5.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    first = next(iter(results.values()))
    ref = first.trajectories.reference[0]
    ax3.plot(ref[:, 0], ref[:, 1], ref[:, 2], "k--", lw=1.2, label="ref")
    ax2.plot(ref[:, 0], ref[:, 1], "k--", lw=1.2, label="ref")
    for i, (name, result) in enumerate(results.items()):
        state = result.trajectories.state
        color = _color(name, i)
        for d in range(min(draws, state.shape[0])):
            label = name if d == 0 else None
            ax3.plot(
                state[d, :, 0],
                state[d, :, 1],
                state[d, :, 2],
                color=color,
                lw=0.7,
                alpha=0.7,
                label=label,
            )
            ax2.plot(state[d, :, 0], state[d, :, 1], color=color, lw=0.7, alpha=0.7, label=label)
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax2.set_xlabel("x (m)")
    ax2.set_ylabel("y (m)")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8, loc="best")
    fig.suptitle(f"{title} (first {draws} draws per controller)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_adaptive(results: dict, path: Path, title: str = "Adaptive estimates") -> Path:
    """Adaptive bound estimates ``b0, b1, b2`` per axis, for controllers that adapt."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex=True)
    labels = ["x", "y", "z", "phi", "theta", "psi"]
    for i, (name, result) in enumerate(results.items()):
        tr, t = _series(result)
        adaptive = np.asarray(tr.info.adaptive)  # (draws, time, 6, 3)
        if not np.any(adaptive):
            continue
        for axis in range(6):
            ax = axes[axis % 3, axis // 3]
            for j, style in enumerate(("-", "--", ":")):
                values = adaptive[:, :, axis, j]
                ax.plot(
                    t,
                    np.median(values, 0),
                    style,
                    color=_color(name, i),
                    lw=1,
                    label=f"{name} b{j}" if axis == 0 else None,
                )
    for axis, label in enumerate(labels):
        ax = axes[axis % 3, axis // 3]
        ax.set_ylabel(f"{label}: b0, b1, b2")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    axes[2, 0].set_xlabel("t (s)")
    axes[2, 1].set_xlabel("t (s)")
    fig.suptitle(f"{title} (median over draws; solid b0, dashed b1, dotted b2)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_all(results: dict, directory: Path, prefix: str = "") -> list[Path]:
    """All figures above into ``directory``; returns their paths."""
    directory = Path(directory)
    results = {k: r for k, r in results.items() if r.trajectories is not None}
    if not results:
        return []
    return [
        plot_tracking(results, directory / f"{prefix}tracking.png"),
        plot_errors(results, directory / f"{prefix}errors.png"),
        plot_inputs(results, directory / f"{prefix}inputs.png"),
        plot_path(results, directory / f"{prefix}path3d.png"),
        plot_adaptive(results, directory / f"{prefix}adaptive.png"),
    ]
