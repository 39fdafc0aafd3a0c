"""Consistency against ground truth: track error, measurement and estimate NEES, keyframes.

Functions of measurement records and trajectories only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.base import keyframe_world_pose
from hvo_graph.eval.metrics import match_timestamps
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import FrameMeasurement, FrameObservations, Plane, Trajectory


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

    delta = Log(T_meas^-1 T_true) with T the world pose (right perturbation, the
    covariance's convention), NEES = delta^T C^-1 delta; 6 on average when the
    covariance C describes the error. A keyframe-relative pose becomes a world pose
    through the true keyframe pose, with the plane re-placed there as the estimators
    do (:func:`~hvo_graph.estimators.base.keyframe_world_pose`): C holds the pixels'
    noise, not the error of the keyframe pose the front end placed the plane with.
    Frame 0 itself (exact by construction) is left out.

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
        reference = poses[f.pose.reference]
        placed = keyframe_world_pose(f.pose, reference.rotation().matrix(), reference.translation())
        measured = gtsam.Pose3(gtsam.Rot3(placed.rotation), np.asarray(placed.position))
        delta = gtsam.Pose3.Logmap(measured.between(poses[f.index]))
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


def trajectory_nees(
    estimate: Trajectory, truth: Trajectory, *, t_start: float | None = None
) -> tuple[float, float]:
    """Mean NEES per degree of freedom of an estimate's pose and twist.

    Pose: delta = Log(T_est^-1 T_true) (right perturbation, the covariance's
    convention) against the pose block; twist: e = xi_true - xi_est against the
    twist block of ``estimate.covariances``. 1 on average when the covariances
    describe the errors; above 1 the estimate is overconfident.

    Args:
        estimate: with (K, 12, 12) covariances; frames matched to ``truth`` by time.
        truth: ground truth.
        t_start: only frames with t >= t_start (None: all).
    Returns:
        (pose NEES / 6, twist NEES / 6), averaged over the matched frames.
    Raises:
        InputError: no covariances, or no frame matched.
    """
    if estimate.covariances is None:
        raise InputError("estimate: no covariances to check (run with covariance on)")
    i_est, i_true = match_timestamps(estimate.t, truth.t, 1e-6)
    if t_start is not None:
        keep = estimate.t[i_est] >= t_start
        i_est, i_true = i_est[keep], i_true[keep]
    if len(i_est) == 0:
        raise InputError("estimate: no frame matches the ground truth's times")
    pose, twist = [], []
    for i, j in zip(i_est, i_true, strict=True):
        est = gtsam.Pose3(gtsam.Rot3(estimate.rotations[i]), estimate.positions[i])
        true = gtsam.Pose3(gtsam.Rot3(truth.rotations[j]), truth.positions[j])
        delta = gtsam.Pose3.Logmap(est.between(true))
        C = estimate.covariances[i]
        pose.append(float(delta @ np.linalg.solve(C[:6, :6], delta)) / 6.0)
        e = truth.twists[j] - estimate.twists[i]
        twist.append(float(e @ np.linalg.solve(C[6:, 6:], e)) / 6.0)
    return float(np.mean(pose)), float(np.mean(twist))
