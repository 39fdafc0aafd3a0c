"""A keyframe's tilt re-fitted from the frames measured against it (frontend.keyframe_tilt).

References: ground truth (a keyframe placed 5 degrees off the plane, frames translating
over it), a Monte Carlo of the chained tilt covariance, and a drawn traverse whose
keyframe chain ran away in tilt before.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X
from gtsam.utils.numerical_derivative import numericalDerivative11

from hvo_graph.errors import InputError
from hvo_graph.estimators.factors import tilt_factor, tilt_residual
from hvo_graph.estimators.measurements import RawMeasurements
from hvo_graph.estimators.noise_estimation import unrolled_poses
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.eval.consistency import trajectory_nees
from hvo_graph.eval.metrics import error_series
from hvo_graph.frontend._points import TrackedFrame
from hvo_graph.frontend.keyframe_tilt import (
    UNKNOWN_TILT_VARIANCE,
    chained_tilt_covariance,
    fused_tilt,
)
from hvo_graph.measurement_table import MeasurementTable
from hvo_graph.pipeline import measure
from hvo_graph.sim.families import draw
from hvo_graph.types import FrameMeasurement, Plane, PoseMeasurement, TiltMeasurement

NORMAL = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
DISTANCE = 1.5
SIGMA = 0.5 / 800.0  # 0.5 px at an 800 px focal length


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def tangent_covariance(normal: np.ndarray, variance: float) -> np.ndarray:
    return variance * (np.eye(3) - np.outer(normal, normal))


def keyframe_scene(placement_deg: float, seed: int = 3):
    """The true keyframe is the world frame; its placement is turned by ``placement_deg``
    about an axis of the plane. Twelve frames translate up to 0.3 d* over 15 plane points."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.5, 0.5, size=(15, 2))
    m = np.column_stack((xy, np.ones(len(xy))))
    points = DISTANCE * m / (m @ NORMAL)[:, None]

    def seen(R, T):
        X = points @ R.T + T
        xy = X[:, :2] / X[:, 2:] + SIGMA * rng.standard_normal((len(X), 2))
        return np.column_stack((xy, np.ones(len(X))))

    ids = np.arange(len(points))
    axis = np.cross(NORMAL, [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)
    R_placed = gtsam.Rot3.Expmap(np.radians(placement_deg) * axis).matrix()
    reference = TrackedFrame(0, 0.0, ids, seen(np.eye(3), np.zeros(3)), R_placed, np.zeros(3))
    frames = []
    for k in range(1, 13):
        R = gtsam.Rot3.Ypr(0.01 * k, -0.02 * k, 0.015 * k).matrix()
        T = np.array([0.04 * k, 0.015 * k, 0.01 * k])
        # stored as the front end keeps them: world -> frame through the placed reference
        frames.append(TrackedFrame(k, k / 30.0, ids, seen(R, T), R @ R_placed, T))
    return reference, frames, Plane(DISTANCE, R_placed @ NORMAL)


def test_a_keyframe_placed_five_degrees_off_is_turned_back_by_its_frames():
    reference, frames, plane = keyframe_scene(5.0)
    assert angle_deg(plane.normal, NORMAL) == pytest.approx(5.0)
    prior = tangent_covariance(plane.normal, np.radians(10.0) ** 2)
    fit = fused_tilt(reference, frames, plane, prior, SIGMA)
    C, posterior = fit.correction, fit.posterior
    assert angle_deg(C @ plane.normal, NORMAL) < 1.0
    assert angle_deg(fit.normal, NORMAL) < 1.0  # the frames' fit alone
    assert np.trace(posterior) < 0.1 * np.trace(prior)
    # the correction turns the camera about its centre: d_r stays, yaw about n_r stays
    assert np.allclose(C @ C.T, np.eye(3), atol=1e-12)
    assert abs(np.cross(plane.normal, C @ plane.normal) @ plane.normal) < 1e-12


def test_a_certain_chain_keeps_its_tilt_and_little_parallax_says_little():
    reference, frames, plane = keyframe_scene(5.0)
    certain = tangent_covariance(plane.normal, np.radians(0.001) ** 2)
    C = fused_tilt(reference, frames, plane, certain, SIGMA).correction
    assert angle_deg(C @ plane.normal, plane.normal) < 0.01
    # only the first frame (4 % of d* translation): the correction is a small part of 5 deg
    prior = tangent_covariance(plane.normal, np.radians(0.5) ** 2)
    fit = fused_tilt(reference, frames[:1], plane, prior, SIGMA)
    C, posterior = fit.correction, fit.posterior
    assert angle_deg(C @ plane.normal, plane.normal) < 1.0
    assert np.trace(posterior) > 0.5 * np.trace(prior)


def test_no_frame_sharing_enough_points_gives_no_correction():
    reference, frames, plane = keyframe_scene(5.0)
    few = [TrackedFrame(f.index, f.t, f.ids[:3], f.m[:3], f.R, f.T) for f in frames]
    prior = tangent_covariance(plane.normal, 0.01)
    assert fused_tilt(reference, few, plane, prior, SIGMA) is None


def test_chained_tilt_covariance_matches_a_monte_carlo():
    rng = np.random.default_rng(5)
    n_r = NORMAL
    Sigma_r = tangent_covariance(n_r, 0.02**2)
    Sigma_r[:] += 0.5 * 0.01**2 * np.outer(np.cross(n_r, [1, 0, 0]), np.cross(n_r, [1, 0, 0]))
    R = gtsam.Rot3.Ypr(0.3, -0.2, 0.1).matrix()
    A = rng.standard_normal((3, 3)) * 0.01
    Sigma_phi = A @ A.T + 1e-4 * np.eye(3)
    expected = chained_tilt_covariance(Sigma_r, R, R @ n_r, Sigma_phi)
    samples = []
    L_r = np.linalg.cholesky(Sigma_r + 1e-14 * np.eye(3))
    L_phi = np.linalg.cholesky(Sigma_phi)
    for _ in range(40000):
        n = n_r + L_r @ rng.standard_normal(3)
        n /= np.linalg.norm(n)
        phi = L_phi @ rng.standard_normal(3)
        # R_rk T_rk Exp(phi): the motion r -> k becomes Exp(-phi) R
        samples.append(gtsam.Rot3.Expmap(-phi).matrix() @ R @ n)
    measured = np.cov(np.array(samples).T)
    assert np.allclose(measured, expected, atol=0.05 * np.abs(expected).max())


def test_a_predicted_keyframe_pose_has_an_unknown_tilt():
    n = np.array([0.0, 0.0, 1.0])
    out = chained_tilt_covariance(np.zeros((3, 3)), np.eye(3), n, None)
    assert np.allclose(out, tangent_covariance(n, UNKNOWN_TILT_VARIANCE))


def test_a_traverse_whose_keyframes_ran_away_in_tilt_keeps_them():
    """Traverse draw 19 (about 16 points in view): one frame measured 6 deg off became a
    keyframe, and without the tilt fit the chain ran away to 60 deg and lost every pose
    after frame 248. Each pose placed in the world through the front end's keyframe."""
    scenario = draw("traverse", 19).scenario
    frames = measure(scenario.observations, scenario)
    errors = []
    for frame in frames:
        pose = frame.pose
        assert pose is not None, frame.index
        R = pose.rotation if pose.reference == 0 else pose.reference_rotation @ pose.rotation
        R_true = scenario.groundtruth.rotations[frame.index]
        errors.append(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R_true.T @ R)))))
    assert max(errors) < 12.0
    assert np.percentile(errors, 90) < 5.0
    # The raw measurements place them the same way (through their own chain of keyframe
    # estimates they had run 100 deg away).
    raw = RawMeasurements().run(frames)
    for frame, R_wc in zip(frames, raw.rotations, strict=True):
        pose = frame.pose
        expected = gtsam.Pose3(gtsam.Rot3(pose.rotation), pose.position)
        if pose.reference != 0:
            keyframe = gtsam.Pose3(gtsam.Rot3(pose.reference_rotation), pose.reference_position)
            expected = keyframe.compose(expected)
        np.testing.assert_allclose(R_wc, expected.rotation().matrix(), atol=1e-9)


