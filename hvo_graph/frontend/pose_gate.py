"""The H_d pose refined and gated: which shared points a frame's pose keeps.

RANSAC's consensus starts the refinement, and a chi^2 gate on every shared point
at the refined pose decides (:meth:`~hvo_graph.geometry._fit.PlaneTransfer.chi2`).
With few points RANSAC can be wrong in a way the gate cannot see: on a narrow
view the rotation-translation ambiguity lets a homography 8 degrees off fit five
of six clean points within a pixel, the refinement from it settles in that wrong
minimum (0.35 m off at 2 m), and the gate then rejects the one good point that
disagrees. :func:`gated_pose` therefore also refines from the DLT of every point
whenever RANSAC left some out and the gate rejects some, and takes that pose when
every point passes half the gate there and it fits better by the MSAC score (chi^2
capped at the gate). Taking it whenever its gate kept more points let a pose pulled
towards off-plane tracks keep them (outlier family pose NEES 1.5 -> 1.7).
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

#: The fit from every point replaces RANSAC's only when every point passes this share of
#: the gate there (and it fits better): a pose pulled towards off-plane tracks keeps them
#: near the gate, and taking it raised the pose NEES on the outlier family.
STRICT_GATE = 0.5


class GatedPose(NamedTuple):
    """A refined motion (R, T), its information matrix (6, 6), the points the gate keeps
    (N,) bool, the linearization at (R, T) on all points (None: not made), and the
    MSAC score sum_i min(chi^2_i, gate) (lower fits better; 0 without a gate)."""

    R: np.ndarray
    T: np.ndarray
    info: np.ndarray
    keep: np.ndarray
    lin: Linearization | None
    score: float = 0.0


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
    chi2 = fit.chi2(lin, info)
    return GatedPose(R, T, info, chi2 <= gate, lin, float(np.minimum(chi2, gate).sum()))


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
    known-normal motion of H_d), taken when every point passes ``STRICT_GATE`` of the
    gate there and its MSAC score is lower (every point's chi^2 capped at the gate: an
    outlier costs the gate whatever its residual)."""
    first = refine_and_gate(fit, R, T, start, steps, huber, gate)
    if start.all() or first.keep.all():
        return first
    try:
        H = euclidean(dlt(fit.m_ref, fit.m_cur), fit.m_ref, fit.m_cur)
        R_all, t_all = known_normal_motion(H, fit.plane.normal, fit.basis)
        every = np.ones(len(fit), dtype=bool)
        strict = None if gate is None else STRICT_GATE * gate
        other = refine_and_gate(fit, R_all, fit.plane.distance * t_all, every, steps, huber, strict)
    except (InputError, np.linalg.LinAlgError):
        return first
    return other if other.keep.all() and other.score < first.score else first
