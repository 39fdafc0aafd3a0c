"""The image path end to end: rendered images -> KLT tracks -> H_d / H_c -> every estimator.

Each seed renders a textured plane (hvo_graph.sim.render) seen by a camera that
follows the paper's sinusoidal twist pattern with a wider sweep, so that the
first frame's features leave the view and the front end moves its pose
reference to keyframes. Pipeline per seed (hvo_graph.image_runs.run_image_seed):

1. ground truth: the body twist xi(t) = [w; v] of
   :func:`hvo_graph.sim.scenario.body_twist` (paper pattern, linear amplitudes
   :data:`LINEAR_AMPLITUDE`), integrated on SE(3) by
   :func:`hvo_graph.sim.scenario.integrate_poses`;
2. images: :func:`hvo_graph.sim.render.render_plane_images` with a seeded texture
   and seeded Gaussian image noise (:data:`IMAGE_NOISE` gray levels);
3. tracks: :func:`hvo_graph.frontend.tracking.track_images` (OpenCV KLT);
4. measurements: :func:`hvo_graph.frontend.measure_sequence` (RANSAC 2 px,
   pixel_sigma :data:`PIXEL_SIGMA`, keyframes when the reference points leave);
5. estimators (:data:`METHODS`): the raw measurements, the paper's Kalman
   filter (paper noisy R_k), the Kalman filter with the front end's R_k, the
   ISAM2 smoother (smoothed and online), the fixed-lag smoother and the
   tightly coupled smoother (``tight``);
6. errors against the rendering's ground truth (hvo_graph.eval.metrics) after
   the first ``--skip`` seconds, and over the time before and after the first
   keyframe switch.

Besides the errors it reports what the image path delivers: keyframe switches,
tracks per frame, frames with a pose / a velocity, the track error against the
ground truth, and the normalized estimation error squared (NEES) of the pose
measurements against frame 0 and against keyframes (6 for a consistent
covariance).

Writes ``<out-dir>/images.md``, ``<out-dir>/figures/images_trajectory`` (.png,
.svg: estimate and truth over time, errors, keyframe switches) and
``<out-dir>/figures/images_tracks.png`` (a rendered frame with its tracks).

Usage::

    python experiments/images.py              # 5 seeds of 15 s, 640 x 480 -> out/images/
    python experiments/images.py --seeds 3 --duration 10
    python experiments/images.py --quick      # 1 seed of 4 s, 320 x 240 -> out/images-quick/
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hvo_graph.arguments import add_monte_carlo_options, finite_float, int_at_least
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_TITLES
from hvo_graph.eval.metrics import (
    QUANTITIES,
)
from hvo_graph.eval.stats import MeanCI, mean_ci
from hvo_graph.frontend import FrontEndConfig
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.image_runs import (
    DEFAULT_DURATION,
    IMAGE_NOISE,
    LINEAR_AMPLITUDE,
    PIXEL_SIGMA,
    ImageRunConfig,
    ImageSeedResult,
    nees_table,
    run_image_seed,
)
from hvo_graph.report.figures import tracks_figure, trajectory_figure
from hvo_graph.report.plotting import figure_style, save_figure, save_png
from hvo_graph.report.progress import ProgressBar
from hvo_graph.report.tables import (
    describe_seeds,
    format_ci,
    format_value,
    markdown_table,
    software_versions,
    write_text_atomic,
)
from hvo_graph.sim.scenario import (
    default_camera,
)

#: The repository (outputs go under it, wherever the script is run from).
ROOT = Path(__file__).resolve().parents[1]
#: Outputs default to out/images/: the repository's docs/ is written only when asked
#: (``--out-dir docs``, as ``make figures`` does).
DEFAULT_OUT_DIR = ROOT / "out" / "images"
QUICK_OUT_DIR = ROOT / "out" / "images-quick"

DEFAULT_SEEDS = 5
#: ``--quick``: one seed of 4 s at 320 x 240 (one keyframe switch, at about 3.5 s).
QUICK_DURATION = 4.0

#: Methods, in table order (names of hvo_graph.estimators.registry.METHODS).
METHODS: tuple[str, ...] = (
    "measurements",
    "kalman",
    "kalman-measured",
    "smoother",
    "smoother-online",
    "fixed-lag",
    "tight",
)
# "tight" puts one projection factor per pixel in the graph: with the images path's ~200
# tracks per frame it costs most of the run's time (docs/smoother.md gives its cost).

TRAJECTORY_FIGSIZE = (11.0, 7.5)  # inches; PNG 1650 x 1125 px at 150 dpi
TRACKS_FIGSIZE = (8.0, 6.6)  # PNG 1200 x 990 px


def quick_camera() -> CameraModel:
    """320 x 240 px, fx = fy = 600 px: a narrower view (1.07 m wide at d* = 2 m) than the
    default camera, so the 4 s quick run leaves the first frame's footprint too."""
    return CameraModel(fx=600.0, fy=600.0, cx=160.0, cy=120.0, width=320, height=240)


