"""Which points of a frame are inliers, where that needs no RANSAC.

RANSAC (OpenCV's ``findHomography``) keeps the largest consensus set it meets among
the homographies of 4-point samples: the points within a transfer distance
(``threshold``) of the sample's homography. When each point lies within the
threshold of the homography fitted to *the other points*, all points form one
consensus set, and RANSAC can find no larger one; with noisy minimal samples it
often returns a smaller one (good points marked as outliers). When exactly one point
lies beyond, and without it every other point is within the threshold of the fit of
the rest, the others are the consensus set: the point left out is off the fit of all
of them. With many points that is the usual case of a noisy frame (with 20 points
and the threshold at 5 pixel sigmas, a fifth of the frames have one point beyond:
its deleted residual also carries the others' fit's error), and RANSAC then ran
on it to return the same set or a smaller one.

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


def deleted_distances(m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """(F, N) each point's transfer distance ||m - pi(H m*)|| from the homography H
    fitted to the other points (first order, see the module docstring); inf or nan
    where the point has no spare (leverage 1) or the fit sends it to infinity.

    Written for few numpy calls: the front end also calls it one frame at a time.
    """
    F, N = m_cur.shape[:2]
    # Hartley normalization of both point sets at once: centroid 0, mean distance sqrt(2).
    xy = np.empty((2, F, N, 2))
    xy[0] = m_ref[..., :2]
    xy[1] = m_cur[..., :2]
    xy -= xy.mean(axis=2, keepdims=True)
    scale = np.sqrt(2.0) / np.sqrt(np.einsum("sfni,sfni->sfn", xy, xy)).mean(axis=2)
    xy *= scale[..., None, None]
    a = np.ones((F, N, 3))
    a[..., :2] = xy[0]
    bx, by = xy[1, ..., 0:1], xy[1, ..., 1:2]
    A = np.zeros((F, N, 2, 9))  # rows x and y of b x (H a) = 0 for h = H.ravel()
    A[:, :, 0, 3:6] = -a
    A[:, :, 0, 6:9] = by * a
    A[:, :, 1, 0:3] = a
    A[:, :, 1, 6:9] = -bx * a
    A = A.reshape(F, 2 * N, 9)
    with np.errstate(divide="ignore", invalid="ignore"):
        # h and the 8 other right singular vectors from the 9 x 9 normal matrix (its
        # eigenvectors; half the time of the SVD of A), the left ones as A V / sigma.
        lam, V = np.linalg.eigh(np.swapaxes(A, 1, 2) @ A)
        h = V[..., 0]
        e = (A @ h[:, :, None]).reshape(F, N, 2)
        U8 = (A @ (V[..., 1:] / np.sqrt(lam[:, None, 1:]))).reshape(F, N, 2, 8)
        P = U8 @ np.swapaxes(U8, -1, -2)  # (F, N, 2, 2) blocks of the hat matrix
        p, q, r = 1.0 - P[..., 0, 0], -P[..., 0, 1], 1.0 - P[..., 1, 1]
        det = p * r - q * q
        # ||(I - P_ii)^-1 e_i|| / ||e_i|| (the adjugate of I - P_ii over its determinant)
        e0, e1 = e[..., 0], e[..., 1]
        grow = np.sqrt(((r * e0 - q * e1) ** 2 + (p * e1 - q * e0) ** 2) / (e0 * e0 + e1 * e1))
        grow = np.where(det > 1e-12, grow / det, np.inf)  # leverage 1: no spare point
        x = a @ np.swapaxes(h.reshape(F, 3, 3), -1, -2)
        d = np.hypot(x[..., 0] / x[..., 2] - bx[..., 0], x[..., 1] / x[..., 2] - by[..., 0])
        # Back to m_cur's units; a point fitted exactly (e_i = 0) but not alone has distance 0.
        d = np.where((d == 0.0) & (det > 1e-12), 0.0, d * grow)
        return d / scale[1][:, None]


def consensus_inliers(
    m_ref: np.ndarray, m_cur: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """(inliers (F, N), decided (F,)): each point within ``threshold`` of the homography of
    the others (:func:`deleted_distances`), and the frames where that answers RANSAC's
    question, so that it need not run: every point within (one consensus set), or
    exactly one point beyond and every other point within ``threshold`` of the fit of
    the others without it (a consensus set of all but that point, which is off the fit
    of all the others). Frames with more points beyond are undecided: RANSAC judges."""
    inliers = deleted_distances(m_ref, m_cur) <= threshold
    outside = np.count_nonzero(~inliers, axis=1)
    decided = outside == 0
    single = np.flatnonzero(outside == 1)
    if single.size:  # the left-out fits again, without the one point beyond
        kept = inliers[single]
        shape = (len(single), m_cur.shape[1] - 1, 3)
        ref = np.broadcast_to(m_ref, m_cur.shape)[single][kept].reshape(shape)
        cur = m_cur[single][kept].reshape(shape)
        decided[single] = np.all(deleted_distances(ref, cur) <= threshold, axis=1)
    return inliers, decided
