"""The twist from the continuous homography H_c of one frame pair (paper Section III-B).

Optical flow by finite difference, mdot = (m1 - m0) / dt at the midpoint
m = (m0 + m1) / 2, and the linear least-squares solve for (w, v/d) with the
plane (n, d) of mid-interval known (:func:`~hvo_graph.geometry.continuous.velocity_known_normal`).
The result is the body twist at the middle of the interval.

Per frame pair this builds the design matrix once and solves it with one SVD
(again only when the residual gate drops points); the points are the front
end's own checked arrays.
"""

from __future__ import annotations

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.continuous import _known_normal_solve
from hvo_graph.types import Plane, VelocityMeasurement


def flow_twist(
    m0: np.ndarray,
    m1: np.ndarray,
    t0: float,
    t1: float,
    plane: Plane,
    sigma: float,
    outlier_chi2: float | None = None,
    min_points: int = 4,
) -> VelocityMeasurement | None:
    """The H_c twist of the points m0 (time t0) -> m1 (time t1), with its covariance.

    Args:
        m0, m1: (N, 3) normalized points of the same tracks in the two frames.
        t0, t1: their times, t1 > t0 (seconds).
        plane: n(t), d(t) in the camera frame at mid-interval.
        sigma: pixel noise in normalized units; the flow's variance is 2 sigma^2 / dt^2
            per coordinate (two independent noisy frames).
        outlier_chi2: points whose flow residual exceeds this chi^2 (2 dof) are left
            out and the twist solved again; None: no gate.
        min_points: fewest points left for a twist (None below).
    Returns:
        The body twist [w; v] at (t0 + t1) / 2 with covariance
        s_f^2 J (A^T A)^-1 J^T, s_f^2 = 2 sigma^2 / dt^2, J = -diag(1, 1, 1, d, d, d).
    """
    if len(m0) < 3:
        raise InputError(f"m0: need at least 3 points, got {len(m0)}")
    dt = t1 - t0
    n, d = plane.normal, plane.distance
    n = n / np.linalg.norm(n)  # as velocity_known_normal's check leaves it
    m_mid = 0.5 * (m0 + m1)
    flow = ((m1 - m0) / dt)[:, :2]
    w, v, A = _known_normal_solve(m_mid, flow, n, d)
    if outlier_chi2 is not None:
        residual = (flow.ravel() - A @ np.concatenate((w, v / d))).reshape(-1, 2)
        keep = np.sum(residual**2, axis=1) * dt**2 / (2.0 * sigma**2) <= outlier_chi2
        if np.count_nonzero(keep) < min_points:
            return None
        if not keep.all():
            w, v, A = _known_normal_solve(m_mid[keep], flow[keep], n, d)
    twist = -np.concatenate((w, v))  # the body twist (body_twist_from_scene_motion)
    cov_wu = (2.0 * sigma**2 / dt**2) * np.linalg.inv(A.T @ A)
    j = np.array([-1.0, -1.0, -1.0, -d, -d, -d])  # J = diag(j): [w_b; v_b] = -[w; d u]
    covariance = j[:, None] * cov_wu * j[None, :]  # J cov_wu J^T
    return VelocityMeasurement(twist, 0.5 * (covariance + covariance.T), 0.5 * (t0 + t1), dt)


def mid_interval_plane(
    motions: list[tuple[np.ndarray, np.ndarray]],
    normal: np.ndarray,
    distance: float,
    points: np.ndarray | None = None,
) -> Plane | None:
    """The plane in the camera frame at mid-interval, from the motions (R, T) (world ->
    camera) known at the interval's ends: the mean of n(t) = R n* (renormalized) and of
    d(t) = d* + n(t)^T T. None when no motion is known, the plane would be behind, or
    the normalized ``points`` (N, 3) seen on it are not in front of it (n^T m <= 0: a
    pose far off, from a few noisy points, turned the plane past them).
    """
    if not motions:
        return None
    normals = [R @ normal for R, _ in motions]
    distances = [distance + float(n @ T) for n, (_, T) in zip(normals, motions, strict=True)]
    n_mid = np.mean(normals, axis=0)
    d_mid = float(np.mean(distances))
    n_mid = n_mid / np.linalg.norm(n_mid)
    if not d_mid > 0 or (points is not None and not float(np.min(points @ n_mid)) > 0):
        return None
    return Plane(d_mid, n_mid)
