"""A keyframe's tilt against the plane, re-fitted from the frames measured against it.

Poses against a keyframe r are measured with the plane placed by the front end's own
estimate of r: n_r = R_r n*, d_r = d* + n_r^T T_r. A tilt error delta of that n_r
biases every pose measured against r by about (|T| / d_r) delta, and the next keyframe
inherits both, so over a long traverse with few points the tilt error can grow from
keyframe to keyframe (on one simulated traverse from 6 to 130 degrees in 2 s). The
homographies carry the tilt themselves: H_d = R + T n_r^T / d_r fixes n_r once the
camera has translated. So before the front end leaves a keyframe, it fits n_r to the
frames measured against it (:func:`~hvo_graph.geometry.plane_normal.refine_plane_normal`,
the reference's own pixels included) and fuses that with the tilt the chain of keyframes
predicts, whose covariance it carries from keyframe to keyframe
(:func:`chained_tilt_covariance`). With little parallax the fit says little and the
chain's tilt stays; with much, the fit bounds the drift.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend._points import HUBER, TrackedFrame, common_points
from hvo_graph.geometry._fit import PlaneTransfer, plane_basis
from hvo_graph.geometry.plane_normal import refine_plane_normal
from hvo_graph.geometry.rotation import skew
from hvo_graph.types import FrameMeasurement, FrameObservations, Plane, TiltMeasurement

if TYPE_CHECKING:
    from hvo_graph.frontend.measure import MeasurementFrontEnd

__all__ = [
    "MAX_FRAMES",
    "MAX_POINTS",
    "KeptFrames",
    "TiltFit",
    "chained_tilt_covariance",
    "fused_tilt",
    "keep_frame",
    "keep_stretch",
    "leave_keyframe",
    "with_tilt",
]

#: Frames measured against a keyframe that are kept for its tilt fit (evenly thinned).
MAX_FRAMES: int = 24

#: Keyframe points fitted (those seen in the most kept frames): the fit grows with P^2.
MAX_POINTS: int = 40

#: Gauss-Newton iterations of the joint fit: it starts at the placed n_r and the
#: measured motions, within noise of the optimum.
FIT_ITERATIONS: int = 4

#: Tilt variance (rad^2) of a reference whose pose was predicted, not measured.
UNKNOWN_TILT_VARIANCE: float = 0.1**2

#: A joint fit is reported to the estimators (``FrameMeasurement.keyframe_tilt``) when
#: its standard deviation is below this (rad): beyond, the frames barely translated
#: and a linearized attitude factor would not describe it.
MAX_REPORTED_SIGMA: float = 0.1

#: ... and when it agrees with the chain's tilt: chi^2 (2 dof) of their difference.
REPORT_GATE: float = 13.815510557964274

#: A keyframe's tilt is reported at the first frame this far from it (||T|| / d_r), or
#: when the front end leaves it, whichever comes first.
REPORT_PARALLAX: float = 0.5


@dataclass(frozen=True)
class TiltFit:
    """What :func:`fused_tilt` found.

    Attributes:
        correction: (3, 3) C: the corrected placement is R_r <- C R_r, T_r <- C T_r, a
            rotation about the camera centre turning n_r to its fused estimate (d_r and
            the heading about n_r unchanged).
        posterior: (3, 3) covariance of the fused n_r.
        normal: (3,) n_r of the frames' joint fit alone (no chain prior).
        covariance: (3, 3) its covariance (rank 2).
    """

    correction: np.ndarray
    posterior: np.ndarray
    normal: np.ndarray
    covariance: np.ndarray
    agreement: float = 0.0

    @property
    def sigma(self) -> float:
        """The joint fit's largest standard deviation of n_r's direction (rad)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.covariance)[-1]))


class KeptFrames(list):
    """The frames kept for the current keyframe's tilt fit, and whether that keyframe's
    tilt has been reported (once per keyframe: later fits reuse the same pixels)."""

    reported: bool = False

    def __init__(self, frames: Sequence[TrackedFrame] = ()) -> None:
        super().__init__(frames)


def keep_frame(front: MeasurementFrontEnd, frame: TrackedFrame) -> None:
    """Keep ``frame`` (measured against ``front``'s keyframe; not against W, whose tilt is
    known) for the tilt fit; past :data:`MAX_FRAMES`, every other older one is dropped
    (the newest, usually of most parallax, always stays). The first frame
    :data:`REPORT_PARALLAX` from the keyframe has the tilt reported (a keyframe kept
    to the end of a sequence is never left)."""
    ref = front._reference
    if ref is None or ref.index == front._world_index:
        return
    frames = front._kept
    frames.append(frame)
    if len(frames) > MAX_FRAMES:
        frames[:] = frames[-2::-2][::-1] + frames[-1:]
    if frames.reported or frame.R is None or ref.R is None or front.normal is None:
        return
    translation = frame.T - frame.R @ ref.R.T @ ref.T  # r -> frame
    if np.linalg.norm(translation) >= REPORT_PARALLAX * front._plane_in(ref).distance:
        _report(front, ref.index, _keyframe_fit(front, ref)[1])


