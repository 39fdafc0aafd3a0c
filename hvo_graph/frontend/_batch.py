"""The front end over a whole known sequence: stretches of frames measured at once.

Offline runs (:func:`~hvo_graph.frontend.measure.measure_sequence`, the command line)
know every frame before the first is measured. Most frames are then "plain": they
see exactly the tracks of the reference and of the previous frame, so no keyframe
logic applies, and their pose and velocity are the same arithmetic on arrays of the
same shape. Such a stretch is measured with one numpy call per step over all its
frames (:mod:`hvo_graph.geometry._fit_batch`), and its records are those
:meth:`MeasurementFrontEnd.process` would return, to rounding (tests/test_frontend_batch.py).

Everything else goes through ``process`` itself, frame by frame: the first frames,
a frame whose point set changes, a frame whose RANSAC or chi^2 gate drops a point,
a degenerate or failing fit (which ``process`` refuses or raises exactly as
always), and every frame while n* is unknown or with the IPPE pose solver. A stretch
is measured speculatively up to its first such frame; the stretch grows while it
succeeds and starts small again after a cut, so a cut wastes little work.
"""

from __future__ import annotations

from collections.abc import Iterable, MutableSequence, Sequence
from typing import TYPE_CHECKING

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend._points import TrackedFrame, shared_count
from hvo_graph.frontend.keyframe_tilt import keep_stretch, with_tilt
from hvo_graph.frontend.normal_search import sequence_normal
from hvo_graph.frontend.velocity import flow_twist, mid_interval_plane
from hvo_graph.geometry import _fit_batch as batch
from hvo_graph.geometry._consensus import consensus_inliers
from hvo_graph.geometry._fit import plane_basis
from hvo_graph.geometry.discrete import DEGENERACY_TOL, _ransac_inliers
from hvo_graph.geometry.transfer import keyframe_plane_jacobian
from hvo_graph.types import (
    FrameMeasurement,
    FrameObservations,
    PointObservations,
    PoseMeasurement,
    VelocityMeasurement,
)

if TYPE_CHECKING:
    from hvo_graph.frontend.measure import MeasurementFrontEnd

#: Frames of the first stretch, and after every frame measured one at a time.
FIRST_STRETCH = 16
#: Longest stretch (bounds the stacked arrays: some MB at 20 points).
MAX_STRETCH = 256


def measure_frames(
    front: MeasurementFrontEnd,
    observations: Iterable[FrameObservations],
    robust_min: int,
    huber: float,
    out: MutableSequence[FrameMeasurement] | None = None,
) -> MutableSequence[FrameMeasurement]:
    """The records ``[front.process(o) for o in observations]`` would give, and the same
    state of ``front`` afterwards; plain stretches measured at once.

    Args:
        robust_min: fewest shared points for RANSAC and the gates (``ROBUST_MIN_POINTS``).
        huber: the refinement's Huber threshold (``HUBER``).
        out: where the records go (``append`` / ``extend``), returned; default a new list.
    """
    out = [] if out is None else out
    if not isinstance(observations, Sequence):  # a list, a lazy track table: not copied
        observations = list(observations)
    if front.normal is None and front._reference is None and front.config.pose_solver != "ippe":
        front.normal_fit = sequence_normal(  # a whole sequence: n* from all of it, at once
            observations,
            front.camera,
            front.plane.distance,
            front._sigma,
            min_points=front.config.min_points,
            ransac_px=front.config.ransac_px,
            huber=huber,
        )
        if front.normal_fit is not None:
            front._normal = front.normal_fit.normal
    i, n, size = 0, len(observations), FIRST_STRETCH
    while i < n:
        stop = min(n, i + size)
        done, one_by_one = _stretch(front, observations, i, stop, robust_min, huber)
        out.extend(done)
        i += len(done)
        if i == stop:
            size = min(2 * size, MAX_STRETCH)
            continue
        for obs in observations[i : i + one_by_one]:
            out.append(front.process(obs))
        i += one_by_one
        size = FIRST_STRETCH
    return out


def _stretch(
    front: MeasurementFrontEnd,
    observations: Sequence[FrameObservations],
    start: int,
    stop: int,
    robust_min: int,
    huber: float,
) -> tuple[list[FrameMeasurement], int]:
    """(records of the plain frames from ``start`` on, how many frames to measure one at a
    time next: 1 at a cut, the whole stretch when numpy refuses a stack)."""
    ref, prev = front._reference, front._previous
    if (
        front.config.pose_solver != "homography"
        or front._normal is None
        or ref is None
        or prev is None
        or prev.R is None
    ):
        return [], 1
    try:
        return _measure(front, observations[start:stop], robust_min, huber), 1
    except np.linalg.LinAlgError:  # a singular stack: let process() meet it frame by frame
        return [], stop - start


