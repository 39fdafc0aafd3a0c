"""One seed of rendered images through the whole pipeline: render, track, measure, estimate.

The library side of ``experiments/images.py``. A seed's motion is the paper's
body-twist pattern with larger linear amplitudes (:data:`LINEAR_AMPLITUDE`),
integrated on SE(3) (:func:`hvo_graph.sim.images.ground_truth`); the frames are
rendered from a seeded procedural texture with image noise
(:func:`hvo_graph.sim.images.render_stream`), tracked with OpenCV's KLT, measured
by the front end (keyframes when the reference points leave) and estimated by
every method (:class:`hvo_graph.montecarlo.MethodRuns`). The result holds the
errors against the ground truth, before and after the first keyframe switch,
and the front end's consistency (:mod:`hvo_graph.eval.consistency`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_TITLES
from hvo_graph.eval.consistency import (
    keyframe_switches,
    pose_nees,
    track_error,
    trajectory_nees,
)
from hvo_graph.eval.metrics import ErrorSummary, error_series, position_rmse_between, summarize
from hvo_graph.eval.stats import mean_ci
from hvo_graph.frontend import FrontEndConfig, measure_sequence
from hvo_graph.frontend.tracking import track_images
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.montecarlo import MethodRuns
from hvo_graph.report.tables import format_ci, markdown_table
from hvo_graph.sim.images import (
    check_view,
    ground_truth,
    plane_texture,
    render_frame,
    render_stream,
)
from hvo_graph.sim.scenario import ScenarioConfig, default_camera, paper_scenario
from hvo_graph.types import FrameMeasurement, FrameObservations, Trajectory

#: Seconds: three keyframe switches with the default motion and camera.
DEFAULT_DURATION = 15.0
#: Frames per second.
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

#: Frames of track history drawn in the tracks figure.
TRAIL_FRAMES = 12


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
        estimate_nees: per method with covariances, (pose, twist) mean NEES per degree of
            freedom of its estimates after ``config.skip`` seconds.
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
    estimate_nees: dict[str, tuple[float, float]] = field(default_factory=dict)
    truth: Trajectory | None = None
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    sample: tuple[int, np.ndarray, list[FrameObservations], int, np.ndarray] | None = None


def run_methods(
    frames: Sequence[FrameMeasurement],
    methods: Sequence[str],
    seed: int,
    *,
    covariance: bool = False,
) -> dict[str, Trajectory]:
    """Every method on the same measurements (one ISAM2 run for both smoother rows);
    ``covariance``: the smoothers report their covariances too."""
    runs = MethodRuns(lambda _solver: frames, seed, covariance=covariance, methods=methods)
    out: dict[str, Trajectory] = {}
    for label in methods:
        try:
            out[label] = runs.trajectory(label)
        except InputError as exc:
            raise InputError(f"seed {seed}, method {label}: {exc}") from exc
    return out


def run_image_seed(
    config: ImageRunConfig, methods: Sequence[str], *, keep: bool = False
) -> ImageSeedResult:
    """Render, track, measure and estimate one seed; errors against the ground truth.

    Args:
        config: the run.
        methods: names from :data:`~hvo_graph.estimators.registry.METHOD_LABELS`
            (homography front end only).
        keep: keep the ground truth, the estimates and a sample frame (for the figures).
    Raises:
        InputError: a motion that leaves the plane's view, or an estimator's InputError
            naming the seed and method.
    """
    motion = config.motion()
    camera, plane = config.camera, motion.plane
    truth = ground_truth(motion)
    distance_range = check_view(camera, plane, truth)
    texture = plane_texture(camera, config.seed)
    rendering = {"noise_sigma": config.image_noise, "seed": config.seed}
    start = time.perf_counter()
    tracks = track_images(
        render_stream(camera, plane, truth, texture, **rendering), truth.t, camera
    )
    frames = measure_sequence(tracks, camera, plane, config.front_end())
    middle = time.perf_counter()
    trajectories = run_methods(frames, methods, config.seed, covariance=True)
    seconds = (middle - start, time.perf_counter() - middle)

    t_start = float(truth.t[0]) + config.skip
    switches, keyframes = keyframe_switches(frames)
    t_switch = float(truth.t[switches[0]]) if switches else None
    summaries, segments, estimate_nees = {}, {}, {}
    for label, trajectory in trajectories.items():
        series = error_series(trajectory, truth)
        summaries[label] = summarize(series, t_start=t_start)
        if trajectory.covariances is not None:
            estimate_nees[label] = trajectory_nees(trajectory, truth, t_start=t_start)
        if t_switch is None:
            segments[label] = (position_rmse_between(series, t_start, math.inf), None)
        else:
            segments[label] = (
                position_rmse_between(series, t_start, t_switch),
                position_rmse_between(series, max(t_start, t_switch), math.inf),
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
        estimate_nees=estimate_nees,
    )
    if keep:
        result.truth = truth
        result.trajectories = trajectories
        # The first keyframe, seen while still measured against frame 0: few points left.
        k = switches[0] - 1 if switches else len(frames) // 2
        image = render_frame(camera, plane, truth, texture, k, **rendering)
        pose = frames[k].pose
        reference = -1 if pose is None else pose.reference
        ids = tracks[reference].ids if pose is not None else np.empty(0, dtype=int)
        shared = np.intersect1d(np.asarray(tracks[k].ids), np.asarray(ids))
        history = list(tracks[max(0, k - TRAIL_FRAMES) : k + 1])
        result.sample = (k, image, history, reference, shared)
    return result


def nees_table(results: Sequence[ImageSeedResult], methods: Sequence[str]) -> str:
    """Markdown table: per method with covariances on every seed, the mean over seeds of
    its pose and twist NEES per degree of freedom with 95 % confidence half-widths."""
    rows = []
    for label in methods:
        if results and all(label in r.estimate_nees for r in results):
            values = np.array([r.estimate_nees[label] for r in results])
            pose, twist = values[:, 0], values[:, 1]
            title = f"{METHOD_TITLES[label]} (`{label}`)"
            rows.append([title, format_ci(mean_ci(pose)), format_ci(mean_ci(twist))])
    return markdown_table(["method", "pose NEES per dof", "twist NEES per dof"], rows)
