"""hvo_graph.geometry.transfer: the transfer residuals, their Jacobians and the retraction,
checked against finite differences."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.geometry.rotation import euler_to_rotation
from hvo_graph.geometry.transfer import (
    linearize_transfer,
    pose_covariance_parts,
    pose_normal_equations,
    projection_jacobian,
    retract_motion,
)
from hvo_graph.types import Plane

PLANE = Plane(distance=2.0, normal=np.array([0.1, -0.2, 1.0]))
R = euler_to_rotation(0.05, -0.03, 0.1)
T = np.array([0.2, -0.1, 0.15])


def points(n: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) reference points m* and their noisy transfers m."""
    rng = np.random.default_rng(seed)
    m_ref = np.column_stack((rng.uniform(-0.3, 0.3, (n, 2)), np.ones(n)))
    X = PLANE.distance * m_ref / (m_ref @ PLANE.normal)[:, None] @ R.T + T
    m_cur = X / X[:, 2:]
    m_cur[:, :2] += rng.normal(scale=1e-3, size=(n, 2))
    return m_ref, m_cur


def test_projection_jacobian_matches_finite_differences():
    X = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 3.0]])
    J = projection_jacobian(X)
    eps = 1e-7
    for j in range(3):
        dX = np.zeros(3)
        dX[j] = eps
        numeric = ((X + dX)[:, :2] / (X + dX)[:, 2:] - X[:, :2] / X[:, 2:]) / eps
        np.testing.assert_allclose(J[:, :, j], numeric, atol=1e-6)


def test_transfer_jacobian_is_the_derivative_under_the_right_perturbation():
    m_ref, m_cur = points()
    lin = linearize_transfer(R, T, m_ref, m_cur, PLANE, sigma=1e-3)
    eps = 1e-7
    for j in range(6):
        delta = np.zeros(6)
        delta[j] = eps
        moved = linearize_transfer(*retract_motion(R, T, delta), m_ref, m_cur, PLANE, 1e-3)
        # r = m - pi(X): the residual moves against the projection
        np.testing.assert_allclose(
            (moved.residual - lin.residual) / eps, -lin.J[:, :, j], atol=1e-5
        )


def test_gauss_newton_steps_reach_the_weighted_optimum():
    m_ref, m_cur = points(seed=1)
    R_k, T_k = R, T
    for _ in range(3):
        info, grad = pose_normal_equations(R_k, T_k, m_ref, m_cur, PLANE, 1e-3)
        R_k, T_k = retract_motion(R_k, T_k, np.linalg.solve(info, grad))
    _, grad = pose_normal_equations(R_k, T_k, m_ref, m_cur, PLANE, 1e-3)
    assert np.linalg.norm(grad) < 1e-6 * np.linalg.norm(info)


def test_a_point_behind_the_camera_is_refused():
    m_ref, m_cur = points()
    with pytest.raises(InputError, match="non-positive depth"):
        linearize_transfer(R, np.array([0.0, 0.0, -10.0]), m_ref, m_cur, PLANE, 1e-3)


def test_covariance_parts_match_monte_carlo_of_each_frames_noise():
    """Noise on the reference points only, then on the current points only: the scatter of
    the refined pose matches C_ref and C_cur, and together they are the total info^-1."""
    m_ref, _ = points(n=6, seed=3)
    sigma = 1e-3
    X = PLANE.distance * m_ref / (m_ref @ PLANE.normal)[:, None] @ R.T + T
    clean = X / X[:, 2:]
    truth = gtsam.Pose3(gtsam.Rot3(R.T), -R.T @ T)

    def refined(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        Rk, Tk = R, T
        for _ in range(4):
            info, grad = pose_normal_equations(Rk, Tk, a, b, PLANE, sigma)
            Rk, Tk = retract_motion(Rk, Tk, np.linalg.solve(info, grad))
        # Log(T_wc_true^-1 T_wc): the right-perturbation tangent the covariances use
        return gtsam.Pose3.Logmap(truth.between(gtsam.Pose3(gtsam.Rot3(Rk.T), -Rk.T @ Tk)))

    rng = np.random.default_rng(7)

    def noisy(m: np.ndarray) -> np.ndarray:
        return np.column_stack((m[:, :2] + sigma * rng.standard_normal((len(m), 2)), m[:, 2]))

    ref_errors = np.array([refined(noisy(m_ref), clean) for _ in range(600)])
    cur_errors = np.array([refined(m_ref, noisy(clean)) for _ in range(600)])
    current, reference = pose_covariance_parts(R, T, m_ref, clean, PLANE, sigma)
    info, _ = pose_normal_equations(R, T, m_ref, clean, PLANE, sigma)
    np.testing.assert_allclose(current + reference, np.linalg.inv(info), rtol=1e-8, atol=1e-14)
    for errors, covariance in ((ref_errors, reference), (cur_errors, current)):
        np.testing.assert_allclose(np.std(errors, axis=0), np.sqrt(np.diag(covariance)), rtol=0.12)
