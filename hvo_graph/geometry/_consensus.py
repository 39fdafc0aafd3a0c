"""Whether every point of a frame is an inlier, so that RANSAC need not run.

RANSAC (OpenCV's ``findHomography``) keeps the largest consensus set it meets among
the homographies of 4-point samples: the points within a transfer distance
(``threshold``) of the sample's homography. When each point lies within the
threshold of the homography fitted to *the other points*, all points form one
consensus set, and RANSAC can find no larger one; with noisy minimal samples it
often returns a smaller one (good points marked as outliers).

The test must see an outlier even though a least-squares fit that includes it leans
towards it: a point displaced by delta from the others' homography shows a residual
of only about (1 - h) delta under the fit of all points, h its leverage (the share of
the fit it controls: 8 parameters over N points, large for few points). The test
therefore judges each point by its *deleted* residual, the distance from the
homography fitted without it, in the first-order form of least squares: the
algebraic residual e_i (2,) of the normalized DLT system A h = 0, premultiplied by
(I - P_ii)^-1, with P_ii the point's 2 x 2 block of the projection onto the column
space of A orthogonal to h (the hat matrix of the DLT's 8 free directions). The
transfer distance of the fit of all points is scaled by ||(I - P_ii)^-1 e_i|| /
||e_i||. With 4 points (no spare point) every P_ii is I: never all inliers.

Shapes: F frames, N points; m_ref (N, 3) or (F, N, 3), m_cur (F, N, 3), normalized
coordinates [x, y, 1].
"""

from __future__ import annotations

import numpy as np


def _hartley(xy: np.ndarray) -> np.ndarray:
    """(..., 3, 3) similarity moving the centroid of (..., N, 2) points to 0 and their mean
    distance to sqrt(2) (coinciding points: scale 1, the system is then degenerate)."""
    c = xy.mean(axis=-2)
    mean_dist = np.linalg.norm(xy - c[..., None, :], axis=-1).mean(axis=-1)
    s = np.sqrt(2.0) / np.where(mean_dist > 0.0, mean_dist, 1.0)
    T = np.zeros((*s.shape, 3, 3))
    T[..., 0, 0] = T[..., 1, 1] = s
    T[..., 0, 2] = -s * c[..., 0]
    T[..., 1, 2] = -s * c[..., 1]
    T[..., 2, 2] = 1.0
    return T


def deleted_distances(m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """(F, N) each point's transfer distance ||m - pi(H m*)|| from the homography H
    fitted to the other points (first order, see the module docstring); inf where
    the point has no spare (leverage 1) or the fit sends it to infinity."""
    F, N = m_cur.shape[:2]
    m_ref = np.broadcast_to(m_ref, m_cur.shape)
    T_ref, T_cur = _hartley(m_ref[..., :2]), _hartley(m_cur[..., :2])
    a = m_ref @ np.swapaxes(T_ref, -1, -2)
    b = m_cur @ np.swapaxes(T_cur, -1, -2)
    A = np.zeros((F, N, 2, 9))  # rows x and y of b x (H a) = 0 for h = H.ravel()
    A[:, :, 0, 3:6] = -a
    A[:, :, 0, 6:9] = b[..., 1:2] * a
    A[:, :, 1, 0:3] = a
    A[:, :, 1, 6:9] = -b[..., 0:1] * a
    A = A.reshape(F, 2 * N, 9)
    U, _, Vt = np.linalg.svd(A, full_matrices=2 * N < 9)
    h = Vt[:, -1]
    e = (A @ h[..., None]).reshape(F, N, 2)
    U8 = U[..., :8].reshape(F, N, 2, 8)
    P = U8 @ np.swapaxes(U8, -1, -2)  # (F, N, 2, 2) blocks of the hat matrix
    p, q, r = 1.0 - P[..., 0, 0], -P[..., 0, 1], 1.0 - P[..., 1, 1]
    det = p * r - q * q
    spare = det > 1e-12  # leverage below 1: the others fix the homography
    det = np.where(spare, det, 1.0)
    e_del = np.stack((r * e[..., 0] - q * e[..., 1], p * e[..., 1] - q * e[..., 0]), -1)
    e_norm = np.linalg.norm(e, axis=-1)
    scale = np.linalg.norm(e_del, axis=-1) / (det * np.where(e_norm > 0.0, e_norm, 1.0))
    scale = np.where(e_norm > 0.0, scale, 1.0 / np.sqrt(det))
    H = np.linalg.solve(T_cur, h.reshape(F, 3, 3) @ T_ref)
    x = m_ref @ np.swapaxes(H, -1, -2)
    z = np.where(x[..., 2] == 0.0, np.nan, x[..., 2])
    d = np.hypot(x[..., 0] / z - m_cur[..., 0], x[..., 1] / z - m_cur[..., 1])
    d = np.where(spare & np.isfinite(d), d * scale, np.inf)
    return d


def all_inliers(m_ref: np.ndarray, m_cur: np.ndarray, threshold: float) -> np.ndarray:
    """(F,) bool: every point within ``threshold`` (normalized units, pixels / focal
    length) of the homography of the others (:func:`deleted_distances`): RANSAC with
    this threshold can keep no more points, and need not run."""
    return np.all(deleted_distances(m_ref, m_cur) <= threshold, axis=1)
