"""Draw the smoother's factor graph for docs/method.md.

Variables are circles (poses X(k), twists V(k)); factors are small squares,
joined by lines to the variables they constrain: the world prior on X(0), pose
priors from H_d against the world frame, a between factor from H_d against a
keyframe, the trapezoid motion factor on X(k-1), X(k), V(k-1), V(k), the twist
random walk, and the mid-interval twist from H_c on V(k-1), V(k).

Usage::

    python experiments/factor_graph_figure.py            # -> docs/figures/factor_graph.{png,svg}
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
    "motion": ("motion: Log(X(k-1)^-1 X(k)) = dt (V(k-1)+V(k))/2", "#D55E00"),
    "walk": ("twist random walk: V(k) - V(k-1) ~ N(0, Q dt)", "#E69F00"),
    "twist": ("twist from H_c at t(k-1/2): (V(k-1)+V(k))/2", "#009E73"),
}


def draw(ax: plt.Axes, frames: int = 5, keyframe: int = 2) -> None:
    """Draw ``frames`` frames; later poses are measured against frame ``keyframe``."""
    xs = [2.2 * k for k in range(frames)]
    y_pose, y_twist = 2.0, 0.0
    radius = 0.34

    def edge(a: tuple[float, float], b: tuple[float, float]) -> None:
        ax.plot([a[0], b[0]], [a[1], b[1]], color="0.35", lw=1.2, zorder=1)

    def factor(at: tuple[float, float], kind: str, to: Sequence[tuple[float, float]]) -> None:
        for var in to:
            edge(at, var)
        ax.add_patch(
            plt.Rectangle(
                (at[0] - 0.13, at[1] - 0.13), 0.26, 0.26, color=FACTORS[kind][1], zorder=3
            )
        )

    poses = [(x, y_pose) for x in xs]
    twists = [(x, y_twist) for x in xs]
    factor((xs[0] - 1.0, y_pose), "world", [poses[0]])
    for k in range(1, frames):
        mid = 0.5 * (xs[k - 1] + xs[k])
        factor((mid, 1.0), "motion", [poses[k - 1], poses[k], twists[k - 1], twists[k]])
        factor((mid, y_twist - 0.55), "walk", [twists[k - 1], twists[k]])
        factor((mid, y_twist - 1.2), "twist", [twists[k - 1], twists[k]])
        if k <= keyframe:
            factor((xs[k], y_pose + 1.0), "pose", [poses[k]])
        else:
            up = (0.5 * (xs[keyframe] + xs[k]), y_pose + 1.1 + 0.35 * (k - keyframe))
            factor(up, "between", [poses[keyframe], poses[k]])
    for k, (p, v) in enumerate(zip(poses, twists, strict=True)):
        for centre, name, face in ((p, f"X({k})", "white"), (v, f"V({k})", "0.93")):
            ax.add_patch(plt.Circle(centre, radius, facecolor=face, edgecolor="black", zorder=4))
            ax.text(*centre, name, ha="center", va="center", fontsize=10, zorder=5)
    ax.text(xs[0] - 1.9, y_pose, "pose\nT_wc", ha="center", va="center", fontsize=9)
    ax.text(xs[0] - 1.9, y_twist, "twist\n[w; v]", ha="center", va="center", fontsize=9)
    ax.set_xlim(xs[0] - 2.5, xs[-1] + 0.8)
    ax.set_ylim(y_twist - 3.0, y_pose + 2.4)
    ax.set_aspect("equal")
    ax.axis("off")
    handles = [
        Line2D([], [], marker="s", ls="", markersize=9, color=colour, label=label)
        for label, colour in FACTORS.values()
    ]
    ax.legend(
        handles=handles,
        loc="lower center",
        ncol=2,
        fontsize=9,
        frameon=False,
    )


def make_figure(out: Path) -> list[Path]:
    """Write factor_graph.png and .svg into ``out``; return their paths."""
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
    return [out / "factor_graph.png", out / "factor_graph.svg"]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures", help="folder")
    args = parser.parse_args(argv)
    for path in make_figure(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
