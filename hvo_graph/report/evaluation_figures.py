"""Figures of ``hvo-graph evaluate --plot DIR``: errors over time, top view, error distribution.

Each function takes the :class:`~hvo_graph.eval.evaluation.Evaluation` of every
estimate and returns a ``Figure``; :func:`write_evaluation_figures` saves them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hvo_graph.eval.evaluation import Evaluation
from hvo_graph.report.plotting import (
    METHOD_STYLE,
    TRUTH_STYLE,
    figure_style,
    new_figure,
    save_figure,
)
from hvo_graph.types import Trajectory

#: Colours for methods without a style of their own (Okabe-Ito, colour-blind safe).
_PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000")
_AXES = ("x", "y", "z")


def _style(label: str, k: int) -> dict[str, object]:
    if label in METHOD_STYLE:
        style = dict(METHOD_STYLE[label])
        style.pop("marker", None)
        style["label"] = label
        return style
    return {"color": _PALETTE[k % len(_PALETTE)], "linestyle": "-", "label": label}


def _subtitle(ev: Evaluation) -> str:
    align = {"none": "not aligned", "origin": "origin aligned"}.get(
        ev.alignment.method, f"{ev.alignment.method.upper()} Umeyama alignment"
    )
    return align


def error_over_time_figure(evaluations: Sequence[Evaluation]) -> Figure:
    """APE translation (m) and rotation (deg) of each estimate against ground-truth time."""
    fig, axes = new_figure(8.0, 5.5, nrows=2, ncols=1, sharex=True)
    for k, ev in enumerate(evaluations):
        style = _style(ev.method, k)
        axes[0, 0].plot(ev.groundtruth.t, ev.ape["trans_m"], **style)
        axes[1, 0].plot(ev.groundtruth.t, ev.ape["rot_deg"], **style)
    axes[0, 0].set_ylabel("APE translation [m]")
    axes[1, 0].set_ylabel("APE rotation [deg]")
    axes[1, 0].set_xlabel("ground-truth time [s]")
    axes[0, 0].set_title(f"absolute pose error over time ({_subtitle(evaluations[0])})")
    axes[0, 0].legend(loc="upper left")
    return fig


def _plane_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two axes along which the ground truth spreads most (in axis order)."""
    spread = np.ptp(positions, axis=0)
    a, b = sorted(np.argsort(spread)[-2:].tolist())
    return int(a), int(b)


def top_view_figure(groundtruth: Trajectory, evaluations: Sequence[Evaluation]) -> Figure:
    """Ground truth and the aligned estimates projected on the plane of largest spread."""
    a, b = _plane_axes(np.asarray(groundtruth.positions))
    fig, axes = new_figure(6.5, 6.0)
    ax = axes[0, 0]
    gt = np.asarray(groundtruth.positions)
    ax.plot(gt[:, a], gt[:, b], **TRUTH_STYLE)
    for k, ev in enumerate(evaluations):
        p = np.asarray(ev.estimate.positions)
        ax.plot(p[:, a], p[:, b], **_style(ev.method, k))
    ax.set_xlabel(f"{_AXES[a]} [m]")
    ax.set_ylabel(f"{_AXES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"trajectories, {_AXES[a]}-{_AXES[b]} plane ({_subtitle(evaluations[0])})")
    ax.legend(loc="best")
    return fig


def error_distribution_figure(evaluations: Sequence[Evaluation]) -> Figure:
    """Box plots of APE and RPE translation errors (m), one box per estimate."""
    fig, axes = new_figure(8.0, 4.0, nrows=1, ncols=2)
    labels = [ev.method for ev in evaluations]
    ev0 = evaluations[0]
    unit = {"f": "frames" if ev0.options.delta != 1 else "frame", "s": "s", "m": "m"}[
        ev0.options.delta_unit
    ]
    for ax, key, title in (
        (axes[0, 0], "ape", "APE translation [m]"),
        (axes[0, 1], "rpe", f"RPE translation [m], delta {ev0.options.delta:g} {unit}"),
    ):
        data = [getattr(ev, key)["trans_m"] for ev in evaluations]
        ax.boxplot(data, tick_labels=labels, showfliers=True)
        ax.set_title(title)
        ax.tick_params(axis="x", labelrotation=20)
    return fig


def write_evaluation_figures(
    directory: str | Path, groundtruth: Trajectory, evaluations: Sequence[Evaluation]
) -> list[Path]:
    """Write error_over_time, top_view and error_distribution (.png and .svg) into ``directory``.

    Returns:
        The files written.
    """
    out = Path(directory)
    written: list[Path] = []
    with figure_style():
        figures = {
            "error_over_time": error_over_time_figure(evaluations),
            "top_view": top_view_figure(groundtruth, evaluations),
            "error_distribution": error_distribution_figure(evaluations),
        }
    for name, fig in figures.items():
        written += save_figure(fig, out / name)
    return written
