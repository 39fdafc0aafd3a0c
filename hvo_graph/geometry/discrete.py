"""Discrete (Euclidean) homography H_d: estimation, normalization, poses.

Conventions (paper eq. 1, NOTES section 2, contract): (R, T) maps coordinates
of the reference frame F* into the current camera frame, X = R X* + T. Plane
points satisfy n*^T X* = d* (n* unit, pointing away from the camera, d* > 0),
hence X = H_d X* and, for normalized image points m = [x/z, y/z, 1]^T,

    m ~ H_d m*,   H_d = R + T n*^T / d* = R + t n*^T,   t := T / d*.

Every function takes normalized homogeneous coordinates as (N, 3) arrays whose
third column is 1, or (N, 2) arrays of [x, y].

The usual pipeline is :func:`estimate_homography` (scale-free H) ->
:func:`euclidean_homography` (scale and sign fixed) -> the motion
(:mod:`hvo_graph.geometry.decomposition`) -> :func:`camera_pose_from_motion`.

Reference: Y. Ma, S. Soatto, J. Kosecka, S. S. Sastry, *An Invitation to 3-D
Vision*, Springer 2004, section 5.3 (the planar homography and its
decomposition); E. Malis, M. Vargas, *Deeper understanding of the homography
decomposition for vision-based control*, INRIA RR-6303, 2007.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from hvo_graph.errors import InputError, as_matrix, as_number, as_points, as_vector
from hvo_graph.geometry._consensus import consensus_inliers
from hvo_graph.types import Plane

#: Smallest accepted ratio sigma_8 / sigma_1 of the (Hartley-normalized) DLT
#: system: below it the point configuration does not determine H (collinear
#: points). Well-spread configurations give 1e-2 .. 1e-1.
DEGENERACY_TOL = 1e-8

#: Tolerance on "the third column of m is 1" and on "the normal is a unit vector".
_UNIT_TOL = 1e-9

#: sigma_1 - sigma_3 of a Euclidean H_d below this (relative): H_d is a rotation (t = 0).
_ROTATION_TOL = 1e-10

#: |sigma_2 - 1| above this: the matrix was not normalized by euclidean_homography.
_EUCLIDEAN_TOL = 1e-6


# --------------------------------------------------------------------------- validation


def normalized_points(m: object, name: str, *, min_points: int = 1) -> np.ndarray:
    """Validate image points and return them as an (N, 3) array [x, y, 1].

    Args:
        m: (N, 2) [x, y] or (N, 3) [x, y, 1] normalized image coordinates.
        name: argument name used in error messages.
        min_points: smallest accepted N.
    Raises:
        InputError: wrong shape, too few points, NaN/inf, or a third column that is not 1.
    """
    a = as_points(m, name, min_points=min_points)
    if a.shape[1] == 2:
        return np.column_stack((a, np.ones(len(a))))
    bad = np.flatnonzero(np.abs(a[:, 2] - 1.0) > _UNIT_TOL)
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"{name}: third column must be 1 (normalized coordinates m = [x/z, y/z, 1]), "
            f"got {float(a[i, 2]):g} in row {i}"
        )
    return a.copy()


def unit_normal(normal: object, name: str = "normal") -> np.ndarray:
    """Validate a plane normal: a finite (3,) vector of unit length (to 1e-9).

    Raises:
        InputError: wrong shape, NaN/inf, or a norm that is not 1.
    """
    n = as_vector(normal, name, 3)
    norm = float(np.linalg.norm(n))
    if abs(norm - 1.0) > _UNIT_TOL:
        raise InputError(f"{name}: expected a unit vector, got norm {norm:.6g}")
    return n / norm


def positive_distance(distance: object, name: str = "distance") -> float:
    """Validate a plane distance: a finite scalar > 0.

    Raises:
        InputError: not a scalar, NaN/inf, or <= 0.
    """
    return as_number(distance, name, above=0.0)


def _pair(m_ref: object, m_cur: object, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    a = normalized_points(m_ref, "m_ref", min_points=min_points)
    b = normalized_points(m_cur, "m_cur", min_points=min_points)
    if len(a) != len(b):
        raise InputError(f"m_cur: expected as many points as m_ref ({len(a)}), got {len(b)}")
    return a, b


# --------------------------------------------------------------------------- DLT


def _hartley(m: np.ndarray) -> np.ndarray:
    """(3, 3) similarity moving the centroid to 0 and the mean distance to sqrt(2)."""
    c = m[:, :2].mean(axis=0)
    mean_dist = np.mean(np.linalg.norm(m[:, :2] - c, axis=1))
    if mean_dist <= 0.0:
        # All points coincide: the DLT rank test below reports it as degenerate.
        mean_dist = 1.0
    s = np.sqrt(2.0) / mean_dist
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _dlt(m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """Normalized DLT (Hartley & Zisserman alg. 4.2); least squares for N > 4.

    The point sets are checked first: either alone is degenerate exactly when more
    than one homography maps it onto itself, i.e. when the DLT system of the
    identity correspondence m -> m has rank < 8. Those two systems and the DLT's own
    (rows x and y of dst × (H src) = 0 for h = H.ravel()) share one batched SVD.
    """
    T_ref, T_cur = _hartley(m_ref), _hartley(m_cur)
    a, b = m_ref @ T_ref.T, m_cur @ T_cur.T
    n = len(a)
    systems = np.zeros((3, 2 * n, 9))  # the systems of (a, a), (b, b) and (a, b)
    src, dst = np.stack((a, b, a)), np.stack((a, b, b))
    systems[:, 0::2, 3:6] = -src
    systems[:, 0::2, 6:9] = dst[:, :, 1:2] * src
    systems[:, 1::2, 0:3] = src
    systems[:, 1::2, 6:9] = -dst[:, :, 0:1] * src
    _, s, Vt = np.linalg.svd(systems, full_matrices=2 * n < 9)
    ratios = s[:, 7] / s[:, 0]  # sigma_8 / sigma_1 (sigma_1 > 0: the third column is 1)
    for ratio, name in zip(ratios[:2], ("m_ref", "m_cur"), strict=True):
        if ratio < DEGENERACY_TOL:
            raise InputError(
                f"{name}: degenerate point configuration (collinear points: all, or all but "
                "one, on a line); the homography is not determined"
            )
    Vt = Vt[2]
    if ratios[2] < DEGENERACY_TOL:
        raise InputError(
            "m_ref, m_cur: degenerate correspondences (the DLT system is rank-deficient, "
            "e.g. collinear points); the homography is not determined"
        )
    Hn = Vt[-1].reshape(3, 3)
    H = np.linalg.solve(T_cur, Hn @ T_ref)
    return H / np.linalg.norm(H)


def collinear(m: np.ndarray, tolerance: float) -> bool:
    """True when points lie on one line within ``tolerance`` (RMS distance from their
    best-fitting line): no homography is determined by them (a line fixes 5 of its 8
    degrees of freedom).

    Args:
        m: (N, 2) or (N, 3) points (normalized coordinates; only x, y are read).
        tolerance: RMS distance, in the units of ``m``.
    """
    m = np.asarray(m, dtype=float)
    if len(m) < 3:
        return True
    xy = m[:, :2] - m[:, :2].mean(axis=0)
    return bool(np.linalg.svd(xy, compute_uv=False)[-1] / np.sqrt(len(xy)) < tolerance)


def estimate_homography(
    m_ref: np.ndarray, m_cur: np.ndarray, *, ransac_threshold: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Estimate H_d (up to scale) with m_cur ~ H_d m_ref.

    Normalized DLT: both point sets are moved to centroid 0 and mean distance
    sqrt(2), the 2N x 9 system m × (H m*) = 0 is solved by SVD (the least
    squares solution of ||h|| = 1 for N > 4), and the normalization is undone.

    Args:
        m_ref: (N, 2|3) normalized points m* in the reference frame, N >= 4.
        m_cur: (N, 2|3) normalized points m in the current frame.
        ransac_threshold: when given, outliers are rejected first with
            ``cv2.findHomography(..., cv2.RANSAC, ransac_threshold)`` (the threshold is a
            transfer distance in normalized-coordinate units, i.e. pixels / focal length),
            then H is re-estimated by DLT on the inliers. RANSAC is not run when every
            point lies within the threshold of the DLT of the other points (all points
            are then one consensus set, and RANSAC can find no larger one), nor when
            exactly one does not and, without it, every other one does (that one is
            left out): :func:`~hvo_graph.geometry._consensus.consensus_inliers`.
    Returns:
        H: (3, 3) homography with ||H||_F = 1 (scale and sign arbitrary: see
            :func:`euclidean_homography`).
        inliers: (N,) bool, all True without RANSAC.
    Raises:
        InputError: fewer than 4 points, mismatched shapes, NaN/inf, degenerate
            (collinear) configurations, or fewer than 4 RANSAC inliers.
    """
    a, b = _pair(m_ref, m_cur, 4)
    inliers = np.ones(len(a), dtype=bool)
    if ransac_threshold is not None:
        thr = as_number(ransac_threshold, "ransac_threshold", above=0.0)
        within, decided = consensus_inliers(a, b[None], thr)
        inliers = within[0] if decided[0] else _ransac_inliers(a, b, thr)
    return _dlt(a[inliers], b[inliers]), inliers