# -- tables ------------------------------------------------------------------------------


def _ci(values: Sequence[float | None]) -> MeanCI | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return mean_ci(finite) if finite else None


def _titled(label: str) -> str:
    return f"{METHOD_TITLES[label]} (`{label}`)"


def error_table(results: Sequence[ImageSeedResult]) -> str:
    """RMSE of every quantity per method: mean over seeds ± 95 % CI half-width."""
    header = ["method"] + [f"{title} [{unit}]" for _, title, unit in QUANTITIES]
    rows = []
    for label in METHODS:
        cells = [
            format_ci(_ci([getattr(r.summaries[label], f"{q}_rmse") for r in results]))
            for q, _, _ in QUANTITIES
        ]
        rows.append([_titled(label), *cells])
    return markdown_table(header, rows)


def segment_table(results: Sequence[ImageSeedResult]) -> str:
    """Position RMSE before and after the first keyframe switch, and per-seed ratios
    against the Kalman filter with measured R."""
    header = [
        "method",
        "before the first switch [m]",
        "after it [m]",
        "after / before",
        "after: ratio to Kalman (measured R)",
    ]
    rows = []
    for label in METHODS:
        before = [r.segments[label][0] for r in results]
        after = [r.segments[label][1] for r in results]
        growth = [
            a / b if a is not None and b else None for a, b in zip(after, before, strict=True)
        ]
        reference = [r.segments["kalman-measured"][1] for r in results]
        ratio = [
            a / b if a is not None and b else None for a, b in zip(after, reference, strict=True)
        ]
        cells = [format_ci(_ci(values)) for values in (before, after, growth, ratio)]
        rows.append([_titled(label), *cells])
    return markdown_table(header, rows)


def seed_table(results: Sequence[ImageSeedResult]) -> str:
    """Per seed: keyframes, tracks, measurements, track error, NEES, two position RMSEs.

    No run times: the page must come out the same for the same seeds (they go to stderr).
    """
    header = [
        "seed",
        "keyframe switches at frame (keyframe)",
        "tracks per frame: mean (min)",
        "frames with pose / velocity",
        "track error [px]",
        "NEES vs frame 0",
        "NEES vs keyframes",
        "position RMSE [m]: smoother / Kalman (measured R)",
    ]
    rows = []
    for r in results:
        frames = len(r.tracks_per_frame)
        switches = ", ".join(f"{s} ({k})" for s, k in zip(r.switches, r.keyframes, strict=True))
        rows.append(
            [
                str(r.seed),
                switches or "none",
                f"{r.tracks_per_frame.mean():.0f} ({r.tracks_per_frame.min()})",
                f"{r.frames_with_pose} / {r.frames_with_velocity} of {frames}",
                format_value(r.track_error_px, 2),
                format_value(r.nees_world, 3),
                format_value(r.nees_keyframe, 3),
                f"{format_value(r.summaries['smoother'].position_rmse)} / "
                f"{format_value(r.summaries['kalman-measured'].position_rmse)}",
            ]
        )
    return markdown_table(header, rows, align="lllrrrrr")


def scenario_text(config: ImageRunConfig) -> str:
    """The run's settings in one paragraph (Markdown)."""
    c, motion = config.camera, config.motion()
    normal = ", ".join(f"{x:.3g}" for x in np.asarray(motion.plane.normal) + 0.0)
    keyframes = (
        "no keyframes"
        if config.keyframe_min_points is None
        else f"keyframe when fewer than {config.keyframe_min_points} points are shared with "
        "the reference"
    )
    return (
        f"a {c.width} x {c.height} camera (fx = fy = {c.fx:g} px, no distortion) at "
        f"{config.fps:g} fps for {config.duration:g} s ({motion.num_frames} frames) over the "
        f"paper's plane (d* = {motion.plane.distance:g} m, n* = ({normal})), "
        "covered by a seeded procedural texture (hvo_graph.render.make_texture, about one "
        f"texel per pixel at d*, tiled); image noise {config.image_noise:g} gray levels. "
        "Motion: the paper's body-twist pattern (hvo_graph.simulation.body_twist) with linear "
        f"amplitudes {LINEAR_AMPLITUDE} m/s (paper: (0.12, -0.1, 0.15)), angular amplitudes "
        "and frequencies as in the paper. Front end: OpenCV KLT tracks "
        "(hvo_graph.tracking defaults), H_d with RANSAC at "
        f"{config.ransac_threshold_px:g} px, pixel_sigma {config.pixel_sigma:g} px, {keyframes}"
    )


