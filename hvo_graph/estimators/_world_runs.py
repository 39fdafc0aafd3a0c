"""Runs of frames posed against the world: added without an update of their own.

Most frames of a sequence add the same things: the H_d pose prior against the world
with the frame's own-pixel covariance, the motion factor from the previous frame, and
initial values (the measured pose, the twist carried over), their H_c twist left out
because two H_d poses against the world already span its interval. Such frames are
found with array tests on a block of frames (:func:`_eligible`: a measurement table's
arrays, or a list's records stacked) and each run of them is added at once:

- offline (``FactorGraphSmoother.run(frames, online=False)``: ISAM2 without its window)
  every factor goes to the back end's
  :class:`~hvo_graph.estimators.factor_store.FactorStore` as numbers, and a run is added
  with a few array operations (:func:`_apply`);
- a back end that updates per frame (fixed-lag, online ISAM2, batch) gets one update
  per frame of the run, with the factors and values the update would make, in its
  order, but without its per-frame checks and records (:func:`_update_each`).

Either way the store, initial values, online log and bookkeeping are those of one
update per frame (tests/test_world_runs.py). Runs need no robust loss (its initial
values are predictions) and no covariances (their record). Every other frame (the
first, a keyframe pose, a twist factor to add, a tilt, numbers the screening does not
pass, a frame out of order or of another type) goes through ``update``, which checks it
and raises exactly as always.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, V, X

from hvo_graph.estimators.measurement_screen import (
    SCREEN_BLOCK,
    Screened,
    plain_frame,
    screen_frames,
    screen_pose_numbers,
    screen_twist_numbers,
    screened,
)
from hvo_graph.measurement_table import MeasurementTable
from hvo_graph.types import FrameMeasurement

if TYPE_CHECKING:
    from hvo_graph.estimators.smoother import FactorGraphSmoother

_ZERO6 = np.zeros(6)
_ZERO66 = np.zeros((6, 6))  # shared by the frames' reference covariances (never written to)


@dataclass(frozen=True)
class WorldRun:
    """Consecutive frames, each posed against the world, to add at once: indices (n,),
    times (n,) s, measured rotations (n, 3, 3) R_wc and positions (n, 3) p_wc, each pose
    factor's screened covariance (n, 6, 6), and which had an H_c twist that their poses
    span (left out) (n,)."""

    indices: np.ndarray
    times: np.ndarray
    rotations: np.ndarray
    positions: np.ndarray
    covariances: np.ndarray
    twists_skipped: np.ndarray


def add_table(smoother: FactorGraphSmoother, table: MeasurementTable) -> None:
    """Every frame of ``table`` into ``smoother``, in order: runs of world-posed frames
    straight from the table's arrays (no records made), every other frame's record
    through ``update``; the open records (not stored as arrays yet) as a list's."""
    sealed = 0
    for first, stop in table.sealed_blocks():
        for a in range(first, stop, SCREEN_BLOCK):
            b = min(stop, a + SCREEN_BLOCK)
            _add_rows(smoother, table.pose_rows(a, b), lambda i, a=a: table[a + i])
        sealed = stop
    add_records(smoother, table[sealed:], bulk=True)


def add_records(
    smoother: FactorGraphSmoother, frames: Sequence[FrameMeasurement], *, bulk: bool
) -> None:
    """Every frame into ``smoother``, in order, a block at a time: with ``bulk``, its runs
    of world-posed frames at once (the other frames screened together), else every frame
    screened and through ``update``."""
    split = smoother.shared_reference_noise
    if bulk:
        for a in range(0, len(frames), SCREEN_BLOCK):
            block = list(frames[a : a + SCREEN_BLOCK])
            _add_rows(smoother, _record_rows(block, split), block.__getitem__)
        return
    for block, entries in screened(frames, split):
        for frame, entry in zip(block, entries, strict=True):
            smoother._screened = frame, entry
            smoother.update(frame)


def _add_rows(
    s: FactorGraphSmoother, rows: dict[str, np.ndarray], record: Callable[[int], FrameMeasurement]
) -> None:
    """The frames of ``rows`` in order: each run of eligible rows at once (once the
    smoother takes runs), every other frame (``record(i)``) through ``update`` with its
    screening entry (the ineligible frames screened together)."""
    eligible, factor = _eligible(s, rows)
    split, n = s.shared_reference_noise, len(eligible)
    made = {i: record(i) for i in np.flatnonzero(~eligible).tolist()}
    screened_made = screen_frames(list(made.values()), split_reference=split)
    screens: dict[int, Screened | None] = dict(zip(made, screened_made, strict=True))
    i = 0
    while i < n:
        if eligible[i] and _applies(s):
            j = i + int(np.argmin(np.append(eligible[i:], False)))  # the first ineligible
            run = WorldRun(
                rows["index"][i:j].astype(np.int64),
                rows["t"][i:j],
                rows["rotation"][i:j],
                rows["position"][i:j],
                factor[i:j],
                rows["moving"][i:j],
            )
            i += _apply(s, run)
            continue
        frame = made[i] if i in made else record(i)
        if i not in screens:  # eligible, but the smoother takes no runs yet
            screens[i] = screen_frames([frame], split_reference=split)[0]
        s._screened = frame, screens[i]
        s.update(frame)
        i += 1


