"""The plane normal n* from several frames at once: one n*, every frame's motion.

With n* unknown, one frame pair's H_d = R + T n*^T / d* gives n* from its
decomposition, but only as well as that pair's parallax allows (a few degrees
at 5 % of d*), and a wrong n* tilts every later pose. Every frame that shares
points with the reference sees the same n*: :func:`refine_plane_normal` fits
n*, each frame's motion (R_k, T_k) and the reference's own point coordinates
mu_i (its pixels are noisy too, and shared by every frame) to all observations
at once, a small bundle adjustment of plane points:

    min  sum_i |m_0i - mu_i|^2 / sigma^2 + sum_k sum_i rho(|m_ki - pi(R_k X*_i + T_k)|^2 / sigma^2),
    X*_i = d* mu_i / (n*^T mu_i),

by Gauss-Newton with the motions eliminated (Schur complement onto n*'s two
tangent directions and the mu_i), Huber-weighted (rho) so that a track off the
plane does not tilt n*. n* enters through the back-projection:

    d X*_i / d n* = -d* mu_i mu_i^T / (n*^T mu_i)^2.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry._fit import plane_basis, retract
from hvo_graph.geometry.transfer import linearize_transfer
from hvo_graph.types import Plane

__all__ = ["NormalFit", "refine_plane_normal"]

#: Most Gauss-Newton iterations of the joint fit.
MAX_ITERATIONS = 30


@dataclass(frozen=True)
class NormalFit:
    """The result of :func:`refine_plane_normal`.

    Attributes:
        normal: (3,) unit n* in the reference frame.
        covariance: (2, 2) covariance of n* in the tangent basis ``basis`` (rad^2).
        basis: (2, 3) orthonormal directions orthogonal to ``normal``.
        motions: [(R_k (3, 3), T_k (3,))] every frame's refined motion.
        reference: (P, 3) the reference's refined normalized points mu_i.
        iterations: Gauss-Newton iterations run.
        cost: the final robust cost (sum of squared whitened residuals, Huber beyond).
        translation_chi2: the largest chi^2 of a frame's translation T_k against its
            covariance (None: not tested); see
            :func:`~hvo_graph.frontend.normal_search.sequence_normal`.
    """

    normal: np.ndarray
    covariance: np.ndarray
    basis: np.ndarray
    motions: list[tuple[np.ndarray, np.ndarray]]
    reference: np.ndarray
    iterations: int
    cost: float
    translation_chi2: float | None = None

    @property
    def sigma_deg(self) -> float:
        """Standard deviation of n*'s direction, degrees (the larger tangent axis)."""
        return float(np.degrees(np.sqrt(np.linalg.eigvalsh(self.covariance)[-1])))


def _frame_system(rows, m_cur, R, T, mu, plane, sigma, basis, huber, size):
    """One frame's blocks: (H_kk 6x6, H_kg 6xG, H_gg GxG, g_k 6, g_g G, robust cost), with
    the global unknowns g = [delta n* (2); delta mu_1 (2); ...] (G = size)."""
    m_ref = mu[rows]
    lin = linearize_transfer(R, T, m_ref, m_cur, plane, sigma)
    d, depth = plane.distance, lin.depth
    dXstar_dn = -d * np.einsum("ni,nj->nij", m_ref, m_ref) / depth[:, None, None] ** 2
    Jg = np.zeros((len(rows), 2, size))  # r moves by -Jg delta_g (as by -J delta_pose)
    Jg[:, :, :2] = lin.P @ R @ dXstar_dn @ basis.T
    for c in range(2):  # d pi / d mu_i: lin.A, into mu_i's two columns
        Jg[np.arange(len(rows)), :, 2 + 2 * rows + c] = lin.A[:, :, c]
    r = lin.residual / sigma
    chi2 = np.einsum("ni,ni->n", r, r)
    dist = np.sqrt(chi2)
    if huber is None:
        w, cost = np.ones_like(dist), chi2
    else:
        w = np.minimum(1.0, huber / np.maximum(dist, 1e-12))
        cost = np.where(dist <= huber, chi2, 2 * huber * dist - huber**2)
    J = lin.J.reshape(-1, 6) / sigma
    Jg = Jg.reshape(-1, size) / sigma
    wr = (np.repeat(w, 2) * r.ravel())[:, None]
    JtW = J.T * np.repeat(w, 2)
    JgtW = Jg.T * np.repeat(w, 2)
    return JtW @ J, JtW @ Jg, JgtW @ Jg, (J.T @ wr)[:, 0], (Jg.T @ wr)[:, 0], float(cost.sum())


