"""The image path end to end: rendered images -> KLT tracks -> H_d / H_c -> every estimator.

Each seed renders a textured plane (hvo_graph.sim.render) seen by a camera that
follows the paper's sinusoidal twist pattern with a wider sweep, so that the
first frame's features leave the view and the front end moves its pose
reference to keyframes. Pipeline per seed:

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
   ISAM2 smoother (smoothed and online) and the fixed-lag smoother;
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

    python experiments/images.py              # 5 seeds of 15 s, 640 x 480 -> docs/
    python experiments/images.py --seeds 3 --duration 10
    python experiments/images.py --quick      # 1 seed of 4 s, 320 x 240 -> out/images-quick/
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from hvo_graph.arguments import add_monte_carlo_options, finite_float, int_at_least
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_TITLES
from hvo_graph.eval.metrics import QUANTITIES, ErrorSeries, ErrorSummary, error_series, summarize
from hvo_graph.eval.stats import MeanCI, mean_ci
from hvo_graph.frontend import FrontEndConfig, measure_sequence
from hvo_graph.frontend.tracking import track_images
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.rotation import rotation_to_euler
from hvo_graph.montecarlo import MethodRuns
from hvo_graph.report.progress import ProgressBar
from hvo_graph.report.tables import (
    describe_seeds,
    format_ci,
    format_value,
    markdown_table,
    software_versions,
    write_text_atomic,
)
from hvo_graph.sim.render import make_texture, render_plane_images
from hvo_graph.sim.scenario import (
    ScenarioConfig,
    body_twist,
    default_camera,
    integrate_poses,
    paper_scenario,
)
from hvo_graph.types import FrameMeasurement, FrameObservations, Plane, Trajectory

#: The repository (outputs default to its docs/ folder, wherever the script is run from).
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT_DIR = ROOT / "docs"
QUICK_OUT_DIR = ROOT / "out" / "images-quick"

DEFAULT_SEEDS = 5
#: Seconds: three keyframe switches with the default motion and camera.
DEFAULT_DURATION = 15.0
#: ``--quick``: one seed of 4 s at 320 x 240 (one keyframe switch, at about 3.5 s).
QUICK_DURATION = 4.0
FPS = 30.0

#: Linear amplitudes A_v (m/s) of the paper's twist pattern (paper: 0.12, -0.10, 0.15). The
#: camera sweeps 2.5 m along x (peak to peak) at 1.7 to 2.1 m from the plane, so the first
#: frame's footprint (1.6 m wide) is left behind after about 4.8 s. The angular amplitudes
#: and all frequencies stay the paper's (hvo_graph.sim.scenario.ScenarioConfig).
LINEAR_AMPLITUDE = (0.8, -0.25, 0.15)

#: Standard deviation of the additive image noise, gray levels (of 0..255).
IMAGE_NOISE = 2.0

#: pixel_sigma of the front end, pixels. The tracks are far more precise than the paper's
#: 0.22 px: on these renders the RMS error of a track against the projection of the plane
#: point it was first seen at is about 0.013 px per coordinate (reported per run in
#: images.md). That error is partly shared by neighbouring tracks and does not average out
#: over ~150 points, so the sigma that makes the pose covariances describe the pose errors
#: is larger: with 0.02 px the poses against frame 0 have a mean NEES of 2 to 4 (images.md;
#: 6 when consistent). The covariances scale with sigma^2, so 0.01 px would give 8 to 16.
PIXEL_SIGMA = 0.02

#: RANSAC threshold of the front end's H_d, pixels.
RANSAC_THRESHOLD_PX = 2.0

#: Methods, in table order (names of hvo_graph.estimators.registry.METHODS).
METHODS: tuple[str, ...] = (
    "measurements",
    "kalman",
    "kalman-measured",
    "smoother",
    "smoother-online",
    "fixed-lag",
)

#: Frames rendered per call (one texture, a fresh noise stream per chunk).
_CHUNK_FRAMES = 30

#: The procedural texture is this many first-image widths a side, then tiles (texels of
#: about one pixel at d*: hvo_graph.sim.render.default_texel_size).
_TEXTURE_FOOTPRINTS = 4

TRAJECTORY_FIGSIZE = (11.0, 7.5)  # inches; PNG 1650 x 1125 px at 150 dpi
TRACKS_FIGSIZE = (8.0, 6.6)  # PNG 1200 x 990 px

#: Frames of track history drawn in the tracks figure.
_TRAIL_FRAMES = 12


def quick_camera() -> CameraModel:
    """320 x 240 px, fx = fy = 600 px: a narrower view (1.07 m wide at d* = 2 m) than the
    default camera, so the 4 s quick run leaves the first frame's footprint too."""
    return CameraModel(fx=600.0, fy=600.0, cx=160.0, cy=120.0, width=320, height=240)


