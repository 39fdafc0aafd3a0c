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

from hvo_graph.estimators.measurement_screen import (
    SCREEN_BLOCK,
    Screened,
    screen_frames,
    screen_pose_numbers,
    screen_twist_numbers,
    screened,
)
from hvo_graph.measurement_table import MeasurementTable
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
    its length (0: none, or not yet: see :func:`_applies`)."""
    s = smoother
    if not _applies(s):
        return 0
    previous = (s._indices[-1], s._times[-1], s._last_reference)
    gaps = s.velocity_factors == "gaps"
    run = world_run(frames, entries, start, previous, s.shared_reference_noise, gaps)
    return 0 if run is None else _apply(s, run)


def _applies(s: FactorGraphSmoother) -> bool:
    """Runs apply from the second frame on, once X(k0) has its anchor (split reference
    noise), and not while streamed refits of the process noise are due."""
    anchored = s._anchored or not s.shared_reference_noise
    return bool(s._indices) and anchored and not s.process_noise.refits


def _apply(s: FactorGraphSmoother, run: WorldRun) -> int:
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
    s._reference_cov.extend([_ZERO66 if s.shared_reference_noise else s._reference_cov[-1]] * n)
    s._last_reference, s._pose = 0, values.atPose3(X(last))
    s.velocity_factor_counts["skipped"] += run.twists_skipped
    # The updates' log: each pose relative to X(k0)'s value, which is the identity here.
    twists = np.tile(s._twist, (n, 1))
    s._online.extend(run.indices, run.times, run.rotations, run.positions, twists, None)
    return n


def add_table(smoother: FactorGraphSmoother, table: MeasurementTable) -> None:
    """Every frame of ``table`` into ``smoother``: its runs of world-posed frames from the
    table's arrays (no records made), every other frame through ``update`` (screened a
    block at a time), in order."""
    sealed = 0
    for first, stop in table.sealed_blocks():
        for start in range(first, stop, SCREEN_BLOCK):
            _add_rows(smoother, table, start, min(stop, start + SCREEN_BLOCK))
        sealed = stop
    add_records(smoother, table[sealed:], bulk=True)


def add_records(
    smoother: FactorGraphSmoother, frames: Sequence[FrameMeasurement], *, bulk: bool
) -> None:
    """Every frame into ``smoother``, screened a block at a time: with ``bulk``, its runs
    of world-posed frames at once (:func:`add_world_run`), every other frame through
    ``update``."""
    for block, entries in screened(frames, smoother.shared_reference_noise):
        i = 0
        while i < len(block):
            added = add_world_run(smoother, block, entries, i) if bulk else 0
            if not added:
                smoother._screened = block[i], entries[i]
                smoother.update(block[i])
            i += added or 1


def _add_rows(s: FactorGraphSmoother, table: MeasurementTable, first: int, stop: int) -> None:
    """Frames [first, stop) of one stored block of ``table``, in order: runs of eligible
    rows at once, every other frame's record through ``update``."""
    rows = table.pose_rows(first, stop)
    eligible, factor = _eligible(s, rows)
    split = s.shared_reference_noise
    records = {i: table[first + i] for i in np.flatnonzero(~eligible).tolist()}
    screens = screen_frames(list(records.values()), split_reference=split)
    entries = dict(zip(records, screens, strict=True))
    i, n = 0, stop - first
    while i < n:
        if eligible[i] and _applies(s):
            j = i + int(np.argmin(np.append(eligible[i:], False)))
            run = WorldRun(
                rows["index"][i:j],
                rows["t"][i:j],
                rows["rotation"][i:j],
                rows["position"][i:j],
                factor[i:j],
                int(rows["moving"][i:j].sum()),
            )
            i += _apply(s, run)
            continue
        if i not in records:  # eligible, but the smoother is not ready for runs yet
            records[i] = table[first + i]
            entries[i] = screen_frames([records[i]], split_reference=split)[0]
        frame = records[i]
        s._screened = frame, entries[i]
        s.update(frame)
        i += 1


def _eligible(s: FactorGraphSmoother, rows: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """((n,) whether each row may be added in a run, (n, 6, 6) its pose factor covariance):
    :func:`world_run`'s tests on arrays; the previous frame of each row is the row before
    (it is added before it, either way), of the first the smoother's latest."""
    split, posed, moving = s.shared_reference_noise, rows["posed"], rows["moving"]
    with np.errstate(all="ignore"):  # NaN or inf: the frame is not eligible
        ok, factor, _, _ = screen_pose_numbers(
            rows["rotation"],
            rows["position"],
            rows["covariance"],
            posed & split,
            lambda r: rows["reference_covariance"][r],
            split,
        )
        twist_ok, _ = screen_twist_numbers(rows["twist"], rows["twist_covariance"])
        index, t = rows["index"], rows["t"]
        last = (
            (s._indices[-1], s._times[-1], s._last_reference) if s._indices else (-1, np.inf, None)
        )
        prev_index = np.append(last[0], index[:-1])
        prev_t = np.append(last[1], t[:-1])
        prev_ref = np.append(-1 if last[2] is None else last[2], rows["reference"][:-1])
        vt, vdt = rows["velocity_times"].T
        start, end = vt - 0.5 * vdt, vt + 0.5 * vdt
        tol = 1e-9 * np.maximum(1.0, np.abs(t))
        usual = (
            np.isfinite(vt)
            & np.isfinite(vdt)
            & (vdt >= 0)
            & (np.abs(start - prev_t) <= tol)
            & (np.abs(end - t) <= tol)
        )
        spanned = (s.velocity_factors == "gaps") & (prev_ref == 0) & usual & twist_ok
        eligible = (
            posed
            & ok
            & (rows["reference"] == 0)
            & (index > prev_index)
            & (t > prev_t)
            & np.isfinite(t)
            & (~moving | spanned)
        )
    return eligible, factor