def _ransac_inliers(a: np.ndarray, b: np.ndarray, threshold: float) -> np.ndarray:
    """(N,) bool: the inliers of OpenCV's RANSAC homography of checked (N, 3) points
    (:func:`estimate_homography`, whose errors it raises)."""
    try:
        H_cv, mask = cv2.findHomography(a[:, :2], b[:, :2], cv2.RANSAC, threshold)
    except cv2.error as exc:
        raise InputError(f"m_ref, m_cur: RANSAC homography failed ({exc.err})") from None
    if H_cv is None or mask is None:
        raise InputError(
            "m_ref, m_cur: RANSAC found no homography (degenerate or collinear points?)"
        )
    inliers = mask.ravel().astype(bool)
    if inliers.sum() < 4:
        raise InputError(f"m_ref, m_cur: RANSAC kept {int(inliers.sum())} inliers, need at least 4")
    return inliers


# --------------------------------------------------------------------------- normalization


def homography_from_motion(
    R: np.ndarray, T: np.ndarray, normal: np.ndarray, distance: float
) -> np.ndarray:
    """H_d = R + T n*^T / d*  (paper section II).

    Args:
        R: (3, 3) rotation, reference -> current (X = R X* + T).
        T: (3,) translation in metres.
        normal: (3,) unit normal n* of the plane in the reference frame.
        distance: d* > 0, plane distance from the reference optical centre.
    Returns:
        (3, 3) Euclidean homography H_d.
    """
    R = as_matrix(R, "R", (3, 3))
    T = as_vector(T, "T", 3)
    n = unit_normal(normal)
    d = positive_distance(distance)
    return R + np.outer(T, n) / d