def _same_tracks(front: MeasurementFrontEnd, block: Sequence[FrameObservations]) -> tuple:
    """(ids kept, raw-id column mask or None, frames) of the leading frames that see the
    same tracks (after exclusions)."""
    raw = np.asarray(block[0].ids)
    empty = (np.empty(0, dtype=int), None, 0)
    if raw.ndim != 1 or len(raw) < 2 or not np.all(raw[1:] > raw[:-1]):
        return empty
    n = len(raw)
    count = next((k for k, o in enumerate(block) if len(o.ids) != n), len(block))
    try:
        stacked = np.array([o.ids for o in block[:count]])
    except ValueError:
        return empty
    if stacked.shape != (count, n):
        return empty
    same = np.all(stacked == raw, axis=1)
    count = int(np.argmin(same)) if not same.all() else count
    mask = ~np.isin(raw, list(front._excluded)) if front._excluded else None
    return (raw if mask is None else raw[mask]), mask, count


def _keeps_reference(front: MeasurementFrontEnd, shared: int, ids: np.ndarray) -> int:
    """How many frames seeing ``ids`` (``shared`` of them in the reference) keep the
    reference (``_earlier_reference``, ``_switch_keyframe``): 0 (the first would move it,
    or might: ``process`` decides), 1 (the next would), or all (-1)."""
    ref, prev, cfg = front._reference, front._previous, front.config
    assert ref is not None and prev is not None
    if shared < max(cfg.min_points, cfg.keyframe_min_points or 0) and front._earlier:
        return 0
    limit = cfg.keyframe_min_points
    if limit is None or shared >= limit:
        return -1
    if prev.index != ref.index and prev.R is not None:
        with_previous = shared_count(prev.ids, ids)
        if with_previous >= (cfg.min_points if shared < cfg.min_points else 2 * shared):
            return 0
    return 1 if len(ids) >= 2 * shared else -1


def _first_bad(bad: np.ndarray) -> int:
    return int(np.argmax(bad)) if bad.any() else len(bad)


def _inputs(
    front: MeasurementFrontEnd, block: Sequence[FrameObservations], mask: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray] | None:
    """(t (F,), m (F, N, 3)) of the frames up to the first that ``process`` would refuse
    (time not increasing, pixels not finite); None when the pixels do not stack."""
    assert front._previous is not None
    try:
        t = np.array([o.t for o in block], dtype=float)
        t_prev = np.concatenate(([float(front._previous.t)], t[:-1]))
        uv = np.array([o.uv for o in block], dtype=float)
    except (ValueError, TypeError):  # process() says what is wrong
        return None
    if uv.shape != (len(block), len(block[0].ids), 2):
        return None
    F = _first_bad(~(t > t_prev) | ~np.all(np.isfinite(uv), axis=(1, 2)))
    if F == 0:
        return t[:0], np.empty((0, 0, 3))
    try:
        m = front.camera.pixel_to_normalized(uv[:F].reshape(-1, 2)).reshape(F, -1, 3)
    except InputError:
        return None
    return t[:F], (m if mask is None else m[:, mask])


def _collinear(m: np.ndarray, tolerance: float) -> np.ndarray:
    """(F,) :func:`~hvo_graph.frontend._points.any_collinear` of each frame's points."""
    xy = m[..., :2] - m[..., :2].mean(axis=1, keepdims=True)
    smallest = np.linalg.svd(xy, compute_uv=False)[:, -1]
    return smallest / np.sqrt(xy.shape[1]) < tolerance


