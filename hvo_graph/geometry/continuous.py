"""Continuous homography H_c: optical flow of plane points -> velocity.

Conventions (Ma et al. section 5.4, paper section II, NOTES section 3). Everything
lives in the CURRENT camera frame. Scene points move relative to the camera as

    Xdot = w^ X + v,

(w, v) being Ma's "scene motion": the negative of the camera's own body twist
(see :func:`body_twist_from_scene_motion`). The plane is n^T X = d with
n = n(t) = R n* and d = d(t) = d* + n(t)^T T (:func:`plane_in_current_frame`),
so plane points obey Xdot = H_c X with

    H_c = w^ + v n^T / d = w^ + u n^T,   u := v / d,

and a normalized image point m = X / z (third component 1) has the flow

    mdot = (I - m e3^T) H_c m           (third component 0: 2 equations per point).

Reference: Y. Ma, S. Soatto, J. Kosecka, S. S. Sastry, *An Invitation to 3-D
Vision*, Springer 2004, section 5.4 (continuous motion; the
continuous homography of a planar scene, its estimation and decomposition).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_matrix, as_points, as_vector
from hvo_graph.geometry.decomposition import (
    select_solution,
)
from hvo_graph.geometry.discrete import (
    DEGENERACY_TOL,
    normalized_points,
    positive_distance,
    unit_normal,
)
from hvo_graph.geometry.rotation import skew

#: lambda_1 - lambda_3 of H_c + H_c^T below this (relative to ||H_c||): u = 0, H_c = w^.
_ROTATION_TOL = 1e-10

#: |lambda_2| of H_c + H_c^T above this (relative to lambda_1 - lambda_3): not normalized.
_MIDDLE_TOL = 1e-6


def _flow(mdot: object, n_points: int) -> np.ndarray:
    """Validate optical flow: (N, 2) [xdot, ydot] or (N, 3) with a zero third column."""
    f = as_points(mdot, "mdot")
    if len(f) != n_points:
        raise InputError(f"mdot: expected as many rows as m ({n_points}), got {len(f)}")
    if f.shape[1] == 3:
        bad = np.flatnonzero(np.abs(f[:, 2]) > 1e-12)
        if bad.size:
            i = int(bad[0])
            raise InputError(
                "mdot: third column must be 0 (flow of m = [x, y, 1]), "
                f"got {float(f[i, 2]):g} in row {i}"
            )
        f = f[:, :2]
    return f


def plane_in_current_frame(
    R: np.ndarray, T: np.ndarray, normal: np.ndarray, distance: float
) -> tuple[np.ndarray, float]:
    """The plane (n(t), d(t)) in the current frame from (n*, d*) and the motion (R, T).

    With X = R X* + T and n*^T X* = d*:  n(t) = R n*,  d(t) = d* + n(t)^T T.

    Args:
        R: (3, 3) rotation reference -> current; T: (3,) translation, metres.
        normal: (3,) unit n*; distance: d* > 0.
    Returns:
        (n (3,), d) with n^T X = d for plane points X in the current frame.
    Raises:
        InputError: bad shapes, or d(t) <= 0 (the camera crossed the plane).
    """
    R = as_matrix(R, "R", (3, 3))
    T = as_vector(T, "T", 3)
    n_ref = unit_normal(normal)
    d_ref = positive_distance(distance)
    n = R @ n_ref
    d = d_ref + float(n @ T)
    if not d > 0:
        raise InputError(f"R, T: the camera is on the far side of the plane (d(t) = {d:.6g} <= 0)")
    return n, d


def continuous_homography(
    w: np.ndarray, v: np.ndarray, normal: np.ndarray, distance: float
) -> np.ndarray:
    """H_c = w^ + v n^T / d in the current frame, scene-motion convention.

    Args:
        w: (3,) angular velocity of the scene points relative to the camera (rad/s).
        v: (3,) linear velocity of the scene points relative to the camera (m/s).
        normal: (3,) unit plane normal n = n(t) in the current frame.
        distance: d = d(t) > 0.
    Returns:
        (3, 3) H_c.
    """
    w = as_vector(w, "w", 3)
    v = as_vector(v, "v", 3)
    n = unit_normal(normal)
    d = positive_distance(distance)
    return skew(w) + np.outer(v, n) / d


def point_flow(m: np.ndarray, H_c: np.ndarray) -> np.ndarray:
    """Optical flow predicted by H_c: mdot = (I - m e3^T) H_c m.

    Args:
        m: (N, 2|3) normalized points in the current frame.
        H_c: (3, 3) continuous homography.
    Returns:
        (N, 3) mdot, third column 0.
    """
    m = normalized_points(m, "m")
    H = as_matrix(H_c, "H_c", (3, 3))
    Hm = m @ H.T
    flow = Hm - m * Hm[:, 2:3]
    flow[:, 2] = 0.0
    return flow


def _flow_system(m: np.ndarray) -> np.ndarray:
    """(2N, 9) A with A h = [xdot_1, ydot_1, ...] for h = H_c.ravel(); A vec(I) = 0."""
    n = len(m)
    x, y = m[:, 0], m[:, 1]
    A = np.zeros((2 * n, 9))
    A[0::2, 0:3] = m
    A[0::2, 6:9] = -x[:, None] * m
    A[1::2, 3:6] = m
    A[1::2, 6:9] = -y[:, None] * m
    return A


def _fix_gamma(H_L: np.ndarray) -> np.ndarray:
    """H_L - gamma I with gamma the middle eigenvalue of (H_L + H_L^T) / 2."""
    gamma = np.linalg.eigvalsh(0.5 * (H_L + H_L.T))[1]
    return H_L - gamma * np.eye(3)


def estimate_continuous_homography(m: np.ndarray, mdot: np.ndarray) -> np.ndarray:
    """Estimate H_c from points and their optical flow (Ma et al. section 5.4).

    The flow equations are linear in the entries of H_c (a 2N x 9 system) but
    only fix H_c up to an added gamma I, because (I - m e3^T) m = 0. The least
    squares solution H_L of minimum norm is computed (after a Hartley-style
    similarity m -> S m, which maps H_c to S H_c S^-1 and keeps the model), then
    H_c = H_L - gamma I with gamma the middle eigenvalue of (H_L + H_L^T) / 2,
    the unique member of the family for which H_c + H_c^T = u n^T + n u^T has a
    zero middle eigenvalue (Ma et al. section 5.4).

    Args:
        m: (N, 2|3) normalized points in the current frame, N >= 4.
        mdot: (N, 2) or (N, 3) (third column 0) flow of m, normalized units per second.
    Returns:
        (3, 3) H_c.
    Raises:
        InputError: fewer than 4 points, mismatched shapes, NaN/inf, or a
            degenerate (collinear) configuration.
    """
    m = normalized_points(m, "m", min_points=4)
    f = _flow(mdot, len(m))
    c = m[:, :2].mean(axis=0)
    spread = float(np.mean(np.linalg.norm(m[:, :2] - c, axis=1)))
    s = np.sqrt(2.0) / spread if spread > 0 else 1.0
    S = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    A = _flow_system(m @ S.T)
    U, sv, Vt = np.linalg.svd(A, full_matrices=False)
    # vec(I) spans the null space exactly, so the rank is at most 8; rank < 8 is degeneracy.
    if not sv[7] > DEGENERACY_TOL * sv[0]:
        raise InputError(
            "m: degenerate point configuration (collinear points: all, or all but one, on a "
            "line); the continuous homography is not determined"
        )
    b = (s * f).ravel()
    h = Vt[:8].T @ ((U[:, :8].T @ b) / sv[:8])
    H_L = np.linalg.solve(S, h.reshape(3, 3) @ S)
    return _fix_gamma(H_L)


@dataclass(frozen=True)
class ContinuousSolution:
    """One decomposition H_c = w^ + u n^T (Ma's scene-motion convention, current frame).

    Attributes:
        angular: (3,) w, angular velocity of the scene relative to the camera (rad/s).
        linear_over_depth: (3,) u = v / d (1/s), v the scene's linear velocity, d = d(t).
        normal: (3,) unit plane normal n = n(t) in the current frame.
    """

    angular: np.ndarray
    linear_over_depth: np.ndarray
    normal: np.ndarray


def decompose_continuous_homography(H_c: np.ndarray) -> list[ContinuousSolution]:
    """All (w, u = v/d, n) with H_c = w^ + u n^T (Ma et al. section 5.4).

    H_c + H_c^T = u n^T + n u^T = V diag(l1, 0, l3) V^T with l1 >= 0 >= l3 and
    V = [v1 v2 v3]. With ||n|| = 1, ||u|| = (l1 - l3) / 2 and, for signs e1, e3,

        u / ||u|| = e1 sqrt(l1 / (l1 - l3)) v1 + e3 sqrt(-l3 / (l1 - l3)) v3
        n         = e1 sqrt(l1 / (l1 - l3)) v1 - e3 sqrt(-l3 / (l1 - l3)) v3
        w^        = H_c - u n^T.

    The four sign choices give two (w, u, n) and their mirrors (w, -u, -n)
    (flipping e3 exchanges the roles of u and n). Positive depth (n^T m > 0,
    :func:`physically_valid_continuous_solutions`) leaves two; a normal prior
    (:func:`select_continuous_solution`) picks one.

    Pure rotation: when H_c + H_c^T = 0 (u = 0) a single solution is returned:
    w from H_c = w^, u = 0 and, by convention, n = e3 (the normal is then
    unobservable and irrelevant).

    Args:
        H_c: (3, 3) continuous homography with zero middle eigenvalue of
            H_c + H_c^T, e.g. from :func:`estimate_continuous_homography`.
    Returns:
        list of :class:`ContinuousSolution` (4, or 1 for a pure rotation).
    Raises:
        InputError: the middle eigenvalue of H_c + H_c^T is not 0.
    """
    H = as_matrix(H_c, "H_c", (3, 3))
    lam, V = np.linalg.eigh(H + H.T)  # ascending: l3, l2, l1
    l3, l2, l1 = lam
    if l1 - l3 <= _ROTATION_TOL * np.linalg.norm(H):
        A = 0.5 * (H - H.T)
        w = np.array([A[2, 1], A[0, 2], A[1, 0]])
        return [ContinuousSolution(w, np.zeros(3), np.array([0.0, 0.0, 1.0]))]
    if abs(l2) > _MIDDLE_TOL * (l1 - l3):
        raise InputError(
            f"H_c: the middle eigenvalue of H_c + H_c^T must be 0, got {l2:.6g} "
            "(estimate H_c with estimate_continuous_homography)"
        )
    v1, v3 = V[:, 2], V[:, 0]
    norm_u = 0.5 * (l1 - l3)
    a = np.sqrt(max(l1, 0.0) / (l1 - l3))
    b = np.sqrt(max(-l3, 0.0) / (l1 - l3))
    solutions = []
    for e3 in (1.0, -1.0):
        direction = a * v1 + e3 * b * v3
        n = a * v1 - e3 * b * v3
        u = norm_u * direction / np.linalg.norm(direction)
        n = n / np.linalg.norm(n)
        W = H - np.outer(u, n)
        A = 0.5 * (W - W.T)
        solutions.append(ContinuousSolution(np.array([A[2, 1], A[0, 2], A[1, 0]]), u, n))
    solutions += [ContinuousSolution(s.angular, -s.linear_over_depth, -s.normal) for s in solutions]
    return solutions


def physically_valid_continuous_solutions(
    solutions: list[ContinuousSolution], m: np.ndarray
) -> list[ContinuousSolution]:
    """Keep the solutions with every point in front of the camera: n^T m_i > 0.

    (The depth of m_i is z_i = d / (n^T m_i) with d > 0.)

    Args:
        solutions: candidates from :func:`decompose_continuous_homography`.
        m: (N, 2|3) normalized points in the current frame.
    """
    m = normalized_points(m, "m")
    return [s for s in solutions if float(np.min(m @ s.normal)) > 0]


def select_continuous_solution(
    solutions: list[ContinuousSolution], normal_prior: np.ndarray
) -> ContinuousSolution:
    """The solution whose normal n is closest in direction to ``normal_prior``.

    Args:
        solutions: non-empty list of candidates.
        normal_prior: (3,) non-zero vector, e.g. n(t) = R n* from the discrete estimate.
    Raises:
        InputError: empty list or zero prior.
    """
    return select_solution(solutions, normal_prior)  # the same rule as for H_d


def velocity_design_matrix(m: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Design matrix of the flow model with known normal, linear in [w; u].

    With H_c m = w × m + (n^T m) u = -m^ w + (n^T m) u, the flow
    mdot = (I - m e3^T) H_c m gives per point the two rows (x then y)

        [ P_m (-m^) | (n^T m) P_m ],   P_m = [[1, 0, -x], [0, 1, -y]].

    Args:
        m: (N, 2|3) normalized points in the current frame.
        normal: (3,) unit plane normal n = n(t) in the current frame.
    Returns:
        (2N, 6) A with A [w; u] = [xdot_1, ydot_1, xdot_2, ...], columns [w; u],
        u = v / d, Ma's scene-motion convention.
    """
    return _design_matrix(normalized_points(m, "m"), unit_normal(normal))


def _design_matrix(m: np.ndarray, n: np.ndarray) -> np.ndarray:
    """:func:`velocity_design_matrix` of checked (N, 3) points and a unit normal."""
    N = len(m)
    P = np.zeros((N, 2, 3))
    P[:, 0, 0] = P[:, 1, 1] = 1.0
    P[:, 0, 2] = -m[:, 0]
    P[:, 1, 2] = -m[:, 1]
    m_hat = np.zeros((N, 3, 3))
    m_hat[:, 0, 1], m_hat[:, 0, 2] = -m[:, 2], m[:, 1]
    m_hat[:, 1, 0], m_hat[:, 1, 2] = m[:, 2], -m[:, 0]
    m_hat[:, 2, 0], m_hat[:, 2, 1] = -m[:, 1], m[:, 0]
    A = np.empty((N, 2, 6))
    A[:, :, :3] = -P @ m_hat
    A[:, :, 3:] = (m @ n)[:, None, None] * P
    return A.reshape(2 * N, 6)


def velocity_known_normal(
    m: np.ndarray, mdot: np.ndarray, normal: np.ndarray, distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Scene motion (w, v) from flow when the plane (n, d) is known.

    mdot = (I - m e3^T)(w^ + u n^T) m is linear in (w, u = v/d): the 2N x 6
    least squares system of :func:`velocity_design_matrix` is solved directly.
    There is no gamma I ambiguity and v = 0 needs no special case. Three points
    in general position suffice.

    Args:
        m: (N, 2|3) normalized points in the current frame, N >= 3.
        mdot: (N, 2) or (N, 3) (third column 0) their flow, per second.
        normal: (3,) unit normal n = n(t) in the current frame.
        distance: d = d(t) > 0 in metres.
    Returns:
        w: (3,) rad/s and v: (3,) m/s, Ma's scene-motion convention (use
        :func:`body_twist_from_scene_motion` for the camera's twist).
    Raises:
        InputError: too few points, bad shapes, NaN/inf, points behind the camera
            (n^T m <= 0), or a rank-deficient system.
    """
    m = normalized_points(m, "m", min_points=3)
    f = _flow(mdot, len(m))
    w, v, _ = _known_normal_solve(m, f, unit_normal(normal), positive_distance(distance))
    return w, v


def _known_normal_solve(
    m: np.ndarray, f: np.ndarray, n: np.ndarray, d: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`velocity_known_normal` of checked arrays: m (N, 3), flow f (N, 2), unit n,
    d > 0; also returns the design matrix A (2N, 6)."""
    if not float(np.min(m @ n)) > 0:
        raise InputError("m: points behind the camera (n^T m <= 0 for the given normal)")
    A = _design_matrix(m, n)
    U, sv, Vt = np.linalg.svd(A, full_matrices=False)
    if not sv[5] > DEGENERACY_TOL * sv[0]:
        raise InputError(
            "m: degenerate point configuration (collinear points); the known-normal "
            "velocity system is rank-deficient"
        )
    x = Vt.T @ ((U.T @ f.ravel()) / sv)
    return x[:3], d * x[3:], A


def body_twist_from_scene_motion(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The camera's body twist [w_b; v_b] = -[w; v] from Ma's scene motion (w, v).

    A static world point P has camera coordinates X = R_wc^T (P - p_wc). With
    the body twist of the contract, Rdot_wc = R_wc w_b^ and pdot_wc = R_wc v_b,
    so Xdot = -w_b^ X - v_b. Ma's continuous homography writes the same motion
    as Xdot = w^ X + v: hence w = -w_b and v = -v_b.

    Args:
        w: (3,) scene angular velocity (rad/s); v: (3,) scene linear velocity (m/s).
    Returns:
        (6,) [w_b; v_b] in the current camera frame (GTSAM Pose3 tangent order).
    """
    w = as_vector(w, "w", 3)
    v = as_vector(v, "v", 3)
    return -np.concatenate((w, v))


__all__ = [
    "ContinuousSolution",
    "body_twist_from_scene_motion",
    "continuous_homography",
    "decompose_continuous_homography",
    "estimate_continuous_homography",
    "physically_valid_continuous_solutions",
    "plane_in_current_frame",
    "point_flow",
    "select_continuous_solution",
    "velocity_design_matrix",
    "velocity_known_normal",
]


def motion_after_twist(
    R: np.ndarray, T: np.ndarray, twist: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """The motion (R, T) (world -> camera, X = R X_w + T) after ``dt`` seconds at a
    constant body twist (contract sign, [w; v]): T_wc(t + dt) = T_wc(t) Exp(dt [w; v])
    to first order in the translation.

    Args:
        R: (3, 3) rotation; T: (3,) translation, metres.
        twist: (6,) body twist [w; v] (rad/s, m/s).
        dt: seconds.
    Returns:
        (R', T'), (3, 3) and (3,).
    """
    R = as_matrix(R, "R", (3, 3))
    T = as_vector(T, "T", 3)
    xi = as_vector(twist, "twist", 6)
    theta = xi[:3] * float(dt)
    angle = float(np.linalg.norm(theta))
    K = skew(theta / angle) if angle > 0 else np.zeros((3, 3))
    step = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K  # Rodrigues
    R_wc, p_wc = R.T, -R.T @ T
    R_next = (R_wc @ step).T
    return R_next, -R_next @ (p_wc + R_wc @ (xi[3:] * float(dt)))
