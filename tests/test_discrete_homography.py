"""Discrete homography H_d = R + t n*^T: estimation, decomposition, known-normal path.

Ground truth comes from simulated planar scenes: a plane (n*, d*) in the
reference frame, points on it seen from the reference camera, moved into the
current frame by X = R X* + T (R from gtsam's Rot3.Expmap) and projected.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hvo_graph.errors import InputError
from hvo_graph.geometry.decomposition import (
    HomographySolution,
    check_points_in_front,
    decompose_homography,
    motion_from_homography_known_normal,
    physically_valid_solutions,
    select_solution,
)
from hvo_graph.geometry.discrete import (
    camera_pose_from_motion,
    estimate_homography,
    euclidean_homography,
    homography_from_motion,
    motion_from_camera_pose,
)
from hvo_graph.geometry.rotation import rot_y

SETTINGS = settings(max_examples=50, deadline=None)
TOL = 1e-8


@dataclass
class Scene:
    R: np.ndarray
    T: np.ndarray
    normal: np.ndarray
    distance: float
    X_ref: np.ndarray  # (N, 3) plane points in the reference frame
    m_ref: np.ndarray  # (N, 3) normalized
    m_cur: np.ndarray

    @property
    def t(self) -> np.ndarray:
        return self.T / self.distance


def _min_triangle_area(m: np.ndarray) -> float:
    xy = m[:4, :2]
    areas = []
    for i, j, k in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
        a, b = xy[j] - xy[i], xy[k] - xy[i]
        areas.append(0.5 * abs(a[0] * b[1] - a[1] * b[0]))
    return min(areas)


coord = st.floats(0.1, 0.6)


@st.composite
def scenes(draw: st.DrawFn, rotation_only: bool = False) -> Scene:
    tilt = draw(st.floats(0.0, 0.7))
    azimuth = draw(st.floats(-np.pi, np.pi))
    normal = np.array(
        [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
    )
    distance = draw(st.floats(0.5, 5.0))
    R = gtsam.Rot3.Expmap(np.array(draw(st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3))))
    R = R.matrix()
    if rotation_only:
        T = np.zeros(3)
    else:
        T = distance * np.array(draw(st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3)))
    # Four points, one per image quadrant, then up to 16 anywhere in [-0.6, 0.6]^2.
    xy = [[sx * draw(coord), sy * draw(coord)] for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    n_extra = draw(st.integers(0, 16))
    xy += [[draw(st.floats(-0.6, 0.6)), draw(st.floats(-0.6, 0.6))] for _ in range(n_extra)]
    m_ref = np.column_stack((np.array(xy), np.ones(len(xy))))
    X_ref = m_ref * (distance / (m_ref @ normal))[:, None]
    X_cur = X_ref @ R.T + T
    assume(np.all(X_cur[:, 2] > 0.2 * distance))
    assume(distance + (R @ normal) @ T > 0.1 * distance)  # current camera in front of the plane
    m_cur = X_cur / X_cur[:, 2:3]
    assume(np.all(np.abs(m_cur[:, :2]) < 2.0))
    assume(_min_triangle_area(m_ref) > 5e-3 and _min_triangle_area(m_cur) > 5e-3)
    return Scene(R, T, normal, distance, X_ref, m_ref, m_cur)


def _close(sol: HomographySolution, R: np.ndarray, t: np.ndarray, n: np.ndarray) -> float:
    return max(
        np.abs(sol.rotation - R).max(),
        np.abs(sol.translation - t).max(),
        np.abs(sol.normal - n).max(),
    )


# ----------------------------------------------------------------------------- recovery


@SETTINGS
@given(scenes())
def test_homography_from_motion_maps_plane_points(scene: Scene) -> None:
    # H_d X* = R X* + T for points on the plane (independent of the image points).
    H = homography_from_motion(scene.R, scene.T, scene.normal, scene.distance)
    np.testing.assert_allclose(scene.X_ref @ H.T, scene.X_ref @ scene.R.T + scene.T, atol=1e-12)


@SETTINGS
@given(scenes())
def test_estimate_and_normalize_recovers_euclidean_homography(scene: Scene) -> None:
    H_true = scene.R + np.outer(scene.t, scene.normal)
    H, inliers = estimate_homography(scene.m_ref, scene.m_cur)
    assert inliers.all()
    # Feed an arbitrary scale and sign: the Euclidean normalization must undo it.
    H_e = euclidean_homography(-2.7 * H, scene.m_ref, scene.m_cur)
    np.testing.assert_allclose(H_e, H_true, atol=TOL)
    # (N, 2) input gives the same answer.
    H2, _ = estimate_homography(scene.m_ref[:, :2], scene.m_cur[:, :2])
    np.testing.assert_allclose(H2, H, atol=1e-12)


@SETTINGS
@given(scenes())
def test_decompose_and_select_recovers_motion(scene: Scene) -> None:
    assume(np.linalg.norm(scene.t) > 0.05)
    # Away from the branch point s1 = 1 or s3 = 1 (translation along the normal), where
    # the two physical solutions merge and any decomposition is only sqrt(eps) accurate.
    s = np.linalg.svd(scene.R + np.outer(scene.t, scene.normal), compute_uv=False)
    assume(min(s[0] / s[1] - 1.0, 1.0 - s[2] / s[1]) > 1e-3)
    H, _ = estimate_homography(scene.m_ref, scene.m_cur)
    H_e = euclidean_homography(H, scene.m_ref, scene.m_cur)
    solutions = decompose_homography(H_e)
    assert len(solutions) == 4
    for sol in solutions:  # every solution reproduces H_d and has R in SO(3)
        np.testing.assert_allclose(sol.rotation @ sol.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(sol.rotation) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(
            sol.rotation + np.outer(sol.translation, sol.normal), H_e, atol=1e-10
        )
    valid = physically_valid_solutions(solutions, scene.m_ref, scene.m_cur)
    assert 1 <= len(valid) <= 2
    best = select_solution(valid, scene.normal)
    assert _close(best, scene.R, scene.t, scene.normal) < TOL
    # Each rejected solution puts some reconstructed point behind a camera (or the
    # current camera behind the plane): rebuild the points with d* = 1.
    for sol in solutions:
        X_ref = scene.m_ref / (scene.m_ref @ sol.normal)[:, None]
        X_cur = X_ref @ sol.rotation.T + sol.translation
        plane_side = 1.0 + sol.normal @ sol.rotation.T @ sol.translation
        ok = np.all(X_ref[:, 2] > 0) and np.all(X_cur[:, 2] > 0) and plane_side > 0
        assert ok == any(sol is v for v in valid)


@SETTINGS
@given(scenes())
def test_known_normal_path_recovers_motion(scene: Scene) -> None:
    H, _ = estimate_homography(scene.m_ref, scene.m_cur)
    H_e = euclidean_homography(H, scene.m_ref, scene.m_cur)
    R, t = motion_from_homography_known_normal(
        H_e, scene.normal, m_ref=scene.m_ref, m_cur=scene.m_cur
    )
    np.testing.assert_allclose(R, scene.R, atol=TOL)
    np.testing.assert_allclose(t, scene.t, atol=TOL)
    # Metric translation and camera pose, checked against gtsam's Pose3: the
    # reference camera frame is the world, so T_wc.transformTo(P) = R P + T.
    R_wc, p_wc = camera_pose_from_motion(R, t * scene.distance)
    pose = gtsam.Pose3(gtsam.Rot3(R_wc), p_wc)
    for P in scene.X_ref[:4]:
        np.testing.assert_allclose(pose.transformTo(P), scene.R @ P + scene.T, atol=1e-7)


@SETTINGS
@given(scenes(rotation_only=True))
def test_pure_rotation(scene: Scene) -> None:
    H, _ = estimate_homography(scene.m_ref, scene.m_cur)
    H_e = euclidean_homography(H, scene.m_ref, scene.m_cur)
    R, t = motion_from_homography_known_normal(H_e, scene.normal)
    np.testing.assert_allclose(R, scene.R, atol=TOL)
    np.testing.assert_allclose(t, 0.0, atol=TOL)
    # H_d is a rotation: one solution, t = 0, normal e3 by convention.
    solutions = decompose_homography(scene.R)
    assert len(solutions) == 1
    np.testing.assert_allclose(solutions[0].rotation, scene.R, atol=1e-12)
    np.testing.assert_array_equal(solutions[0].translation, np.zeros(3))
    np.testing.assert_array_equal(solutions[0].normal, [0.0, 0.0, 1.0])
    assert physically_valid_solutions(solutions, scene.m_ref, scene.m_cur) == solutions


def test_frame_zero_identity() -> None:
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    R, t = motion_from_homography_known_normal(np.eye(3), n)
    np.testing.assert_allclose(R, np.eye(3), rtol=0, atol=4 * np.finfo(float).eps)
    np.testing.assert_allclose(t, np.zeros(3), rtol=0, atol=4 * np.finfo(float).eps)
    # Same from estimated H with identical images (frame 0 against itself).
    m = np.array([[0.1, 0.2, 1.0], [-0.3, 0.25, 1.0], [-0.2, -0.3, 1.0], [0.35, -0.1, 1.0]])
    H, _ = estimate_homography(m, m)
    H_e = euclidean_homography(H, m, m)
    np.testing.assert_allclose(H_e, np.eye(3), atol=1e-14)
    R, t = motion_from_homography_known_normal(H_e, n, m_ref=m, m_cur=m)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(t, np.zeros(3), atol=1e-14)
    (sol,) = decompose_homography(H_e)
    np.testing.assert_allclose(sol.rotation, np.eye(3), atol=1e-14)
    np.testing.assert_array_equal(sol.translation, np.zeros(3))


@pytest.mark.parametrize("scale", [1e-4, 1e-6, 1e-8])
def test_known_normal_path_with_tiny_translation(scale: float) -> None:
    # Near H_d = I the normal is ill-conditioned but (R, t) with known n* are not.
    n = np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
    R = gtsam.Rot3.Expmap(np.array([0.02, -0.01, 0.03])).matrix()
    t = scale * np.array([0.3, -0.5, 0.8])
    H = R + np.outer(t, n)
    R_est, t_est = motion_from_homography_known_normal(H / np.linalg.svd(H)[1][1], n)
    np.testing.assert_allclose(R_est, R, atol=1e-14)
    np.testing.assert_allclose(t_est, t, rtol=1e-6, atol=1e-15)


# ----------------------------------------------------------------------------- OpenCV


@SETTINGS
@given(scenes())
def test_decomposition_agrees_with_opencv(scene: Scene) -> None:
    """Same solution set as cv2.decomposeHomographyMat (Malis-Vargas), K = I.

    OpenCV divides H by its middle singular value, as we do, and returns unit
    normals and t = T/d* with H = R + t n^T, so the two sets are compared
    directly (no sign or scale fix-up), as a one-to-one matching in any order.
    OpenCV treats H^T H - I < 1e-3 as a pure rotation: such scenes are skipped.
    OpenCV 5.0 also returns NaN for some exact boundary cases (e.g. R = I,
    t = [0, 0.5, 0], n* = [0.48, 0, 0.88]: a zero diagonal entry of H^T H - I);
    those are skipped too (our decomposition of them is checked by the recovery tests).
    OpenCV's closed form (square roots of minors of H^T H - I) loses digits when a
    minor is near zero (e.g. 1.7e-7 on its normal for R = Exp([0, 0, 1e-10]),
    t = [0, 0.125, 0], n* = e3, where ours is exact), so agreement is checked to
    1e-5 (1.6e-6 was seen for a 0.03 rad turn about y, t = [0, 0.0137, 0], n* in the
    xz plane); accuracy against ground truth is checked to 1e-8 by the recovery tests.
    """
    H_e = scene.R + np.outer(scene.t, scene.normal)
    assume(np.abs(H_e.T @ H_e - np.eye(3)).max() > 1e-2)
    ours = decompose_homography(H_e)
    count, Rs, ts, ns = cv2.decomposeHomographyMat(H_e, np.eye(3))
    assume(all(np.all(np.isfinite(a)) for a in (*Rs, *ts, *ns)))
    assert count == len(ours) == 4
    theirs = list(zip(Rs, ts, ns, strict=True))
    unmatched = list(range(4))
    for sol in ours:
        errs = [
            _close(sol, theirs[k][0], theirs[k][1].ravel(), theirs[k][2].ravel()) for k in unmatched
        ]
        k = int(np.argmin(errs))
        assert errs[k] < 1e-5
        unmatched.pop(k)
    assert not unmatched


# ----------------------------------------------------------------------------- RANSAC


def test_ransac_rejects_outliers() -> None:
    rng = np.random.default_rng(7)
    n = np.array([0.2, 0.1, 1.0]) / np.linalg.norm([0.2, 0.1, 1.0])
    R = gtsam.Rot3.Expmap(np.array([0.1, -0.2, 0.05])).matrix()
    T = np.array([0.3, -0.1, 0.2])
    m_ref = np.column_stack((rng.uniform(-0.5, 0.5, (30, 2)), np.ones(30)))
    X = m_ref * (2.0 / (m_ref @ n))[:, None] @ R.T + T
    m_cur = X / X[:, 2:3]
    outliers = np.array([3, 11, 19, 25])
    m_cur[outliers, :2] += rng.uniform(0.1, 0.2, (4, 2))
    H, inliers = estimate_homography(m_ref, m_cur, ransac_threshold=1e-3)
    expected = np.ones(30, dtype=bool)
    expected[outliers] = False
    np.testing.assert_array_equal(inliers, expected)
    H_e = euclidean_homography(H, m_ref[inliers], m_cur[inliers])
    np.testing.assert_allclose(H_e, R + np.outer(T, n) / 2.0, atol=1e-10)
    # Without RANSAC the outliers spoil the least-squares fit.
    H_ls, _ = estimate_homography(m_ref, m_cur)
    assert np.abs(euclidean_homography(H_ls, m_ref, m_cur) - H_e).max() > 1e-3


# ----------------------------------------------------------------------------- poses


@SETTINGS
@given(scenes())
def test_camera_pose_round_trip(scene: Scene) -> None:
    R_wc, p_wc = camera_pose_from_motion(scene.R, scene.T)
    # The current camera centre maps to the origin of the current frame.
    np.testing.assert_allclose(scene.R @ p_wc + scene.T, 0.0, atol=1e-12)
    R, T = motion_from_camera_pose(R_wc, p_wc)
    np.testing.assert_allclose(R, scene.R, atol=1e-15)
    np.testing.assert_allclose(T, scene.T, atol=1e-12)


# ----------------------------------------------------------------------------- bad input

M4 = np.array([[0.1, 0.2, 1.0], [-0.3, 0.25, 1.0], [-0.2, -0.3, 1.0], [0.35, -0.1, 1.0]])


def test_too_few_points() -> None:
    with pytest.raises(InputError, match=r"^m_ref: need at least 4 points, got 3$"):
        estimate_homography(M4[:3], M4[:3])


def test_mismatched_shapes() -> None:
    with pytest.raises(InputError, match=r"m_cur: expected as many points as m_ref \(4\), got 5"):
        estimate_homography(M4, np.vstack((M4, M4[:1])))
    with pytest.raises(InputError, match=r"m_ref: expected an array of shape \(N, 2\) or \(N, 3\)"):
        estimate_homography(np.ones((4, 4)), M4)
    with pytest.raises(InputError, match=r"m_cur: third column must be 1 .* got 2 in row 1"):
        estimate_homography(M4, M4 * np.array([[1], [2], [1], [1]]))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_inf(bad: float) -> None:
    m = M4.copy()
    m[2, 0] = bad
    with pytest.raises(InputError, match=r"^m_cur: contains NaN or inf$"):
        estimate_homography(M4, m)


def test_collinear_points() -> None:
    line = np.column_stack((np.linspace(-0.5, 0.5, 6), 0.3 * np.linspace(-0.5, 0.5, 6) + 0.1))
    with pytest.raises(InputError, match=r"^m_ref: degenerate point configuration \(collinear"):
        estimate_homography(line, M4[[0, 1, 2, 3, 0, 1], :2] + 0.01 * np.arange(6)[:, None])
    # Three of four collinear.
    three = np.array([[-0.4, -0.4], [0.0, 0.0], [0.4, 0.4], [0.3, -0.2]])
    with pytest.raises(InputError, match=r"^m_cur: degenerate point configuration \(collinear"):
        estimate_homography(M4, three)
    # All but one collinear among more points.
    five = np.array([[-0.4, 0.1], [-0.1, 0.1], [0.2, 0.1], [0.5, 0.1], [0.0, -0.3]])
    with pytest.raises(InputError, match="collinear"):
        estimate_homography(five, five)


def test_ransac_bad_threshold() -> None:
    with pytest.raises(InputError, match=r"^ransac_threshold: expected a finite number > 0"):
        estimate_homography(M4, M4, ransac_threshold=-1.0)


def test_points_behind_camera() -> None:
    # A 70 deg turn about y: reference points with x* > cot(70 deg) ~ 0.36 end up
    # behind the current camera, and m^T H m* changes sign between points.
    R = rot_y(np.deg2rad(70.0))
    xs = np.array([-0.5, -0.2, 0.0, 0.2, 0.5, 0.8])
    m_ref = np.column_stack((xs, 0.3 * np.cos(5 * xs), np.ones(6)))
    X = m_ref @ R.T
    m_cur = X / X[:, 2:3]
    with pytest.raises(InputError, match=r"points behind the camera"):
        euclidean_homography(R, m_ref, m_cur)


def test_check_points_in_front_rejects_mirror_solution() -> None:
    n = np.array([0.0, 0.0, 1.0])
    R = gtsam.Rot3.Expmap(np.array([0.05, 0.1, -0.02])).matrix()
    t = np.array([0.2, -0.1, 0.1])
    X = M4 @ R.T + t  # d* = 1 and n = e3: X* = m*
    m_cur = X / X[:, 2:3]
    check_points_in_front(M4, m_cur, R, t, n)  # the truth passes
    with pytest.raises(InputError, match=r"^m_ref: points behind the camera in the reference"):
        check_points_in_front(M4, m_cur, R, -t, -n)
    H = R + np.outer(t, n)
    H_e = H / np.linalg.svd(H)[1][1]
    with pytest.raises(InputError, match=r"points behind the camera"):
        motion_from_homography_known_normal(H_e, -n, m_ref=M4, m_cur=m_cur)


def test_non_euclidean_homography_is_rejected() -> None:
    n = np.array([0.0, 0.0, 1.0])
    H = np.eye(3) + np.outer([0.1, 0.2, 0.05], n)
    H = H / np.linalg.svd(H)[1][1]
    with pytest.raises(InputError, match=r"^H_euclid: middle singular value must be 1, got 2"):
        decompose_homography(2.0 * H)
    with pytest.raises(InputError, match=r"^H_euclid: det\(H\) = .* <= 0: wrong sign"):
        motion_from_homography_known_normal(-H, n)
    with pytest.raises(InputError, match=r"^H: rank < 2"):
        euclidean_homography(np.outer([1.0, 0, 0], [0, 0, 1.0]), M4, M4)


def test_bad_plane_and_selection_arguments() -> None:
    with pytest.raises(InputError, match=r"^normal: expected a unit vector, got norm 2"):
        homography_from_motion(np.eye(3), np.zeros(3), [0.0, 0.0, 2.0], 1.0)
    with pytest.raises(InputError, match=r"^distance: expected a finite number > 0"):
        homography_from_motion(np.eye(3), np.zeros(3), [0.0, 0.0, 1.0], 0.0)
    with pytest.raises(InputError, match=r"^R: expected shape \(3, 3\)"):
        homography_from_motion(np.eye(2), np.zeros(3), [0.0, 0.0, 1.0], 1.0)
    with pytest.raises(InputError, match=r"^solutions: empty list"):
        select_solution([], [0.0, 0.0, 1.0])
    with pytest.raises(InputError, match=r"^normal_prior: expected a non-zero vector"):
        select_solution(decompose_homography(np.eye(3)), np.zeros(3))
