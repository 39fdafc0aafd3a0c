"""From observations to a trajectory in one call: front end + estimator.

This is what the command line's ``estimate`` runs, and the shortest way to use
the library from an offline pipeline::

    from hvo_graph.io.config import load_scene
    from hvo_graph.io.tracks import read_tracks
    from hvo_graph.pipeline import estimate

    scene = load_scene("camera.yaml")
    trajectory = estimate(read_tracks("tracks.csv"), scene, method="smoother")
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.registry import (
    COMMAND_METHODS,
    EstimatorOptions,
    build_estimator,
    check_applicable,
)
from hvo_graph.estimators.registry import method as registry_method
from hvo_graph.frontend import (
    DEFAULT_PIXEL_SIGMA,
    FrontEndConfig,
    MeasurementFrontEnd,
    measure_sequence,
)
from hvo_graph.frontend.health import front_end_health
from hvo_graph.frontend.pixel_noise import PixelNoiseEstimate, estimate_pixel_sigma
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.plane_normal import NormalFit
from hvo_graph.measurement_table import frame_columns
from hvo_graph.types import FrameMeasurement, FrameObservations, Plane, Trajectory

#: Every ``--method`` (:data:`hvo_graph.estimators.registry.COMMAND_METHODS`); the
#: first is the default.
METHODS: tuple[str, ...] = COMMAND_METHODS


class SceneLike(Protocol):
    camera: CameraModel
    plane: Plane
    pixel_sigma: float | None


#: Front-end options of :func:`measure` / :func:`estimate` (every method reads them).
FRONT_END_OPTIONS: tuple[str, ...] = (
    "pixel_sigma",
    "ransac",
    "ransac_threshold_px",
    "outlier_chi2",
    "reject_after",
)


def make_estimator(method: str = "smoother", **options: object) -> Estimator:
    """Build the estimator behind ``--method`` (the factory of its registry row).

    Args:
        method: one of :data:`METHODS`.
        options: :class:`~hvo_graph.estimators.registry.EstimatorOptions` fields,
            e.g. ``seed`` (the Kalman filter's random initial state), ``kalman_r``
            ("paper-noisy", "paper-noise-free", "measured"), ``lag`` (fixed-lag
            window, s), ``robust`` / ``robust_threshold``, ``covariance``,
            ``acceleration_sigma`` ("auto" or numbers), ``shared_reference_noise``,
            ``velocity_factors``, ``motion_model``, ``relinearize_threshold``,
            ``relinearize_skip``.
    Raises:
        InputError: an unknown method or option, or an option that does not apply
            to ``method`` (never silently ignored).
    """
    _check_method(method)
    check_applicable(method, options)
    options.pop("online", None)
    return build_estimator(method, EstimatorOptions(**options))  # type: ignore[arg-type]


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise InputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")


def front_end_config(
    scene: SceneLike, *, method: str = "smoother", **options: object
) -> FrontEndConfig:
    """The front end's settings for ``method`` on ``scene`` (pixel noise from the scene
    unless ``pixel_sigma`` is given; the pose solver of the method's registry row).

    Args:
        options: :data:`FRONT_END_OPTIONS` (``FrontEndConfig`` fields).
    """
    unknown = sorted(set(options) - set(FRONT_END_OPTIONS))
    if unknown:
        raise InputError(
            f"{unknown[0]}: unknown front-end option, expected one of "
            f"{', '.join(FRONT_END_OPTIONS)}"
        )
    given = dict(options)
    sigma = next(
        (s for s in (given.pop("pixel_sigma", None), scene.pixel_sigma) if s is not None),
        DEFAULT_PIXEL_SIGMA,
    )
    return FrontEndConfig(
        pixel_sigma=sigma,
        pose_solver=registry_method(method).pose_solver,
        **given,  # type: ignore[arg-type]
    )


def measure(
    observations: Sequence[FrameObservations],
    scene: SceneLike,
    *,
    method: str = "smoother",
    **front_end: object,
) -> list[FrameMeasurement]:
    """Per-frame measurements for ``method``: with its registry row's pose solver
    (IPPE poses for "ippe", H_d otherwise) and the :data:`FRONT_END_OPTIONS` given
    (without a pixel sigma, given or in ``scene``: the tracks' own, :func:`pixel_noise`)."""
    check_plane(observations, scene, method)
    pixel_noise(observations, scene, front_end)
    config = front_end_config(scene, method=method, **front_end)
    return measure_sequence(observations, scene.camera, scene.plane, config)


def check_plane(
    observations: Sequence[FrameObservations], scene: SceneLike, method: str = "smoother"
) -> None:
    """An InputError naming ``plane.normal`` when ``method`` needs n* and the scene has
    none (IPPE), or when most points of the first frame with points lie behind the plane
    as given (n*^T m <= 0 for their normalized rays m): n* points from the camera
    towards the plane, and a flipped sign would otherwise give a mirrored motion or a
    failure deep in the front end."""
    normal = scene.plane.normal
    if normal is None and registry_method(method).pose_solver == "ippe":
        raise InputError(
            f"plane.normal: required by method {method!r} (IPPE does not estimate n*; "
            "the homography methods do)"
        )
    first = next((o for o in observations if len(o.ids)), None)
    if normal is None or first is None:
        return
    m = scene.camera.pixel_to_normalized(np.asarray(first.uv, dtype=float).reshape(-1, 2))
    behind = int(np.count_nonzero(m @ np.asarray(normal) <= 0))
    if 2 * behind > len(m):
        flipped = ", ".join(f"{0.0 - float(c):g}" for c in normal)
        raise InputError(
            f"plane.normal: {behind} of the {len(m)} points of frame {first.index} are behind "
            f"the plane as given (n*^T m <= 0); n* points from the camera towards the plane "
            f"(the flipped normal would be [{flipped}])"
        )


def pixel_noise(
    observations: Sequence[FrameObservations], scene: SceneLike, front_end: dict[str, object]
) -> PixelNoiseEstimate | None:
    """The pixel noise read from the tracks when neither ``front_end["pixel_sigma"]`` nor
    the scene gives it (:func:`~hvo_graph.frontend.pixel_noise.estimate_pixel_sigma`);
    None when given, or too few tracks to tell.

    Only an estimate above :data:`DEFAULT_PIXEL_SIGMA` (the paper's noise, in force
    otherwise) is set as ``front_end["pixel_sigma"]``: the differences see a tracker's
    frame-to-frame noise, not errors that neighbouring tracks share or that drift. On
    rendered 640x480 images KLT's differences give 0.008 px while the H_d poses err as
    if from 0.04 px (pose NEES ~20 with 0.008), so a lower estimate is reported, not used.
    """
    if front_end.get("pixel_sigma") is not None or scene.pixel_sigma is not None:
        return None
    noise = estimate_pixel_sigma(observations)
    if noise is not None and noise.sigma > DEFAULT_PIXEL_SIGMA:
        front_end["pixel_sigma"] = noise.sigma
    return noise


@dataclass
class EstimateRun:
    """Everything one :func:`run_estimate` did, for reports (``run.json``).

    Attributes:
        method: the method.
        trajectory: the final (or, with ``online``, causal) estimate.
        estimator: the estimator after the run (fitted noise, counts).
        frames: the front end's measurements (a
            :class:`~hvo_graph.measurement_table.MeasurementTable` from :func:`run_estimate`).
        front_end: the front end's settings in force.
        options: the estimator options given.
        excluded_tracks: track ids the front end left out as off the plane.
        normal_fit: n* fitted to the whole sequence when the scene did not give it
            (:func:`~hvo_graph.frontend.normal_search.sequence_normal`), else None.
        pixel_noise: the pixel noise read from the tracks when neither the options nor
            the scene gave it (:func:`pixel_noise`; in force when it is
            ``front_end.pixel_sigma``), else None.
    """

    method: str
    trajectory: Trajectory
    estimator: Estimator
    frames: Sequence[FrameMeasurement]
    front_end: FrontEndConfig
    options: dict[str, object]
    excluded_tracks: frozenset[int] = frozenset()
    normal_fit: NormalFit | None = None
    pixel_noise: PixelNoiseEstimate | None = None

    def summary(self) -> dict[str, object]:
        """The run as plain values: settings in force, noise chosen, data rejected, and the
        front end's health (:func:`~hvo_graph.frontend.health.front_end_health`)."""
        est = self.estimator
        defaults = EstimatorOptions()
        applicable = [o for o in registry_method(self.method).options if o != "online"]
        settings: dict[str, object] = {o: getattr(defaults, o) for o in applicable}
        settings.update(self.options)
        sigma = getattr(est, "acceleration_sigma", None)
        if sigma is not None:
            settings["acceleration_sigma"] = list(sigma)
            fit = getattr(getattr(est, "process_noise", None), "fit", None)
            settings["acceleration_sigma_fitted"] = fit is not None
        if isinstance(getattr(est, "motion_model", None), str):
            settings["motion_model"] = est.motion_model  # "auto" resolved
        if hasattr(est, "process_noise") and not hasattr(est, "acceleration_sigma"):
            settings["kalman_process_noise"] = [float(q) for q in est.process_noise]
            if settings.get("acceleration_sigma") == "auto":  # the filter's own Q_k
                settings.pop("acceleration_sigma")
        columns = frame_columns(self.frames)
        counts = {
            "frames": len(self.frames),
            "frames_with_pose": int(columns.has_pose.sum()),
            "frames_with_velocity": int(columns.has_velocity.sum()),
            "points": int(columns.num_points.sum()),
            "rejected_points": int(columns.num_rejected.sum()),
            "frames_with_rejections": int((columns.num_rejected > 0).sum()),
            "excluded_tracks": sorted(self.excluded_tracks),
        }
        if hasattr(est, "velocity_factor_counts"):
            counts["velocity_factors"] = dict(est.velocity_factor_counts)
        if hasattr(est, "rejected_tracks"):  # the tightly coupled smoother's own gate
            counts["landmarks"] = est.counts["landmarks"]
            counts["pixel_observations"] = est.counts["observations"]
            counts["off_plane_tracks"] = sorted(est.rejected_tracks)
        return {
            "method": self.method,
            "options": settings,
            "front_end": {
                k: getattr(self.front_end, k) for k in self.front_end.__dataclass_fields__
            }
            | {"ransac_px_in_force": self.front_end.ransac_px},
            "counts": counts,
            "front_end_health": front_end_health(self.frames).as_dict(),
            **({"plane_normal_fit": self._normal_summary()} if self.normal_fit else {}),
            **(
                {"pixel_noise_estimated": {**dataclasses.asdict(self.pixel_noise), "used": used}}
                if (used := self.pixel_noise_used) is not None
                else {}
            ),
        }

    @property
    def pixel_noise_used(self) -> bool | None:
        """Whether the pixel noise read from the tracks is in force (None: none read)."""
        if self.pixel_noise is None:
            return None
        return self.front_end.pixel_sigma == self.pixel_noise.sigma

    def _normal_summary(self) -> dict[str, object]:
        fit = self.normal_fit
        assert fit is not None
        return {
            "normal": [float(x) for x in fit.normal],
            "sigma_deg": fit.sigma_deg,
            "frames": len(fit.motions),
            "translation_chi2": fit.translation_chi2,
        }


def run_estimate(
    observations: Sequence[FrameObservations],
    scene: SceneLike,
    method: str = "smoother",
    *,
    online: bool = False,
    **options: object,
) -> EstimateRun:
    """:func:`estimate`, keeping what a report needs (the estimator, the measurements)."""
    _check_method(method)
    front = {k: options.pop(k) for k in list(options) if k in FRONT_END_OPTIONS}
    check_plane(observations, scene, method)
    noise = pixel_noise(observations, scene, front)
    if online:
        options["online"] = True
    estimator = make_estimator(method, **options)
    config = front_end_config(scene, method=method, **front)
    front_end = MeasurementFrontEnd(scene.camera, scene.plane, config)
    frames = front_end.process_table(observations)
    _check_measured(frames, front_end, method)
    smoothed = estimator.run(frames, online=online)
    trajectory = estimator.online_trajectory() if online else smoothed
    if not options.get("covariance") and trajectory.covariances is not None:
        trajectory = dataclasses.replace(trajectory, covariances=None)
    options.pop("online", None)
    return EstimateRun(
        *(method, trajectory, estimator, frames, config, options),
        front_end.excluded_tracks,
        front_end.normal_fit,
        noise,
    )


def _check_measured(
    frames: Sequence[FrameMeasurement], front_end: MeasurementFrontEnd, method: str
) -> None:
    """An InputError when nothing of a sequence could be measured: its trajectory would be
    the motion model's start state alone, whatever the camera did."""
    if len(frames) < 2:
        return
    if front_end.normal is None:
        raise InputError(
            "plane.normal: not given, and the sequence has too little parallax to estimate it "
            "(no frame moved 5 % of d* while sharing 4 points with the first); "
            "give plane.normal in the camera file"
        )
    columns = frame_columns(frames)
    if not method.startswith("tight") and not (
        columns.has_pose[1:].any() or columns.has_velocity.any()
    ):
        raise InputError(
            "tracks: no frame could be measured (none shares 4 points, not on one line, "
            "with the first frame or with the frame before it)"
        )


def estimate(
    observations: Sequence[FrameObservations],
    scene: SceneLike,
    method: str = "smoother",
    *,
    online: bool = False,
    **options: object,
) -> Trajectory:
    """Estimate the trajectory of a tracked sequence.

    Args:
        observations: frames of tracked points (contract tracks CSV).
        scene: camera, plane (d*, optionally n*) and pixel noise (contract YAML).
        method: one of :data:`METHODS`.
        online: return the causal (filtered) estimate of each frame instead of
            the final (smoothed) one (methods with "online" in their options).
        options: front-end options (:data:`FRONT_END_OPTIONS`: ``pixel_sigma``,
            ``ransac``, ``ransac_threshold_px``, ``outlier_chi2``, ``reject_after``)
            and estimator options (:func:`make_estimator`), e.g.
            ``estimate(obs, scene, acceleration_sigma=0.1)``.
    Returns:
        One pose and twist per frame (and covariances when ``covariance=True``).
    Raises:
        InputError: bad input, or an option that does not apply to ``method``.
    """
    return run_estimate(observations, scene, method, online=online, **options).trajectory
