"""The front end's measurements of a whole sequence, stored column by column.

A :class:`~hvo_graph.types.FrameMeasurement` of a 4-point frame holds some 1.5 kB
of numbers (rotation, position, the 6 x 6 covariances, the (6, 2N) reference
Jacobian, the kept points) in a dozen small numpy arrays and four record objects:
about 3.5 kB of process memory per frame, 350 MB for 100,000 frames.
:class:`MeasurementTable` keeps the numbers of each block of frames in a few
stacked arrays instead and makes the records on demand, one frame at a time, as a
read-only sequence: ``table[k]`` and ``for frame in table`` give records equal,
number for number and type for type, to those appended. The columns every report
reads (which frames have a pose, their references, the point counts) are arrays.

Records that do not have the usual form (keyframe-relative poses with their plane
fields, a keyframe tilt, missing parts of the pose's noise split, other shapes or types) are kept
as given.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np

from hvo_graph.types import (
    FrameMeasurement,
    PointObservations,
    PoseMeasurement,
    VelocityMeasurement,
)

#: Frames per sealed block (the records of one block are held as objects until sealed).
BLOCK_FRAMES = 2048

# Fixed-size fields: name -> (shape, source); ragged fields are stored flat.
_POSE_FIELDS = {"rotation": (3, 3), "position": (3,), "covariance": (6, 6)}
_SHARED = {"reference_covariance": (6, 6)}
_VELOCITY_FIELDS = {"twist": (6,), "covariance": (6, 6)}


def _plain(array: object, shape: tuple[int, ...]) -> bool:
    return type(array) is np.ndarray and array.dtype == np.float64 and array.shape == shape  # type: ignore[union-attr]


def _compact_pose(pose: PoseMeasurement | None) -> bool:
    if pose is None:
        return True
    if type(pose) is not PoseMeasurement or type(pose.reference) is not int:
        return False
    if any(
        x is not None
        for x in (pose.reference_rotation, pose.reference_position, pose.plane_jacobian)
    ):
        return False
    if not all(_plain(getattr(pose, k), s) for k, s in _POSE_FIELDS.items()):
        return False
    ids, jac = pose.reference_ids, pose.reference_jacobian
    return (
        _plain(pose.reference_covariance, (6, 6))
        and type(ids) is np.ndarray
        and ids.dtype == np.int64
        and ids.ndim == 1
        and _plain(jac, (6, 2 * len(ids)))
    )


def _compact_velocity(velocity: VelocityMeasurement | None) -> bool:
    if velocity is None:
        return True
    return (
        type(velocity) is VelocityMeasurement
        and all(_plain(getattr(velocity, k), s) for k, s in _VELOCITY_FIELDS.items())
        and type(velocity.t) is type(velocity.dt)
        and type(velocity.t) in (float, np.float64)
    )


def _compact_points(points: PointObservations | None) -> bool:
    if points is None:
        return True
    ids, m = points.ids, points.m
    return (
        type(points) is PointObservations
        and type(ids) is np.ndarray
        and ids.dtype == np.int64
        and ids.ndim == 1
        and _plain(m, (len(ids), 2))
        and type(points.sigma) is float
        and type(points.distance) is float
    )


def _compact(frame: FrameMeasurement) -> bool:
    return (
        type(frame) is FrameMeasurement
        and type(frame.index) is int
        and type(frame.t) is float
        and type(frame.num_points) is int
        and type(frame.num_rejected) is int
        and _compact_pose(frame.pose)
        and _compact_velocity(frame.velocity)
        and _compact_points(frame.points)
        and frame.keyframe_tilt is None
    )


_UPPER = np.triu_indices(6)
_LOWER = (_UPPER[1], _UPPER[0])


class _Covariances:
    """(n, 6, 6) covariances: their 21 upper-triangular entries when every one is exactly
    symmetric (as the front end makes them), else as given."""

    def __init__(self, stack: np.ndarray) -> None:
        self.symmetric = bool(np.array_equal(stack, np.swapaxes(stack, 1, 2)))
        self.values = stack[:, _UPPER[0], _UPPER[1]].copy() if self.symmetric else stack

    def __getitem__(self, k: int) -> np.ndarray:
        if not self.symmetric:
            return self.values[k]
        out = np.empty((6, 6))
        out[_UPPER] = out[_LOWER] = self.values[k]
        return out

    def unpacked(self, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """(n, 6, 6) the matrices ``rows`` (default all: one call, not one per record)."""
        if not self.symmetric:
            return self.values[rows]
        values = self.values[rows]
        out = np.empty((len(values), 6, 6))
        out[:, _UPPER[0], _UPPER[1]] = out[:, _LOWER[0], _LOWER[1]] = values
        return out


def _offsets(lengths: list[int]) -> np.ndarray:
    return np.concatenate(([0], np.cumsum(lengths, dtype=np.int64)))


class _Block:
    """The numbers of up to :data:`BLOCK_FRAMES` consecutive frames, stacked."""

    def __init__(self, frames: list[FrameMeasurement]) -> None:
        n = len(frames)
        self.kept: dict[int, FrameMeasurement] = {}  # rows kept as given
        compact = [_compact(f) for f in frames]
        for row, (ok, f) in enumerate(zip(compact, frames, strict=True)):
            if not ok:
                self.kept[row] = f
        plain = [f for ok, f in zip(compact, frames, strict=True) if ok]
        # Row -> position among the plain rows (-1: kept as given).
        self.slot = np.cumsum(compact, dtype=np.int64) - 1
        self.slot[~np.asarray(compact, dtype=bool)] = -1
        poses = [f.pose for f in plain if f.pose is not None]
        velocities = [f.velocity for f in plain if f.velocity is not None]
        points = [f.points for f in plain if f.points is not None]
        self.pose_row = np.cumsum([f.pose is not None for f in plain], dtype=np.int64) - 1
        self.velocity_row = np.cumsum([f.velocity is not None for f in plain], dtype=np.int64) - 1
        self.points_row = np.cumsum([f.points is not None for f in plain], dtype=np.int64) - 1
        self.has = np.array(
            [(f.pose is not None, f.velocity is not None, f.points is not None) for f in plain],
            dtype=bool,
        ).reshape(-1, 3)
        self.pose = {
            k: np.array([getattr(p, k) for p in poses]).reshape(-1, *s)
            for k, s in {**_POSE_FIELDS, **_SHARED}.items()
        }
        for k in ("covariance", "reference_covariance"):
            self.pose[k] = _Covariances(self.pose[k])  # type: ignore[assignment]
        self.reference = np.array([p.reference for p in poses], dtype=np.int64)
        self.reference_ids = np.concatenate(
            [p.reference_ids for p in poses] or [np.empty(0, np.int64)]
        )
        self.ref_offsets = _offsets([len(p.reference_ids) for p in poses])  # type: ignore[arg-type]
        # Each (6, 2N) Jacobian flat, row-major: record k's is a C-ordered view again.
        self.jacobian = np.concatenate(
            [p.reference_jacobian.ravel() for p in poses] or [np.empty(0)]  # type: ignore[union-attr]
        )
        self.velocity = {
            k: np.array([getattr(v, k) for v in velocities]).reshape(-1, *s)
            for k, s in _VELOCITY_FIELDS.items()
        }
        self.velocity["covariance"] = _Covariances(self.velocity["covariance"])  # type: ignore[assignment]
        times = [(v.t, v.dt) for v in velocities]
        self.velocity_times = np.array(times, dtype=float).reshape(-1, 2)
        self.velocity_float = [type(v.t) is float for v in velocities]
        self.point_ids = np.concatenate([p.ids for p in points] or [np.empty(0, np.int64)])
        self.point_m = np.concatenate([p.m for p in points] or [np.empty((0, 2))])
        self.point_offsets = _offsets([len(p.ids) for p in points])
        self.point_scalars = np.array([(p.sigma, p.distance) for p in points]).reshape(-1, 2)
        # The normal arrays themselves (a front end shares one object): identity kept.
        self.normals: list[np.ndarray] = []
        ids_of: dict[int, int] = {}
        self.normal_of = np.array(
            [ids_of.setdefault(id(p.normal), len(ids_of)) for p in points],
            dtype=np.int64,
        )
        seen: set[int] = set()
        for p in points:
            if id(p.normal) not in seen:
                seen.add(id(p.normal))
                self.normals.append(p.normal)
        self.size = n

    def pose_rows(self, a: int, b: int) -> dict[str, np.ndarray]:
        """Rows [a, b)'s poses and twists as arrays (:meth:`MeasurementTable.pose_rows`)."""
        slot = self.slot[a:b]
        n, plain = len(slot), np.flatnonzero(slot >= 0)
        posed, moving = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        posed[plain], moving[plain] = self.has[slot[plain], 0], self.has[slot[plain], 1]
        k, v = self.pose_row[slot[posed]], self.velocity_row[slot[moving]]

        def spread(values: np.ndarray, mask: np.ndarray, fill: float = 0.0) -> np.ndarray:
            out = np.full((n, *values.shape[1:]), fill, dtype=values.dtype)
            out[mask] = values
            return out

        covariances = (self.pose["covariance"], self.pose["reference_covariance"])
        return {
            "posed": posed,
            "reference": spread(self.reference[k], posed, -1),
            "rotation": spread(self.pose["rotation"][k], posed),
            "position": spread(self.pose["position"][k], posed),
            "covariance": spread(covariances[0].unpacked(k), posed),  # type: ignore[attr-defined]
            "reference_covariance": spread(covariances[1].unpacked(k), posed),  # type: ignore[attr-defined]
            "moving": moving,
            "velocity_times": spread(self.velocity_times[v], moving),
            "twist": spread(self.velocity["twist"][v], moving),
            "twist_covariance": spread(self.velocity["covariance"].unpacked(v), moving),  # type: ignore[attr-defined]
        }

    def records(
        self, index: list[int], t: list[float], counts: list[list[int]]
    ) -> Iterator[FrameMeasurement]:
        """Every record of the block in order (index, t, counts: the block's rows), the
        covariances unpacked all at once (each record's a view into one array)."""
        covariances = (self.pose["covariance"], self.pose["reference_covariance"])
        unpacked = {"velocity": self.velocity["covariance"].unpacked()}  # type: ignore[attr-defined]
        unpacked["pose"], unpacked["reference"] = (c.unpacked() for c in covariances)  # type: ignore[attr-defined]
        for row in range(self.size):
            yield self.record(row, index[row], t[row], counts[row], unpacked)

    def record(
        self,
        row: int,
        index: int,
        t: float,
        counts: tuple[int, int] | list[int],
        unpacked: dict[str, np.ndarray] | None = None,
    ) -> FrameMeasurement:
        slot = int(self.slot[row])
        if slot < 0:
            return self.kept[row]
        if unpacked is None:
            pose_cov, reference_cov = self.pose["covariance"], self.pose["reference_covariance"]
            velocity_cov = self.velocity["covariance"]
        else:
            pose_cov, reference_cov = unpacked["pose"], unpacked["reference"]
            velocity_cov = unpacked["velocity"]
        has_pose, has_velocity, has_points = self.has[slot]
        pose = velocity = points = None
        if has_pose:
            k = int(self.pose_row[slot])
            a, b = self.ref_offsets[k], self.ref_offsets[k + 1]
            pose = PoseMeasurement(
                self.pose["rotation"][k],
                self.pose["position"][k],
                pose_cov[k],
                reference=int(self.reference[k]),
                reference_covariance=reference_cov[k],
                reference_jacobian=self.jacobian[12 * a : 12 * b].reshape(6, 2 * (b - a)),
                reference_ids=self.reference_ids[a:b],
            )
        if has_velocity:
            k = int(self.velocity_row[slot])
            t_mid, dt = self.velocity_times[k]
            if self.velocity_float[k]:
                t_mid, dt = float(t_mid), float(dt)
            velocity = VelocityMeasurement(self.velocity["twist"][k], velocity_cov[k], t_mid, dt)
        if has_points:
            k = int(self.points_row[slot])
            a, b = self.point_offsets[k], self.point_offsets[k + 1]
            sigma, distance = self.point_scalars[k]
            points = PointObservations(
                ids=self.point_ids[a:b],
                m=self.point_m[a:b],
                sigma=float(sigma),
                normal=self.normals[int(self.normal_of[k])],
                distance=float(distance),
            )
        return FrameMeasurement(index, t, pose, velocity, counts[0], counts[1], points)


