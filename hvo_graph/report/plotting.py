"""Shared figure style of the experiments: one colour and line style per method everywhere.

Figures are built on ``matplotlib.figure.Figure`` directly (no pyplot, so no
global figure state and no GUI backend) and written by :func:`save_figure` as
PNG and SVG. Colours are the Okabe-Ito palette (readable with colour-vision
deficiencies); methods that overlap (the three smoothers) also differ by line
style.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHODS
from hvo_graph.eval.bounds import BOUND, BOUND_TITLE

#: Resolution of the PNG files, dots per inch.
FIGURE_DPI = 150

#: Plot style per method (the style and title of each row of
#: hvo_graph.estimators.registry.METHODS), keyword arguments of ``Axes.plot``:
#: color, linestyle, marker, label.
METHOD_STYLE: dict[str, dict[str, object]] = {
    m.name: {**m.style, "label": m.title} for m in METHODS
} | {BOUND: {"color": "#000000", "linestyle": ":", "marker": "_", "label": BOUND_TITLE}}

#: Ground truth in time plots: dashed black.
TRUTH_STYLE: dict[str, object] = {
    "color": "#000000",
    "linestyle": "--",
    "linewidth": 1.2,
    "label": "ground truth",
}

#: rcParams of every figure (see :func:`figure_style`).
STYLE_RC: dict[str, object] = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "lines.linewidth": 1.4,
    "savefig.facecolor": "white",
    "figure.facecolor": "white",
    # fixed element ids and no date: the same figure gives the same SVG bytes
    "svg.hashsalt": "hvo_graph",
    "svg.fonttype": "path",
}


def method_style(label: str, *, marker: bool = False) -> dict[str, object]:
    """Keyword arguments of ``Axes.plot`` for ``label`` (a copy; marker only if asked).

    Unknown labels get a neutral grey with the label as legend text.
    """
    style = dict(METHOD_STYLE.get(label, {"color": "#666666", "linestyle": "-", "label": label}))
    if not marker:
        style.pop("marker", None)
    return style


@contextmanager
def figure_style() -> Iterator[None]:
    """Context in which figures are created and saved with :data:`STYLE_RC`."""
    with matplotlib.rc_context(STYLE_RC):
        yield


def new_figure(
    width: float, height: float, nrows: int = 1, ncols: int = 1, **subplot_kw: object
) -> tuple[Figure, np.ndarray]:
    """A ``Figure`` of ``width`` x ``height`` inches (constrained layout) and its axes,
    an (nrows, ncols) array of ``Axes``.

    The PNG written by :func:`save_figure` is then exactly
    round(width * FIGURE_DPI) x round(height * FIGURE_DPI) pixels.
    """
    fig = Figure(figsize=(width, height), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **subplot_kw)
    return fig, axes


def log_axis(ax: Axes, axis: str = "y") -> None:
    """Log scale on ``axis`` ("x" or "y") with plain-number tick labels (0.02, not 2 x 10^-2).

    Minor ticks are labelled too when the axis spans at most one decade, those at
    2 and 5 times a power of ten when it spans at most two (otherwise only the
    powers of ten are).
    """
    if axis not in ("x", "y"):
        raise InputError(f"axis: expected 'x' or 'y', got {axis!r}")
    target = ax.yaxis if axis == "y" else ax.xaxis
    (ax.set_yscale if axis == "y" else ax.set_xscale)("log")

    def plain(value: float, _pos: object = None) -> str:
        return f"{value:g}"

    def minor(value: float, _pos: object = None) -> str:
        low, high = (ax.get_ylim if axis == "y" else ax.get_xlim)()
        decades = math.log10(high / low) if low > 0 else math.inf
        if decades > 2.0:
            return ""
        mantissa = value / 10 ** math.floor(math.log10(value) + 1e-9)
        return plain(value) if decades <= 1.0 or round(mantissa) in (2, 5) else ""

    target.set_major_formatter(FuncFormatter(plain))
    target.set_minor_formatter(FuncFormatter(minor))


def save_figure(fig: Figure, path_without_ext: str | Path, *, dpi: int = FIGURE_DPI) -> list[Path]:
    """Write ``fig`` as ``<path>.png`` (``dpi``) and ``<path>.svg``, each atomically.

    Each file is written to a temporary name in the same folder and renamed,
    so a reader never sees half a figure. Creates the folder.

    Returns:
        [png path, svg path].
    """
    base = Path(path_without_ext)
    if base.suffix in (".png", ".svg"):
        raise InputError(f"path_without_ext: give the path without extension, got {base}")
    base.parent.mkdir(parents=True, exist_ok=True)
    written = []
    with figure_style():
        for ext, metadata in (("png", {"Software": None}), ("svg", {"Date": None})):
            final = base.with_name(f"{base.name}.{ext}")
            tmp = base.with_name(f".{base.name}.{os.getpid()}.tmp.{ext}")
            fig.savefig(tmp, format=ext, dpi=dpi, metadata=metadata)
            os.replace(tmp, final)
            written.append(final)
    return written


def save_png(fig: Figure, path: str | Path, *, dpi: int = FIGURE_DPI) -> Path:
    """Write ``fig`` as ``<path>.png`` only, atomically; creates the folder."""
    path = Path(path).with_suffix(".png")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.png")
    with figure_style():
        fig.savefig(tmp, format="png", dpi=dpi, metadata={"Software": None})
    os.replace(tmp, path)
    return path
