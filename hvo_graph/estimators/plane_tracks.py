"""Is a track a point of the plane? The likelihood-ratio test of the tight smoother.

A point off the plane n*^T X = d* projects like a plane point only while the camera
does not translate: with parallax, no plane point fits all of its observations. Given
the poses T_wc(k) of the frames that saw the track, the test compares the best fit of
its normalized observations m_k (isotropic noise sigma_k) by a point held on the
plane (2 unknowns) with the best fit by a free point (3 unknowns)::

    statistic = min_{X on plane} chi^2(X) - min_X chi^2(X)

For a plane point, and poses far better known than one pixel, the statistic follows
chi^2 with 1 degree of freedom (one constraint): above :data:`DEFAULT_TRACK_CHI2` the
track is off the plane. Unlike a gate on each observation's residual, it pools every
observation of the track, so a small parallax seen over many frames is enough.

The poses are estimates, though: where the graph observes them weakly (e.g. a rotation
about x traded against a translation along y, with the map bending along), the motion
model may bias them by a pixel or more, and a long clean track then fails the test.
:func:`graph_statistic` is the same statistic with the poses, twists and other landmarks
free to move at the cost the rest of the graph puts on moving them: the track's
residuals judged against pixel noise plus the poses' uncertainty (their posterior
covariance, correlations over time and with the map included). It costs two
Levenberg-Marquardt solves of the graph around the track, so it is only asked of the
tracks that fail the test above.
"""

from __future__ import annotations

from collections.abc import Collection

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X as _X

from hvo_graph.estimators.least_squares import levenberg_marquardt

__all__ = ["DEFAULT_TRACK_CHI2", "graph_statistic", "off_plane_keys", "off_plane_statistic"]

#: chi^2_1(0.999): the likelihood-ratio statistic beyond which a track is off the plane.
DEFAULT_TRACK_CHI2: float = 10.827566170662733

#: Gauss-Newton iterations of each fit (the problems have 2 or 3 unknowns).
_ITERATIONS = 20

#: Most Levenberg-Marquardt iterations of each solve of :func:`graph_statistic` (from the
#: graph's optimum, only the track's copy and what it pulls on move).
_GRAPH_ITERATIONS: int = 20

#: Key of the copy of the tested track in :func:`graph_statistic` (no graph uses "t").
_COPY = gtsam.symbol("t", 0)

_UNIT_CALIBRATION = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)

#: Depth (normalized units) below which a point is behind the camera: no fit there.
_MIN_DEPTH = 1e-6


