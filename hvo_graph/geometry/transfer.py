"""Transfer error of plane points under H_d: residuals, Jacobians, normal equations.

The reference frame F* (frame 0 or a keyframe) sees the plane n*^T X* = d*.
A reference point m*_i (normalized, (3,) with third entry 1) back-projects to
the plane point X*_i = d* m*_i / (n*^T m*_i); the motion (R, T) of the paper
(X = R X* + T) transfers it into the current frame, X_i = R X*_i + T, where it
should project onto the current observation m_i. The transfer residual is

    r_i = m_i[:2] - pi(X_i),   pi(X) = X[:2] / X[2],

and with isotropic noise sigma (normalized units) on both observations its
covariance is Sigma_i = sigma^2 (I + A_i A_i^T), A_i = d pi(X_i) / d m*_i[:2].

The pose is perturbed on the right of the camera pose T_wc = (R^T, -R^T T),
T_wc Exp([dtheta; dp]) (GTSAM's retract, tangent order [rot; trans]). The
weighted Gauss-Newton step on sum_i r_i^T Sigma_i^-1 r_i is the front end's
refinement of the H_d pose, and its information matrix the pose covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.discrete import camera_pose_from_motion
from hvo_graph.geometry.rotation import skew
from hvo_graph.types import Plane


def projection_jacobian(X: np.ndarray) -> np.ndarray:
    """(N, 2, 3) Jacobians d pi / d X of pi(X) = X[:2] / X[2] at the points X, (N, 3)."""
    z = X[:, 2]
    J = np.zeros((len(X), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0 / z
    J[:, 0, 2] = -X[:, 0] / z**2
    J[:, 1, 2] = -X[:, 1] / z**2
    return J


@dataclass(frozen=True)
class TransferLinearization:
    """The transfer residuals of N plane points and their whitened Jacobian at (R, T).

    Attributes:
        depth: (N,) n*^T m*_i.
        P: (N, 2, 3) d pi / d X at X_i.
        J: (N, 2, 6) d pi(X_i) / d[dtheta; dp], right perturbation of T_wc.
        JtW: (N, 6, 2) J_i^T Sigma_i^-1.
        residual: (N, 2) m_i[:2] - pi(X_i).
        A: (N, 2, 2) d pi(X_i) / d m*_i[:2], how the reference observation moves the residual.
    """

    depth: np.ndarray
    P: np.ndarray
    J: np.ndarray
    JtW: np.ndarray
    residual: np.ndarray
    A: np.ndarray


def pixel_covariance(A: np.ndarray, sigma: float) -> np.ndarray:
    """(N, 2, 2) Sigma_i = sigma^2 (I + A_i A_i^T): a transfer residual's covariance from
    the noise of its current and its reference observation, A (N, 2, 2)."""
    return sigma**2 * (np.eye(2)[None] + A @ np.transpose(A, (0, 2, 1)))


def linearize_transfer(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
) -> TransferLinearization:
    """Linearize the transfer residuals of the points m_ref -> m_cur at the motion (R, T).

    Args:
        R: (3, 3) rotation, reference -> current frame (X = R X* + T).
        T: (3,) translation, metres.
        m_ref: (N, 3) normalized reference points m*.
        m_cur: (N, 3) normalized current points m.
        plane: n* (required) and d* in the reference frame.
        sigma: pixel noise in normalized units (pixels / focal length).
    Raises:
        InputError: a transferred point with non-positive depth.
    """
    n, d = plane.normal, plane.distance
    depth = m_ref @ n
    X_star = d * m_ref / depth[:, None]
    X = X_star @ R.T + T
    if np.any(X[:, 2] <= 0):
        raise InputError("points behind the camera: a plane point has non-positive depth")
    P = projection_jacobian(X)
    residual = m_cur[:, :2] - X[:, :2] / X[:, 2:3]
    # dX/d[dtheta, dp] for the right perturbation of T_wc: [X^, -I].
    dX = np.concatenate(
        (np.stack([skew(x) for x in X]), np.broadcast_to(-np.eye(3), (len(X), 3, 3))), axis=2
    )
    J = P @ dX
    dXstar = d * (
        np.eye(3)[None] / depth[:, None, None]
        - np.einsum("ni,j->nij", m_ref, n) / depth[:, None, None] ** 2
    )
    A = P @ R @ dXstar[:, :, :2]  # (N, 2, 2)
    W = np.linalg.inv(pixel_covariance(A, sigma))
    return TransferLinearization(depth, P, J, np.transpose(J, (0, 2, 1)) @ W, residual, A)


def pose_normal_equations(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
    huber: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Information matrix and gradient of the weighted transfer error at (R, T).

    Arguments as :func:`linearize_transfer`; ``huber``: a Huber threshold on each
    point's whitened residual norm d_i (iteratively reweighted least squares: weight
    min(1, huber / d_i)), None for plain least squares.

    Returns:
        (6, 6) information sum_i w_i J_i^T Sigma_i^-1 J_i and (6,) sum_i w_i J_i^T
        Sigma_i^-1 r_i: the Gauss-Newton step is info^-1 grad, and (w = 1) info^-1 the
        pose covariance.
    """
    lin = linearize_transfer(R, T, m_ref, m_cur, plane, sigma)
    JtW = lin.JtW
    if huber is not None:
        cov = pixel_covariance(lin.A, sigma)
        d = np.sqrt(
            np.einsum(
                "ni,ni->n", lin.residual, np.linalg.solve(cov, lin.residual[..., None])[..., 0]
            )
        )
        JtW = JtW * np.minimum(1.0, huber / np.maximum(d, 1e-12))[:, None, None]
    return np.sum(JtW @ lin.J, axis=0), np.einsum("nij,nj->i", JtW, lin.residual)