def euclidean_homography(H: np.ndarray, m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """Fix the scale and sign of an estimated homography (Ma et al. section 5.3).

    The scale is chosen so that the middle singular value is 1 (that of
    R + t n*^T); the sign so that m_i^T H m*_i > 0 for every point, because for
    the Euclidean H_d, z m = z* H_d m*, so m^T H_d m* = (z / z*) ||m||^2 > 0 when
    the point is in front of both cameras.

    Args:
        H: (3, 3) homography up to scale, m_cur ~ H m_ref.
        m_ref: (N, 2|3) normalized reference points m*.
        m_cur: (N, 2|3) normalized current points m.
    Returns:
        (3, 3) Euclidean H_d.
    Raises:
        InputError: H of rank < 2, or points that disagree on the sign of
            m^T H m* (points behind the camera: not a valid homography).
    """
    H = as_matrix(H, "H", (3, 3))
    a, b = _pair(m_ref, m_cur, 1)
    return _euclidean(H, a, b)


def _euclidean(H: np.ndarray, m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """:func:`euclidean_homography` on checked inputs (H (3, 3), points (N, 3))."""
    s = np.linalg.svd(H, compute_uv=False)
    if not s[1] > 1e-12 * max(s[0], np.finfo(float).tiny):
        raise InputError("H: rank < 2, not a homography between two views of a plane")
    H = H / s[1]
    g = np.einsum("ij,jk,ik->i", m_cur, H, m_ref)
    if np.all(g < 0):
        H, g = -H, -g
    if not np.all(g > 0):
        raise InputError(
            "m_ref, m_cur: points behind the camera: m^T H m* changes sign between points "
            "(not a valid homography for points in front of both cameras)"
        )
    return H


def _euclidean_input(H_euclid: object) -> np.ndarray:
    H = as_matrix(H_euclid, "H_euclid", (3, 3))
    s = np.linalg.svd(H, compute_uv=False)
    if abs(s[1] - 1.0) > _EUCLIDEAN_TOL:
        raise InputError(
            f"H_euclid: middle singular value must be 1, got {s[1]:.6g} "
            "(normalize with euclidean_homography first)"
        )
    det = float(np.linalg.det(H))
    if not det > 0:
        # det(R + t n^T) = 1 + n^T R^T t = d(t) / d*, positive while the camera stays on
        # the same side of the plane; a negative value is a wrong sign of H.
        raise InputError(
            f"H_euclid: det(H) = {det:.6g} <= 0: wrong sign (normalize with "
            "euclidean_homography) or the camera crossed the plane"
        )
    return H


# --------------------------------------------------------------------------- poses


def camera_pose_from_motion(R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose T_wc in the reference (world) frame from the point motion (R, T).

    X = R X* + T maps reference coordinates into the current camera frame, so
    the current camera has R_wc = R^T and centre p_wc = -R^T T.

    Args:
        R: (3, 3) rotation; T: (3,) translation in metres (T = d* t).
    Returns:
        (R_wc (3, 3), p_wc (3,)).
    """
    R = as_matrix(R, "R", (3, 3))
    T = as_vector(T, "T", 3)
    return R.T.copy(), -R.T @ T


def motion_from_camera_pose(R_wc: np.ndarray, p_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`camera_pose_from_motion`: R = R_wc^T, T = -R_wc^T p_wc.

    Args:
        R_wc: (3, 3) camera orientation in the world (reference) frame.
        p_wc: (3,) camera centre in the world frame, metres.
    Returns:
        (R (3, 3), T (3,)) with X = R X* + T.
    """
    R_wc = as_matrix(R_wc, "R_wc", (3, 3))
    p_wc = as_vector(p_wc, "p_wc", 3)
    return R_wc.T.copy(), -R_wc.T @ p_wc


__all__ = [
    "DEGENERACY_TOL",
    "camera_pose_from_motion",
    "estimate_homography",
    "euclidean_homography",
    "homography_from_motion",
    "motion_from_camera_pose",
    "normalized_points",
    "positive_distance",
    "unit_normal",
]


#: Names that moved to :mod:`hvo_graph.geometry.decomposition` (kept for one release).
_MOVED_NAMES = (
    "HomographySolution",
    "decompose_homography",
    "physically_valid_solutions",
    "check_points_in_front",
    "select_solution",
    "motion_from_homography_known_normal",
)


def __getattr__(name: str) -> object:
    if name in _MOVED_NAMES:
        from hvo_graph.geometry import decomposition  # imports this module: no top-level cycle

        warnings.warn(
            f"{__name__}.{name} moved to {decomposition.__name__}.{name}; the old path "
            "will be removed in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(decomposition, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def ippe_motion(
    m_ref: np.ndarray, m_cur: np.ndarray, plane: Plane
) -> tuple[np.ndarray, np.ndarray]:
    """The motion (R, T) of plane points by OpenCV's ``solvePnP(SOLVEPNP_IPPE)``.

    The per-frame method a user would pick without this library: the reference
    points back-projected onto the plane, X*_i = d* m*_i / (n*^T m*_i), then the
    planar PnP solution for the current observations.

    Args:
        m_ref: (N, 3) normalized reference points m*.
        m_cur: (N, 3) normalized current points m.
        plane: n* (required) and d* in the reference frame.
    Returns:
        (3, 3) R and (3,) T with X = R X* + T.
    Raises:
        InputError: when solvePnP fails.
    """
    n, d = plane.normal, plane.distance
    X_star = d * m_ref / (m_ref @ n)[:, None]
    ok, rvec, tvec = cv2.solvePnP(
        np.ascontiguousarray(X_star.reshape(-1, 1, 3)),
        np.ascontiguousarray(m_cur[:, :2]).reshape(-1, 1, 2),
        np.eye(3),
        None,
        flags=cv2.SOLVEPNP_IPPE,
    )
    if not ok:
        raise InputError("solvePnP (IPPE) failed on this frame's plane points")
    return cv2.Rodrigues(rvec)[0], tvec.ravel()
