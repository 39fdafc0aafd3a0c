"""Draw the two factor graphs for docs/method.md.

Variables are circles (poses X(k), twists V(k), landmarks L(j)); factors are
small squares, joined by lines to the variables they constrain.

- ``factor_graph``, the homography smoother: the world prior on X(0), pose
  priors from H_d against the world frame, a between factor from H_d against a
  keyframe, the white-noise-acceleration motion factor on X(k-1), V(k-1), X(k), V(k)
  (GTSAM's ``WnoaMotionFactorPose3``), and the mid-interval twist from H_c on V(k-1), V(k);
- ``factor_graph_tight``, the tightly coupled graph: the same world prior and
  motion factors, a plane prior n*^T L(j) = d* on every landmark and one
  projection factor per pixel observation, on X(k) and L(j); no H_d or H_c factor.

Usage::

    python experiments/factor_graph_figure.py   # -> docs/figures/factor_graph{,_tight}.{png,svg}
    python experiments/factor_graph_figure.py --out DIR
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.lines import Line2D

from hvo_graph.report.plotting import figure_style, save_figure

ROOT = Path(__file__).resolve().parents[1]

#: Factor kinds: (label for the legend, face colour).
FACTORS = {
    "world": ("world prior on X(0) (defines W = F*)", "black"),
    "pose": ("pose from H_d, reference W (prior)", "#0072B2"),
    "between": ("pose from H_d, reference keyframe (between)", "#56B4E9"),
    "motion": ("motion: white-noise-acceleration prior on X(k-1), V(k-1), X(k), V(k)", "#D55E00"),
    "twist": ("twist from H_c at t(k-1/2): (V(k-1)+V(k))/2", "#009E73"),
}

#: The tightly coupled graph's factor kinds (the motion factor as above).
TIGHT_FACTORS = {
    "world": FACTORS["world"],
    "plane": ("plane: n*^T L(j) = d* (landmark on the plane)", "#CC79A7"),
    "projection": ("projection: pixel of L(j) in frame k (Huber)", "#0072B2"),
    "motion": FACTORS["motion"],
}

#: Frames each landmark of the tight drawing is seen in: tracks begin and end.
TIGHT_TRACKS = ((0, 1, 2), (0, 1, 2, 3, 4), (1, 2, 3, 4), (3, 4))


Point = tuple[float, float]
RADIUS = 0.34


def _factor(ax: plt.Axes, at: Point, colour: str, to: Sequence[Point]) -> None:
    for var in to:
        ax.plot([at[0], var[0]], [at[1], var[1]], color="0.35", lw=1.2, zorder=1)
    ax.add_patch(plt.Rectangle((at[0] - 0.13, at[1] - 0.13), 0.26, 0.26, color=colour, zorder=3))


def _variable(ax: plt.Axes, centre: Point, name: str, face: str) -> None:
    ax.add_patch(plt.Circle(centre, RADIUS, facecolor=face, edgecolor="black", zorder=4))
    ax.text(*centre, name, ha="center", va="center", fontsize=10, zorder=5)


def _motion_chain(
    ax: plt.Axes, poses: Sequence[Point], twists: Sequence[Point], y_twist: float, kinds: dict
) -> None:
    """World prior on X(0), the motion factor between frames, variables."""
    xs = [p[0] for p in poses]
    _factor(ax, (xs[0] - 1.0, poses[0][1]), kinds["world"][1], [poses[0]])
    for k in range(1, len(poses)):
        mid = 0.5 * (xs[k - 1] + xs[k])
        to = [poses[k - 1], poses[k], twists[k - 1], twists[k]]
        _factor(ax, (mid, 0.5 * (poses[0][1] + y_twist)), kinds["motion"][1], to)
    for k, (p, v) in enumerate(zip(poses, twists, strict=True)):
        _variable(ax, p, f"X({k})", "white")
        _variable(ax, v, f"V({k})", "0.93")
    ax.text(xs[0] - 1.9, poses[0][1], "pose\nT_wc", ha="center", va="center", fontsize=9)
    ax.text(xs[0] - 1.9, y_twist, "twist\n[w; v]", ha="center", va="center", fontsize=9)


def _legend(ax: plt.Axes, kinds: dict) -> None:
    handles = [
        Line2D([], [], marker="s", ls="", markersize=9, color=colour, label=label)
        for label, colour in kinds.values()
    ]
    ax.legend(handles=handles, loc="lower center", ncol=2, fontsize=9, frameon=False)


def draw(ax: plt.Axes, frames: int = 5, keyframe: int = 2) -> None:
    """Draw ``frames`` frames; later poses are measured against frame ``keyframe``."""
    xs = [2.2 * k for k in range(frames)]
    y_pose, y_twist = 2.0, 0.0

    def factor(at: Point, kind: str, to: Sequence[Point]) -> None:
        _factor(ax, at, FACTORS[kind][1], to)

    poses = [(x, y_pose) for x in xs]
    twists = [(x, y_twist) for x in xs]
    _motion_chain(ax, poses, twists, y_twist, FACTORS)
    for k in range(1, frames):
        mid = 0.5 * (xs[k - 1] + xs[k])
        factor((mid, y_twist - 1.2), "twist", [twists[k - 1], twists[k]])
        if k <= keyframe:
            factor((xs[k], y_pose + 1.0), "pose", [poses[k]])
        else:
            up = (0.5 * (xs[keyframe] + xs[k]), y_pose + 1.1 + 0.35 * (k - keyframe))
            factor(up, "between", [poses[keyframe], poses[k]])
    ax.set_xlim(xs[0] - 2.5, xs[-1] + 0.8)
    ax.set_ylim(y_twist - 3.0, y_pose + 2.4)
    ax.set_aspect("equal")
    ax.axis("off")
    _legend(ax, FACTORS)


def draw_tight(ax: plt.Axes, frames: int = 5) -> None:
    """Draw the tightly coupled graph over ``frames`` frames and :data:`TIGHT_TRACKS`."""
    xs = [2.2 * k for k in range(frames)]
    y_landmark, y_pose, y_twist = 4.6, 2.0, 0.0
    poses = [(x, y_pose) for x in xs]
    twists = [(x, y_twist) for x in xs]
    spread = (xs[-1] - xs[0]) / max(len(TIGHT_TRACKS) - 1, 1)
    landmarks = [(xs[0] + j * spread, y_landmark) for j in range(len(TIGHT_TRACKS))]
    for j, seen in enumerate(TIGHT_TRACKS):
        lx, ly = landmarks[j]
        _factor(ax, (lx, ly + 0.85), TIGHT_FACTORS["plane"][1], [landmarks[j]])
        for k in seen:
            # the projection factor sits on its edge, nearer the pose
            at = (0.35 * lx + 0.65 * xs[k], 0.35 * ly + 0.65 * y_pose)
            _factor(ax, at, TIGHT_FACTORS["projection"][1], [landmarks[j], poses[k]])
    _motion_chain(ax, poses, twists, y_twist, TIGHT_FACTORS)
    for j, centre in enumerate(landmarks):
        _variable(ax, centre, f"L({j})", "#FFF3C4")
    ax.text(xs[0] - 1.9, y_landmark, "plane\npoint", ha="center", va="center", fontsize=9)
    ax.set_xlim(xs[0] - 2.5, xs[-1] + 0.8)
    ax.set_ylim(y_twist - 2.6, y_landmark + 1.3)
    ax.set_aspect("equal")
    ax.axis("off")
    _legend(ax, TIGHT_FACTORS)


def make_figure(out: Path) -> list[Path]:
    """Write factor_graph and factor_graph_tight (.png and .svg) into ``out``; return
    their paths."""
    with figure_style():
        fig, ax = plt.subplots(figsize=(10.0, 6.4))
        draw(ax)
        ax.set_title(
            "hvo_graph factor graph: poses X(k), twists V(k); "
            f"poses from frame {2 + 1} on are measured against keyframe 2",
            fontsize=11,
        )
        fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.93)
        save_figure(fig, out / "factor_graph")
        plt.close(fig)
        fig, ax = plt.subplots(figsize=(10.0, 6.4))
        draw_tight(ax)
        ax.set_title(
            "hvo_graph tightly coupled graph: poses X(k), twists V(k), plane points L(j); "
            "tracks begin and end",
            fontsize=11,
        )
        fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.93)
        save_figure(fig, out / "factor_graph_tight")
        plt.close(fig)
    return [
        out / f"{name}.{ext}"
        for name in ("factor_graph", "factor_graph_tight")
        for ext in ("png", "svg")
    ]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures", help="folder")
    args = parser.parse_args(argv)
    for path in make_figure(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
