"""CameraModel (pixels <-> normalized m) and the paper's Euler-angle conventions.

References: the Brown-Conrady distortion formula written out here and OpenCV
(cv2.undistortPoints / cv2.projectPoints) for the camera; gtsam's Rot3 for
rotations, and numerical differentiation of R(t) = R0 Exp(t w) for eqs. 3-5.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.rotation import (
    euler_rates,
    euler_to_rotation,
    nearest_rotation,
    rotation_to_euler,
    skew,
    wrap_angle,
)

SETTINGS = settings(max_examples=50, deadline=None)


def _brown_conrady(xy: np.ndarray, k: np.ndarray) -> np.ndarray:
    """OpenCV's 5-coefficient model k1 k2 p1 p2 k3, written out independently."""
    k1, k2, p1, p2, k3 = k
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack((xd, yd))


cameras = st.builds(
    lambda fx, fy, cx, cy: CameraModel(fx, fy, cx, cy, 640, 480),
    st.floats(300.0, 1500.0),
    st.floats(300.0, 1500.0),
    st.floats(250.0, 390.0),
    st.floats(180.0, 300.0),
)
distortions = st.tuples(
    st.floats(-0.3, 0.3),
    st.floats(-0.1, 0.1),
    st.floats(-2e-3, 2e-3),
    st.floats(-2e-3, 2e-3),
    st.floats(-0.02, 0.02),
).map(np.array)
normalized = st.lists(
    st.tuples(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4)), min_size=1, max_size=20
).map(lambda xy: np.column_stack((np.array(xy), np.ones(len(xy)))))


def _with_distortion(cam: CameraModel, k: np.ndarray) -> CameraModel:
    return CameraModel(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, k)


# ----------------------------------------------------------------------------- camera


@SETTINGS
@given(cameras, normalized)
def test_pixel_normalized_round_trip_without_distortion(cam: CameraModel, m: np.ndarray) -> None:
    uv = cam.normalized_to_pixel(m)
    np.testing.assert_allclose(uv, (m @ cam.K.T)[:, :2], atol=1e-9)
    np.testing.assert_allclose(cam.pixel_to_normalized(uv), m, atol=1e-12)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, np.zeros(5)).reshape(-1, 2)
    np.testing.assert_allclose(cam.pixel_to_normalized(uv)[:, :2], ref, atol=1e-12)
    # (N, 2) input is accepted too.
    np.testing.assert_allclose(cam.normalized_to_pixel(m[:, :2]), uv, atol=1e-12)


@SETTINGS
@given(cameras, distortions, normalized)
@example(  # strong barrel distortion: OpenCV's default 5 iterations leave ~1e-5 here
    CameraModel(800.0, 810.0, 320.0, 240.0, 640, 480),
    np.array([-0.3, 0.1, 2e-3, -2e-3, -0.02]),
    np.array([[0.4, 0.4, 1.0], [-0.4, 0.35, 1.0], [0.05, -0.4, 1.0]]),
)
def test_pixel_normalized_round_trip_with_distortion(
    cam: CameraModel, k: np.ndarray, m: np.ndarray
) -> None:
    cam = _with_distortion(cam, k)
    uv = cam.normalized_to_pixel(m)
    xd = _brown_conrady(m[:, :2], k)
    np.testing.assert_allclose(uv[:, 0], cam.fx * xd[:, 0] + cam.cx, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], cam.fy * xd[:, 1] + cam.cy, atol=1e-9)
    # Undistortion inverts distortion to far below a pixel (1e-9 normalized ~ 1e-6 px).
    np.testing.assert_allclose(cam.pixel_to_normalized(uv), m, atol=1e-9)


@SETTINGS
@given(
    cameras,
    distortions,
    st.lists(
        st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(2.0, 10.0)),
        min_size=1,
        max_size=10,
    ),
)
def test_project_agrees_with_opencv(cam: CameraModel, k: np.ndarray, pts: list) -> None:
    cam = _with_distortion(cam, k)
    X = np.array(pts)
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, k)
    np.testing.assert_allclose(cam.project(X), ref.reshape(-1, 2), atol=1e-9)


def test_project_rejects_points_behind_camera() -> None:
    cam = CameraModel(800.0, 800.0, 320.0, 240.0, 640, 480)
    with pytest.raises(InputError, match=r"^points: a point is behind the camera \(z <= 0\)$"):
        cam.project(np.array([[0.0, 0.0, 1.0], [0.1, 0.2, -1.0]]))


def test_in_view() -> None:
    cam = CameraModel(800.0, 800.0, 320.0, 240.0, 640, 480)
    uv = np.array([[-0.5, -0.5], [639.5, 479.5], [-0.6, 10.0], [100.0, 479.6], [5.0, 5.0]])
    np.testing.assert_array_equal(cam.in_view(uv), [True, True, False, False, True])
    np.testing.assert_array_equal(cam.in_view(uv, margin=10.0), [False] * 5)


