"""Covariances of poses measured against keyframes: they share the keyframe's error.

Reference: the ground truth of a simulated traverse whose points leave the view
(keyframe switches), pose NEES per degree of freedom over noise draws.
"""

from __future__ import annotations

import itertools

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from hvo_graph.estimators.registry import EstimatorOptions, build_estimator
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.eval.consistency import pose_nees as measurement_nees
from hvo_graph.frontend import FrontEndConfig, MeasurementFrontEnd
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import FrameObservations, Plane, Trajectory

CAMERA = CameraModel(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
NORMAL = np.array([0.0, 0.0, 1.0])
DISTANCE = 2.0
FPS = 30.0
SIGMA = 0.5  # pixels


def traverse(seed: int, frames: int = 240):
    """A camera sliding 0.8 m/s over a plane of scattered points, turning slowly: the
    points the first frame sees are gone after ~2 s, so the front end takes keyframes."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform((-2.5, -1.6), (9.5, 1.6), size=(600, 2))
    points = np.column_stack((xy, np.full(len(xy), DISTANCE)))
    twist = np.array([0.0, 0.02, 0.05, 0.8, 0.05, 0.0])  # [w; v], body frame
    poses = [gtsam.Pose3.Expmap(twist * k / FPS) for k in range(frames)]
    return observe(points, poses, rng), poses


def out_and_back(seed: int, frames: int = 240):
    """The camera slides 5 m out over the plane and back: the front end takes two or three
    keyframes on the way out and returns to them (points seen again) on the way back."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform((-2.5, -1.6), (8.5, 1.6), size=(700, 2))
    points = np.column_stack((xy, np.full(len(xy), DISTANCE)))
    phase = 2.0 * np.pi * np.arange(frames) / frames
    poses = [
        gtsam.Pose3(
            gtsam.Rot3.Expmap(np.array([0.0, 0.02, 0.05]) * np.sin(a)),
            np.array([2.5 * (1.0 - np.cos(a)), 0.1 * np.sin(a), 0.0]),
        )
        for a in phase
    ]
    return observe(points, poses, rng), poses


def observe(points: np.ndarray, poses: list, rng: np.random.Generator) -> list:
    """Noisy pixels of the points in view of each pose, ids = point rows."""
    obs = []
    for k, pose in enumerate(poses):
        Xc = (points - pose.translation()) @ pose.rotation().matrix()
        uv = np.column_stack(
            (
                CAMERA.fx * Xc[:, 0] / Xc[:, 2] + CAMERA.cx,
                CAMERA.fy * Xc[:, 1] / Xc[:, 2] + CAMERA.cy,
            )
        )
        inside = np.flatnonzero(
            (Xc[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
        )
        noisy = uv[inside] + SIGMA * rng.standard_normal((len(inside), 2))
        obs.append(FrameObservations(k, k / FPS, inside, noisy))
    return obs


def measure(obs):
    front = MeasurementFrontEnd(CAMERA, Plane(DISTANCE, NORMAL), FrontEndConfig(pixel_sigma=SIGMA))
    return front.process_all(obs)


def returns(frames) -> bool:
    """Whether the poses go back to an earlier keyframe (not the world frame)."""
    refs = [f.pose.reference for f in frames if f.pose is not None]
    switches = refs[:1] + [b for a, b in itertools.pairwise(refs) if b != a]
    return any(0 < b < a for a, b in itertools.pairwise(switches))


def pose_nees(trajectory, poses, skip: int = 30) -> float:
    values = []
    for k in range(skip, len(poses)):
        est = gtsam.Pose3(gtsam.Rot3(trajectory.rotations[k]), trajectory.positions[k])
        delta = gtsam.Pose3.Logmap(est.between(poses[k]))
        values.append(delta @ np.linalg.solve(trajectory.covariances[k][:6, :6], delta) / 6)
    return float(np.mean(values))


@pytest.mark.parametrize("method", ["smoother", "batch", "fixed-lag"])
def test_poses_against_keyframes_have_honest_covariances(method):
    """Before keyframe copies in the error covariance, each pose was reported as if its
    keyframe were exact: pose NEES per dof 31-199 on these draws (mean 114; now 0.9)."""
    nees, switches = [], []
    for seed in range(4):
        obs, poses = traverse(seed)
        frames = measure(obs)
        switches.append(len({f.pose.reference for f in frames if f.pose is not None}) - 1)
        estimator = build_estimator(method, EstimatorOptions(covariance=True, lag=1.0))
        nees.append(pose_nees(estimator.run(frames), poses))
    assert min(switches) >= 2
    assert 0.5 <= np.mean(nees) <= 2.0, nees


@pytest.mark.parametrize("method", ["smoother", "batch", "fixed-lag"])
def test_poses_against_a_keyframe_seen_again_have_honest_covariances(method):
    """Coming back to a keyframe closes a loop through it. While the chain treated such a
    keyframe as known, the loop pinned the whole trajectory: pose NEES per dof 5.4
    (smoother) and 9.6 (fixed-lag) on these draws; about 1 with the keyframe's copy kept."""
    nees = []
    for seed in (1, 2, 4, 5):
        obs, poses = out_and_back(seed)
        frames = measure(obs)
        assert returns(frames)
        estimator = build_estimator(method, EstimatorOptions(covariance=True, lag=1.0))
        nees.append(pose_nees(estimator.run(frames), poses))
    assert 0.5 <= np.mean(nees) <= 2.0, nees


def test_keyframe_copies_keep_the_graph_information():
    """The chain's information with keyframe copies (two at once where the camera comes
    back) is the factor graph's: its inverse matches GTSAM's marginals of the recorded
    factors at the estimate."""
    obs, _ = out_and_back(2)
    frames = measure(obs)
    estimator = FactorGraphSmoother(compute_covariance=True)
    estimator.run(frames)
    record, indices = estimator.record, estimator._indices
    values = gtsam.Values()
    finals = estimator.backend.final(indices, marginals=False)
    for k, (pose, twist, _) in zip(indices, finals, strict=True):
        values.insert(X(k), pose)
        values.insert(gtsam.symbol_shorthand.V(k), np.asarray(twist))
    graph = gtsam.NonlinearFactorGraph()
    for factor in record.motion + record.fixed + record.measurement:
        graph.add(factor)
    for item in record.shared:
        graph.add(item.factor)
    marginals = gtsam.Marginals(graph, values)

    system = record.system(values, indices, estimator._times, record.keyframes)
    K, size = system.fixed.shape[:2]
    assert size >= 24  # pose, twist and keyframe copies, two or more at once
    diagonal, upper = system.information()
    information = np.zeros((K * size, K * size))
    for n in range(K):
        block = slice(n * size, (n + 1) * size)
        information[block, block] = diagonal[n]
        if n + 1 < K:
            after = slice((n + 1) * size, (n + 2) * size)
            information[block, after] = upper[n]
            information[after, block] = upper[n].T
    scale = 1.0 / np.sqrt(np.diag(information))
    P = scale[:, None] * np.linalg.inv(scale[:, None] * information * scale) * scale
    for n in range(0, K, 20):
        ours = P[n * size : n * size + 6, n * size : n * size + 6]
        theirs = marginals.marginalCovariance(X(indices[n]))
        sd = np.sqrt(np.diag(theirs))  # compared as correlations and relative variances
        np.testing.assert_allclose(ours / np.outer(sd, sd), theirs / np.outer(sd, sd), atol=1e-3)


def test_error_covariance_does_not_depend_on_how_the_shared_sources_are_sliced(monkeypatch):
    """The shared pixels are solved for a slice of sources at a time (memory); the result
    is the same for any slicing. Before the bias probe was limited to [pose; twist], the
    keyframe copies' near-duplicate directions turned rounding into twist variance up to
    3x off between slicings."""
    from hvo_graph.estimators import error_covariance

    obs, _ = out_and_back(2)
    estimator = FactorGraphSmoother(compute_covariance=True)
    estimator.run(measure(obs))
    finals = [(p, np.asarray(v)) for p, v, _ in estimator.backend.final(estimator._indices)]
    covariances = []
    for chunk_bytes in (1, 2**40):  # 32 sources a slice; all at once
        monkeypatch.setattr(error_covariance, "SHARED_CHUNK_BYTES", chunk_bytes)
        covariances.append(
            estimator.record.covariances(
                finals, estimator._indices, estimator._times, anchored=True
            )[1:]  # frame 0: the anchor itself, zero up to rounding
        )
    sd = np.sqrt(np.einsum("kii->ki", covariances[1]))
    sliced, whole = (c / sd[:, :, None] / sd[:, None, :] for c in covariances)
    np.testing.assert_allclose(sliced, whole, atol=1e-6)


@pytest.mark.parametrize("scene", ["traverse", "out_and_back"])
def test_measured_kalman_reports_its_error_across_keyframes(scene, monkeypatch):
    """The measured-R filter composes keyframe poses with its own estimate of the keyframe;
    taking that as exact, its covariance left the keyframe's error out: pose NEES per dof
    25 (traverse) and 27 (out and back) on these draws. Its error covariance with the
    keyframes cloned in brings both near 1, and leaves the estimates as they were."""
    from hvo_graph.estimators.kalman import KalmanBaseline

    draw, seeds = (traverse, range(4)) if scene == "traverse" else (out_and_back, (1, 2, 4, 5))
    nees = []
    for seed in seeds:
        obs, poses = draw(seed)
        frames = measure(obs)
        options = EstimatorOptions(covariance=True, seed=seed)
        tracked = build_estimator("kalman-measured", options).run(frames)
        nees.append(pose_nees(tracked, poses))
        if seed == seeds[0]:
            with monkeypatch.context() as patch:
                patch.setattr(KalmanBaseline, "_track_keyframe", lambda self, frame: None)
                untracked = build_estimator("kalman-measured", options).run(frames)
            np.testing.assert_array_equal(tracked.positions, untracked.positions)
            np.testing.assert_array_equal(tracked.rotations, untracked.rotations)
            assert pose_nees(untracked, poses) > 4.0  # the keyframes taken as exact
    assert 0.5 <= np.mean(nees) <= 2.0, nees


def test_keyframe_world_pose_jacobian_matches_numerical_differentiation():
    """dg/dc (the world pose of a keyframe-relative pose, plane re-placed, in the filter's
    Euler-angle coordinates, per keyframe coordinate) against central differences."""
    from hvo_graph.estimators.kalman_keyframes import world_pose, world_pose_jacobian

    obs, _ = traverse(1)
    poses = [f.pose for f in measure(obs) if f.pose is not None and f.pose.reference]
    assert poses and all(p.plane_jacobian is not None for p in poses)
    rng = np.random.default_rng(2)
    for pose in poses[:: max(len(poses) // 6, 1)]:
        keyframe = np.r_[rng.normal(0.0, 0.5, 3), rng.normal(0.0, 0.3, 3)]
        numerical = np.empty((6, 6))
        for i, step in enumerate(1e-6 * np.eye(6)):
            d = world_pose(pose, keyframe + step) - world_pose(pose, keyframe - step)
            numerical[:, i] = d / 2e-6
        np.testing.assert_allclose(
            world_pose_jacobian(pose, keyframe), numerical, atol=1e-6 * np.abs(numerical).max()
        )


def test_front_end_poses_against_keyframes_are_honest():
    """The front end places the plane in each keyframe with its own estimate of the
    keyframe; checked through the true keyframe with the plane re-placed there, the
    poses' NEES is the 6 of an honest covariance. Compared relative to the keyframe
    as measured (the placement error left in), the same poses read 10-480."""
    ours, as_measured = [], []
    for scene in (traverse, out_and_back):
        for seed in range(2):
            obs, poses = scene(seed)
            frames = measure(obs)
            truth = Trajectory(
                t=np.array([o.t for o in obs]),
                rotations=np.array([p.rotation().matrix() for p in poses]),
                positions=np.array([p.translation() for p in poses]),
                twists=np.zeros((len(poses), 6)),
            )
            ours.append(measurement_nees(frames, truth)[1])
            values = []
            for f in frames:
                if f.pose is None or f.pose.reference in (0, f.index):
                    continue
                Z = gtsam.Pose3(gtsam.Rot3(f.pose.rotation), f.pose.position)
                true = poses[f.pose.reference].between(poses[f.index])
                delta = gtsam.Pose3.Logmap(Z.between(true))
                values.append(delta @ np.linalg.solve(f.pose.covariance, delta))
            as_measured.append(np.mean(values))
    assert 4.5 <= np.mean(ours) <= 8.0, ours
    assert min(as_measured) > 1.3 * max(ours), (as_measured, ours)
