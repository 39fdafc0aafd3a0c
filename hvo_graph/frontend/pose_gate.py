"""The H_d pose refined and gated: which shared points a frame's pose keeps.

RANSAC's consensus starts the refinement, and a chi^2 gate on every shared point
at the refined pose decides (:meth:`~hvo_graph.geometry._fit.PlaneTransfer.chi2`).
With few points RANSAC can be wrong in a way the gate cannot see: on a narrow
view the rotation-translation ambiguity lets a homography 8 degrees off fit five
of six clean points within a pixel, the refinement from it settles in that wrong
minimum (0.35 m off at 2 m), and the gate then rejects the one good point that
disagrees. :func:`gated_pose` therefore also refines from the DLT of every point
whenever RANSAC left some out and the gate rejects some, and keeps whichever
pose the gate keeps more points of.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry._fit import (
    Linearization,
    PlaneTransfer,
    dlt,
    euclidean,
    known_normal_motion,
)


class GatedPose(NamedTuple):
    """A refined motion (R, T), its information matrix (6, 6), the points the gate keeps
    (N,) bool, and the linearization at (R, T) on all points (None: not made)."""

    R: np.ndarray
    T: np.ndarray
    info: np.ndarray
    keep: np.ndarray
    lin: Linearization | None


def refine_and_gate(
    fit: PlaneTransfer,
    R: np.ndarray,
    T: np.ndarray,
    start: np.ndarray,
    steps: int,
    huber: float | None,
    gate: float | None,
) -> GatedPose:
    """Gauss-Newton ``steps`` (3 more with a ``huber`` loss) from (R, T) on the points
    ``start``, then every point with chi^2 <= ``gate`` kept (None: every point)."""
    start_fit = fit if start.all() else fit.subset(start)
    R, T, info = start_fit.refine(R, T, steps + (3 if huber and steps else 0), huber)
    if gate is None:
        return GatedPose(R, T, info, np.ones(len(fit), dtype=bool), None)
    lin = fit.linearize(R, T)
    return GatedPose(R, T, info, fit.chi2(lin, info) <= gate, lin)


def gated_pose(
    fit: PlaneTransfer,
    R: np.ndarray,
    T: np.ndarray,
    start: np.ndarray,
    steps: int,
    huber: float | None,
    gate: float | None,
) -> GatedPose:
    """:func:`refine_and_gate` from RANSAC's (R, T) and inliers ``start``; when RANSAC
    left points out and the gate rejects some, also from the DLT of every point (the
    known-normal motion of H_d): the pose whose gate keeps more points."""
    first = refine_and_gate(fit, R, T, start, steps, huber, gate)
    if start.all() or first.keep.all():
        return first
    try:
        H = euclidean(dlt(fit.m_ref, fit.m_cur), fit.m_ref, fit.m_cur)
        R_all, t_all = known_normal_motion(H, fit.plane.normal, fit.basis)
        every = np.ones(len(fit), dtype=bool)
        other = refine_and_gate(fit, R_all, fit.plane.distance * t_all, every, steps, huber, gate)
    except (InputError, np.linalg.LinAlgError):
        return first
    return other if np.count_nonzero(other.keep) > np.count_nonzero(first.keep) else first
