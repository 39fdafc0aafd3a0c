"""The front end's H_d pose fit for many frames at once (a leading frame axis F).

The arithmetic of :mod:`hvo_graph.geometry._fit` (the normalized DLT, the Euclidean
normalization, the known-normal motion, the Gauss-Newton refinement of the transfer
error, its chi^2 gate and the pose noise), written over stacks of frames that share
one reference point set: every frame of a stretch in which the same tracks are
matched against the same reference. The per-frame path pays the interpreter for
some hundred numpy calls on 4 to 20 rows; here each call covers the whole stack.

Point subsets (RANSAC's inliers, the points a gate keeps) are weights w (F, N) of 0 or
1: a point of weight 0 adds exact zeros to every sum, so the result is that of the
per-frame function on the subset, to rounding. Nothing raises: where the per-frame
functions would raise an InputError (degenerate points, points behind the camera,
det(H) <= 0), the frame is marked in a boolean ``bad`` array and the caller measures
it with the per-frame path, which raises or refuses exactly as before. Shapes: F
frames, N points; m_ref (N, 3) is shared, m_cur (F, N, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.geometry.discrete import DEGENERACY_TOL

_SKEW_ROWS = np.array([0, 0, 1, 1, 2, 2])
_SKEW_COLS = np.array([1, 2, 0, 2, 0, 1])
_SKEW_SRC = np.array([2, 1, 2, 0, 1, 0])
_SKEW_SIGN = np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
_EPS = np.finfo(float).eps


def _tr(a: np.ndarray) -> np.ndarray:
    """Transpose of the last two axes."""
    return np.swapaxes(a, -1, -2)


def hartley(m: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(F, 3, 3) :func:`~hvo_graph.geometry.discrete._hartley` of the points of weight 1
    of (F | 1, N, 3) points, weights w (F, N)."""
    xy = m[..., :2]
    count = w.sum(axis=1)
    c = np.einsum("fn,fni->fi", w, np.broadcast_to(xy, (len(w), *xy.shape[-2:]))) / count[:, None]
    dist = np.linalg.norm(xy - c[:, None, :], axis=-1)
    mean_dist = np.sum(w * dist, axis=1) / count
    mean_dist = np.where(mean_dist <= 0.0, 1.0, mean_dist)
    s = np.sqrt(2.0) / mean_dist
    T = np.zeros((*s.shape, 3, 3))
    T[..., 0, 0] = T[..., 1, 1] = s
    T[..., 0, 2] = -s * c[..., 0]
    T[..., 1, 2] = -s * c[..., 1]
    T[..., 2, 2] = 1.0
    return T


def dlt(m_ref: np.ndarray, m_cur: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H (F, 3, 3) with ||H||_F = 1, bad (F,)): the normalized DLT of
    :func:`~hvo_graph.geometry.discrete._dlt` per frame on its points of weight 1;
    ``bad`` where it would raise (a degenerate point set or correspondence)."""
    F = len(m_cur)
    T_ref = hartley(m_ref[None], w)
    T_cur = hartley(m_cur, w)
    a = (m_ref @ _tr(T_ref)) * w[..., None]  # zero rows: the points left out
    b = (m_cur @ _tr(T_cur)) * w[..., None]
    # The identity systems of each point set only say whether it is degenerate; frames
    # with the same reference weights share the reference's (computed once).
    if F == 1 or w.all():  # one set (every point used: the usual case)
        weights, first = w[:1], np.zeros(F, dtype=int)
    else:
        weights, first = np.unique(w, axis=0, return_inverse=True)[:2]
    a_sets = (m_ref @ _tr(hartley(m_ref[None], weights))) * weights[..., None]
    ratio_ref = _ratios(_system(a_sets, a_sets))[np.ravel(first)]
    ratio_cur = _ratios(_system(b, b))
    h, ratio = _null_vectors(_system(a, b))
    bad = ~(
        (ratio_ref >= DEGENERACY_TOL) & (ratio_cur >= DEGENERACY_TOL) & (ratio >= DEGENERACY_TOL)
    )
    Hn = h.reshape(F, 3, 3)
    H = np.linalg.solve(T_cur, Hn @ T_ref)
    return H / np.linalg.norm(H, axis=(1, 2))[:, None, None], bad


def _system(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(F, 2N, 9) DLT systems: rows x and y of dst x (H src) = 0 for h = H.ravel()."""
    F, n = src.shape[:2]
    A = np.zeros((F, 2 * n, 9))
    A[:, 0::2, 3:6] = -src
    A[:, 0::2, 6:9] = dst[..., 1:2] * src
    A[:, 1::2, 0:3] = src
    A[:, 1::2, 6:9] = -dst[..., 0:1] * src
    return A