def test_unrolled_poses_go_through_the_keyframe_as_measured():
    """A keyframe whose placement the front end corrected after its own pose was measured:
    the unrolled increments are the measured relative poses, with no jump."""
    I6 = 1e-4 * np.eye(6)
    world = [gtsam.Pose3(gtsam.Rot3.Rz(0.01 * k), np.array([0.02 * k, 0, 0])) for k in range(3)]
    corrected = world[2].compose(gtsam.Pose3(gtsam.Rot3.Rx(np.radians(5.0)), np.zeros(3)))
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.01), np.array([0.02, 0.0, 0.0]))
    frames = [
        FrameMeasurement(k, k / 30.0, PoseMeasurement(P.rotation().matrix(), P.translation(), I6))
        for k, P in enumerate(world)
    ]
    frames.append(
        FrameMeasurement(
            3,
            0.1,
            PoseMeasurement(
                step.rotation().matrix(),
                step.translation(),
                I6,
                reference=2,
                reference_rotation=corrected.rotation().matrix(),
                reference_position=corrected.translation(),
            ),
        )
    )
    _, s, _ = unrolled_poses(frames)
    assert np.allclose(s[3] - s[2], gtsam.Pose3.Logmap(step), atol=1e-12)


def a_tilt(frame: int, R_wr: np.ndarray, sigma_deg: float = 1.0) -> TiltMeasurement:
    n_r = R_wr.T @ NORMAL
    return TiltMeasurement(frame, n_r, NORMAL, tangent_covariance(n_r, np.radians(sigma_deg) ** 2))