def images_markdown(
    results: Sequence[ImageSeedResult], *, command: str, figures: Sequence[str] = ()
) -> str:
    """The whole ``images.md`` page."""
    config = results[0].config
    seeds = [r.seed for r in results]
    low = min(r.distance_range[0] for r in results)
    high = max(r.distance_range[1] for r in results)
    n = len(results)
    seeds_text = f"{n} seed" if n == 1 else f"{n} seeds"
    lines = [
        "# Results on rendered images: tracking, keyframes and every estimator",
        "",
        "Generated by `experiments/images.py`; do not edit by hand (`make figures` "
        "regenerates it, and the same seeds give the same numbers).",
        "",
        f"- Command: `{command}`",
        f"- Scene: {scenario_text(config)}. The camera stays {low:.2f} to {high:.2f} m from "
        "the plane and sees it over the whole image in every frame.",
        f"- Seeds: {describe_seeds(seeds)} ({seeds_text}); each seed draws the texture, the "
        "image noise and the Kalman filters' random initial state.",
        f"- Software: {software_versions()}.",
        "- Errors against the rendering's ground truth (poses integrated from the generating "
        "twist, and that twist): position ||p - p_gt|| (m), orientation angle of R_gt^T R "
        "(deg), body linear velocity ||v - v_gt|| (m/s), body angular velocity "
        f"||w - w_gt|| (rad/s); RMSE over the frames with t >= {config.skip:g} s, then the "
        "mean over seeds with a Student-t 95 % confidence interval.",
        "",
        f"### RMSE: mean over {seeds_text} ± 95 % confidence half-width",
        "",
        error_table(results),
        "",
        "### Position RMSE before and after the first keyframe switch",
        "",
        "Before: from the end of the skipped start to the first frame measured against a "
        "keyframe; after: from there to the end (further switches included). Ratios are "
        "taken per seed, then averaged.",
        "",
        segment_table(results),
        "",
        "### Consistency of the reported covariances",
        "",
        "NEES per dof of each estimate's pose and twist after the skipped start (1: honest; above "
        "1: overconfident); the front end is told 0.02 px, more than the tracks' error below.",
        "",
        nees_table(results, METHODS),
        "",
        "### Tracking, keyframes and measurement consistency per seed",
        "",
        "Track error: RMS per coordinate of every observation against the projection of the "
        "plane point it was first seen at (ground truth). NEES: mean delta^T C^-1 delta of the "
        "pose measurements, delta = Log(T_meas^-1 T_true) in the world (keyframe poses through "
        "the true keyframe, the plane re-placed there), C the front end's covariance; 6 if honest.",
        "",
        seed_table(results),
        "",
        "### Methods",
        "",
        "- raw measurements (`measurements`): the front end's H_d pose and H_c twist, no fusion.",
        "- Kalman (`kalman`): the paper's 12-state filter with the paper's noisy-run R_k.",
        "- Kalman, measured R (`kalman-measured`): R_k from the front end's covariances.",
        "- ISAM2 smoothed / online (`smoother`, `smoother-online`): the factor graph, keyframe "
        "poses as between factors; final values, and each frame right after its update.",
        "- fixed-lag (`fixed-lag`): the same graph in a 1 s window.",
        "- tight (`tight`): each tracked pixel a projection factor on a plane landmark.",
    ]
    if figures:
        lines += ["", "### Figures", ""]
        lines += [f"![{Path(f).stem.replace('_', ' ')}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


# -- figures -----------------------------------------------------------------------------

_FIGURE_METHODS = ("measurements", "kalman", "kalman-measured", "smoother")


def plot_trajectory(result: ImageSeedResult, path: Path) -> list[Path]:
    """Position and orientation against time (truth and estimates) over their errors, with
    the keyframe switches as vertical lines."""
    if result.truth is None:
        raise InputError("plot_trajectory: the seed was run without keep=True")
    c = result.config
    with figure_style():
        fig = trajectory_figure(
            result.truth,
            result.trajectories,
            _FIGURE_METHODS,
            shown="smoother",
            switches=result.switches,
            t_evaluated=result.truth.t[0] + c.skip,
            size=TRAJECTORY_FIGSIZE,
            title=f"Rendered images, seed {result.seed}: {c.camera.width} x {c.camera.height} "
            f"px, {c.fps:g} fps, image noise {c.image_noise:g}; dotted lines: keyframe switches",
        )
        return save_figure(fig, path)


def plot_tracks(result: ImageSeedResult, path: Path) -> Path:
    """The sample frame with the trails of its tracks: points shared with the frame's pose
    reference (used for H_d) and the others (used for H_c only). PNG only."""
    if result.sample is None:
        raise InputError("plot_tracks: the seed was run without keep=True")
    k, image, history, reference, shared = result.sample
    switch = "" if not result.switches else f"; the next frame takes frame {k} as keyframe"
    title = (
        f"Seed {result.seed}, frame {k} (t = {k / result.config.fps:.2f} s): "
        f"{len(history[-1].ids)} KLT tracks, trails over {len(history) - 1} frames\n"
        f"pose against frame {reference}{switch}"
    )
    with figure_style():
        fig = tracks_figure(image, history, shared, reference, size=TRACKS_FIGSIZE, title=title)
    return save_png(fig, path)


# -- command line ------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="images.py",
        description="Rendered images -> KLT tracks -> measurements -> every estimator, "
        "with keyframes (RMSE, 95 % CI over seeds).",
    )
    parser.add_argument(
        "--seeds", type=int_at_least(1), help=f"use seeds 0..N-1 (default {DEFAULT_SEEDS})"
    )
    parser.add_argument(
        "--duration",
        type=finite_float(0.0, strict=True),
        help=f"seconds (default {DEFAULT_DURATION:g}; {QUICK_DURATION:g} with --quick)",
    )
    parser.add_argument(
        "--image-noise",
        type=finite_float(0.0, strict=False),
        default=IMAGE_NOISE,
        help=f"image noise, gray levels (default {IMAGE_NOISE:g})",
    )
    parser.add_argument(
        "--pixel-sigma",
        type=finite_float(0.0, strict=True),
        default=PIXEL_SIGMA,
        help=f"the front end's pixel noise, px (default {PIXEL_SIGMA:g})",
    )
    parser.add_argument(
        "--keyframe-min-points",
        type=int_at_least(4),
        default=FrontEndConfig().keyframe_min_points,
        help="the front end's keyframe threshold (default: the library's)",
    )
    add_monte_carlo_options(
        parser,
        quick_help=f"1 seed of {QUICK_DURATION:g} s at 320 x 240 px (fx = 600 px) unless given",
        quick_out="out/images-quick/",
        default_out="out/images/; make figures passes --out-dir docs",
        workers=False,
        figures_option=False,
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the image experiment; returns the exit code (argparse exits 2 on bad options)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    seeds = list(range(args.seeds or (1 if args.quick else DEFAULT_SEEDS)))
    duration = args.duration or (QUICK_DURATION if args.quick else DEFAULT_DURATION)
    out_dir = args.out_dir or (QUICK_OUT_DIR if args.quick else DEFAULT_OUT_DIR)
    camera = quick_camera() if args.quick else default_camera()
    log = sys.stderr if not args.no_progress else None
    results: list[ImageSeedResult] = []
    try:
        configs = [
            ImageRunConfig(
                seed=seed,
                duration=duration,
                camera=camera,
                image_noise=args.image_noise,
                pixel_sigma=args.pixel_sigma,
                keyframe_min_points=args.keyframe_min_points,
                skip=args.skip,
            )
            for seed in seeds
        ]
        with ProgressBar(len(configs), label="seeds", enabled=log is not None) as bar:
            for i, config in enumerate(configs):
                result = run_image_seed(config, METHODS, keep=i == 0)
                results.append(result)
                if log is not None:
                    print(
                        f"seed {config.seed}: {len(result.tracks_per_frame)} frames, images + "
                        f"tracks + front end {result.seconds[0]:.1f} s, estimators "
                        f"{result.seconds[1]:.1f} s, keyframe switches at {result.switches}",
                        file=log,
                    )
                bar.update()
    except InputError as exc:
        parser.error(str(exc))
    fig_dir = out_dir / "figures"
    plot_trajectory(results[0], fig_dir / "images_trajectory")
    plot_tracks(results[0], fig_dir / "images_tracks")
    figures = ["figures/images_trajectory.png", "figures/images_tracks.png"]
    command = shlex.join(["python", "experiments/images.py", *argv])
    page = images_markdown(results, command=command, figures=figures)
    write_text_atomic(out_dir / "images.md", page)
    print(f"seeds {describe_seeds(seeds)}; written to {out_dir}/images.md\n")
    print(error_table(results))
    print()
    print(segment_table(results))
    print()
    print(nees_table(results, METHODS))
    print()
    print(seed_table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