def _keyframe_fit(
    front: MeasurementFrontEnd, ref: TrackedFrame
) -> tuple[np.ndarray, TiltFit | None]:
    """The chain's covariance of n_r (:data:`UNKNOWN_TILT_VARIANCE` when not recorded)
    and :func:`fused_tilt` of the frames kept against ``ref``."""
    plane = front._plane_in(ref)
    prior = front._tilt.get(ref.index)
    if prior is None:
        prior = UNKNOWN_TILT_VARIANCE * (np.eye(3) - np.outer(plane.normal, plane.normal))
    if ref.index == front._world_index:  # n* is known there
        return prior, None
    fit = fused_tilt(
        ref,
        front._kept,
        plane,
        prior,
        front._sigma,
        min_points=front.config.min_points,
        huber=HUBER,
    )
    return prior, fit


def _report(front: MeasurementFrontEnd, index: int, fit: TiltFit | None) -> None:
    """The joint fit as the next record's ``keyframe_tilt``, when precise enough and in
    agreement with the chain (:data:`MAX_REPORTED_SIGMA`, :data:`REPORT_GATE`)."""
    if fit is None or front._kept.reported or front.normal is None:
        return
    if fit.sigma < MAX_REPORTED_SIGMA and fit.agreement < REPORT_GATE:
        front._tilt_measurement = TiltMeasurement(
            index, fit.normal, front.normal.copy(), fit.covariance
        )
        front._kept.reported = True


def with_tilt(record: FrameMeasurement, tilt: TiltMeasurement | None) -> FrameMeasurement:
    """``record`` carrying ``tilt`` as its ``keyframe_tilt`` (as it is for None)."""
    return record if tilt is None else dataclasses.replace(record, keyframe_tilt=tilt)


def keep_stretch(
    front: MeasurementFrontEnd,
    observations: Sequence[FrameObservations],
    t: np.ndarray,
    ids: np.ndarray,
    m: np.ndarray,
    R: np.ndarray,
    T: np.ndarray,
) -> TiltMeasurement | None:
    """:func:`keep_frame` for a stretch measured at once: ``observations`` (all but its
    last frame, ``front``'s previous one by now), their times t, the stretch's track
    ``ids``, points m (F, N, 3) and world -> frame motions R (F, 3, 3), T (F, 3).
    Returns the tilt reported on the way, for the stretch's last record (or None)."""
    if front._reference is None or front._reference.index == front._world_index:
        return None
    for k, obs in enumerate(observations):
        keep_frame(front, TrackedFrame(obs.index, t[k], ids, m[k], R[k], T[k]))
    assert front._previous is not None
    keep_frame(front, front._previous)
    tilt, front._tilt_measurement = front._tilt_measurement, None
    return tilt


def chained_tilt_covariance(
    reference_tilt: np.ndarray,
    rotation: np.ndarray,
    normal: np.ndarray,
    rotation_covariance: np.ndarray | None,
) -> np.ndarray:
    """(3, 3) covariance of n_k = R n_r, the plane normal in a new keyframe k.

    Args:
        reference_tilt: (3, 3) covariance of n_r in the old reference r.
        rotation: (3, 3) motion R from r to k.
        normal: (3,) n_k.
        rotation_covariance: (3, 3) covariance of k's measured rotation (right
            perturbation phi of R_rk: n_k moves by [n_k]_x phi); None: k's pose was
            predicted, its tilt is :data:`UNKNOWN_TILT_VARIANCE` more uncertain.
    """
    N = skew(normal)
    if rotation_covariance is None:
        own = UNKNOWN_TILT_VARIANCE * (N @ N.T)
    else:
        own = N @ rotation_covariance @ N.T
    return rotation @ reference_tilt @ rotation.T + own