def refine_plane_normal(
    reference: np.ndarray,
    frames: Sequence[tuple[np.ndarray, np.ndarray]],
    motions: Sequence[tuple[np.ndarray, np.ndarray]],
    normal: np.ndarray,
    distance: float,
    sigma: float,
    *,
    huber: float | None = None,
    max_iterations: int = MAX_ITERATIONS,
) -> NormalFit:
    """n*, every frame's motion and the reference points fitted to all observations.

    Args:
        reference: (P, 3) normalized points of the reference frame (third column 1).
        frames: per frame (rows (N_k,) int into ``reference``, m_cur (N_k, 3)): the
            frame's normalized observations of those reference points.
        motions: per frame the starting (R_k (3, 3), T_k (3,) metres), X = R X* + T.
        normal: (3,) starting unit n* (e.g. from one frame's decomposition).
        distance: d*, metres.
        sigma: pixel noise in normalized units.
        huber: Huber threshold on each observation's whitened residual norm (None:
            Gaussian); the reference's own observations are Gaussian.
        max_iterations: most Gauss-Newton iterations.
    Returns:
        The :class:`NormalFit`.
    Raises:
        InputError: no frame, or a point behind a camera at the start.
    """
    if not frames or len(frames) != len(motions):
        raise InputError("refine_plane_normal: expected one motion per frame, at least one")
    observed = np.asarray(reference, dtype=float)
    size = 2 + 2 * len(observed)
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    motions = [(np.asarray(R, float), np.asarray(T, float)) for R, T in motions]

    def system(n, motions, mu):
        basis = plane_basis(n)
        plane = Plane(distance, n)
        blocks = [
            _frame_system(rows, m, R, T, mu, plane, sigma, basis, huber, size)
            for (rows, m), (R, T) in zip(frames, motions, strict=True)
        ]
        own = (observed[:, :2] - mu[:, :2]).ravel() / sigma  # the reference's pixels
        return basis, blocks, own, sum(b[5] for b in blocks) + float(own @ own)

    mu = observed.copy()
    basis, blocks, own, cost = system(n, motions, mu)
    S = np.eye(size)
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (reported)
        S, b = np.zeros((size, size)), np.zeros(size)
        S[2:, 2:] += np.eye(size - 2) / sigma**2
        b[2:] += own / sigma
        for H_kk, H_kg, H_gg, g_k, g_g, _ in blocks:
            K = np.linalg.solve(H_kk, np.column_stack((H_kg, g_k)))
            S += H_gg - H_kg.T @ K[:, :-1]
            b += g_g - H_kg.T @ K[:, -1]
        step_g = np.linalg.solve(S, b)
        deltas = [np.linalg.solve(H_kk, g_k - H_kg @ step_g) for H_kk, H_kg, _, g_k, _, _ in blocks]
        step = 1.0
        while step > 1e-3:  # Gauss-Newton, halved until the robust cost falls
            n_new = n + step * basis.T @ step_g[:2]
            n_new /= np.linalg.norm(n_new)
            mu_new = mu.copy()
            mu_new[:, :2] += step * step_g[2:].reshape(-1, 2)
            moved = [
                retract(R, T, step * delta) for (R, T), delta in zip(motions, deltas, strict=True)
            ]
            try:
                new = system(n_new, moved, mu_new)
            except InputError:  # a point behind a camera: too long a step
                step *= 0.5
                continue
            if new[3] <= cost:
                break
            step *= 0.5
        else:
            break
        converged = np.linalg.norm(step * step_g[:2]) < 1e-10 or cost - new[3] < 1e-10 * cost
        n, motions, mu, (basis, blocks, own, cost) = n_new, moved, mu_new, new
        if converged:
            break
    covariance = np.linalg.inv(S)[:2, :2]
    return NormalFit(n, covariance, basis, motions, mu, iterations, float(cost))