def test_the_tilt_residual_is_zero_at_the_truth_and_its_jacobian_is_gtsams_numerical_one():
    R_wr = gtsam.Rot3.Ypr(0.4, -0.3, 0.2)
    tilt = a_tilt(3, R_wr.matrix())
    e, _ = tilt_residual(R_wr.matrix(), tilt)
    assert np.allclose(e, 0.0, atol=1e-15)
    X_r = gtsam.Pose3(gtsam.Rot3.Ypr(0.45, -0.25, 0.1), np.array([0.3, -0.2, 1.0]))
    _, H = tilt_residual(X_r.rotation().matrix(), tilt)
    numerical = numericalDerivative11(
        lambda pose: tilt_residual(pose.rotation().matrix(), tilt)[0], X_r, 1e-6
    )
    assert np.allclose(H, numerical, atol=1e-8)


def test_the_tilt_factor_turns_a_keyframe_to_the_measured_attitude():
    """A keyframe held by a weak prior 5 deg off: the factor brings its tilt back to the
    measured one and leaves its heading about n* and its position alone."""
    R_true = gtsam.Rot3.Ypr(0.4, -0.3, 0.2)
    tilt = a_tilt(7, R_true.matrix(), sigma_deg=0.1)
    off = gtsam.Pose3(R_true.compose(gtsam.Rot3.Rx(np.radians(5.0))), np.array([1.0, 2.0, 0.5]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(7), off, gtsam.noiseModel.Isotropic.Sigma(6, 0.5)))
    graph.add(tilt_factor(tilt))
    values = gtsam.Values()
    values.insert(X(7), off)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize().atPose3(X(7))
    n_est = result.rotation().matrix().T @ NORMAL
    assert angle_deg(n_est, tilt.normal) < 0.01
    assert np.allclose(result.translation(), off.translation(), atol=1e-6)