class MeasurementTable(Sequence[FrameMeasurement]):
    """A read-only sequence of :class:`~hvo_graph.types.FrameMeasurement`, stored as
    stacked arrays per block of frames (see the module docstring).

    Records are added with :meth:`append` / :meth:`extend` in frame order; ``table[k]``
    builds record k anew on every access (equal, not identical, to the one appended).

    Args:
        frames: records to start with.
    """

    def __init__(self, frames: Iterable[FrameMeasurement] = ()) -> None:
        self._blocks: list[_Block] = []
        self._first: list[int] = []  # position of each block's first frame
        self._open: list[FrameMeasurement] = []
        # Frame numbers and times of the stored blocks (arrays), then of the open records.
        self._sealed_index, self._sealed_t = np.zeros(0, np.int64), np.zeros(0)
        self._index: list[int] = []
        self._t: list[float] = []
        self._columns = np.zeros((0, 5), dtype=np.int64)  # sealed rows' integer columns
        self._pending: list[tuple[int, ...]] = []
        self.extend(frames)
        self.compact()

    def append(self, frame: FrameMeasurement) -> None:
        """Add the next frame's record."""
        if not isinstance(frame, FrameMeasurement):
            raise TypeError(f"expected a FrameMeasurement, got {type(frame).__name__}")
        self._open.append(frame)
        self._index.append(frame.index)
        self._t.append(frame.t)
        pose = frame.pose
        self._pending.append(
            (
                pose is not None,
                frame.velocity is not None,
                int(frame.num_points),
                int(frame.num_rejected),
                -1 if pose is None else int(pose.reference),
            )
        )
        if len(self._open) >= BLOCK_FRAMES:
            self.compact()

    def extend(self, frames: Iterable[FrameMeasurement]) -> None:
        """:meth:`append` each record in turn."""
        for frame in frames:
            self.append(frame)

    def compact(self) -> MeasurementTable:
        """Store the records appended since the last block as arrays (done by itself
        every :data:`BLOCK_FRAMES` frames; call it after the last); returns the table."""
        if self._open:
            self._first.append(len(self) - len(self._open))
            self._blocks.append(_Block(self._open))
            self._sealed_index = np.append(self._sealed_index, np.array(self._index, np.int64))
            self._sealed_t = np.append(self._sealed_t, np.array(self._t, dtype=float))
            self._open, self._index, self._t = [], [], []
            self._all_columns()
        return self

    def _all_columns(self) -> np.ndarray:
        if self._pending:
            more = np.array(self._pending, dtype=np.int64).reshape(-1, 5)
            self._columns = np.concatenate((self._columns, more))
            self._pending = []
        return self._columns

    def __len__(self) -> int:
        return len(self._sealed_index) + len(self._open)

    @overload
    def __getitem__(self, k: int) -> FrameMeasurement: ...

    @overload
    def __getitem__(self, k: slice) -> list[FrameMeasurement]: ...

    def __getitem__(self, k: int | slice) -> FrameMeasurement | list[FrameMeasurement]:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        n = len(self)
        i = int(k) + n if int(k) < 0 else int(k)
        if not 0 <= i < n:
            raise IndexError(f"frame {k} out of range ({n} frames)")
        opened = len(self) - len(self._open)
        if i >= opened:
            return self._open[i - opened]
        block = bisect.bisect_right(self._first, i) - 1
        row = i - self._first[block]
        counts = self._all_columns()[i, 2:4]
        index, t = int(self._sealed_index[i]), float(self._sealed_t[i])
        return self._blocks[block].record(row, index, t, (int(counts[0]), int(counts[1])))

    def __iter__(self) -> Iterator[FrameMeasurement]:
        columns, sealed = self._all_columns(), len(self._sealed_index)
        for first, block in zip(self._first, self._blocks, strict=True):
            rows = slice(first, first + block.size)
            index, t = self._sealed_index[rows].tolist(), self._sealed_t[rows].tolist()
            yield from block.records(index, t, columns[rows, 2:4].tolist())
        for i in range(sealed, len(self)):  # the open records, as appended
            yield self[i]

    def sealed_blocks(self) -> list[tuple[int, int]]:
        """(first, stop) positions of each block stored as arrays (the open records follow)."""
        return [(f, f + block.size) for f, block in zip(self._first, self._blocks, strict=True)]

    def pose_rows(self, first: int, stop: int) -> dict[str, np.ndarray]:
        """Frames [first, stop) of one sealed block as arrays, no records made: "index",
        "t" (n,); "posed" (n,) a pose in the usual form (False also where the record is
        kept as given: keyframe fields, a tilt); "reference" (n,) (-1: none);
        "rotation" (n, 3, 3), "position" (n, 3), "covariance" and
        "reference_covariance" (n, 6, 6); "moving" (n,) a twist in the usual form;
        "velocity_times" (n, 2) its (t, dt); "twist" (n, 6), "twist_covariance" (n, 6, 6)
        (zeros where absent)."""
        block = bisect.bisect_right(self._first, first) - 1
        start = self._first[block]
        rows = self._blocks[block].pose_rows(first - start, stop - start)
        rows["index"], rows["t"] = self._sealed_index[first:stop], self._sealed_t[first:stop]
        return rows

    @property
    def has_pose(self) -> np.ndarray:
        """(K,) bool: the frame has a pose measurement."""
        return self._all_columns()[:, 0].astype(bool)

    @property
    def has_velocity(self) -> np.ndarray:
        """(K,) bool: the frame has a twist measurement."""
        return self._all_columns()[:, 1].astype(bool)

    @property
    def num_points(self) -> np.ndarray:
        """(K,) int: points observed per frame."""
        return self._all_columns()[:, 2].copy()

    @property
    def num_rejected(self) -> np.ndarray:
        """(K,) int: of those, points rejected as outliers."""
        return self._all_columns()[:, 3].copy()

    @property
    def references(self) -> np.ndarray:
        """(K,) int: each pose's reference frame (-1 where the frame has no pose)."""
        return self._all_columns()[:, 4].copy()

    @property
    def indices(self) -> list[int]:
        """The frame indices, in order."""
        return [*self._sealed_index.tolist(), *self._index]