#: Below this sigma_8 / sigma_1 a system's ratio (and null vector) come from its SVD:
#: from the eigenvalues of A^T A, squared, the ratio would not resolve DEGENERACY_TOL.
_EIGEN_RATIO: float = 1e-5


def _ratios(A: np.ndarray) -> np.ndarray:
    """(F,) sigma_8 / sigma_1 of each (F, R, 9) system: the square roots of the eigenvalues
    of the 9 x 9 A^T A (cheaper than the SVD of A), the SVD where it is below
    :data:`_EIGEN_RATIO`."""
    lam = np.linalg.eigvalsh(_tr(A) @ A)
    ratio = np.sqrt(np.maximum(lam[:, 1], 0.0) / lam[:, 8])
    low = np.flatnonzero(~(ratio >= _EIGEN_RATIO))
    if low.size:
        s = np.linalg.svd(A[low], compute_uv=False)
        ratio[low] = s[:, 7] / s[:, 0]
    return ratio


def _null_vectors(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(h (F, 9), ratio (F,)): each (F, R, 9) system's unit right singular vector of its
    smallest singular value (the eigenvector of A^T A of its smallest eigenvalue) and
    sigma_8 / sigma_1 (:func:`_ratios`), the SVD's where the ratio is small."""
    lam, V = np.linalg.eigh(_tr(A) @ A)
    h = V[:, :, 0]
    ratio = np.sqrt(np.maximum(lam[:, 1], 0.0) / lam[:, 8])
    low = np.flatnonzero(~(ratio >= _EIGEN_RATIO))
    if low.size:
        _, s, Vt = np.linalg.svd(A[low], full_matrices=A.shape[1] < 9)
        h[low], ratio[low] = Vt[:, -1], s[:, 7] / s[:, 0]
    return h, ratio


def euclidean(
    H: np.ndarray, m_ref: np.ndarray, m_cur: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(H_d (F, 3, 3), bad (F,)): :func:`~hvo_graph.geometry.discrete._euclidean` per frame
    on its points of weight 1."""
    s = np.linalg.svd(H, compute_uv=False)
    bad = ~(s[:, 1] > 1e-12 * np.maximum(s[:, 0], np.finfo(float).tiny))
    H = H / s[:, 1, None, None]
    g = np.einsum("fij,fjk,ik->fi", m_cur, H, m_ref)
    used = w > 0
    flip = np.all((g < 0) | ~used, axis=1)
    H = np.where(flip[:, None, None], -H, H)
    g = np.where(flip[:, None], -g, g)
    return H, bad | ~np.all((g > 0) | ~used, axis=1)


def known_normal_motion(
    H: np.ndarray, normal: np.ndarray, basis: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R (F, 3, 3), t (F, 3), bad (F,)): :func:`~hvo_graph.geometry._fit.known_normal_motion`
    per frame; ``bad`` where det(H) <= 0."""
    bad = ~(np.linalg.det(H) > 0)
    u1, u2 = basis
    B = (H @ u1)[:, :, None] * u1 + (H @ u2)[:, :, None] * u2
    U, _, Vt = np.linalg.svd(B)
    d = np.ones((len(H), 3))
    d[:, 2] = np.sign(np.linalg.det(U @ Vt))
    R = (U * d[:, None, :]) @ Vt
    return R, H @ normal - R @ normal, bad


def retract(R: np.ndarray, T: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~hvo_graph.geometry._fit.retract` per frame: the motion after the right
    perturbation T_wc Exp(delta) (GTSAM's Pose3 retract: compose with Pose3.Expmap)."""
    w, v = delta[:, :3], delta[:, 3:]
    theta2 = np.einsum("fi,fi->f", w, w)
    near = theta2 <= _EPS
    theta = np.sqrt(theta2)
    safe_t = np.where(near, 1.0, theta)
    safe_t2 = np.where(near, 1.0, theta2)
    s_half = np.sin(safe_t / 2.0)
    A = np.where(near, 1.0, np.sin(safe_t) / safe_t)
    B = np.where(near, 0.5, 2.0 * s_half * s_half / safe_t2)
    C = np.where(near, 1.0 / 6.0, (1.0 - A) / safe_t2)
    W = np.zeros((len(w), 3, 3))
    W[:, _SKEW_ROWS, _SKEW_COLS] = w[:, _SKEW_SRC] * _SKEW_SIGN
    Rd = np.eye(3) + A[:, None, None] * W + B[:, None, None] * (W @ W)
    Wv = _cross(w, v)
    td = v + B[:, None] * Wv + C[:, None] * _cross(w, Wv)
    R_wc = _tr(R)
    p = -(R_wc @ T[..., None])[..., 0]
    R_new_wc = R_wc @ Rd
    p_new = p + (R_wc @ td[..., None])[..., 0]
    R_new = _tr(R_new_wc)
    return R_new, -(R_new @ p_new[..., None])[..., 0]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F, 3) row-wise a x b: np.cross's products, without its axis handling."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=1)


@dataclass(frozen=True)
class _Entries:
    """The linearization of F frames' N points, entry by entry, each an (F, N) array:
    rows (J's two rows, 6 entries each), weighted (J^T Sigma^-1: 6 rows of 2), residual
    (x, y), A (a, b, c, d: [[a, b], [c, d]]), cov (c00, c01, c11), inv (the same of
    Sigma^-1), bad (F,)."""

    rows: tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]
    weighted: tuple[tuple[np.ndarray, np.ndarray], ...]
    residual: tuple[np.ndarray, np.ndarray]
    A: tuple[np.ndarray, ...]
    cov: tuple[np.ndarray, np.ndarray, np.ndarray]
    inv: tuple[np.ndarray, np.ndarray, np.ndarray]
    bad: np.ndarray


class BatchTransfer:
    """:class:`~hvo_graph.geometry._fit.PlaneTransfer` of F frames against one reference.

    Args:
        m_ref: (N, 3) reference points; m_cur: (F, N, 3) current points, row by row the
            same tracks; normal, distance: n*, d* in the reference frame; sigma: pixel
            noise in normalized units.
    """

    def __init__(
        self,
        m_ref: np.ndarray,
        m_cur: np.ndarray,
        normal: np.ndarray,
        distance: float,
        sigma: float,
    ):
        n, d = normal, distance
        depth = m_ref @ n
        self.X_star = d * m_ref / depth[:, None]
        dXstar = d * (
            np.eye(3)[None] / depth[:, None, None]
            - np.einsum("ni,j->nij", m_ref, n) / depth[:, None, None] ** 2
        )
        self.dXstar2 = dXstar[:, :, :2]
        # The linearization works on (F, N) arrays, one per entry: numpy's inner loop then
        # runs over N points of F frames, not over a 2- or 6-long last axis. Hence X*^T
        # (3, N), dX*/dm* as (3, 2N) (the m* x columns of every point, then the y ones) and
        # the current points' x and y apart.
        self._Xstar_columns = np.ascontiguousarray(self.X_star.T)
        self._dXstar_columns = self.dXstar2.transpose(1, 2, 0).reshape(3, 2 * len(m_ref))
        self._current_xy = np.ascontiguousarray(np.moveaxis(m_cur[..., :2], -1, 0))
        self.sigma = sigma

    def _entries(self, R: np.ndarray, T: np.ndarray) -> _Entries:
        """Every entry of the linearization at (R, T), each an (F, N) array."""
        X = R @ self._Xstar_columns + T[:, :, None]  # (F, 3, N)
        x, y, z = X[:, 0], X[:, 1], X[:, 2]
        bad = ~(z.min(axis=1) > 0)
        iz = 1.0 / z
        u, v = x * iz, y * iz  # pi(X)
        uz, vz = u * iz, v * iz
        N = z.shape[1]
        uv, minus_iz = u * v, -iz
        zero = np.zeros_like(iz)
        rows = (
            (uv, -1.0 - u * u, v, minus_iz, zero, uz),  # J's two rows, entry by entry
            (1.0 + v * v, -uv, -u, zero, minus_iz, vz),
        )
        M = R @ self._dXstar_columns  # (F, 3, 2N): R dX*/dm*, x columns then y columns
        a = iz * M[:, 0, :N] - uz * M[:, 2, :N]  # A = [[a, b], [c, d]] per point
        b = iz * M[:, 0, N:] - uz * M[:, 2, N:]
        c = iz * M[:, 1, :N] - vz * M[:, 2, :N]
        d = iz * M[:, 1, N:] - vz * M[:, 2, N:]
        s2 = self.sigma**2
        c00, c01, c11 = (
            s2 * (1.0 + (a * a + b * b)),
            s2 * (a * c + b * d),
            s2 * (1.0 + (c * c + d * d)),
        )
        det = c00 * c11 - c01 * c01
        i00, i01, i11 = c11 / det, -c01 / det, c00 / det
        # J_i^T Sigma_i^-1 (6 x 2), entry by entry (J's zero entries left out of the sums)
        one_vv = rows[1][0]
        weighted = (
            (uv * i00 + one_vv * i01, uv * i01 + one_vv * i11),
            (rows[0][1] * i00 - uv * i01, rows[0][1] * i01 - uv * i11),
            (v * i00 - u * i01, v * i01 - u * i11),
            (minus_iz * i00, minus_iz * i01),
            (minus_iz * i01, minus_iz * i11),
            (uz * i00 + vz * i01, uz * i01 + vz * i11),
        )
        residual = (self._current_xy[0] - u, self._current_xy[1] - v)
        return _Entries(
            rows, weighted, residual, (a, b, c, d), (c00, c01, c11), (i00, i01, i11), bad
        )

    def linearize(self, R: np.ndarray, T: np.ndarray) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """((J, JtW, residual, A, cov, inv), bad (F,)) as ``PlaneTransfer.linearize`` per
        frame (inv: the (F, N, 2, 2) Sigma_i^-1); ``bad`` where a transferred point has
        non-positive depth (or NaN).

        J = P [X^ | -I], A = P R dX*/dm*, Sigma_i = s^2 (I + A A^T) and its inverse are
        written out entry by entry, each entry an (F, N) array (numpy's stacked matmul
        pays per 2 x 2 block, and F N blocks are thousands), then put in place. The same
        numbers to rounding."""
        e = self._entries(R, T)
        F, N = e.bad.shape[0], e.residual[0].shape[1]
        c00, c01, c11 = e.cov
        i00, i01, i11 = e.inv
        return (
            np.stack((*e.rows[0], *e.rows[1]), axis=-1).reshape(F, N, 2, 6),
            np.stack([x for pair in e.weighted for x in pair], axis=-1).reshape(F, N, 6, 2),
            np.stack(e.residual, axis=-1),
            np.stack(e.A, axis=-1).reshape(F, N, 2, 2),
            np.stack((c00, c01, c01, c11), axis=-1).reshape(F, N, 2, 2),
            np.stack((i00, i01, i01, i11), axis=-1).reshape(F, N, 2, 2),
        ), e.bad

    def normal_equations(
        self, R: np.ndarray, T: np.ndarray, huber: float | None, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(info (F, 6, 6), grad (F, 6), bad (F,)) as ``PlaneTransfer.normal_equations`` on
        the points of weight 1: sum_i J_i^T W_i J_i and J_i^T W_i r_i, as (F, 6, 2N) @ (F,
        2N, 6) products over the points' x rows, then their y rows."""
        e = self._entries(R, T)
        r0, r1 = e.residual
        if huber is not None:
            i00, i01, i11 = e.inv
            d = np.sqrt(i00 * r0 * r0 + 2.0 * i01 * r0 * r1 + i11 * r1 * r1)
            w = w * np.minimum(1.0, huber / np.maximum(d, 1e-12))
        F, N = w.shape
        JtW = np.stack([x for pair in e.weighted for x in pair], axis=1).reshape(F, 6, 2 * N)
        JtW *= np.concatenate((w, w), axis=1)[:, None, :]
        J = np.stack([x for pair in zip(*e.rows, strict=True) for x in pair], axis=1)
        info = JtW @ J.reshape(F, 6, 2 * N).transpose(0, 2, 1)
        grad = (JtW @ np.concatenate((r0, r1), axis=1)[..., None])[..., 0]
        return info, grad, e.bad

    def refine(
        self, R: np.ndarray, T: np.ndarray, steps: int, huber: float | None, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(R, T, info before the last step, bad) as ``PlaneTransfer.refine`` per frame on
        the points of weight 1."""
        info, grad, bad = self.normal_equations(R, T, huber, w)
        for step in range(steps):
            if step:
                info, grad, more = self.normal_equations(R, T, huber, w)
                bad |= more
            # A bad frame's numbers are discarded; keep them finite for the solve.
            info = np.where(bad[:, None, None], np.eye(6), info)
            grad = np.where(bad[:, None], 0.0, grad)
            R, T = retract(R, T, np.linalg.solve(info, grad[..., None])[..., 0])
        return R, T, info, bad

    @staticmethod
    def chi2(lin: tuple[np.ndarray, ...], info: np.ndarray) -> np.ndarray:
        """(F, N) ``PlaneTransfer.chi2`` per frame: r^T (Sigma_i + J_i info^-1 J_i^T)^-1 r."""
        J, _, residual, _, cov, _ = lin
        F, N = J.shape[:2]
        G = (J.reshape(F, 2 * N, 6) @ np.linalg.inv(info)).reshape(F, N, 2, 6)
        j0, j1 = J[..., 0, :], J[..., 1, :]
        c00 = cov[..., 0, 0] + np.sum(G[..., 0, :] * j0, axis=-1)
        c01 = cov[..., 0, 1] + np.sum(G[..., 0, :] * j1, axis=-1)
        c11 = cov[..., 1, 1] + np.sum(G[..., 1, :] * j1, axis=-1)
        det = c00 * c11 - c01 * c01
        r0, r1 = residual[..., 0], residual[..., 1]
        return (c11 * r0 * r0 - 2.0 * c01 * r0 * r1 + c00 * r1 * r1) / det

    def noise(
        self, lin: tuple[np.ndarray, ...], w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(covariance, reference covariance, reference Jacobian (F, 6, 2N): zero columns for
        the points of weight 0), as ``PlaneTransfer.noise`` per frame on the points of
        weight 1."""
        J, JtW, _, A, _, _ = lin
        JtW = JtW * w[..., None, None]
        F, n = J.shape[:2]
        sigma = self.sigma
        rows = _point_columns(JtW)
        info = rows @ J.reshape(F, 2 * n, 6)
        JtWA = np.empty_like(JtW)  # J_i^T Sigma_i^-1 A_i
        JtWA[..., 0] = JtW[..., 0] * A[..., None, 0, 0] + JtW[..., 1] * A[..., None, 1, 0]
        JtWA[..., 1] = JtW[..., 0] * A[..., None, 0, 1] + JtW[..., 1] * A[..., None, 1, 1]
        H = np.linalg.solve(info, rows)
        G = np.linalg.solve(info, _point_columns(JtWA))
        current, reference = sigma**2 * (H @ _tr(H)), sigma**2 * (G @ _tr(G))
        covariance = 0.5 * (current + _tr(current) + reference + _tr(reference))
        return covariance, 0.5 * (reference + _tr(reference)), -sigma * G


def _point_columns(M: np.ndarray) -> np.ndarray:
    """(F, 6, 2N): the (F, N, 6, 2) blocks side by side (columns 2i, 2i+1: point i)."""
    F, N = M.shape[:2]
    return M.transpose(0, 2, 1, 3).reshape(F, 6, 2 * N)