@dataclass(frozen=True)
class ImageRunConfig:
    """One seed of the image experiment.

    Attributes:
        seed: seeds the texture, the image noise and the Kalman filters' initial state.
        duration: seconds; frames at t = k / fps.
        fps: frames per second.
        camera: the rendering camera (the paper's 640 x 480, f = 800 px by default).
        image_noise: standard deviation of the image noise, gray levels.
        pixel_sigma: the front end's pixel noise, pixels (drives the covariances).
        keyframe_min_points: the front end's keyframe threshold (default: the library's,
            :class:`hvo_graph.frontend.FrontEndConfig`).
        ransac_threshold_px: the front end's RANSAC threshold on H_d, pixels.
        skip: seconds at the start left out of the errors.
    """

    seed: int = 0
    duration: float = DEFAULT_DURATION
    fps: float = FPS
    camera: CameraModel = field(default_factory=default_camera)
    image_noise: float = IMAGE_NOISE
    pixel_sigma: float = PIXEL_SIGMA
    keyframe_min_points: int | None = FrontEndConfig.keyframe_min_points
    ransac_threshold_px: float = RANSAC_THRESHOLD_PX
    skip: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.skip) and 0 <= self.skip < self.duration):
            raise InputError(
                f"skip: expected a number of seconds in [0, duration = {self.duration:g}), "
                f"got {self.skip!r}"
            )

    def motion(self) -> ScenarioConfig:
        """The generating motion: the paper's twist pattern with :data:`LINEAR_AMPLITUDE`."""
        return paper_scenario(
            noisy=False,
            duration=self.duration,
            fps=self.fps,
            camera=self.camera,
            linear_amplitude=LINEAR_AMPLITUDE,
            seed=self.seed,
        )

    def front_end(self) -> FrontEndConfig:
        """The front-end settings of this run."""
        return FrontEndConfig(
            pixel_sigma=self.pixel_sigma,
            ransac_threshold_px=self.ransac_threshold_px,
            keyframe_min_points=self.keyframe_min_points,
        )


@dataclass
class ImageSeedResult:
    """What one seed of the image experiment measured.

    Attributes:
        seed: the seed.
        config: the run's settings.
        summaries: per method, RMSE and max after ``config.skip`` seconds.
        segments: per method, position RMSE (m) over [t0 + skip, t_s) and [t_s, end],
            t_s the first keyframe switch (None when there was none, or no frame).
        switches: frame indices at which the pose reference moved to a keyframe
            (the first frame measured against each new keyframe).
        keyframes: the keyframes, in order (the pose reference of those frames).
        tracks_per_frame: (K,) tracked points per frame.
        frames_with_pose: frames with a pose measurement.
        frames_with_velocity: frames with a velocity measurement.
        track_error_px: RMS per coordinate of every track against the reprojection of
            the plane point it was first seen at (ground truth), pixels.
        nees_world: mean NEES of the pose measurements against frame 0 (frames after 0).
        nees_keyframe: mean NEES of the pose measurements against keyframes (None: none).
        distance_range: (min, max) distance from the camera centre to the plane, metres.
        seconds: wall-clock time of (images + tracks + front end, estimators).
        truth: the ground truth (kept for the figures).
        trajectories: per method, the estimate (kept for the figures).
        sample: (frame index, image, observations of the last frames, the frame's pose
            reference, ids shared with it) for the tracks figure: the last frame measured
            against frame 0 (the first keyframe), or the middle frame; None unless kept.
    """

    seed: int
    config: ImageRunConfig
    summaries: dict[str, ErrorSummary]
    segments: dict[str, tuple[float | None, float | None]]
    switches: list[int]
    keyframes: list[int]
    tracks_per_frame: np.ndarray
    frames_with_pose: int
    frames_with_velocity: int
    track_error_px: float
    nees_world: float | None
    nees_keyframe: float | None
    distance_range: tuple[float, float]
    seconds: tuple[float, float]
    truth: Trajectory | None = None
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    sample: tuple[int, np.ndarray, list[FrameObservations], int, np.ndarray] | None = None