def test_the_smoother_keeps_a_long_traverse_level_offline_and_online():
    """Traverse draw 19: the raw keyframe chain runs away (tens of degrees); with the
    keyframes' tilts in the graph the smoother stays within a few degrees and says so."""
    scenario = draw("traverse", 19).scenario
    frames = measure(scenario.observations, scenario)
    assert sum(f.keyframe_tilt is not None for f in frames) >= 10
    for online in (False, True):
        smoother = FactorGraphSmoother(compute_covariance=True)
        trajectory = smoother.run(frames, online=online)
        series = error_series(trajectory, scenario.groundtruth)
        assert series.orientation.max() < 3.0
        assert series.position.max() < 0.2
        pose_nees, _ = trajectory_nees(trajectory, scenario.groundtruth)
        assert pose_nees < 5.0


def test_the_front_ends_tilt_fits_are_honest_over_traverses():
    """NEES of the reported keyframe normals (2 dof) against the true ones, 10 draws."""
    nees = []
    for seed in range(10):
        scenario = draw("traverse", seed).scenario
        for frame in measure(scenario.observations, scenario):
            tilt = frame.keyframe_tilt
            if tilt is None:
                continue
            n_true = scenario.groundtruth.rotations[tilt.frame].T @ tilt.world_normal
            B = np.linalg.svd(tilt.normal[None, :])[2][1:]
            e = B @ n_true
            nees.append(float(e @ np.linalg.solve(B @ tilt.covariance @ B.T, e)) / 2.0)
    assert len(nees) >= 15
    assert 0.5 < np.mean(nees) < 2.0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"frame": 99},
            "frame 40: keyframe_tilt.frame: 99 is not an earlier frame of this sequence",
        ),
        (
            {"normal": np.array([0.0, 0.0, 2.0])},
            "frame 40: keyframe_tilt.normal: expected a unit vector, norm 2.0",
        ),
        (
            {"world_normal": np.array([0.0, 1.0])},
            "frame 40: keyframe_tilt.world_normal: expected shape (3,), got (2,)",
        ),
        (
            {"covariance": np.zeros((3, 3))},
            "frame 40: keyframe_tilt.covariance (across normal): "
            "expected a positive definite matrix",
        ),
    ],
)
def test_a_bad_keyframe_tilt_is_refused_by_name(change, message):
    scenario = draw("traverse", 0).scenario
    frames = measure(scenario.observations[:41], scenario)
    good = a_tilt(10, scenario.groundtruth.rotations[10])
    frames[40] = dataclasses.replace(frames[40], keyframe_tilt=dataclasses.replace(good, **change))
    with pytest.raises(InputError) as error:
        FactorGraphSmoother().run(frames)
    assert str(error.value) == message


def test_a_measurement_table_keeps_the_keyframe_tilt():
    scenario = draw("traverse", 19).scenario
    frames = measure(scenario.observations[:120], scenario)
    table = MeasurementTable(frames).compact()
    tilted = [k for k, f in enumerate(frames) if f.keyframe_tilt is not None]
    assert tilted
    for k in tilted:
        assert table[k].keyframe_tilt is frames[k].keyframe_tilt


def test_a_keyframe_kept_to_the_end_has_its_tilt_reported_once_the_camera_moved_away():
    """Traverse draw 53 stays on its last keyframe (frame 164) for 4.5 s: never left, it
    is reported at the first frame half a plane distance from it. No keyframe twice."""
    scenario = draw("traverse", 53).scenario
    frames = measure(scenario.observations, scenario)
    reported = [f.keyframe_tilt.frame for f in frames if f.keyframe_tilt is not None]
    last = max(f.pose.reference for f in frames if f.pose is not None)
    assert last in reported
    assert len(reported) == len(set(reported))
    at = next(f for f in frames if f.keyframe_tilt is not None and f.keyframe_tilt.frame == last)
    truth = scenario.groundtruth
    moved = np.linalg.norm(truth.positions[at.index] - truth.positions[last])
    assert moved > 0.4 * scenario.plane.distance
