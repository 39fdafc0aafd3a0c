"""Offline runs of the default smoother: frames posed against the world, added in bulk.

In an offline run (``FactorGraphSmoother.run(frames, online=False)``: ISAM2 without its
window, no robust loss, no covariances) every factor goes to the back end's
:class:`~hvo_graph.estimators.factor_store.FactorStore` as numbers, and most frames add
the same things: the H_d pose prior against the world with the frame's own-pixel
covariance, the motion factor from the previous frame, and initial values (the
measured pose, the twist carried over), their H_c twist left out because two H_d poses
against the world already span its interval. :func:`add_world_run` adds a run of such
frames with a few array operations instead of an update per frame: the same store,
initial values and bookkeeping as those updates (tests/test_world_runs.py). Every other
frame (the first, a keyframe pose, a twist factor to add, a tilt, numbers the screening
did not pass, a frame out of order) goes through ``update``, which checks it and raises
exactly as always.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, V, X

from hvo_graph.estimators.measurement_checks import Screened
from hvo_graph.types import FrameMeasurement, VelocityMeasurement

if TYPE_CHECKING:
    from hvo_graph.estimators.smoother import FactorGraphSmoother

_ZERO6 = np.zeros(6)
_ZERO66 = np.zeros((6, 6))  # shared by the frames' reference covariances (never written to)


@dataclass(frozen=True)
class WorldRun:
    """Consecutive frames, each posed against the world, to add at once: indices (n,),
    times (n,) s, measured rotations (n, 3, 3) R_wc and positions (n, 3) p_wc, each pose
    factor's screened covariance (n, 6, 6), and how many of them had an H_c twist that
    their poses span (left out)."""

    indices: np.ndarray
    times: np.ndarray
    rotations: np.ndarray
    positions: np.ndarray
    covariances: np.ndarray
    twists_skipped: int


def _usual_interval(velocity: VelocityMeasurement, previous_time: float, t: float) -> bool:
    """Whether the twist is over [t_previous, t] (to the tolerance of
    :func:`~.measurement_checks.twist_nodes`), with a valid time and interval."""
    if not (math.isfinite(velocity.t) and math.isfinite(velocity.dt) and velocity.dt >= 0):
        return False
    tol = 1e-9 * max(1.0, abs(t))
    start, end = velocity.t - 0.5 * velocity.dt, velocity.t + 0.5 * velocity.dt
    return abs(start - previous_time) <= tol and abs(end - t) <= tol


def world_run(
    frames: Sequence[FrameMeasurement],
    entries: Sequence[Screened | None],
    start: int,
    previous: tuple[int, float, int | None],
    split_reference: bool,
    skip_spanned: bool,
) -> WorldRun | None:
    """The frames from ``start`` on that need no update of their own (None: not one).

    Args:
        frames, entries: a block of frames and their screening entries.
        previous: (index, time, pose reference or None) of the frame before ``start``.
        split_reference: ``shared_reference_noise`` (each pose's reference share apart).
        skip_spanned: the "gaps" twist policy (else every twist is a factor: a frame
            with one needs its update).
    """
    index, time, reference = previous
    stop, skipped = start, 0
    for frame, entry in zip(frames[start:], entries[start:], strict=True):
        pose, velocity, t = frame.pose, frame.velocity, frame.t
        if (
            entry is None
            or pose is None
            or frame.keyframe_tilt is not None
            or type(frame.index) is not int
            or frame.index <= index
            or type(t) is not float
            or not (t > time and math.isfinite(t))
            or type(pose.reference) is not int
            or pose.reference != 0
            or (split_reference and entry[1] is None)
        ):
            break
        if velocity is not None:
            if not (skip_spanned and reference == 0 and _usual_interval(velocity, time, t)):
                break
            skipped += 1
        index, time, reference = frame.index, t, 0
        stop += 1
    if stop == start:
        return None
    run = frames[start:stop]
    return WorldRun(
        indices=np.array([f.index for f in run], dtype=np.int64),
        times=np.array([f.t for f in run]),
        rotations=np.array([f.pose.rotation for f in run]),  # type: ignore[union-attr]
        positions=np.array([f.pose.position for f in run]),  # type: ignore[union-attr]
        covariances=np.array([entry[0] for entry in entries[start:stop]]),  # type: ignore[index]
        twists_skipped=skipped,
    )


def add_world_run(
    smoother: FactorGraphSmoother,
    frames: Sequence[FrameMeasurement],
    entries: Sequence[Screened | None],
    start: int,
) -> int:
    """Add the :func:`world_run` from ``start`` on to ``smoother`` as its updates would;
    its length (0: none, or not yet: before the first frame and the anchor, or while
    streamed refits of the process noise are due)."""
    s = smoother
    split = s.shared_reference_noise
    if not s._indices or s.process_noise.refits or (split and not s._anchored):
        return 0
    previous = (s._indices[-1], s._times[-1], s._last_reference)
    run = world_run(frames, entries, start, previous, split, s.velocity_factors == "gaps")
    if run is None:
        return 0
    n, last = len(run.times), int(run.indices[-1])
    poses = np.hstack((run.rotations.reshape(n, 9), run.positions, run.covariances.reshape(n, 36)))
    dts = np.diff(run.times, prepend=s._times[-1])
    s.backend.store.add_world_frames(run.indices, dts, s.acceleration_sigma, s.motion_model, poses)
    values = gtsam.Values()  # X(k) the measured pose, V(k) the twist carried over
    for k, R, p in zip(run.indices.tolist(), run.rotations, run.positions, strict=True):
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(R), p))
        values.insert(V(k), s._twist)
        if s.motion_model == "wnj":
            values.insert(A(k), _ZERO6)
    s.backend.add(gtsam.NonlinearFactorGraph(), values, last, float(run.times[-1] - s._times[0]))
    s._indices.extend(run.indices.tolist())
    s._times.extend(run.times.tolist())
    s._reference_cov.extend([_ZERO66 if split else s._reference_cov[-1]] * n)
    s._last_reference, s._pose = 0, values.atPose3(X(last))
    s.velocity_factor_counts["skipped"] += run.twists_skipped
    # The updates' log: each pose relative to X(k0)'s value, which is the identity here.
    twists = np.tile(s._twist, (n, 1))
    s._online.extend(run.indices, run.times, run.rotations, run.positions, twists, None)
    return n
