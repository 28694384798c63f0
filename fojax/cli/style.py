"""One look for every figure: controller colours, the reference, bands, legends, files.

* :data:`CONTROLLER_COLORS`: one colour per controller, the same in every figure
  (Okabe-Ito, readable with the common colour-vision deficiencies). Nothing else uses
  these colours: the reference is black, the adaptive estimates ``b0, b1, b2`` (or
  ``a0, a1, a2``) are told apart by :data:`ESTIMATE_STYLES` (line styles) in their
  controller's colour.
* The reference is drawn last, on top of the curves (``zorder``), dashed black with a
  white edge so that it stays visible over a band of the same height.
* Legends sit outside the axes (:func:`legend_below`), never over the data.
* :func:`save` writes a PNG at :data:`DPI` and a vector copy (PDF) beside it.
* :func:`attempt` draws one figure and turns a failure into a warning naming it, so a
  failing figure never loses the results written before it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

__all__ = [
    "CONTROLLER_COLORS",
    "DPI",
    "ESTIMATE_STYLES",
    "attempt",
    "band",
    "color",
    "envelope",
    "legend_below",
    "pyplot",
    "reference",
    "save",
    "suptitle",
]

CONTROLLER_COLORS = {
    "afonftsmc": "#D55E00",  # vermillion: the paper's controller
    "anftsmc": "#0072B2",  # blue
    "fobsmc": "#009E73",  # bluish green
    "bsmc": "#CC79A7",  # reddish purple
    "fl": "#E69F00",  # orange
}
"""Controller name -> colour, used by every figure."""

_SPARE_COLORS = ("#56B4E9", "#7F7F7F", "#8C564B", "#332288", "#117733")
"""For controllers registered later, in order of appearance."""

REFERENCE_COLOR = "black"

ESTIMATE_STYLES = ("-", "--", ":")
"""Line styles of the adaptive estimates ``b0, b1, b2`` (solid, dashed, dotted)."""

DPI = 160
"""Resolution of the PNG files (the PDF beside each is vector)."""

BAND_PERCENTILES = (5, 50, 95)


def pyplot():
    """``matplotlib.pyplot`` on the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def color(name: str, index: int = 0) -> str:
    """The colour of controller ``name`` (a spare colour for an unknown one)."""
    return CONTROLLER_COLORS.get(name) or _SPARE_COLORS[index % len(_SPARE_COLORS)]


def band(ax, t, values, color_):
    """Median line and 5-95 % band over draws of ``values`` ``(draws, time)`` (nothing
    when there is no draw)."""
    values = np.asarray(values, dtype=float)
    if values.shape[0] == 0:
        return
    low, mid, high = np.nanpercentile(values, BAND_PERCENTILES, axis=0)
    ax.plot(t, mid, color=color_, lw=1.2, zorder=3)
    if values.shape[0] > 1:
        ax.fill_between(t, low, high, color=color_, alpha=0.22, lw=0, zorder=2)


def envelope(ax, t, low, high, color_, alpha=0.25):
    """The full-rate range of a command: the band from ``low`` to ``high``.

    ``low``, ``high``: ``(draws, blocks)``, the smallest and largest command within
    each saved block (:class:`fojax.simulator.Snapshot`). Drawn: the median over draws
    of each edge, the band between them filled and its edges as thin lines, so that a
    command that does not chatter (the band collapses) still shows as a line.
    """
    t = np.asarray(t, dtype=float)
    low = np.nanmedian(np.asarray(low, dtype=float), axis=0)
    high = np.nanmedian(np.asarray(high, dtype=float), axis=0)
    if t.size > 1:  # each value holds over its block (t - block, t]: add the first start
        t = np.concatenate([[t[0] - (t[1] - t[0])], t])
        low, high = np.concatenate([low[:1], low]), np.concatenate([high[:1], high])
    ax.fill_between(t, low, high, color=color_, alpha=alpha, lw=0, zorder=2, step="pre")
    for edge in (high, low):
        ax.step(t, edge, where="pre", color=color_, lw=0.9, zorder=3)


def reference(ax, t, values):
    """The reference: dashed black, over every curve, with a white edge; returns its line."""
    from matplotlib import patheffects

    edge = [patheffects.withStroke(linewidth=2.4, foreground="white")]
    look = dict(color=REFERENCE_COLOR, ls="--", lw=1.2, label="reference", zorder=10)
    return ax.plot(t, values, **look, path_effects=edge)[0]


def legend_below(fig, handles, labels=None, ncol=None, fontsize=9):
    """One legend for the figure, below the axes, outside the data (the figure must
    use the ``constrained`` layout, which keeps room for it)."""
    if labels is None:
        labels = [h.get_label() for h in handles]
    ncol = ncol or min(len(handles), 7)
    return fig.legend(
        handles, labels, loc="outside lower center", ncol=ncol, fontsize=fontsize, frameon=False
    )


def suptitle(fig, title: str, caption: str = "", fontsize: int = 10):
    """The figure's title and, below it, its caption wrapped to the figure's width."""
    import textwrap

    # About 0.6 em per character; half an inch of margin.
    width = max(40, int((fig.get_figwidth() - 0.5) * 72 / (0.62 * fontsize)))
    lines = [title] + (textwrap.wrap(caption, width) if caption else [])
    return fig.suptitle("\n".join(lines), fontsize=fontsize)


def draws_caption(
    results: dict,
    curves: str = "median and 5-95 % band",
    statistics: str = "the statistics in summary.json",
) -> str:
    """What the ``curves`` show and what the ``statistics`` use, with the true counts."""
    total = next(iter(results.values())).draws
    kept = min(r.trajectories.time.shape[0] for r in results.values())
    shown = f"the first {kept} of {total} draws" if kept < total else f"all {total} draws"
    return f"{curves} over {shown} (diverged draws left out); {statistics} use all {total} draws"


def valid_kept(result) -> np.ndarray:
    """``(kept,)`` bool: the kept draws that did not diverge."""
    kept = result.trajectories.time.shape[0]
    return np.asarray(result.valid)[:kept]


def label(name: str, result) -> str:
    """Legend label of a controller: its name, and how many draws diverged."""
    diverged = int(result.draws - np.sum(result.valid))
    return name if diverged == 0 else f"{name} ({diverged}/{result.draws} diverged)"


def save(fig, path: Path, quantize: bool = False) -> Path:
    """``path`` (PNG at :data:`DPI`) and the same figure as ``path.with_suffix('.pdf')``.

    ``quantize``: store the PNG with a 256-colour palette (about a third of the size).
    Returns ``path``.
    """
    import io

    plt = pyplot()
    path = Path(path)
    try:
        if quantize:
            from PIL import Image

            buffer = io.BytesIO()
            fig.savefig(buffer, dpi=DPI, format="png")
            buffer.seek(0)
            with Image.open(buffer) as image:
                image.convert("RGB").quantize(colors=256).save(path, optimize=True)
        else:
            fig.savefig(path, dpi=DPI)
        fig.savefig(path.with_suffix(".pdf"))
    finally:
        plt.close(fig)
    return path


def attempt(name: str, draw, *args, **kwargs):
    """``draw(*args, **kwargs)``; on any exception, a warning naming the figure and None.

    Results are written before figures; a figure that cannot be drawn (a missing
    plotting library, a full disk, data it cannot show) must not lose them.
    """
    try:
        return draw(*args, **kwargs)
    except Exception as error:  # noqa: BLE001 - any failure of one figure is reported
        warning = f"figure {name} was not drawn ({type(error).__name__}: {error})"
        print(f"warning: {warning}; the results are written", file=sys.stderr, flush=True)
        return None