def _record_rows(frames: Sequence[FrameMeasurement], split: bool) -> dict[str, np.ndarray]:
    """A block of records as :meth:`MeasurementTable.pose_rows` gives a table's: "posed"
    only where the frame has the form a table stores as arrays (int index, float time,
    no tilt, a pose with an int reference, float64 arrays; its reference share, split)."""
    n = len(frames)
    posed = np.array(
        [
            type(f.index) is int
            and type(f.t) is float
            and f.keyframe_tilt is None
            and f.pose is not None
            and type(f.pose.reference) is int
            and (not split or f.pose.reference_covariance is not None)
            and plain_frame(f, split)
            for f in frames
        ],
        dtype=bool,
    )
    rows: dict[str, np.ndarray] = {"posed": posed}
    try:  # the numbers of every frame: a later frame is judged against its predecessor
        rows["index"] = np.array([f.index for f in frames], dtype=float)
        rows["t"] = np.array([f.t for f in frames], dtype=float)
    except (TypeError, ValueError):  # not numbers: every frame its own update
        rows["index"], rows["t"] = np.full(n, np.nan), np.full(n, np.nan)
        rows["posed"] = np.zeros(n, dtype=bool)
    poses = [f.pose if p else None for f, p in zip(frames, posed, strict=True)]
    moving = posed & np.array([f.velocity is not None for f in frames], dtype=bool)
    velocities = [f.velocity if m else None for f, m in zip(frames, moving, strict=True)]

    def stack(values: list, shape: tuple[int, ...], fill: float = 0.0) -> np.ndarray:
        return np.array([np.full(shape, fill) if v is None else v for v in values], dtype=float)

    rows["reference"] = np.array([-1 if p is None else p.reference for p in poses])
    rows["rotation"] = stack([p and p.rotation for p in poses], (3, 3))
    rows["position"] = stack([p and p.position for p in poses], (3,))
    rows["covariance"] = stack([p and p.covariance for p in poses], (6, 6))
    rows["reference_covariance"] = stack([p and p.reference_covariance for p in poses], (6, 6))
    rows["moving"] = moving
    rows["velocity_times"] = stack([v and (v.t, v.dt) for v in velocities], (2,))
    rows["twist"] = stack([v and v.twist for v in velocities], (6,))
    rows["twist_covariance"] = stack([v and v.covariance for v in velocities], (6, 6))
    return rows


def _applies(s: FactorGraphSmoother) -> bool:
    """Runs apply from the second frame on, once X(k0) has its anchor (split reference
    noise), and not while streamed refits of the process noise are due."""
    anchored = s._anchored or not s.shared_reference_noise
    return bool(s._indices) and anchored and not s.process_noise.refits


def _apply(s: FactorGraphSmoother, run: WorldRun) -> int:
    if s.backend.windowed:
        return _update_each(s, run)
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
    s.velocity_factor_counts["skipped"] += int(run.twists_skipped.sum())
    # The updates' log: each pose relative to X(k0)'s value, which is the identity here.
    twists = np.tile(s._twist, (n, 1))
    s._online.extend(run.indices, run.times, run.rotations, run.positions, twists, None)
    return n


def _update_each(s: FactorGraphSmoother, run: WorldRun) -> int:
    """A back end that updates per frame (a window: fixed-lag, online ISAM2; batch): each
    frame's motion factor, pose prior and initial values as its update makes them, in the
    same order, without the update's checks (the screening passed) and records. Should a
    GTSAM update raise, the smoother is left as that frame's ``update`` would leave it."""
    n, split, store = len(run.times), s.shared_reference_noise, s.backend.store
    rotations, positions, twists = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 6))
    first, t0, model, sigma = s._indices[0], s._times[0], s.motion_model, s.acceleration_sigma
    frames = zip(
        run.indices.tolist(), run.times.tolist(), run.rotations, run.positions, strict=True
    )
    started = done = 0  # frames in the bookkeeping; frames whose update returned
    try:
        for i, (k, t, R, p) in enumerate(frames):
            dt = t - s._times[-1]
            graph = gtsam.NonlinearFactorGraph()
            store.add_frame(k)
            for factor in s._motion(model, s._indices[-1], k, dt, sigma):
                graph.add(factor)
            store.add_motion(dt, sigma, model)
            s._indices.append(k)
            s._times.append(t)
            started = i + 1
            measured = gtsam.Pose3(gtsam.Rot3(R), p)
            graph.add(gtsam.PriorFactorPose3(X(k), measured, s._pose_noise(run.covariances[i])))
            store.add_pose_prior(measured, run.covariances[i])
            values = gtsam.Values()
            values.insert(X(k), measured)
            values.insert(V(k), s._twist)
            if model == "wnj":
                values.insert(A(k), _ZERO6)
            s._pose, twist, _ = s.backend.add(graph, values, k, t - t0)
            s._twist = twists[i] = twist
            relative = s._relative(s._pose, s.backend.current_pose(first))
            rotations[i] = relative.rotation().matrix()
            positions[i] = relative.translation()
            done = i + 1
    finally:  # what each update sets before its GTSAM update, then its log entry
        s._reference_cov.extend([_ZERO66 if split else s._reference_cov[-1]] * started)
        if started:
            s._last_reference, s._world_posed = 0, True
        s.velocity_factor_counts["skipped"] += int(run.twists_skipped[:started].sum())
        rows = slice(0, done)
        s._online.extend(
            run.indices[rows], run.times[rows], rotations[rows], positions[rows], twists[rows], None
        )
    return n


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
