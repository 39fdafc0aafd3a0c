"""Decomposition of the Euclidean homography H_d = R + t n*^T into the motion (R, t, n*).

Normal unknown: :func:`decompose_homography` gives the four solutions,
:func:`physically_valid_solutions` keeps those with the points in front of both
cameras, :func:`select_solution` picks one with a prior. Normal known:
:func:`motion_from_homography_known_normal`, the path that stays accurate near
H_d = I. Conventions as in :mod:`hvo_graph.geometry.discrete`.

Reference: Y. Ma, S. Soatto, J. Kosecka, S. S. Sastry, *An Invitation to 3-D
Vision*, Springer 2004, section 5.3; E. Malis, M. Vargas, *Deeper understanding
of the homography decomposition for vision-based control*, INRIA RR-6303, 2007.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_matrix, as_vector
from hvo_graph.geometry.discrete import (
    _ROTATION_TOL,
    _euclidean_input,
    _pair,
    unit_normal,
)
from hvo_graph.geometry.rotation import nearest_rotation


@dataclass(frozen=True)
class HomographySolution:
    """One decomposition H_d = R + t n*^T.

    Attributes:
        rotation: (3, 3) R, reference -> current (X = R X* + T).
        translation: (3,) t = T / d* (T in metres, d* the reference plane distance).
        normal: (3,) unit plane normal n* in the reference frame.
    """

    rotation: np.ndarray
    translation: np.ndarray
    normal: np.ndarray


def decompose_homography(H_euclid: np.ndarray) -> list[HomographySolution]:
    """All (R, t = T/d*, n*) with H_d = R + t n*^T (Ma et al. section 5.3).

    With H_d = U diag(s1, 1, s3) V^T and V = [v1 v2 v3],

        u_{1,2} = (sqrt(1 - s3^2) v1 +- sqrt(s1^2 - 1) v3) / sqrt(s1^2 - s3^2)
        R_i = [H v2, H u_i, (H v2) × (H u_i)] [v2, u_i, v2 × u_i]^T
        n_i = v2 × u_i,  t_i = (H - R_i) n_i

    and the two mirrored solutions (R_i, -t_i, -n_i): four in all, in the order
    (R1, t1, n1), (R2, t2, n2), (R1, -t1, -n1), (R2, -t2, -n2). Positive depth
    (:func:`physically_valid_solutions`) normally leaves two; a normal prior
    (:func:`select_solution`) picks one.

    Pure rotation: when s1 = s3 (= 1, i.e. H_d is a rotation) the translation is 0
    and the normal is unobservable; a single solution is returned with
    R = H_d (projected onto SO(3)), t = 0 and, by convention, n* = e3 = [0, 0, 1]
    (any normal is exact; e3 passes every positive-depth test).

    Conditioning: as s1 -> 1 or s3 -> 1 (translation along the plane normal) the
    two physical solutions merge, and the normal is only sqrt(eps)-accurate
    (about 1e-8 even for exact data); as t -> 0 the normal is undetermined. With
    n* known use :func:`motion_from_homography_known_normal` instead.

    Args:
        H_euclid: (3, 3) Euclidean homography (middle singular value 1, positive
            depth sign), e.g. from :func:`euclidean_homography`.
    Returns:
        list of :class:`HomographySolution` (4, or 1 for a pure rotation).
    Raises:
        InputError: H_euclid not normalized (middle singular value != 1) or with
            det <= 0.
    """
    H = _euclidean_input(H_euclid)
    _, s, Vt = np.linalg.svd(H)
    s1, s3 = s[0] / s[1], s[2] / s[1]
    if s1 - s3 <= _ROTATION_TOL:
        return [HomographySolution(nearest_rotation(H), np.zeros(3), np.array([0.0, 0.0, 1.0]))]
    v1, v2, v3 = Vt
    # Clip tiny negative round-off when s1 or s3 equals 1 (translation along n(t)).
    a = np.sqrt(max(1.0 - s3 * s3, 0.0))
    b = np.sqrt(max(s1 * s1 - 1.0, 0.0))
    c = np.sqrt(s1 * s1 - s3 * s3)
    solutions = []
    for u in ((a * v1 + b * v3) / c, (a * v1 - b * v3) / c):
        U = np.column_stack((v2, u, np.cross(v2, u)))
        Hv2, Hu = H @ v2, H @ u
        W = np.column_stack((Hv2, Hu, np.cross(Hv2, Hu)))
        R = nearest_rotation(W @ U.T)
        n = np.cross(v2, u)
        n /= np.linalg.norm(n)
        solutions.append(HomographySolution(R, (H - R) @ n, n))
    solutions += [
        HomographySolution(sol.rotation, -sol.translation, -sol.normal) for sol in solutions
    ]
    return solutions


def _front_margins(
    a: np.ndarray, b: np.ndarray, R: np.ndarray, t: np.ndarray, n: np.ndarray
) -> tuple[float, float, float]:
    """Smallest n*^T m*_i, d(t)/d* = 1 + n*^T R^T t, smallest (R n*)^T m_i.

    Depths are z*_i = d* / (n*^T m*_i) in the reference frame and
    z_i = d(t) / (n(t)^T m_i) in the current one, with n(t) = R n* and
    d(t) = d* (1 + n*^T R^T t): all positive iff the three numbers are.
    """
    return (
        float(np.min(a @ n)),
        float(1.0 + n @ R.T @ t),
        float(np.min(b @ (R @ n))),
    )


def physically_valid_solutions(
    solutions: list[HomographySolution], m_ref: np.ndarray, m_cur: np.ndarray
) -> list[HomographySolution]:
    """Keep the solutions that put every point in front of both cameras.

    Tests (all strict): n*^T m*_i > 0 (reference depth), 1 + n*^T R^T t > 0
    (the current camera is on the same side of the plane, d(t) > 0), and
    (R n*)^T m_i > 0 (current depth). For a generic motion two of the four
    solutions of :func:`decompose_homography` survive.

    Args:
        solutions: candidates from :func:`decompose_homography`.
        m_ref, m_cur: (N, 2|3) the correspondences the homography came from.
    Returns:
        the surviving solutions, in input order (possibly empty).
    """
    a, b = _pair(m_ref, m_cur, 1)
    return [
        sol
        for sol in solutions
        if min(_front_margins(a, b, sol.rotation, sol.translation, sol.normal)) > 0
    ]


def check_points_in_front(
    m_ref: np.ndarray, m_cur: np.ndarray, R: np.ndarray, t: np.ndarray, normal: np.ndarray
) -> None:
    """Raise unless every point is in front of both cameras for the motion (R, t, n*).

    Same tests as :func:`physically_valid_solutions`.

    Args:
        m_ref, m_cur: (N, 2|3) normalized correspondences.
        R: (3, 3) rotation reference -> current; t: (3,) T / d*; normal: (3,) unit n*.
    Raises:
        InputError: "points behind the camera" naming the frame that fails.
    """
    a, b = _pair(m_ref, m_cur, 1)
    R = as_matrix(R, "R", (3, 3))
    t = as_vector(t, "t", 3)
    n = unit_normal(normal)
    ref, side, cur = _front_margins(a, b, R, t, n)
    if not ref > 0:
        raise InputError("m_ref: points behind the camera in the reference frame (n*^T m* <= 0)")
    if not side > 0:
        raise InputError(
            "points behind the camera: the current camera is behind the plane (1 + n*^T R^T t <= 0)"
        )
    if not cur > 0:
        raise InputError("m_cur: points behind the camera in the current frame ((R n*)^T m <= 0)")


def select_solution(
    solutions: list[HomographySolution], normal_prior: np.ndarray
) -> HomographySolution:
    """The solution whose normal n* is closest in direction to ``normal_prior``.

    Args:
        solutions: non-empty list of candidates (anything with a ``normal``; the
            continuous homography's solutions are selected the same way).
        normal_prior: (3,) non-zero vector (normalized here), e.g. the known n*
            or the previous frame's estimate.
    Raises:
        InputError: empty list or zero prior.
    """
    if not solutions:
        raise InputError("solutions: empty list, nothing to select")
    p = as_vector(normal_prior, "normal_prior", 3)
    if not np.linalg.norm(p) > 0:
        raise InputError("normal_prior: expected a non-zero vector")
    return max(solutions, key=lambda sol: float(sol.normal @ p))


def motion_from_homography_known_normal(
    H_euclid: np.ndarray,
    normal: np.ndarray,
    *,
    m_ref: np.ndarray | None = None,
    m_cur: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t = T/d*) from H_d = R + t n*^T when n* is known.

    For u1, u2 an orthonormal basis of the plane orthogonal to n*,
    H_d u_i = R u_i exactly; R is the rotation that best maps u_i onto H_d u_i
    (Wahba / orthogonal Procrustes by SVD, with the det = +1 correction), and
    t = H_d n* - R n*. Unlike the general decomposition this stays
    well-conditioned as t -> 0: H_d = I gives R = I, t = 0 to machine precision.

    Args:
        H_euclid: (3, 3) Euclidean homography (middle singular value 1, positive
            depth sign), e.g. from :func:`euclidean_homography`.
        normal: (3,) unit plane normal n* in the reference frame.
        m_ref, m_cur: optional (N, 2|3) correspondences; when given, the result is
            checked with :func:`check_points_in_front`.
    Returns:
        R: (3, 3) rotation reference -> current.
        t: (3,) T / d*.
    Raises:
        InputError: H_euclid not normalized, bad normal, or (with points) points
            behind the camera.
    """
    H = _euclidean_input(H_euclid)
    n = unit_normal(normal)
    # Rows 2 and 3 of V^T in the SVD of the 1 x 3 matrix n^T: an orthonormal basis of n-perp.
    basis = np.linalg.svd(n[None, :])[2][1:]
    B = sum(np.outer(H @ u, u) for u in basis)
    U, _, Vt = np.linalg.svd(B)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    t = H @ n - R @ n
    if m_ref is not None or m_cur is not None:
        if m_ref is None or m_cur is None:
            raise InputError("m_ref, m_cur: give both or neither")
        check_points_in_front(m_ref, m_cur, R, t, n)
    return R, t