def test_camera_validation() -> None:
    with pytest.raises(InputError, match=r"^camera.fx: expected a finite number > 0, got -1"):
        CameraModel(-1.0, 800.0, 320.0, 240.0, 640, 480)
    with pytest.raises(InputError, match=r"^camera.width: expected a positive integer, got 640.5"):
        CameraModel(800.0, 800.0, 320.0, 240.0, 640.5, 480)
    with pytest.raises(InputError, match=r"^camera.distortion: expected 4, 5, 8, 12 or 14"):
        CameraModel(800.0, 800.0, 320.0, 240.0, 640, 480, np.zeros(3))
    cam = CameraModel(800.0, 800.0, 320.0, 240.0, 640, 480)
    with pytest.raises(InputError, match=r"^uv: expected an array of shape \(N, 2\)"):
        cam.pixel_to_normalized(np.zeros((3, 3)))
    with pytest.raises(InputError, match=r"^m: third column must be > 0"):
        cam.normalized_to_pixel(np.array([[0.1, 0.2, 0.0]]))


# ----------------------------------------------------------------------------- rotation

angles = st.tuples(
    st.floats(-3.1, 3.1),  # roll
    st.floats(-1.5, 1.5),  # pitch, away from +-90 deg
    st.floats(-3.1, 3.1),  # yaw
)


@SETTINGS
@given(angles)
def test_euler_matches_gtsam_and_round_trips(rpw: tuple[float, float, float]) -> None:
    r, p, w = rpw
    R = euler_to_rotation(r, p, w)
    ref = (gtsam.Rot3.Ry(w) * gtsam.Rot3.Rx(p) * gtsam.Rot3.Rz(r)).matrix()
    np.testing.assert_allclose(R, ref, atol=1e-14)
    np.testing.assert_allclose(rotation_to_euler(R), rpw, atol=1e-9)


@SETTINGS
@given(
    st.tuples(st.floats(-3.1, 3.1), st.floats(-1.3, 1.3), st.floats(-3.1, 3.1)),
    st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
)
def test_euler_rates_match_numerical_derivative(rpw: tuple, w_body: list) -> None:
    """Paper eqs. 3-5 against d/dt of rotation_to_euler(R0 Exp(t w)) (body rates)."""
    r, p, w = rpw
    R0 = gtsam.Rot3(euler_to_rotation(r, p, w))
    h = 1e-6

    def angles_at(t: float) -> np.ndarray:
        return np.array(
            rotation_to_euler(R0.compose(gtsam.Rot3.Expmap(t * np.array(w_body))).matrix())
        )

    numeric = wrap_angle(angles_at(h) - angles_at(-h)) / (2 * h)
    np.testing.assert_allclose(euler_rates(r, p, np.array(w_body)), numeric, atol=1e-6)


def test_gimbal_lock() -> None:
    with pytest.raises(InputError, match=r"^pitch is \+-90 deg: the Euler rate equations"):
        euler_rates(0.2, np.pi / 2, np.array([0.1, 0.2, 0.3]))
    with pytest.raises(InputError, match=r"^rotation: pitch is \+-90 deg \(gimbal lock\)"):
        rotation_to_euler(euler_to_rotation(0.3, -np.pi / 2, 0.2))


def test_rotation_bad_input() -> None:
    with pytest.raises(InputError, match=r"^R: expected shape \(3, 3\), got \(2, 2\)$"):
        rotation_to_euler(np.eye(2))
    with pytest.raises(InputError, match=r"^w_body: expected shape \(3,\), got \(2,\)$"):
        euler_rates(0.0, 0.0, np.zeros(2))
    with pytest.raises(InputError, match=r"^w: contains NaN or inf$"):
        skew(np.array([0.0, np.nan, 1.0]))


@SETTINGS
@given(
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
)
def test_skew_is_cross_product(w: list, x: list) -> None:
    np.testing.assert_allclose(skew(np.array(w)) @ np.array(x), np.cross(w, x), atol=1e-12)


@SETTINGS
@given(
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    st.lists(st.floats(-0.1, 0.1), min_size=9, max_size=9),
)
def test_nearest_rotation_matches_gtsam(rv: list, noise: list) -> None:
    R = gtsam.Rot3.Expmap(np.array(rv)).matrix()
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-12)
    M = R + np.array(noise).reshape(3, 3)
    Q = nearest_rotation(M)
    np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Q) == pytest.approx(1.0)
    np.testing.assert_allclose(Q, gtsam.Rot3.ClosestTo(M).matrix(), atol=1e-9)


def test_wrap_angle() -> None:
    a = np.array([0.0, np.pi, -np.pi, 3 * np.pi, -0.5, 2 * np.pi + 0.5, -7.0])
    wrapped = wrap_angle(a)
    assert np.all((wrapped > -np.pi) & (wrapped <= np.pi))
    np.testing.assert_allclose(np.sin(wrapped), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(wrapped[[0, 1, 2, 4, 5]], [0.0, np.pi, np.pi, -0.5, 0.5], atol=1e-12)
