"""The fast per-frame paths equal the straightforward, argument-checking functions.

The front end fits each H_d pose with :mod:`hvo_graph.geometry._fit` (constants
computed once per frame, one linearization shared by the gate and the noise), the
velocity with one design matrix, the Kalman filter with Python-float Euler
matrices, and the process-noise fit inverts its Cholesky factors by substitution.
Each must give what the public functions (or numpy's own inverse) give.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from hvo_graph.estimators.kalman_model import (
    _euler_angles,
    _euler_rates,
    _rotation,
    euler_rate_matrix,
)
from hvo_graph.frontend.velocity import flow_twist
from hvo_graph.geometry._fit import PlaneTransfer, dlt, euclidean, known_normal_motion, plane_basis
from hvo_graph.geometry._fit import retract as fast_retract
from hvo_graph.geometry.continuous import velocity_design_matrix, velocity_known_normal
from hvo_graph.geometry.decomposition import motion_from_homography_known_normal
from hvo_graph.geometry.discrete import estimate_homography, euclidean_homography
from hvo_graph.geometry.rotation import euler_to_rotation, rotation_to_euler
from hvo_graph.geometry.transfer import (
    pose_noise,
    pose_normal_equations,
    retract_motion,
    transfer_chi2,
)
from hvo_graph.types import Plane

TOL = 1e-12


def plane_scene(n_points: int, seed: int):
    """A tilted plane seen from two poses with pixel-like noise: m_ref, m_cur, plane, R, T."""
    rng = np.random.default_rng(seed)
    normal = np.array([0.1, -0.2, 1.0])
    plane = Plane(2.0, normal / np.linalg.norm(normal))
    xy = rng.uniform(-0.4, 0.4, (n_points, 2))
    m_ref = np.column_stack((xy, np.ones(n_points)))
    X_star = plane.distance * m_ref / (m_ref @ plane.normal)[:, None]
    R = gtsam.Rot3.RzRyRx(0.05, -0.08, 0.03).matrix()
    T = np.array([0.1, -0.05, 0.2])
    X = X_star @ R.T + T
    m_cur = X / X[:, 2:3]
    m_cur[:, :2] += 1e-3 * rng.standard_normal((n_points, 2))
    return m_ref, m_cur, plane, R, T


def close(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.max(np.abs(a - b)) <= TOL * max(1.0, np.max(np.abs(b)))


@pytest.mark.parametrize("n_points", [4, 20])
@pytest.mark.parametrize("huber", [None, 2.0])
def test_pose_fit_equals_the_transfer_functions(n_points, huber):
    m_ref, m_cur, plane, R, T = plane_scene(n_points, seed=n_points)
    sigma = 1e-3
    fit = PlaneTransfer(m_ref, m_cur, plane, sigma)
    # Away from the optimum, as in the first Gauss-Newton step.
    R0, T0 = retract_motion(R, T, np.array([0.01, -0.02, 0.01, 0.03, 0.0, -0.02]))
    info, grad = fit.normal_equations(R0, T0, huber)
    info_ref, grad_ref = pose_normal_equations(R0, T0, m_ref, m_cur, plane, sigma, huber)
    assert close(info, info_ref) and close(grad, grad_ref)
    delta = np.linalg.solve(info, grad)
    assert all(map(close, fast_retract(R0, T0, delta), retract_motion(R0, T0, delta)))
    lin = fit.linearize(R0, T0)
    assert close(fit.chi2(lin, info), transfer_chi2(R0, T0, m_ref, m_cur, plane, sigma, info))
    for fast, reference in zip(
        fit.noise(lin), pose_noise(R0, T0, m_ref, m_cur, plane, sigma), strict=True
    ):
        assert close(fast, reference)
    keep = np.arange(n_points) != 1
    sub = fit.subset(keep)
    assert close(
        sub.normal_equations(R0, T0)[0],
        pose_normal_equations(R0, T0, m_ref[keep], m_cur[keep], plane, sigma)[0],
    )


@pytest.mark.parametrize("n_points", [4, 9])
def test_homography_pose_equals_the_public_path(n_points):
    m_ref, m_cur, plane, _, _ = plane_scene(n_points, seed=7)
    H_ref, _ = estimate_homography(m_ref, m_cur)
    H = dlt(m_ref, m_cur)
    assert close(H, H_ref)
    E = euclidean(H, m_ref, m_cur)
    assert close(E, euclidean_homography(H_ref, m_ref, m_cur))
    R_fast, t_fast = known_normal_motion(E, plane.normal, plane_basis(plane.normal))
    R_ref, t_ref = motion_from_homography_known_normal(E, plane.normal)
    assert close(R_fast, R_ref) and close(t_fast, t_ref)


def test_flow_twist_equals_the_known_normal_solve():
    rng = np.random.default_rng(3)
    m0 = np.column_stack((rng.uniform(-0.4, 0.4, (8, 2)), np.ones(8)))
    m1 = m0 + np.column_stack((0.01 * rng.standard_normal((8, 2)), np.zeros(8)))
    normal = np.array([0.05, 0.1, 1.0])
    plane = Plane(1.5, normal)
    meas = flow_twist(m0, m1, 0.0, 1 / 30, plane, 1e-3)
    mid, flow = 0.5 * (m0 + m1), (m1 - m0) * 30
    w, v = velocity_known_normal(mid, flow, plane.normal, plane.distance)
    assert close(meas.twist, -np.concatenate((w, v)))
    A = velocity_design_matrix(mid, plane.normal)
    J = -np.diag([1.0, 1.0, 1.0, 1.5, 1.5, 1.5])
    expected = J @ ((2.0 * 1e-6 * 30**2) * np.linalg.inv(A.T @ A)) @ J.T
    assert close(meas.covariance, expected)


def test_kalman_euler_helpers_equal_the_rotation_functions():
    rng = np.random.default_rng(5)
    for r, p, w in rng.uniform(-1.5, 1.5, (50, 3)):
        R = euler_to_rotation(r, p, w)
        assert close(_rotation(r, p, w), R)
        assert close(_euler_angles(R), rotation_to_euler(R))
        assert close(_euler_rates(r, p, "x"), euler_rate_matrix(r, p))


def test_a_reused_pose_fit_equals_a_fresh_one():
    m_ref, m_cur, plane, R, T = plane_scene(6, seed=11)
    kept = PlaneTransfer(m_ref, m_ref.copy(), plane, 1e-3)
    reused = PlaneTransfer.reuse(kept, m_ref, m_cur, plane, 1e-3)
    assert reused is not kept and kept.m_cur is not m_cur  # the kept one is unchanged
    fresh = PlaneTransfer(m_ref, m_cur, plane, 1e-3)
    assert all(map(close, reused.normal_equations(R, T), fresh.normal_equations(R, T)))
    other_plane = Plane(plane.distance, plane.normal)
    assert PlaneTransfer.reuse(kept, m_ref, m_cur, other_plane, 1e-3).plane is other_plane


@pytest.mark.parametrize("n_points", [4, 20])
def test_batched_pose_fit_equals_the_per_frame_one(n_points):
    """The stacked fit (_fit_batch, entry by entry 2 x 2 algebra) against PlaneTransfer on
    each frame: linearization, Huber and point-subset normal equations, chi^2, noise
    (relative to each array's largest entry: covariances are ~1e-8)."""
    from hvo_graph.geometry._fit_batch import BatchTransfer

    def close(a, b) -> bool:
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b))

    m_ref, m_cur, plane, R, T = plane_scene(n_points, seed=3 * n_points)
    rng = np.random.default_rng(n_points)
    frames = 5
    m = np.repeat(m_cur[None], frames, axis=0)
    m[..., :2] += 2e-3 * rng.standard_normal((frames, n_points, 2))
    m[1, 0, :2] += 0.05  # an outlier: the Huber weights and the gate see it
    motions = [retract_motion(R, T, 0.02 * rng.standard_normal(6)) for _ in range(frames)]
    Rs, Ts = np.array([r for r, _ in motions]), np.array([t for _, t in motions])
    w = np.ones((frames, n_points))
    w[2, 1] = 0.0  # a point left out of one frame's fit
    sigma = 1e-3
    batch = BatchTransfer(m_ref, m, plane.normal, plane.distance, sigma)
    (J, JtW, residual, A, cov, inv), bad = batch.linearize(Rs, Ts)
    assert not bad.any()
    info_h, grad_h, _ = batch.normal_equations(Rs, Ts, 2.0, w)
    info, _, _ = batch.normal_equations(Rs, Ts, None, w)
    chi2 = batch.chi2((J, JtW, residual, A, cov, inv), info)
    noise = batch.noise((J, JtW, residual, A, cov, inv), w)
    for k in range(frames):
        one = PlaneTransfer(m_ref, m[k], plane, sigma)
        lin = one.linearize(Rs[k], Ts[k])
        for got, want in zip(
            (J, JtW, residual, A, cov), (lin.J, lin.JtW, lin.residual, lin.A, lin.cov), strict=True
        ):
            assert close(got[k], want)
        assert close(inv[k], np.linalg.inv(lin.cov))
        used = w[k] > 0
        sub = one.subset(used)
        want_h = sub.normal_equations(Rs[k], Ts[k], 2.0)
        assert close(info_h[k], want_h[0]) and close(grad_h[k], want_h[1])
        want_info = sub.normal_equations(Rs[k], Ts[k])[0]
        assert close(info[k], want_info)
        assert close(chi2[k], one.chi2(lin, want_info))
        want_noise = sub.noise(sub.linearize(Rs[k], Ts[k]))
        assert close(noise[0][k], want_noise[0]) and close(noise[1][k], want_noise[1])
        assert close(noise[2][k][:, np.repeat(used, 2)], want_noise[2])
        assert not noise[2][k][:, np.repeat(~used, 2)].any()


