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

from collections.abc import Sequence
from typing import Protocol

from hvo_graph.errors import InputError
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.registry import (
    COMMAND_METHODS,
    DEFAULT_LAG,
    EstimatorOptions,
    build_estimator,
)
from hvo_graph.estimators.registry import method as registry_method
from hvo_graph.frontend import DEFAULT_PIXEL_SIGMA, FrontEndConfig, measure_sequence
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import FrameMeasurement, FrameObservations, Plane, Trajectory

#: Every ``--method`` (:data:`hvo_graph.estimators.registry.COMMAND_METHODS`); the
#: first is the default.
METHODS: tuple[str, ...] = COMMAND_METHODS


class SceneLike(Protocol):
    camera: CameraModel
    plane: Plane
    pixel_sigma: float | None


def make_estimator(
    method: str = "smoother",
    *,
    seed: int | None = 0,
    kalman_r: str = "paper-noisy",
    kalman_world_velocity: bool = False,
    lag: float = DEFAULT_LAG,
    robust: str | None = None,
    covariance: bool = False,
) -> Estimator:
    """Build the estimator behind ``--method`` (the factory of its registry row).

    Args:
        method: one of :data:`METHODS`.
        seed: random initial state of the Kalman filter (paper); None for unseeded.
        kalman_r: R_k preset of the Kalman filter: "paper-noisy",
            "paper-noise-free" or "measured" (front-end covariances, diagonal).
        kalman_world_velocity: rotate measured v into the world frame before the
            Kalman update (not the paper's form).
        lag: window of the fixed-lag smoother, seconds.
        robust: None, "huber" or "cauchy" loss on the smoother's measurement factors.
        covariance: smoothers also return per-frame marginal covariances.
    """
    _check_method(method)
    options = EstimatorOptions(
        seed=seed,
        kalman_r=kalman_r,
        kalman_world_velocity=kalman_world_velocity,
        lag=lag,
        robust=robust,
        covariance=covariance,
    )
    return build_estimator(method, options)


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise InputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")


def measure(
    observations: Sequence[FrameObservations],
    scene: SceneLike,
    *,
    method: str = "smoother",
    pixel_sigma: float | None = None,
    ransac_threshold_px: float | None = None,
) -> list[FrameMeasurement]:
    """Per-frame measurements for ``method``: with its registry row's pose solver
    (IPPE poses for "ippe", H_d otherwise)."""
    sigma = next(
        (s for s in (pixel_sigma, scene.pixel_sigma) if s is not None), DEFAULT_PIXEL_SIGMA
    )
    config = FrontEndConfig(
        pixel_sigma=sigma,
        ransac_threshold_px=ransac_threshold_px,
        pose_solver=registry_method(method).pose_solver,
    )
    return measure_sequence(observations, scene.camera, scene.plane, config)


def estimate(
    observations: Sequence[FrameObservations],
    scene: SceneLike,
    method: str = "smoother",
    *,
    online: bool = False,
    pixel_sigma: float | None = None,
    ransac_threshold_px: float | None = None,
    **options: object,
) -> Trajectory:
    """Estimate the trajectory of a tracked sequence.

    Args:
        observations: frames of tracked points (contract tracks CSV).
        scene: camera, plane (d*, optionally n*) and pixel noise (contract YAML).
        method: one of :data:`METHODS`.
        online: return the causal (filtered) estimate of each frame instead of
            the final (smoothed) one.
        pixel_sigma: overrides the scene's pixel noise (pixels).
        ransac_threshold_px: reject outlier tracks with RANSAC on H_d.
        options: passed to :func:`make_estimator`.
    Returns:
        One pose and twist per frame (and covariances when requested).
    """
    _check_method(method)
    estimator = make_estimator(method, **options)  # type: ignore[arg-type]
    frames = measure(
        observations,
        scene,
        method=method,
        pixel_sigma=pixel_sigma,
        ransac_threshold_px=ransac_threshold_px,
    )
    smoothed = estimator.run(frames)
    return estimator.online_trajectory() if online else smoothed