def _chi2_and_jacobian(
    X: np.ndarray, Rt: np.ndarray, p: np.ndarray, m: np.ndarray, w: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """chi^2 of point X (3,), whitened residuals (2n,) and their Jacobian (2n, 3) in X."""
    c = np.einsum("kij,kj->ki", Rt, X[None] - p)  # camera coordinates (n, 3)
    z = c[:, 2]
    if np.any(z < _MIN_DEPTH):
        return np.inf, np.empty(0), np.empty((0, 3))
    r = (m - c[:, :2] / z[:, None]) * w[:, None]
    d = np.zeros((len(z), 2, 3))  # d(projection)/dc
    d[:, 0, 0] = d[:, 1, 1] = 1.0 / z
    d[:, :, 2] = -c[:, :2] / (z * z)[:, None]
    J = -(d @ Rt) * w[:, None, None]  # d r / d X
    return float(np.sum(r * r)), r.reshape(-1), J.reshape(-1, 3)


def _fit(
    X: np.ndarray,
    basis: np.ndarray,
    Rt: np.ndarray,
    p: np.ndarray,
    m: np.ndarray,
    w: np.ndarray,
) -> tuple[float, np.ndarray]:
    """Least squares over X + basis^T a (basis (q, 3)) from X: damped Gauss-Newton steps
    accepted only when chi^2 decreases; returns (chi^2, X)."""
    chi2, r, J = _chi2_and_jacobian(X, Rt, p, m, w)
    if not np.isfinite(chi2):
        return chi2, X
    damping = 1e-9
    for _ in range(_ITERATIONS):
        A = J @ basis.T
        H = A.T @ A
        g = A.T @ r
        step = np.linalg.solve(H + damping * np.trace(H) * np.eye(len(H)), -g)
        candidate = X + basis.T @ step
        new, r_new, J_new = _chi2_and_jacobian(candidate, Rt, p, m, w)
        if not new < chi2:
            damping *= 100.0
            if damping > 1e3:
                break
            continue
        done = chi2 - new <= 1e-10 * chi2 + 1e-12
        X, chi2, r, J = candidate, new, r_new, J_new
        damping = max(damping / 10.0, 1e-12)
        if done:
            break
    return chi2, X


def off_plane_statistic(
    rotations: np.ndarray,
    positions: np.ndarray,
    m: np.ndarray,
    sigma: np.ndarray,
    normal: np.ndarray,
    distance: float,
    start: np.ndarray,
) -> float:
    """The likelihood-ratio statistic of one track (module docstring): >= 0, ~chi^2_1 for a
    point of the plane.

    Args:
        rotations: (n, 3, 3) R_wc of the frames that saw the track.
        positions: (n, 3) p_wc of those frames.
        m: (n, 2) the track's normalized coordinates (x/z, y/z) in those frames.
        sigma: (n,) standard deviation of each coordinate of m.
        normal, distance: n* (3,) and d* of the plane in W.
        start: (3,) a point of the plane near the track (e.g. its landmark).
    Returns:
        chi^2 of the best plane point minus chi^2 of the best free point; inf when no
        plane point near ``start`` is in front of every camera.
    """
    Rt = np.transpose(np.asarray(rotations, dtype=float), (0, 2, 1))
    p = np.asarray(positions, dtype=float)
    m = np.asarray(m, dtype=float)
    w = 1.0 / np.asarray(sigma, dtype=float)
    n = np.asarray(normal, dtype=float)
    X = np.asarray(start, dtype=float) + (distance - n @ start) * n  # onto the plane
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    in_plane = np.vstack((a, np.cross(n, a)))
    on_plane, X = _fit(X, in_plane, Rt, p, m, w)
    if not np.isfinite(on_plane):
        return np.inf
    free, _ = _fit(X, np.eye(3), Rt, p, m, w)
    return max(0.0, on_plane - free)


def off_plane_keys(
    rotations: np.ndarray,
    positions: np.ndarray,
    frame: np.ndarray,
    key: np.ndarray,
    m: np.ndarray,
    sigma: np.ndarray,
    plane: tuple[np.ndarray, float],
    threshold: float = DEFAULT_TRACK_CHI2,
    *,
    skip: Collection[int] = (),
) -> list[int]:
    """The landmarks whose observations no plane point fits: :func:`off_plane_statistic`
    above ``threshold``, for every landmark with at least 3 observations.

    Args:
        rotations, positions: (F, 3, 3) R_wc and (F, 3) p_wc of the frames.
        frame: (N,) row of each observation's frame in ``rotations``.
        key: (N,) the landmark (any integer id) of each observation.
        m: (N, 2) normalized coordinates; sigma: (N,) their standard deviations.
        plane: (n* (3,), d*) in W.
        threshold: chi^2 of the test (default chi^2_1(0.999)).
        skip: landmarks not to test (already rejected).
    Returns:
        The failing landmarks, in increasing order.
    """
    normal, distance = np.asarray(plane[0], dtype=float), float(plane[1])
    key = np.asarray(key)
    order = np.argsort(key, kind="stable")
    unique, starts = np.unique(key[order], return_index=True)
    failed = []
    for landmark, rows in zip(unique.tolist(), np.split(order, starts[1:]), strict=True):
        if landmark in skip or len(rows) < 3:
            continue
        R, p = rotations[frame[rows]], positions[frame[rows]]
        ray = R[0] @ np.array([m[rows[0], 0], m[rows[0], 1], 1.0])
        along = float(normal @ ray)
        depth = (distance - float(normal @ p[0])) / along if abs(along) > 1e-9 else -1.0
        start = p[0] + depth * ray if depth > 0 else normal * distance
        statistic = off_plane_statistic(R, p, m[rows], sigma[rows], normal, distance, start)
        if statistic > threshold:
            failed.append(int(landmark))
    return failed


def graph_statistic(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    frames: np.ndarray,
    m: np.ndarray,
    sigma: np.ndarray,
    plane_noise: gtsam.noiseModel.Base,
    start: np.ndarray,
    *,
    held: Collection[int] = (),
) -> float:
    """The off-plane statistic of one track with the poses uncertain (module docstring).

    A copy of the track's observations (Gaussian, ``sigma``) on a new point joins
    ``graph`` at its optimum ``values``; the statistic is twice the optimal error with the
    copy held on the plane minus twice the optimal error with it free, every other
    variable free to move too (but ``held``). Linearized, that is the statistic of
    :func:`off_plane_statistic` with each residual's covariance sigma^2 I + J P J^T
    (P the graph's joint covariance of the track's poses, J the projections' pose
    Jacobians): residuals that look like a pose error the graph allows (along its weakly
    observed directions) count less than with the poses fixed.

    Args:
        graph: the factors around the track (its own included), their optimum ``values``
            (X(k) ``Pose3`` T_wc, and whatever else the factors touch).
        frames: (n,) frame index k of each observation (its pose key X(k)).
        m: (n, 2) normalized coordinates; sigma: (n,) their standard deviations.
        plane_noise: the noise model of the landmarks' plane prior (n*^T L = d*).
        start: (3,) a point of the plane near the track (its landmark).
        held: keys not to move (the frames at the edge of a window of the graph).
    Returns:
        The statistic, >= 0.
    """
    free = gtsam.NonlinearFactorGraph(graph)
    for k, point, s in zip(np.asarray(frames).tolist(), np.asarray(m, float), sigma, strict=True):
        noise = gtsam.noiseModel.Isotropic.Sigma(2, float(s))
        copy = gtsam.GenericProjectionFactorCal3_S2(point, noise, _X(k), _COPY, _UNIT_CALIBRATION)
        free.add(copy)
    start = np.asarray(start, dtype=float)
    on_plane = gtsam.NonlinearFactorGraph(free)
    on_plane.add(gtsam.PriorFactorPoint3(_COPY, start, plane_noise))
    initial = gtsam.Values(values)
    initial.insert(_COPY, start)
    fit, _ = levenberg_marquardt(on_plane, initial, max_iterations=_GRAPH_ITERATIONS, fixed=held)
    fit_free, _ = levenberg_marquardt(free, fit, max_iterations=_GRAPH_ITERATIONS, fixed=held)
    return max(0.0, 2.0 * (on_plane.error(fit) - free.error(fit_free)))
