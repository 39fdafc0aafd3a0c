"""The front end's per-frame H_d pose fit, with few numpy calls per frame.

The same arithmetic as the public, argument-checking functions of
:mod:`hvo_graph.geometry.transfer` and :mod:`hvo_graph.geometry.decomposition`
(tests/test_geometry_fit.py holds the two to 1e-12), arranged for speed on the
4 to a few hundred points of one frame: inputs are the front end's own arrays
(finite, (N, 3) with a third column of 1), so they are not checked again; what
depends only on the reference points and the plane (back-projections, their
derivatives) is computed once per frame, not once per Gauss-Newton step; every
per-point quantity is one array operation over all points (no loop over points);
and the linearization at the final pose serves both the chi^2 gate and the
pose's noise.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.discrete import _dlt, _euclidean
from hvo_graph.types import Plane

# Rows, columns, source coordinate and sign of the six non-zero entries of X^ (skew(X)).
_SKEW_ROWS = np.array([0, 0, 1, 1, 2, 2])
_SKEW_COLS = np.array([1, 2, 0, 2, 0, 1])
_SKEW_SRC = np.array([2, 1, 2, 0, 1, 0])
_SKEW_SIGN = np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
_I2 = np.eye(2)[None]


@dataclass(slots=True)
class Linearization:
    """The transfer residuals of N points and their whitened Jacobian at one motion (R, T).

    Attributes (as :class:`~hvo_graph.geometry.transfer.TransferLinearization`):
        J: (N, 2, 6) d pi(X_i) / d[dtheta; dp]; JtW: (N, 6, 2) J_i^T Sigma_i^-1;
        residual: (N, 2); A: (N, 2, 2) d pi(X_i) / d m*_i[:2]; cov: (N, 2, 2) Sigma_i.
    """

    J: np.ndarray
    JtW: np.ndarray
    residual: np.ndarray
    A: np.ndarray
    cov: np.ndarray

    def information(self) -> np.ndarray:
        """(6, 6) sum_i J_i^T Sigma_i^-1 J_i."""
        return np.sum(self.JtW @ self.J, axis=0)


class PlaneTransfer:
    """The transfer error of the points m_ref -> m_cur on the plane, for any motion (R, T).

    Args:
        m_ref, m_cur: (N, 3) normalized points (third column 1) of the reference and the
            current frame, the same tracks row by row.
        plane: n* and d* in the reference frame (n* required).
        sigma: pixel noise in normalized units.
    """

    def __init__(self, m_ref: np.ndarray, m_cur: np.ndarray, plane: Plane, sigma: float):
        n, d = plane.normal, plane.distance
        self.m_ref, self.m_cur, self.plane, self.sigma = m_ref, m_cur, plane, sigma
        depth = m_ref @ n
        self.depth = depth
        self.X_star = d * m_ref / depth[:, None]
        dXstar = d * (
            np.eye(3)[None] / depth[:, None, None]
            - np.einsum("ni,j->nij", m_ref, n) / depth[:, None, None] ** 2
        )
        self.dXstar2 = dXstar[:, :, :2]
        self.current = m_cur[:, :2]
        N = len(m_ref)
        self._dX = np.zeros((N, 3, 6))
        self._dX[:, :, 3:] = -np.eye(3)
        self._P = np.zeros((N, 2, 3))
        self._basis: np.ndarray | None = None

    @classmethod
    def reuse(
        cls,
        kept: PlaneTransfer | None,
        m_ref: np.ndarray,
        m_cur: np.ndarray,
        plane: Plane,
        sigma: float,
    ) -> PlaneTransfer:
        """A :class:`PlaneTransfer`, sharing ``kept``'s constants when its reference points
        and plane are the very same arrays (the same reference and tracks as before)."""
        if kept is None or kept.m_ref is not m_ref or kept.plane is not plane:
            return cls(m_ref, m_cur, plane, sigma)
        other = copy.copy(kept)
        other.m_cur, other.current, other.sigma = m_cur, m_cur[:, :2], sigma
        return other

    @property
    def basis(self) -> np.ndarray:
        """(2, 3) :func:`plane_basis` of the plane's normal (computed once)."""
        if self._basis is None:
            self._basis = plane_basis(self.plane.normal)
        return self._basis

    def refine(
        self, R: np.ndarray, T: np.ndarray, steps: int, huber: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gauss-Newton ``steps`` on the weighted transfer error (:meth:`normal_equations`,
        ``huber`` as there) from (R, T): (R, T, information before the last step; with 0
        steps, at (R, T))."""
        info, grad = self.normal_equations(R, T, huber)
        for step in range(steps):
            if step:
                info, grad = self.normal_equations(R, T, huber)
            R, T = retract(R, T, np.linalg.solve(info, grad))
        return R, T, info

    def __len__(self) -> int:
        return len(self.m_ref)

    def subset(self, keep: np.ndarray) -> PlaneTransfer:
        """The same for the points ``keep`` (bool mask or indices)."""
        return PlaneTransfer(self.m_ref[keep], self.m_cur[keep], self.plane, self.sigma)

    def linearize(self, R: np.ndarray, T: np.ndarray) -> Linearization:
        """:func:`~hvo_graph.geometry.transfer.linearize_transfer` at (R, T).

        Raises:
            InputError: a transferred point with non-positive depth.
        """
        X = self.X_star @ R.T + T
        z = X[:, 2]
        if not z.min() > 0:  # (NaN too)
            raise InputError("points behind the camera: a plane point has non-positive depth")
        P = self._P.copy()
        P[:, 0, 0] = P[:, 1, 1] = 1.0 / z
        P[:, :, 2] = -X[:, :2] / (z**2)[:, None]
        residual = self.current - X[:, :2] / X[:, 2:3]
        dX = self._dX.copy()
        dX[:, _SKEW_ROWS, _SKEW_COLS] = X[:, _SKEW_SRC] * _SKEW_SIGN
        J = P @ dX
        A = P @ R @ self.dXstar2
        cov = self.sigma**2 * (_I2 + A @ np.transpose(A, (0, 2, 1)))
        JtW = np.transpose(J, (0, 2, 1)) @ np.linalg.inv(cov)
        return Linearization(J, JtW, residual, A, cov)

    def normal_equations(
        self, R: np.ndarray, T: np.ndarray, huber: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`~hvo_graph.geometry.transfer.pose_normal_equations`: (info, grad)."""
        lin = self.linearize(R, T)
        JtW, r = lin.JtW, lin.residual
        if huber is not None:
            d = np.sqrt(np.einsum("ni,ni->n", r, np.linalg.solve(lin.cov, r[..., None])[..., 0]))
            JtW = JtW * np.minimum(1.0, huber / np.maximum(d, 1e-12))[:, None, None]
        return np.sum(JtW @ lin.J, axis=0), np.einsum("nij,nj->i", JtW, r)

    def chi2(self, lin: Linearization, info: np.ndarray) -> np.ndarray:
        """:func:`~hvo_graph.geometry.transfer.transfer_chi2` from the linearization at the
        fitted motion and the fit's information matrix."""
        J = lin.J
        cov = lin.cov + J @ np.linalg.solve(info, np.transpose(J, (0, 2, 1)))
        whitened = np.linalg.solve(cov, lin.residual[..., None])[..., 0]
        return np.einsum("ni,ni->n", lin.residual, whitened)

    def noise(self, lin: Linearization) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`~hvo_graph.geometry.transfer.pose_noise` from the linearization at the
        fitted motion: (covariance, reference covariance, reference Jacobian)."""
        sigma, n = self.sigma, len(self.m_ref)
        JtW = lin.JtW
        info = np.sum(JtW @ lin.J, axis=0)
        # Columns point by point ([u_1, v_1, u_2, ...]): (N, 6, 2) -> (6, 2N).
        H = np.linalg.solve(info, JtW.transpose(1, 0, 2).reshape(6, 2 * n))
        G = np.linalg.solve(info, (JtW @ lin.A).transpose(1, 0, 2).reshape(6, 2 * n))
        current, reference = sigma**2 * (H @ H.T), sigma**2 * (G @ G.T)
        covariance = 0.5 * (current + current.T + reference + reference.T)
        return covariance, 0.5 * (reference + reference.T), -sigma * G


def retract(R: np.ndarray, T: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~hvo_graph.geometry.transfer.retract_motion` without the argument checks."""
    R_wc = R.T
    pose = gtsam.Pose3(gtsam.Rot3(R_wc), -R_wc @ T).retract(delta)
    R_new = pose.rotation().matrix().T
    return R_new, -R_new @ pose.translation()


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """(3, 3) B B^T-like projector data: rows 2 and 3 of V^T in the SVD of n^T, an
    orthonormal basis of the plane orthogonal to n (as
    :func:`~hvo_graph.geometry.decomposition.motion_from_homography_known_normal`)."""
    return np.linalg.svd(normal[None, :])[2][1:]


def known_normal_motion(
    H: np.ndarray, normal: np.ndarray, basis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t = T / d*) from a Euclidean H_d (:func:`euclidean` output) and the known n*,
    as :func:`~hvo_graph.geometry.decomposition.motion_from_homography_known_normal`.

    Args:
        basis: (2, 3) :func:`plane_basis` of ``normal``.
    Raises:
        InputError: det(H) <= 0 (wrong sign, or the camera crossed the plane).
    """
    det = float(np.linalg.det(H))
    if not det > 0:
        raise InputError(
            f"H_euclid: det(H) = {det:.6g} <= 0: wrong sign (normalize with "
            "euclidean_homography) or the camera crossed the plane"
        )
    u1, u2 = basis
    B = np.outer(H @ u1, u1) + np.outer(H @ u2, u2)
    U, _, Vt = np.linalg.svd(B)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return R, H @ normal - R @ normal


def euclidean(H: np.ndarray, m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """:func:`~hvo_graph.geometry.discrete.euclidean_homography` without the argument
    checks (the points are the front end's (N, 3) arrays)."""
    return _euclidean(H, m_ref, m_cur)


def dlt(m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """H (up to scale, ||H||_F = 1) by the normalized DLT of
    :func:`~hvo_graph.geometry.discrete.estimate_homography`, without RANSAC and without
    the argument checks (the points are the front end's (N, 3) arrays, N >= 4)."""
    return _dlt(m_ref, m_cur)