def ground_truth(motion: ScenarioConfig) -> Trajectory:
    """Poses T_wc (Magnus-integrated) and body twists [w; v] at the frame times of ``motion``."""
    t = np.arange(motion.num_frames) / motion.fps
    rotations, positions = integrate_poses(motion, t)
    return Trajectory(t, rotations, positions, body_twist(motion, t))


def check_view(camera: CameraModel, plane: Plane, truth: Trajectory) -> tuple[float, float]:
    """Check that every frame sees the plane over the whole image; return the distance range.

    In camera k the plane is n_k^T X = d_k with n_k = R_wc^T n*, d_k = d* - n*^T p_wc.
    The camera is in front when d_k > 0, and the ray of a normalized point m meets the
    plane in front of the camera when n_k^T m > 0: linear in m, so the four image corners
    decide for the whole (convex) image. The texture tiles the plane, so a frame that
    meets the plane everywhere is textured everywhere.

    Returns:
        (min, max) of d_k over the frames, metres.
    Raises:
        InputError: naming the first frame that fails.
    """
    n = np.asarray(plane.normal, dtype=float)
    w, h = camera.width - 1.0, camera.height - 1.0
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    m = camera.pixel_to_normalized(corners)
    distances = plane.distance - np.asarray(truth.positions) @ n
    for k, (R_wc, d_k) in enumerate(zip(truth.rotations, distances, strict=True)):
        if not d_k > 0:
            raise InputError(
                f"frame {k} (t = {truth.t[k]:.3f} s): the camera is not in front of the plane"
            )
        if np.any(m @ (R_wc.T @ n) <= 0):
            raise InputError(
                f"frame {k} (t = {truth.t[k]:.3f} s): an image corner looks past the plane's "
                "horizon (part of the image would be untextured)"
            )
    return float(distances.min()), float(distances.max())


def _chunk_seed(seed: int, chunk: int) -> int:
    """Independent noise seed of each rendered chunk of frames."""
    return int(np.random.SeedSequence([seed, chunk]).generate_state(1)[0])


def _texture(config: ImageRunConfig) -> np.ndarray:
    side = _TEXTURE_FOOTPRINTS * max(config.camera.width, config.camera.height)
    return make_texture(side, seed=config.seed)


def render_chunk(
    config: ImageRunConfig, plane: Plane, truth: Trajectory, texture: np.ndarray, chunk: int
) -> list[np.ndarray]:
    """The images of frames [chunk * 30, (chunk + 1) * 30), uint8 (height, width)."""
    start = chunk * _CHUNK_FRAMES
    stop = min(len(truth), start + _CHUNK_FRAMES)
    poses = list(zip(truth.rotations[start:stop], truth.positions[start:stop], strict=True))
    return render_plane_images(
        config.camera,
        plane,
        poses,
        texture=texture,
        noise_sigma=config.image_noise,
        seed=_chunk_seed(config.seed, chunk),
    )


