"""Figures of one run: estimates against the truth over their errors, and a frame's tracks.

Presentation only: the data (trajectories, images, tracks) come in, a
``Figure`` goes out; the callers save it (:mod:`hvo_graph.report.plotting`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from hvo_graph.eval.metrics import error_series
from hvo_graph.geometry.rotation import rotation_to_euler
from hvo_graph.report.plotting import TRUTH_STYLE, log_axis, method_style, new_figure
from hvo_graph.types import FrameObservations, Trajectory

_COMPONENTS = (("x", "y", "z"), ("roll", "pitch", "yaw"))
_COMPONENT_COLORS = ("#0072B2", "#009E73", "#D55E00")


def euler_degrees(rotations: np.ndarray) -> np.ndarray:
    """(K, 3) roll, pitch, yaw in degrees (hvo_graph.geometry.rotation.rotation_to_euler)."""
    return np.degrees(np.array([rotation_to_euler(R) for R in rotations]))


def trajectory_figure(
    truth: Trajectory,
    estimates: Mapping[str, Trajectory],
    methods: Sequence[str],
    *,
    shown: str,
    switches: Sequence[int],
    t_evaluated: float,
    size: tuple[float, float],
    title: str,
) -> Figure:
    """Position and orientation against time (truth and the ``shown`` estimate) over the
    errors of ``methods``, with the keyframe switches (frame indices) as vertical lines.

    The error axes are logarithmic, their lower limit from the frames at t >= ``t_evaluated``.
    Call inside :func:`~hvo_graph.report.plotting.figure_style`.
    """
    fig, axes = new_figure(*size, nrows=2, ncols=2, sharex=True)
    truth_values = (np.asarray(truth.positions), euler_degrees(truth.rotations))
    smoothed = estimates[shown]
    estimate_values = (np.asarray(smoothed.positions), euler_degrees(smoothed.rotations))
    for ax, names, true, est in zip(
        axes[0], _COMPONENTS, truth_values, estimate_values, strict=True
    ):
        for i, (name, color) in enumerate(zip(names, _COMPONENT_COLORS, strict=True)):
            ax.plot(truth.t, true[:, i], color="#000000", linestyle="--", linewidth=1.0)
            ax.plot(smoothed.t, est[:, i], color=color, linewidth=1.4, label=name)
        ax.legend(loc="upper left", ncols=3)
    axes[0, 0].set_title("position: ISAM2 smoothed (solid), truth (dashed)")
    axes[0, 0].set_ylabel("position [m]")
    axes[0, 1].set_title("orientation (Euler angles): ISAM2 smoothed, truth")
    axes[0, 1].set_ylabel("angle [deg]")
    for ax, quantity, unit in zip(axes[1], ("position", "orientation"), ("m", "deg"), strict=True):
        low, high = [], []
        for label in methods:
            series = error_series(estimates[label], truth)
            e = getattr(series, quantity)
            ok = e > 0
            ax.plot(series.t[ok], e[ok], **method_style(label))
            evaluated = e[ok & (series.t >= t_evaluated - 1e-9)]
            low.append(evaluated.min())
            high.append(evaluated.max())
        log_axis(ax)
        # Frame 0 is exact by construction: the lower limit comes from the evaluated frames.
        ax.set_ylim(0.5 * min(low), 1.5 * max(high))
        ax.set_title(f"{quantity} error")
        ax.set_ylabel(f"{quantity} error [{unit}]")
        ax.set_xlabel("time [s]")
    for ax in axes.flat:
        for k, s in enumerate(switches):
            ax.axvline(
                truth.t[s],
                color="#777777",
                linestyle=":",
                linewidth=1.0,
                label="keyframe switch" if k == 0 else None,
            )
    handles, labels = axes[1, 0].get_legend_handles_labels()
    handles.append(axes[0, 0].plot([], [], **TRUTH_STYLE)[0])
    labels.append(str(TRUTH_STYLE["label"]))
    fig.legend(handles, labels, loc="outside lower center", ncols=3)
    fig.suptitle(title)
    return fig


def tracks_figure(
    image: np.ndarray,
    history: Sequence[FrameObservations],
    shared: np.ndarray,
    reference: int,
    *,
    size: tuple[float, float],
    title: str,
) -> Figure:
    """A frame (the last of ``history``) with the trails of its tracks: the points
    ``shared`` with its pose reference (used for H_d) and the others (H_c only).

    Call inside :func:`~hvo_graph.report.plotting.figure_style`.
    """
    current = history[-1]
    fig, axes = new_figure(*size)
    ax = axes[0, 0]
    ax.imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    trails: dict[int, list[np.ndarray]] = {}
    for obs in history:
        for i, uv in zip(np.asarray(obs.ids).tolist(), obs.uv, strict=True):
            trails.setdefault(int(i), []).append(np.asarray(uv, dtype=float))
    shared_set = set(np.asarray(shared).tolist())
    styles = {
        True: ("#56B4E9", f"{len(shared_set)} shared with frame {reference}: H_d and H_c"),
        False: ("#E69F00", f"{len(current.ids) - len(shared_set)} others: H_c only"),
    }
    drawn: set[bool] = set()
    for i, uv in zip(np.asarray(current.ids).tolist(), current.uv, strict=True):
        used = int(i) in shared_set
        color, label = styles[used]
        trail = np.array(trails[int(i)])
        ax.plot(trail[:, 0], trail[:, 1], color=color, linewidth=1.0)
        ax.plot(
            uv[0], uv[1], "o", color=color, markersize=3, label=label if used not in drawn else None
        )
        drawn.add(used)
    ax.set_xlim(-0.5, image.shape[1] - 0.5)
    ax.set_ylim(image.shape[0] - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.grid(False)
    ax.legend(loc="lower left", framealpha=0.9)
    ax.set_title(title)
    return fig