def _ransac(front: MeasurementFrontEnd, m_ref: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(F, N) RANSAC inliers of the leading frames (all True without RANSAC; where the
    left-out fits decide, their inliers: ``consensus_inliers``), up to the first frame
    whose RANSAC fails or keeps fewer than ``min_points`` (``process`` refuses it)."""
    threshold = front.config.ransac_px
    if threshold is None:
        return np.ones(m.shape[:2], dtype=bool)
    threshold /= front.camera.mean_focal
    # Frames the left-out fits decide need no RANSAC (estimate_homography).
    inliers, decided = consensus_inliers(m_ref, m, threshold)
    for k in np.flatnonzero(~decided).tolist():
        try:
            inliers[k] = _ransac_inliers(m_ref, m[k], threshold)
        except InputError:
            return inliers[:k]
        if np.count_nonzero(inliers[k]) < front.config.min_points:
            return inliers[:k]
    return inliers


def _poses(
    front: MeasurementFrontEnd,
    m_ref: np.ndarray,
    m: np.ndarray,
    start: np.ndarray,
    gated: bool,
    huber: float,
) -> tuple:
    """The H_d pose of each frame as ``MeasurementFrontEnd._measure_pose`` from the points
    m_ref (N, 3), m (F, N, 3) it shares with the reference and RANSAC's inliers ``start``
    (F, N): (frames before the first that is not plain, then for those
    R, T, the Huber threshold each (R, T) is the optimum with (None: least squares), the
    gate's keep (F, N), covariance, shared covariance, shared Jacobian (F, 6, 2N))."""
    ref, cfg = front._reference, front.config
    assert ref is not None and front._normal is not None
    plane = front._plane_in(ref)
    w0 = start.astype(float)
    H, bad = batch.dlt(m_ref, m, w0)
    H, more = batch.euclidean(H, m_ref, m, w0)
    bad |= more
    R, tn, more = batch.known_normal_motion(H, plane.normal, plane_basis(plane.normal))
    bad |= more
    steps = cfg.refine_iterations + 1
    hub = huber if gated else None
    fit = batch.BatchTransfer(m_ref, m, plane.normal, plane.distance, front._sigma)
    more_steps = 3 if hub and steps else 0
    R, T, info, more = fit.refine(R, plane.distance * tn, steps + more_steps, hub, w0)
    bad |= more
    lin, more = fit.linearize(R, T)
    bad |= more
    keep = np.ones_like(start)
    if gated:
        keep = fit.chi2(lin, info) <= cfg.outlier_chi2
        bad |= np.count_nonzero(keep, axis=1) < cfg.min_points
        # RANSAC and the gate both left points out: ``process`` also tries every point.
        bad |= np.any(~start, axis=1) & np.any(~keep, axis=1)
    refit = np.flatnonzero(np.any(keep != start, axis=1) & ~bad)
    w = keep.astype(float)
    if len(refit):  # the gate changed the points: refine again on those it kept
        sub = batch.BatchTransfer(m_ref, m[refit], plane.normal, plane.distance, front._sigma)
        R[refit], T[refit], info[refit], more = sub.refine(
            R[refit], T[refit], steps, None, w[refit]
        )
        bad[refit] |= more
        lin, more = fit.linearize(R, T)
        bad |= more
    F = _first_bad(bad)
    lin = tuple(a[:F] for a in lin)
    loss: list[float | None] = [hub] * F  # the loss each frame's (R, T) is the optimum of
    for k in refit[refit < F].tolist():
        loss[k] = None
    return (F, R[:F], T[:F], loss, keep[:F], *fit.noise(lin, w[:F]))


def _reject(front: MeasurementFrontEnd, ids: np.ndarray, keep: np.ndarray) -> int:
    """Count the gate's rejections frame by frame as ``process`` does; returns the frames
    up to and including the first that excludes a track (the next sees other tracks)."""
    for k in np.flatnonzero(~keep.all(axis=1)).tolist():
        excluded = len(front._excluded)
        front._reject(ids[~keep[k]])
        if len(front._excluded) != excluded:
            return k + 1
    return len(keep)


def _measure(
    front: MeasurementFrontEnd,
    block: Sequence[FrameObservations],
    robust_min: int,
    huber: float,
) -> list[FrameMeasurement]:
    """The records of the leading plain frames of ``block`` (state of ``front`` updated)."""
    ids, mask, F = _same_tracks(front, block)
    if F == 0:
        return []
    block = block[:F]
    inputs = _inputs(front, block, mask)
    if inputs is None or len(inputs[0]) == 0:
        return []
    t, m = inputs
    ref, prev, cfg = front._reference, front._previous, front.config
    assert ref is not None and prev is not None and prev.R is not None
    shared, ia, ib = np.intersect1d(ref.ids, ids, assume_unique=True, return_indices=True)
    S = len(shared)
    stays = _keeps_reference(front, S, ids)
    if S < cfg.min_points or stays == 0:
        return []
    m_ref = ref.m[ia]
    m_cur = m if S == len(ids) else m[:, ib]
    same_prev = len(prev.ids) == len(ids) and np.array_equal(prev.ids, ids)
    if front._collinear(m_ref) or (same_prev and front._collinear(prev.m)):
        return []
    bad = _collinear(m_cur, front._collinear.tolerance)
    if S != len(ids):  # the next frame's velocity checks all the points
        bad |= _collinear(m, front._collinear.tolerance)
    F = min(_first_bad(bad), len(bad) if stays < 0 else 1)
    robust = S >= robust_min
    start = _ransac(front, m_ref, m_cur[:F]) if robust else np.ones((F, S), dtype=bool)
    if len(start) == 0:
        return []
    F, R, T, loss, keep, covariance, shared_covariance, shared_jacobian = _poses(
        front, m_ref, m_cur[: len(start)], start, robust and cfg.outlier_chi2 is not None, huber
    )
    F = _reject(front, shared, keep[:F])
    if F == 0:
        return []
    t, m, m_cur = t[:F], m[:F], m_cur[:F]
    plane = front._plane_in(ref)
    R_rc = np.swapaxes(R[:F], 1, 2).copy()
    p_rc = -(R_rc @ T[:F, :, None])[..., 0]
    Rw, Tw = R[:F] @ ref.R, R[:F] @ ref.T + T[:F]  # world -> current
    gated = len(ids) >= robust_min
    if same_prev:
        velocities = _velocities(front, (prev.R, prev.T, prev.m, prev.t), t, m, Rw, Tw, gated)
    else:  # the first frame shares other points with the one before
        first = TrackedFrame(block[0].index, block[0].t, ids, m[0], Rw[0], Tw[0])
        velocities = [front._measure_velocity(first)]
        if F > 1:
            before = (Rw[0], Tw[0], m[0], t[0])
            velocities += _velocities(front, before, t[1:], m[1:], Rw[1:], Tw[1:], gated)
    xy = m[..., :2] / m[..., 2:3]
    out = []
    keyframe: dict[str, np.ndarray] = {}
    all_kept = keep.all(axis=1).tolist()
    for k, obs in enumerate(block[:F]):
        kept, jacobian, seen_ids, m_seen = keep[k], shared_jacobian[k], ids, xy[k]
        kept_ids = shared
        if not all_kept[k]:
            kept_ids, jacobian = shared[kept], jacobian[:, np.repeat(kept, 2)]
            seen = ~np.isin(ids, shared[~kept])
            seen_ids, m_seen = ids[seen], m_seen[seen]
        if ref.index != front._world_index:
            keyframe = {
                "reference_rotation": ref.R.T.copy(),
                "reference_position": -ref.R.T @ ref.T,
                "plane_jacobian": keyframe_plane_jacobian(
                    R[k], T[k], m_ref[kept], m_cur[k][kept], plane, front._sigma, loss[k]
                ),
            }
        pose = PoseMeasurement(
            *(R_rc[k], p_rc[k], covariance[k]),
            reference=0 if ref.index == front._world_index else ref.index,  # 0: W
            reference_covariance=shared_covariance[k],
            reference_jacobian=jacobian,
            reference_ids=kept_ids.copy(),
            **keyframe,
        )
        points = PointObservations(
            seen_ids.copy(), m_seen, front._sigma, front._normal, front.plane.distance
        )
        rejected = len(obs.ids) - len(ids) + len(shared) - len(kept_ids)
        out.append(
            FrameMeasurement(obs.index, obs.t, pose, velocities[k], len(obs.ids), rejected, points)
        )
    last = block[F - 1]
    front._previous = TrackedFrame(last.index, last.t, ids, m[-1], Rw[-1], Tw[-1])
    front._previous_rotation_covariance = covariance[F - 1][:3, :3]
    out[-1] = with_tilt(out[-1], keep_stretch(front, block[: F - 1], t, ids, m, Rw, Tw))
    front._rejected_ids = []
    twists = [v for v in velocities if v is not None]
    if twists:
        front._last_twist = np.asarray(twists[-1].twist)
    return out


def _velocities(
    front: MeasurementFrontEnd,
    before: tuple,
    t: np.ndarray,
    m: np.ndarray,
    Rw: np.ndarray,
    Tw: np.ndarray,
    gated: bool,
) -> list[VelocityMeasurement | None]:
    """The H_c twist of each frame against the one before (``MeasurementFrontEnd.
    _measure_velocity``), the same points in every frame and in ``before`` = (R, T, m, t)
    of the frame before the first; frames whose plane, solve or gate is not plain are
    measured by :func:`~hvo_graph.frontend.velocity.flow_twist` itself."""
    cfg = front.config
    assert front._normal is not None
    normal, distance, sigma = front._normal, front.plane.distance, front._sigma
    R0 = np.concatenate((before[0][None], Rw[:-1]))
    T0 = np.concatenate((before[1][None], Tw[:-1]))
    m0 = np.concatenate((before[2][None], m[:-1]))
    t0 = np.concatenate(([before[3]], t[:-1]))
    n_a, n_b = R0 @ normal, Rw @ normal
    d_a = distance + np.einsum("fi,fi->f", n_a, T0)
    d_b = distance + np.einsum("fi,fi->f", n_b, Tw)
    n = (n_a + n_b) / 2.0
    d = (d_a + d_b) / 2.0
    for _ in range(3):  # mid_interval_plane, Plane and flow_twist each normalize n
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
    dt = t - t0
    m_mid = 0.5 * (m0 + m)
    flow = ((m - m0) / dt[:, None, None])[..., :2]
    A = _design_matrices(m_mid, n)
    F, N = m.shape[:2]
    U, sv, Vt = np.linalg.svd(A, full_matrices=False)
    plain = (d > 0) & (np.min(np.einsum("fni,fi->fn", m_mid, n), axis=1) > 0)
    plain &= sv[:, 5] > DEGENERACY_TOL * sv[:, 0]
    f = flow.reshape(F, 2 * N)
    x = (np.swapaxes(Vt, 1, 2) @ ((np.swapaxes(U, 1, 2) @ f[..., None])[..., 0] / sv)[..., None])[
        ..., 0
    ]
    w, v = x[:, :3], d[:, None] * x[:, 3:]
    if gated and cfg.outlier_chi2 is not None:
        u = np.concatenate((w, v / d[:, None]), axis=1)
        residual = (f - (A @ u[..., None])[..., 0]).reshape(F, N, 2)
        chi2 = np.sum(residual**2, axis=2) * (dt**2)[:, None] / (2.0 * sigma**2)
        plain &= np.all(chi2 <= cfg.outlier_chi2, axis=1)
    twist = -np.concatenate((w, v), axis=1)
    AtA = np.where(plain[:, None, None], np.swapaxes(A, 1, 2) @ A, np.eye(6))  # invertible
    cov_wu = (2.0 * sigma**2 / dt**2)[:, None, None] * np.linalg.inv(AtA)
    j = -np.ones((F, 6))
    j[:, 3:] = -d[:, None]
    covariance = j[:, :, None] * cov_wu * j[:, None, :]
    covariance = 0.5 * (covariance + np.swapaxes(covariance, 1, 2))
    mid = 0.5 * (t0 + t)
    out: list[VelocityMeasurement | None] = []
    limit = cfg.outlier_chi2 if gated else None
    rows = zip(plain.tolist(), twist, covariance, mid.tolist(), dt.tolist(), strict=True)
    for k, (is_plain, twist_k, covariance_k, mid_k, dt_k) in enumerate(rows):
        if is_plain:
            out.append(VelocityMeasurement(twist_k, covariance_k, mid_k, dt_k))
            continue
        motions = [(R0[k], T0[k]), (Rw[k], Tw[k])]
        plane = mid_interval_plane(motions, normal, distance, m_mid[k])
        out.append(
            None
            if plane is None
            else flow_twist(m0[k], m[k], t0[k], t[k], plane, sigma, limit, cfg.min_points)
        )
    return out


def _design_matrices(m: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(F, 2N, 6) :func:`~hvo_graph.geometry.continuous._design_matrix` of each frame's
    (N, 3) points and its unit normal n (F, 3)."""
    F, N = m.shape[:2]
    P = np.zeros((F, N, 2, 3))
    P[..., 0, 0] = P[..., 1, 1] = 1.0
    P[..., 0, 2] = -m[..., 0]
    P[..., 1, 2] = -m[..., 1]
    m_hat = np.zeros((F, N, 3, 3))
    m_hat[..., 0, 1], m_hat[..., 0, 2] = -m[..., 2], m[..., 1]
    m_hat[..., 1, 0], m_hat[..., 1, 2] = m[..., 2], -m[..., 0]
    m_hat[..., 2, 0], m_hat[..., 2, 1] = -m[..., 1], m[..., 0]
    A = np.empty((F, N, 2, 6))
    A[..., :3] = -P @ m_hat
    A[..., 3:] = np.einsum("fni,fi->fn", m, n)[..., None, None] * P
    return A.reshape(F, 2 * N, 6)