def render_stream(
    config: ImageRunConfig, plane: Plane, truth: Trajectory, texture: np.ndarray
) -> Iterator[np.ndarray]:
    """Every frame's image, rendered a chunk at a time (bounded memory)."""
    for chunk in range(-(-len(truth) // _CHUNK_FRAMES)):
        yield from render_chunk(config, plane, truth, texture, chunk)


def track_error(
    tracks: Sequence[FrameObservations], truth: Trajectory, camera: CameraModel, plane: Plane
) -> float:
    """RMS per coordinate (pixels) of every observation after a track's first one.

    Each track's plane point is its first observation back-projected through the true
    pose (ray-plane intersection); later observations are compared with that point's
    projection through the true poses. This is the error the front end sees: a pose is
    measured from where the points are now against where they were in the reference.
    """
    n, d = np.asarray(plane.normal, dtype=float), plane.distance
    first: dict[int, np.ndarray] = {}
    squared, count = 0.0, 0
    for obs in tracks:
        R_wc, p_wc = truth.rotations[obs.index], truth.positions[obs.index]
        ids = np.asarray(obs.ids).tolist()
        rays = camera.pixel_to_normalized(np.asarray(obs.uv, dtype=float)) @ R_wc.T
        known = np.array([i in first for i in ids], dtype=bool)
        for i, ray in zip(np.asarray(ids)[~known], rays[~known], strict=True):
            first[int(i)] = p_wc + (d - n @ p_wc) / (n @ ray) * ray
        if known.any():
            X = np.array([first[i] for i, k in zip(ids, known, strict=True) if k])
            uv = camera.project((X - p_wc) @ R_wc)
            diff = uv - np.asarray(obs.uv, dtype=float)[known]
            squared += float(np.sum(diff**2))
            count += diff.size
    return math.sqrt(squared / count) if count else float("nan")


def pose_nees(frames: Sequence[FrameMeasurement], truth: Trajectory) -> tuple[float | None, ...]:
    """Mean NEES of the pose measurements against frame 0 and against keyframes.

    delta = Log(T_meas^-1 T_true) with T the pose in the reference frame (right
    perturbation, the covariance's convention), NEES = delta^T C^-1 delta; 6 on average
    when the covariance C describes the error. Frame 0 itself (exact by construction)
    is left out.

    Returns:
        (mean NEES against frame 0, mean NEES against keyframes); None where no frame.
    """
    poses = [
        gtsam.Pose3(gtsam.Rot3(R), p) for R, p in zip(truth.rotations, truth.positions, strict=True)
    ]
    world, keyframe = [], []
    for f in frames:
        if f.pose is None or f.index == f.pose.reference:
            continue
        measured = gtsam.Pose3(gtsam.Rot3(f.pose.rotation), np.asarray(f.pose.position))
        true_relative = poses[f.pose.reference].between(poses[f.index])
        delta = gtsam.Pose3.Logmap(measured.between(true_relative))
        value = float(delta @ np.linalg.solve(f.pose.covariance, delta))
        (world if f.pose.reference == 0 else keyframe).append(value)
    return tuple(float(np.mean(v)) if v else None for v in (world, keyframe))


def keyframe_switches(frames: Sequence[FrameMeasurement]) -> tuple[list[int], list[int]]:
    """(first frame against each new keyframe, the keyframes), in time order."""
    switches, keyframes, current = [], [], 0
    for f in frames:
        if f.pose is not None and f.pose.reference != current:
            current = f.pose.reference
            switches.append(f.index)
            keyframes.append(current)
    return switches, keyframes


def _segment_rmse(series: ErrorSeries, start: float, stop: float) -> float | None:
    keep = (series.t >= start - 1e-9) & (series.t < stop - 1e-9)
    e = series.position[keep]
    return float(math.sqrt(np.mean(e**2))) if e.size else None


def run_methods(frames: Sequence[FrameMeasurement], seed: int) -> dict[str, Trajectory]:
    """Every method of :data:`METHODS` on the same measurements (one ISAM2 run for both
    smoother rows)."""
    runs = MethodRuns(lambda _solver: frames, seed)
    out: dict[str, Trajectory] = {}
    for label in METHODS:
        try:
            out[label] = runs.trajectory(label)
        except InputError as exc:
            raise InputError(f"seed {seed}, method {label}: {exc}") from exc
    return out


def run_image_seed(config: ImageRunConfig, *, keep: bool = False) -> ImageSeedResult:
    """Render, track, measure and estimate one seed; errors against the ground truth.

    Args:
        config: the run.
        keep: keep the ground truth, the estimates and a sample frame (for the figures).
    Raises:
        InputError: a motion that leaves the plane's view, or an estimator's InputError
            naming the seed and method.
    """
    motion = config.motion()
    camera, plane = config.camera, motion.plane
    truth = ground_truth(motion)
    distance_range = check_view(camera, plane, truth)
    texture = _texture(config)
    start = time.perf_counter()
    tracks = track_images(render_stream(config, plane, truth, texture), truth.t, camera)
    frames = measure_sequence(tracks, camera, plane, config.front_end())
    middle = time.perf_counter()
    trajectories = run_methods(frames, config.seed)
    seconds = (middle - start, time.perf_counter() - middle)

    t_start = float(truth.t[0]) + config.skip
    switches, keyframes = keyframe_switches(frames)
    t_switch = float(truth.t[switches[0]]) if switches else None
    summaries, segments = {}, {}
    for label, trajectory in trajectories.items():
        series = error_series(trajectory, truth)
        summaries[label] = summarize(series, t_start=t_start)
        if t_switch is None:
            segments[label] = (_segment_rmse(series, t_start, math.inf), None)
        else:
            segments[label] = (
                _segment_rmse(series, t_start, t_switch),
                _segment_rmse(series, max(t_start, t_switch), math.inf),
            )
    nees_world, nees_keyframe = pose_nees(frames, truth)
    result = ImageSeedResult(
        seed=config.seed,
        config=config,
        summaries=summaries,
        segments=segments,
        switches=switches,
        keyframes=keyframes,
        tracks_per_frame=np.array([len(o.ids) for o in tracks]),
        frames_with_pose=sum(f.pose is not None for f in frames),
        frames_with_velocity=sum(f.velocity is not None for f in frames),
        track_error_px=track_error(tracks, truth, camera, plane),
        nees_world=nees_world,
        nees_keyframe=nees_keyframe,
        distance_range=distance_range,
        seconds=seconds,
    )
    if keep:
        result.truth = truth
        result.trajectories = trajectories
        # The first keyframe, seen while still measured against frame 0: few points left.
        k = switches[0] - 1 if switches else len(frames) // 2
        image = render_chunk(config, plane, truth, texture, k // _CHUNK_FRAMES)[k % _CHUNK_FRAMES]
        pose = frames[k].pose
        reference = -1 if pose is None else pose.reference
        ids = tracks[reference].ids if pose is not None else np.empty(0, dtype=int)
        shared = np.intersect1d(np.asarray(tracks[k].ids), np.asarray(ids))
        history = list(tracks[max(0, k - _TRAIL_FRAMES) : k + 1])
        result.sample = (k, image, history, reference, shared)
    return result


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
        "### Tracking, keyframes and measurement consistency per seed",
        "",
        "Track error: RMS per coordinate of every observation against the projection of the "
        "plane point the track was first seen at (ground truth). NEES: mean over frames of "
        "delta^T C^-1 delta of the pose measurements (delta = Log(T_meas^-1 T_true) in the "
        "reference frame, C the front end's covariance), against frame 0 and against "
        "keyframes; about 6 when C describes the error, far above 6 when an error source is "
        "missing from C.",
        "",
        seed_table(results),
        "",
        "### Methods",
        "",
        "- raw measurements (`measurements`): the front end's per-frame pose (H_d, composed "
        "with the measured keyframe pose) and twist (H_c), no fusion.",
        "- Kalman (`kalman`): the paper's 12-state filter with the paper's noisy-run R_k.",
        "- Kalman, measured R (`kalman-measured`): the same filter with R_k from the front "
        "end's covariances and the smoother's process noise (hvo_graph.experiment).",
        "- ISAM2 smoothed / online (`smoother`, `smoother-online`): the factor graph, keyframe "
        "poses as between factors; final values, and each frame right after its update.",
        "- fixed-lag (`fixed-lag`): the same graph in a 1 s window.",
    ]
    if figures:
        lines += ["", "### Figures", ""]
        lines += [f"![{Path(f).stem.replace('_', ' ')}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


# -- figures -----------------------------------------------------------------------------

_FIGURE_METHODS = ("measurements", "kalman", "kalman-measured", "smoother")


def _euler_degrees(rotations: np.ndarray) -> np.ndarray:
    """(K, 3) roll, pitch, yaw in degrees (hvo_graph.geometry.rotation.rotation_to_euler)."""
    return np.degrees(np.array([rotation_to_euler(R) for R in rotations]))


def plot_trajectory(result: ImageSeedResult, path: Path) -> list[Path]:
    """Position and orientation against time (truth and estimates) over their errors, with
    the keyframe switches as vertical lines."""
    from hvo_graph.report.plotting import (
        TRUTH_STYLE,
        figure_style,
        log_axis,
        method_style,
        new_figure,
        save_figure,
    )

    truth = result.truth
    if truth is None:
        raise InputError("plot_trajectory: the seed was run without keep=True")
    components = (("x", "y", "z"), ("roll", "pitch", "yaw"))
    component_colors = ("#0072B2", "#009E73", "#D55E00")
    with figure_style():
        fig, axes = new_figure(*TRAJECTORY_FIGSIZE, nrows=2, ncols=2, sharex=True)
        truth_values = (np.asarray(truth.positions), _euler_degrees(truth.rotations))
        smoothed = result.trajectories["smoother"]
        estimate_values = (np.asarray(smoothed.positions), _euler_degrees(smoothed.rotations))
        for ax, names, true, est in zip(
            axes[0], components, truth_values, estimate_values, strict=True
        ):
            for i, (name, color) in enumerate(zip(names, component_colors, strict=True)):
                ax.plot(truth.t, true[:, i], color="#000000", linestyle="--", linewidth=1.0)
                ax.plot(smoothed.t, est[:, i], color=color, linewidth=1.4, label=name)
            ax.legend(loc="upper left", ncols=3)
        axes[0, 0].set_title("position: ISAM2 smoothed (solid), truth (dashed)")
        axes[0, 0].set_ylabel("position [m]")
        axes[0, 1].set_title("orientation (Euler angles): ISAM2 smoothed, truth")
        axes[0, 1].set_ylabel("angle [deg]")
        for ax, quantity, unit in zip(
            axes[1], ("position", "orientation"), ("m", "deg"), strict=True
        ):
            low, high = [], []
            for label in _FIGURE_METHODS:
                series = error_series(result.trajectories[label], truth)
                e = getattr(series, quantity)
                ok = e > 0
                ax.plot(series.t[ok], e[ok], **method_style(label))
                evaluated = e[ok & (series.t >= truth.t[0] + result.config.skip - 1e-9)]
                low.append(evaluated.min())
                high.append(evaluated.max())
            log_axis(ax)
            # Frame 0 is exact by construction: the lower limit comes from the evaluated frames.
            ax.set_ylim(0.5 * min(low), 1.5 * max(high))
            ax.set_title(f"{quantity} error")
            ax.set_ylabel(f"{quantity} error [{unit}]")
            ax.set_xlabel("time [s]")
        for ax in axes.flat:
            for k, s in enumerate(result.switches):
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
        c = result.config
        fig.suptitle(
            f"Rendered images, seed {result.seed}: {c.camera.width} x {c.camera.height} px, "
            f"{c.fps:g} fps, image noise {c.image_noise:g}; dotted lines: keyframe switches"
        )
        return save_figure(fig, path)


def plot_tracks(result: ImageSeedResult, path: Path) -> Path:
    """The sample frame with the trails of its tracks: points shared with the frame's pose
    reference (used for H_d) and the others (used for H_c only). PNG only."""
    from hvo_graph.report.plotting import FIGURE_DPI, figure_style, new_figure

    if result.sample is None:
        raise InputError("plot_tracks: the seed was run without keep=True")
    k, image, history, reference, shared = result.sample
    current = history[-1]
    with figure_style():
        fig, axes = new_figure(*TRACKS_FIGSIZE)
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
                uv[0],
                uv[1],
                "o",
                color=color,
                markersize=3,
                label=label if used not in drawn else None,
            )
            drawn.add(used)
        ax.set_xlim(-0.5, image.shape[1] - 0.5)
        ax.set_ylim(image.shape[0] - 0.5, -0.5)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.grid(False)
        ax.legend(loc="lower left", framealpha=0.9)
        c = result.config
        switch = "" if not result.switches else f"; the next frame takes frame {k} as keyframe"
        ax.set_title(
            f"Seed {result.seed}, frame {k} (t = {k / c.fps:.2f} s): {len(current.ids)} KLT "
            f"tracks, trails over {len(history) - 1} frames\npose against frame {reference}"
            f"{switch}"
        )
        path = Path(path).with_suffix(".png")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.png")
        fig.savefig(tmp, format="png", dpi=FIGURE_DPI, metadata={"Software": None})
        os.replace(tmp, path)
        return path


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
                result = run_image_seed(config, keep=i == 0)
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
    print(seed_table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
