"""Continuous homography H_c = w^ + v n^T / d: flow model, estimation, decomposition.

Optical flow ground truth is derived independently of the H_c model: from the
3D motion of the plane points (Xdot = w^ X + v, mdot = (Xdot z - X zdot) / z^2)
and, for the sign of the camera twist, by finite differences of the projection
of static world points seen from a camera moving along gtsam's Pose3.Expmap.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hvo_graph.errors import InputError
from hvo_graph.geometry.continuous import (
    body_twist_from_scene_motion,
    continuous_homography,
    decompose_continuous_homography,
    estimate_continuous_homography,
    physically_valid_continuous_solutions,
    plane_in_current_frame,
    point_flow,
    select_continuous_solution,
    velocity_design_matrix,
    velocity_known_normal,
)

SETTINGS = settings(max_examples=50, deadline=None)
TOL = 1e-8


@dataclass
class FlowScene:
    w: np.ndarray
    v: np.ndarray
    normal: np.ndarray  # n(t), current frame
    distance: float  # d(t)
    m: np.ndarray  # (N, 3)
    mdot: np.ndarray  # (N, 3), from the 3D motion

    @property
    def u(self) -> np.ndarray:
        return self.v / self.distance


def _min_triangle_area(m: np.ndarray) -> float:
    xy = m[:4, :2]
    areas = []
    for i, j, k in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
        a, b = xy[j] - xy[i], xy[k] - xy[i]
        areas.append(0.5 * abs(a[0] * b[1] - a[1] * b[0]))
    return min(areas)


def _vec(lo: float, hi: float) -> st.SearchStrategy[list[float]]:
    return st.lists(st.floats(lo, hi), min_size=3, max_size=3)


coord = st.floats(0.1, 0.6)


@st.composite
def flow_scenes(draw: st.DrawFn, pure_rotation: bool = False) -> FlowScene:
    tilt = draw(st.floats(0.0, 0.7))
    azimuth = draw(st.floats(-np.pi, np.pi))
    normal = np.array(
        [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
    )
    distance = draw(st.floats(0.5, 5.0))
    w = np.array(draw(_vec(-1.0, 1.0)))
    v = np.zeros(3) if pure_rotation else np.array(draw(_vec(-2.0, 2.0)))
    xy = [[sx * draw(coord), sy * draw(coord)] for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    n_extra = draw(st.integers(0, 16))
    xy += [[draw(st.floats(-0.6, 0.6)), draw(st.floats(-0.6, 0.6))] for _ in range(n_extra)]
    m = np.column_stack((np.array(xy), np.ones(len(xy))))
    assume(_min_triangle_area(m) > 5e-3)
    # Independent derivation from the 3D motion of the plane points.
    X = m * (distance / (m @ normal))[:, None]
    Xdot = np.cross(w, X) + v
    z, zdot = X[:, 2:3], Xdot[:, 2:3]
    mdot = (Xdot * z - X * zdot) / z**2
    return FlowScene(w, v, normal, distance, m, mdot)


# ----------------------------------------------------------------------------- model


@SETTINGS
@given(flow_scenes())
def test_flow_model_matches_3d_motion(scene: FlowScene) -> None:
    H_c = continuous_homography(scene.w, scene.v, scene.normal, scene.distance)
    np.testing.assert_allclose(point_flow(scene.m, H_c), scene.mdot, atol=1e-12)
    A = velocity_design_matrix(scene.m, scene.normal)
    assert A.shape == (2 * len(scene.m), 6)
    np.testing.assert_allclose(
        A @ np.concatenate((scene.w, scene.u)), scene.mdot[:, :2].ravel(), atol=1e-12
    )


@SETTINGS
@given(flow_scenes())
def test_known_normal_velocity(scene: FlowScene) -> None:
    w, v = velocity_known_normal(scene.m, scene.mdot, scene.normal, scene.distance)
    np.testing.assert_allclose(w, scene.w, atol=TOL)
    np.testing.assert_allclose(v, scene.v, atol=TOL)
    # (N, 2) flow is accepted too.
    w2, v2 = velocity_known_normal(scene.m[:, :2], scene.mdot[:, :2], scene.normal, scene.distance)
    np.testing.assert_allclose(np.concatenate((w2, v2)), np.concatenate((w, v)), atol=1e-13)


@SETTINGS
@given(flow_scenes())
def test_estimate_and_decompose(scene: FlowScene) -> None:
    u = scene.u
    assume(np.linalg.norm(u) > 0.05)
    # Away from u parallel to n, where the two solutions merge and the
    # decomposition is only sqrt(eps)-accurate.
    assume(abs(u @ scene.normal) / np.linalg.norm(u) < 0.99)
    H_true = continuous_homography(scene.w, scene.v, scene.normal, scene.distance)
    H_c = estimate_continuous_homography(scene.m, scene.mdot)
    np.testing.assert_allclose(H_c, H_true, atol=TOL)
    solutions = decompose_continuous_homography(H_c)
    assert len(solutions) == 4
    for sol in solutions:  # each reproduces H_c with a unit normal
        assert np.linalg.norm(sol.normal) == pytest.approx(1.0, abs=1e-12)
        W = np.array(
            [
                [0.0, -sol.angular[2], sol.angular[1]],
                [sol.angular[2], 0.0, -sol.angular[0]],
                [-sol.angular[1], sol.angular[0], 0.0],
            ]
        )
        np.testing.assert_allclose(W + np.outer(sol.linear_over_depth, sol.normal), H_c, atol=1e-10)
    valid = physically_valid_continuous_solutions(solutions, scene.m)
    assert 1 <= len(valid) <= 2
    best = select_continuous_solution(valid, scene.normal)
    np.testing.assert_allclose(best.angular, scene.w, atol=TOL)
    np.testing.assert_allclose(best.linear_over_depth, u, atol=TOL)
    np.testing.assert_allclose(best.normal, scene.normal, atol=TOL)


@SETTINGS
@given(flow_scenes(pure_rotation=True))
def test_pure_rotation(scene: FlowScene) -> None:
    w, v = velocity_known_normal(scene.m, scene.mdot, scene.normal, scene.distance)
    np.testing.assert_allclose(w, scene.w, atol=TOL)
    np.testing.assert_allclose(v, 0.0, atol=TOL)
    assume(np.linalg.norm(scene.w) > 0.05)
    H_c = estimate_continuous_homography(scene.m, scene.mdot)
    (sol,) = decompose_continuous_homography(H_c)
    np.testing.assert_allclose(sol.angular, scene.w, atol=TOL)
    np.testing.assert_array_equal(sol.linear_over_depth, np.zeros(3))
    np.testing.assert_array_equal(sol.normal, [0.0, 0.0, 1.0])


def test_no_motion() -> None:
    m = np.array([[0.1, 0.2, 1.0], [-0.3, 0.25, 1.0], [-0.2, -0.3, 1.0], [0.35, -0.1, 1.0]])
    H_c = estimate_continuous_homography(m, np.zeros((4, 2)))
    np.testing.assert_allclose(H_c, 0.0, atol=1e-15)
    (sol,) = decompose_continuous_homography(H_c)
    np.testing.assert_allclose(sol.angular, 0.0, atol=1e-15)


# ----------------------------------------------------------------------------- conventions


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    st.lists(st.floats(-0.4, 0.4), min_size=3, max_size=3),
)
def test_body_twist_sign_by_finite_differences(w_b: list, v_b: list, rv: list) -> None:
    """A camera moving with body twist xi = [w_b; v_b] (d/dt T_wc = T_wc xi^, gtsam's
    Pose3 tangent) sees flow that the model reproduces with (w, v) = -xi, and
    body_twist_from_scene_motion(velocity_known_normal(...)) returns xi.
    """
    xi = np.array(w_b + v_b)
    T0 = gtsam.Pose3(gtsam.Rot3.Expmap(np.array(rv)), np.array([0.1, -0.2, 0.3]))
    # World plane: 3 m in front of the camera at t = 0, tilted.
    n0 = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    m0 = np.array([[0.3, 0.2, 1], [-0.3, 0.25, 1], [-0.2, -0.3, 1], [0.35, -0.1, 1], [0, 0.05, 1]])
    X0 = m0 * (3.0 / (m0 @ n0))[:, None]
    P = np.array([T0.transformFrom(x) for x in X0])  # static world points

    def image(dt: float) -> np.ndarray:
        pose = T0.compose(gtsam.Pose3.Expmap(dt * xi))
        X = np.array([pose.transformTo(p) for p in P])
        return X / X[:, 2:3]

    h = 1e-5
    mdot = (image(h) - image(-h)) / (2 * h)
    np.testing.assert_allclose(image(0.0), m0, atol=1e-12)
    H_c = continuous_homography(-xi[:3], -xi[3:], n0, 3.0)
    np.testing.assert_allclose(point_flow(m0, H_c), mdot, atol=1e-7)
    w, v = velocity_known_normal(m0, mdot, n0, 3.0)
    np.testing.assert_allclose(body_twist_from_scene_motion(w, v), xi, atol=1e-7)


@SETTINGS
@given(
    st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3),
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    st.floats(0.0, 0.7),
    st.floats(1.0, 5.0),
)
def test_plane_in_current_frame(rv: list, T: list, tilt: float, d_ref: float) -> None:
    R = gtsam.Rot3.Expmap(np.array(rv)).matrix()
    T = np.array(T)
    n_ref = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    assume(d_ref + (R @ n_ref) @ T > 0.1)
    # Three plane points in the reference frame, moved into the current frame.
    e1 = np.cross(n_ref, [0.0, 1.0, 0.0])
    X_ref = d_ref * n_ref + np.array([[0, 0, 0], e1, [0.0, 1.0, 0.0]])
    X_cur = X_ref @ R.T + T
    n, d = plane_in_current_frame(R, T, n_ref, d_ref)
    np.testing.assert_allclose(X_cur @ n, d, atol=1e-12)
    assert np.linalg.norm(n) == pytest.approx(1.0)
    assert d > 0


# ----------------------------------------------------------------------------- bad input

M4 = np.array([[0.1, 0.2, 1.0], [-0.3, 0.25, 1.0], [-0.2, -0.3, 1.0], [0.35, -0.1, 1.0]])
N = np.array([0.0, 0.0, 1.0])


def test_too_few_points() -> None:
    with pytest.raises(InputError, match=r"^m: need at least 4 points, got 3$"):
        estimate_continuous_homography(M4[:3], np.zeros((3, 2)))
    with pytest.raises(InputError, match=r"^m: need at least 3 points, got 2$"):
        velocity_known_normal(M4[:2], np.zeros((2, 2)), N, 1.0)


def test_shapes_and_values() -> None:
    with pytest.raises(InputError, match=r"^mdot: expected as many rows as m \(4\), got 5$"):
        estimate_continuous_homography(M4, np.zeros((5, 2)))
    with pytest.raises(InputError, match=r"^mdot: third column must be 0 .* got 0.5 in row 2$"):
        estimate_continuous_homography(M4, np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0.5], [0, 0, 0]]))
    with pytest.raises(InputError, match=r"^mdot: expected an array of shape"):
        velocity_known_normal(M4, np.zeros(8), N, 1.0)
    with pytest.raises(InputError, match=r"^H_c: expected shape \(3, 3\), got \(2, 2\)$"):
        point_flow(M4, np.eye(2))
    with pytest.raises(InputError, match=r"^normal: expected a unit vector"):
        continuous_homography(np.zeros(3), np.zeros(3), [0.0, 1.0, 1.0], 1.0)
    with pytest.raises(InputError, match=r"^distance: expected a finite number > 0"):
        velocity_known_normal(M4, np.zeros((4, 2)), N, -2.0)


@pytest.mark.parametrize("bad", [np.nan, -np.inf])
def test_nan_inf(bad: float) -> None:
    f = np.zeros((4, 2))
    f[1, 1] = bad
    with pytest.raises(InputError, match=r"^mdot: contains NaN or inf$"):
        estimate_continuous_homography(M4, f)
    m = M4.copy()
    m[0, 0] = bad
    with pytest.raises(InputError, match=r"^m: contains NaN or inf$"):
        velocity_known_normal(m, np.zeros((4, 2)), N, 1.0)


def test_collinear_points() -> None:
    line = np.column_stack((np.linspace(-0.5, 0.5, 6), 0.2 * np.linspace(-0.5, 0.5, 6)))
    with pytest.raises(InputError, match=r"^m: degenerate point configuration \(collinear"):
        estimate_continuous_homography(line, np.zeros((6, 2)))
    three = np.array([[-0.4, -0.4], [0.0, 0.0], [0.4, 0.4], [0.3, -0.2]])
    with pytest.raises(InputError, match=r"^m: degenerate point configuration \(collinear"):
        estimate_continuous_homography(three, np.zeros((4, 2)))
    # Two distinct points, repeated: rank-deficient known-normal system.
    two = np.array([[0.1, 0.1], [0.3, -0.2], [0.1, 0.1], [0.3, -0.2]])
    with pytest.raises(InputError, match=r"^m: degenerate point configuration \(collinear"):
        velocity_known_normal(two, np.zeros((4, 2)), N, 1.0)


def test_points_behind_camera() -> None:
    with pytest.raises(InputError, match=r"^m: points behind the camera"):
        velocity_known_normal(M4, np.zeros((4, 2)), -N, 1.0)
    with pytest.raises(InputError, match=r"^R, T: the camera is on the far side of the plane"):
        plane_in_current_frame(np.eye(3), [0.0, 0.0, -2.0], N, 1.0)


def test_unnormalized_continuous_homography_is_rejected() -> None:
    H = continuous_homography([0.1, 0.2, 0.3], [0.5, -0.2, 0.1], N, 2.0)
    with pytest.raises(InputError, match=r"^H_c: the middle eigenvalue of H_c \+ H_c\^T must be 0"):
        decompose_continuous_homography(H + 0.3 * np.eye(3))
    with pytest.raises(InputError, match=r"^solutions: empty list"):
        select_continuous_solution([], N)