def fused_tilt(
    reference: TrackedFrame,
    frames: Sequence[TrackedFrame],
    plane: Plane,
    prior: np.ndarray,
    sigma: float,
    *,
    min_points: int = 4,
    huber: float | None = None,
) -> TiltFit | None:
    """The rotation that corrects the reference's tilt, its tilt covariance after, and
    the joint fit of the frames alone.

    Args:
        reference: the keyframe r (``m``: its normalized points).
        frames: frames measured against it, their ``R``, ``T`` world -> frame motions
            (as ``reference``'s).
        plane: n_r = R_r n*, d_r in the reference, as the poses were measured.
        prior: (3, 3) covariance of n_r from the chain (:func:`chained_tilt_covariance`).
        sigma: pixel noise in normalized units.
        min_points: fewest points a frame must share with the reference.
        huber: the fit's Huber threshold (whitened residual norm).
    Returns:
        The :class:`TiltFit`, or None when no frame can be fitted.
    """
    assert reference.R is not None and reference.T is not None
    n = plane.normal
    observed: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for frame in frames:
        if frame.R is None or frame.T is None:
            continue
        _, rows, cols = np.intersect1d(
            reference.ids, frame.ids, assume_unique=True, return_indices=True
        )
        if len(rows) >= min_points:
            R = frame.R @ reference.R.T  # r -> frame
            observed.append((rows, frame.m[cols], R, frame.T - R @ reference.T))
    if not observed:
        return None
    m_ref = reference.m
    if len(m_ref) > MAX_POINTS:
        seen = np.bincount(np.concatenate([o[0] for o in observed]), minlength=len(m_ref))
        keep = np.zeros(len(m_ref), dtype=bool)
        keep[np.argsort(-seen, kind="stable")[:MAX_POINTS]] = True
        renumber = np.cumsum(keep) - 1
        observed = [(renumber[r[keep[r]]], m[keep[r]], R, T) for r, m, R, T in observed]
        observed = [o for o in observed if len(o[0]) >= min_points]
        m_ref = m_ref[keep]
        if not observed:
            return None
    try:
        fit = refine_plane_normal(
            m_ref,
            [(rows, m) for rows, m, _, _ in observed],
            [(R, T) for _, _, R, T in observed],
            n,
            plane.distance,
            sigma,
            huber=huber,
            max_iterations=FIT_ITERATIONS,
        )
    except (InputError, np.linalg.LinAlgError):
        return None
    # Fuse in the tangent plane of n_r: the chain's prior and the fit's estimate.
    basis = plane_basis(n)  # (2, 3)
    to_basis = basis @ fit.basis.T
    fitted = to_basis @ fit.covariance @ to_basis.T
    chained = basis @ prior @ basis.T
    gain = chained @ np.linalg.inv(chained + fitted)
    delta = gain @ (basis @ fit.normal)
    posterior = chained - gain @ chained
    fused = n + basis.T @ delta
    fused /= np.linalg.norm(fused)
    return TiltFit(
        _rotation_between(n, fused),
        basis.T @ (0.5 * (posterior + posterior.T)) @ basis,
        fit.normal,
        fit.basis.T @ fit.covariance @ fit.basis,
        float(basis @ fit.normal @ np.linalg.solve(chained + fitted, basis @ fit.normal)),
    )


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation turning the direction of ``a`` to that of ``b``."""
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-15:
        return np.eye(3)
    angle = np.arctan2(s, float(a @ b))
    return gtsam.Rot3.Expmap(angle * axis / s).matrix()


def leave_keyframe(front: MeasurementFrontEnd) -> TrackedFrame:
    """The previous frame, ready to become the new keyframe of ``front``.

    The current reference's tilt is re-fitted first (:func:`fused_tilt`; ``front``'s
    reference replaced by the corrected one, the joint fit left for the current frame's
    record as a :class:`~hvo_graph.types.TiltMeasurement`), the previous frame's pose
    re-measured against it, and the new keyframe's tilt covariance recorded
    (:func:`chained_tilt_covariance`).
    """
    ref, prev = front._reference, front._previous
    assert ref is not None and prev is not None and prev.R is not None and ref.R is not None
    normal = front.normal
    assert normal is not None
    posterior, fused = _keyframe_fit(front, ref)
    if fused is not None:
        C, posterior = fused.correction, fused.posterior
        corrected = TrackedFrame(ref.index, ref.t, ref.ids, ref.m, C @ ref.R, C @ ref.T)
        _report(front, ref.index, fused)
        prev = _remeasured(front, ref, corrected, prev, HUBER)
        front._reference, ref = corrected, corrected
        front._tilt[ref.index] = posterior
    assert prev.R is not None
    front._tilt[prev.index] = chained_tilt_covariance(
        posterior, prev.R @ ref.R.T, prev.R @ normal, front._previous_rotation_covariance
    )
    return prev


def _remeasured(
    front: MeasurementFrontEnd,
    old: TrackedFrame,
    corrected: TrackedFrame,
    frame: TrackedFrame,
    huber: float,
) -> TrackedFrame:
    """``frame``'s world pose against the ``corrected`` reference: its motion from the
    reference refined with the re-placed plane (kept as it was when too few points)."""
    assert old.R is not None and old.T is not None and frame.R is not None
    assert corrected.R is not None and corrected.T is not None and frame.T is not None
    R = frame.R @ old.R.T
    T = frame.T - R @ old.T
    m_ref, m_cur = common_points(corrected, frame.ids, frame.m)
    if front._previous_rotation_covariance is not None and len(m_ref) >= front.config.min_points:
        fit = PlaneTransfer(m_ref, m_cur, front._plane_in(corrected), front._sigma)
        try:
            R, T, _ = fit.refine(R, T, front.config.refine_iterations + 1, huber)
        except (InputError, np.linalg.LinAlgError):
            pass
    # R_rel = R_f R_r^T compounds the rounding of both: back onto SO(3)
    R = gtsam.Rot3.ClosestTo(R).matrix()
    return TrackedFrame(
        frame.index, frame.t, frame.ids, frame.m, R @ corrected.R, R @ corrected.T + T
    )