def pose_covariance_parts(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The pose covariance info^-1 at (R, T), split by where the pixel noise comes from.

    At the Gauss-Newton optimum the pose error is delta = sum_i H_i (e_i - A_i e*_i),
    H_i = info^-1 J_i^T Sigma_i^-1, with e_i the current and e*_i the reference
    pixel noise (each sigma^2 I). So info^-1 = C_cur + C_ref with

        C_cur = sigma^2 sum_i H_i H_i^T,   C_ref = sigma^2 sum_i (H_i A_i)(H_i A_i)^T.

    C_ref is shared by every pose measured against the same reference frame
    (one draw of e*): those poses' errors are correlated through it, while the
    current parts are independent from frame to frame.

    Arguments as :func:`linearize_transfer`.

    Returns:
        (C_cur, C_ref), each (6, 6) symmetric, tangent order [rot; trans].
    """
    H, G = pose_noise_jacobians(R, T, m_ref, m_cur, plane, sigma)
    current, reference = sigma**2 * (H @ H.T), sigma**2 * (G @ G.T)
    return 0.5 * (current + current.T), 0.5 * (reference + reference.T)


def pose_noise_jacobians(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """How the fitted pose moves with each pixel's noise: delta = H e - G e*.

    Arguments as :func:`linearize_transfer`; e (2N,) is the current and e* (2N,)
    the reference frame's pixel noise, point by point ([u_1, v_1, u_2, ...]).

    Returns:
        (H, G), each (6, 2N), tangent order [rot; trans] (right perturbation):
        d delta / d e = H and d delta / d e* = -G.
    """
    lin = linearize_transfer(R, T, m_ref, m_cur, plane, sigma)
    info = np.sum(lin.JtW @ lin.J, axis=0)
    H = np.linalg.solve(info, np.concatenate(list(lin.JtW), axis=1))  # (6, 2N)
    G = np.linalg.solve(info, np.concatenate(list(lin.JtW @ lin.A), axis=1))
    return H, G


def transfer_chi2(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
    info: np.ndarray,
) -> np.ndarray:
    """(N,) chi^2 (2 dof) of each point's transfer residual at a fitted motion (R, T).

    The residual's covariance is the pixels' Sigma_i plus the motion's own
    uncertainty J_i info^-1 J_i^T: a motion fitted on few points extrapolates
    poorly to the others, and Sigma_i alone would call good points outliers.

    Args:
        R, T, m_ref, m_cur, plane, sigma: as :func:`linearize_transfer`.
        info: (6, 6) information matrix of the fitted motion.
    """
    lin = linearize_transfer(R, T, m_ref, m_cur, plane, sigma)
    cov = pixel_covariance(lin.A, sigma) + lin.J @ np.linalg.solve(
        info, np.transpose(lin.J, (0, 2, 1))
    )
    whitened = np.linalg.solve(cov, lin.residual[..., None])[..., 0]
    return np.einsum("ni,ni->n", lin.residual, whitened)


def keyframe_plane_jacobian(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
    huber: float | None = None,
) -> np.ndarray:
    """(6, 6) d xi_rc / d xi_wr of a refined keyframe-relative pose (implicit function theorem).

    The plane in the keyframe is n_r = R_wr^T n*, d_r = d* - n*^T p_wr; a right perturbation
    T_wr Exp([phi; rho]) moves it by dn_r = n_r^ phi, dd_r = -n_r^T rho. The transfer
    residuals r_i = m_i - pi(R X*_i + T), X*_i = d_r m*_i / (n_r^T m*_i), then move by
    (dr/dpi) dpi. The optimum keeps sum_i J_i^T psi_i(r_i) = 0, so it moves by
    (sum J^T M J)^-1 sum J^T M (dr/dpi) dpi with M_i = d psi_i / d r_i: W_i for least
    squares; with a Huber loss (threshold k on d_i = |r_i|_W), beyond the threshold
    M_i = (k / d_i) (W_i - W_i r_i r_i^T W_i / d_i^2): the weight moves with the plane
    too, and leaving that out (or weighting one side only) was off by up to 50 % when
    the keyframe's plane was placed far from the truth.

    Args:
        R, T, m_ref, m_cur, sigma: as :func:`linearize_transfer`, at the refined optimum.
        plane: (n_r, d_r), the plane in the keyframe.
        huber: the Huber threshold of the fit that gave (R, T) (``pose_normal_equations``),
            None for least squares.
    """
    n, d = plane.normal, plane.distance
    lin = linearize_transfer(R, T, m_ref, m_cur, plane, sigma)
    depth = lin.depth
    # dX*/dn and dX*/dd at fixed m*, then through (phi, rho) of T_wr.
    dXs_dn = -d * np.einsum("ni,nj->nij", m_ref, m_ref) / depth[:, None, None] ** 2
    dXs_dd = m_ref / depth[:, None]
    dXs_dxi = np.concatenate(
        (dXs_dn @ skew(n), -np.einsum("ni,j->nij", dXs_dd, n)), axis=2
    )  # (N, 3, 6)
    dr_dxi = -(lin.P @ R @ dXs_dxi)  # (N, 2, 6)
    JtM = lin.JtW
    if huber is not None:
        r = lin.residual
        Wr = np.linalg.solve(pixel_covariance(lin.A, sigma), r[..., None])[..., 0]
        d = np.sqrt(np.einsum("ni,ni->n", r, Wr))
        beyond = d > huber
        if beyond.any():
            JtWr = np.einsum("nij,nj->ni", lin.JtW[beyond], r[beyond])
            outer = JtWr[:, :, None] * Wr[beyond][:, None, :] / d[beyond, None, None] ** 2
            JtM = JtM.copy()
            JtM[beyond] = (huber / d[beyond])[:, None, None] * (lin.JtW[beyond] - outer)
    return np.linalg.solve(np.sum(JtM @ lin.J, axis=0), np.sum(JtM @ dr_dxi, axis=0))


def retract_motion(
    R: np.ndarray, T: np.ndarray, delta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The motion (R, T) = T_cw after the right perturbation T_wc Exp(delta), delta (6,).

    Returns:
        (3, 3) R and (3,) T of the perturbed pose.
    """
    R_wc, p_wc = camera_pose_from_motion(R, T)
    pose = gtsam.Pose3(gtsam.Rot3(R_wc), p_wc).retract(delta)
    R_new = pose.rotation().matrix().T
    return R_new, -R_new @ pose.translation()


def pose_noise(
    R: np.ndarray,
    T: np.ndarray,
    m_ref: np.ndarray,
    m_cur: np.ndarray,
    plane: Plane,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A fitted pose's noise (:func:`pose_noise_jacobians`), as an H_d measurement carries it.

    Returns:
        covariance (6, 6) = C_cur + C_ref; C_ref (6, 6), the reference frame's share;
        J (6, 2N) = -sigma G, how the pose error moves per pixel standard deviation of
        the reference points' noise (C_ref = J J^T).
    """
    H, G = pose_noise_jacobians(R, T, m_ref, m_cur, plane, sigma)
    current, reference = sigma**2 * (H @ H.T), sigma**2 * (G @ G.T)
    covariance = 0.5 * (current + current.T + reference + reference.T)
    return covariance, 0.5 * (reference + reference.T), -sigma * G