def test_batched_null_vectors_and_ratios_are_the_svds():
    from hvo_graph.geometry import _fit_batch

    rng = np.random.default_rng(3)
    A = rng.normal(size=(60, 8, 9))  # 4 points: 8 rows, a null space of one vector or more
    B = rng.normal(size=(60, 40, 9))  # 20 points
    # Near-degenerate systems (sigma_8 / sigma_1 ~1e-3 and ~1e-9: the second below the
    # degeneracy tolerance, where the SVD decides).
    for systems in (A, B):
        U, s, Vt = np.linalg.svd(systems[:10], full_matrices=False)
        s[:5, 7], s[5:, 7] = 1e-3 * s[:5, 0], 1e-9 * s[5:, 0]
        systems[:10] = (U * s[:, None, :]) @ Vt
    for systems in (A, B):
        _, s, Vt = np.linalg.svd(systems, full_matrices=True)
        want = s[:, 7] / s[:, 0]
        h, ratio = _fit_batch._null_vectors(systems)
        np.testing.assert_allclose(_fit_batch._ratios(systems), want, rtol=1e-6)
        np.testing.assert_allclose(ratio, want, rtol=1e-6)
        assert np.all((want[5:10] < 1e-8) == (ratio[5:10] < 1e-8))
        # The null vector up to sign: the residual of the smallest singular value.
        np.testing.assert_allclose(np.abs(np.sum(h * Vt[:, -1], axis=1)), 1.0, atol=1e-9)