@dataclass(frozen=True)
class FrameColumns:
    """The per-frame counts reports read, as arrays over K frames.

    Attributes:
        index: (K,) int frame numbers.
        has_pose, has_velocity: (K,) bool.
        num_points, num_rejected: (K,) int.
        references: (K,) int reference frame of each pose (-1 where none).
    """

    index: np.ndarray
    has_pose: np.ndarray
    has_velocity: np.ndarray
    num_points: np.ndarray
    num_rejected: np.ndarray
    references: np.ndarray


def frame_columns(frames: Sequence[FrameMeasurement]) -> FrameColumns:
    """:class:`FrameColumns` of any sequence of records (a :class:`MeasurementTable`'s
    without making its records)."""
    if isinstance(frames, MeasurementTable):
        return FrameColumns(
            np.array(frames.indices, dtype=np.int64),
            frames.has_pose,
            frames.has_velocity,
            frames.num_points,
            frames.num_rejected,
            frames.references,
        )
    rows = [
        (
            f.index,
            f.pose is not None,
            f.velocity is not None,
            f.num_points,
            f.num_rejected,
            -1 if f.pose is None else f.pose.reference,
        )
        for f in frames
    ]
    table = np.array(rows, dtype=np.int64).reshape(-1, 6)
    return FrameColumns(
        table[:, 0],
        table[:, 1] > 0,
        table[:, 2] > 0,
        table[:, 3],
        table[:, 4],
        table[:, 5],
    )
