"""Feature tracks, the contract's CSV: header ``frame,t,id,u,v``, one row per observation.

- ``frame``: integer >= 0, non-decreasing down the file (rows of a frame are contiguous);
- ``t``: seconds, equal on all rows of a frame, strictly increasing from frame to frame;
- ``id``: integer id of a physical plane point; unique within a frame;
- ``u``, ``v``: pixel coordinates (OpenCV: the centre of the top-left pixel is (0, 0)).

Frames are the distinct ``frame`` values present in the file. A frame number
that does not occur (a gap, e.g. 0, 1, 3) has no row, hence no time, and so no
:class:`~hvo_graph.types.FrameObservations`: the frames read back are those
with at least one row, in file order, keeping their numbers as ``index``.

Reading is vectorised (numpy parses the body, checks run on whole columns), so
a file of 30,000 frames x 100 points reads in a few seconds; errors name the
first offending line (1-based).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import overload

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.io._common import (
    PathLike,
    atomic_write_text,
    check_finite,
    csv_body,
    first_line,
    parse_table,
    plain_csv_table,
    read_text,
)
from hvo_graph.types import FrameObservations

HEADER = "frame,t,id,u,v"
_COLUMNS = tuple(HEADER.split(","))
#: Integers above this are not exact in a float64 column.
_MAX_INT = 2.0**53


def read_tracks(path: PathLike) -> list[FrameObservations]:
    """Read a tracks CSV.

    Args:
        path: the CSV file.
    Returns:
        One :class:`FrameObservations` per distinct frame number, in file order;
        ``ids`` (N,) int64, ``uv`` (N, 2) float64 in file row order.
    Raises:
        InputError, OSError: as :func:`read_track_table`.
    """
    return list(read_track_table(path))


class TrackTable(Sequence[FrameObservations]):
    """The frames of a tracks CSV as a read-only sequence of :class:`FrameObservations`,
    kept as the file's columns (ids, uv) and made one frame at a time on access (a
    fraction of the memory of the list :func:`read_tracks` returns); ``table[k]`` is
    equal to ``read_tracks(path)[k]``.

    Args:
        index: (F,) frame numbers; t: (F,) times; starts: (F + 1,) first row of each
            frame (and the row count); ids: (R,) int64; uv: (R, 2) float64.
    """

    def __init__(
        self, index: np.ndarray, t: np.ndarray, starts: np.ndarray, ids: np.ndarray, uv: np.ndarray
    ) -> None:
        self._index, self._t, self._starts = index, t, starts  # arrays: 8 bytes a number
        self._ids, self._uv = ids, uv

    def __len__(self) -> int:
        return len(self._index)

    def rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every observation as columns: (R,) frame number, (R,) time, (R,) id, (R, 2) uv."""
        counts = np.diff(self._starts)
        return np.repeat(self._index, counts), np.repeat(self._t, counts), self._ids, self._uv

    @overload
    def __getitem__(self, k: int) -> FrameObservations: ...

    @overload
    def __getitem__(self, k: slice) -> list[FrameObservations]: ...

    def __getitem__(self, k: int | slice) -> FrameObservations | list[FrameObservations]:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        i = k + len(self) if k < 0 else k
        if not 0 <= i < len(self):
            raise IndexError(f"frame {k} out of range ({len(self)} frames)")
        s, e = int(self._starts[i]), int(self._starts[i + 1])
        return FrameObservations(
            index=int(self._index[i]),
            t=float(self._t[i]),
            ids=self._ids[s:e].copy(),
            uv=self._uv[s:e].copy(),
        )


def read_track_table(path: PathLike) -> TrackTable:
    """Read a tracks CSV as a :class:`TrackTable` (what :func:`read_tracks` lists).

    Raises:
        InputError: "<file>:<line>: ..." for a bad header, a row that is not 5
            numbers, NaN/inf, a non-integer or negative frame, a non-integer id,
            a decreasing frame number, a time that differs within a frame or
            does not increase between frames, a duplicate id within a frame, or
            a file with no rows.
        OSError: when the file cannot be read.
    """
    text = read_text(path)
    table = plain_csv_table(path, text, HEADER, len(_COLUMNS))  # the usual file, fast
    if table is None:
        body, linenos = csv_body(path, text, HEADER)
        if not body:
            raise InputError(f"{path}:2: expected at least one observation row after the header")
        table = parse_table(path, body, linenos, _COLUMNS, ",")
    else:
        linenos = np.arange(2, len(table) + 2)
    del text
    check_finite(path, table, linenos, _COLUMNS)
    frame, t, ids, uv = table[:, 0], table[:, 1], table[:, 2], table[:, 3:5]

    for col, values in (("frame", frame), ("id", ids)):
        row = first_line((values != np.floor(values)) | (np.abs(values) >= _MAX_INT), linenos)
        if row is not None:
            raise InputError(f"{path}:{row}: column '{col}': expected an integer below 2^53")
    row = first_line(frame < 0, linenos)
    if row is not None:
        raise InputError(f"{path}:{row}: column 'frame': expected an integer >= 0")

    step = np.diff(frame)
    row = first_line(np.concatenate(([False], step < 0)), linenos)
    if row is not None:
        raise InputError(f"{path}:{row}: column 'frame': frame numbers must not decrease")
    same = np.concatenate(([False], step == 0))
    new = np.concatenate(([False], step > 0))
    dt = np.concatenate(([0.0], np.diff(t)))
    row = first_line(same & (dt != 0), linenos)
    if row is not None:
        raise InputError(f"{path}:{row}: column 't': expected the same time on all rows of a frame")
    row = first_line(new & (dt <= 0), linenos)
    if row is not None:
        raise InputError(
            f"{path}:{row}: column 't': time must increase strictly from one frame to the next"
        )

    # Duplicate ids within a frame: sort by (frame, id), compare neighbours, and
    # report the later of the two rows.
    order = np.lexsort((ids, frame))
    dup = (frame[order][1:] == frame[order][:-1]) & (ids[order][1:] == ids[order][:-1])
    if dup.any():
        later = np.maximum(order[1:][dup], order[:-1][dup])
        i = int(later.min())
        raise InputError(
            f"{path}:{linenos[i]}: column 'id': id {int(ids[i])} appears twice in frame "
            f"{int(frame[i])}"
        )

    starts = np.flatnonzero(np.concatenate(([True], step > 0)))
    return TrackTable(
        frame[starts].astype(np.int64),
        t[starts],
        np.append(starts, len(frame)),
        ids.astype(np.int64),
        np.ascontiguousarray(uv),
    )


def write_tracks(path: PathLike, observations: Sequence[FrameObservations]) -> None:
    """Write observations as a tracks CSV (atomically; times and pixels at full precision).

    Args:
        path: destination file.
        observations: frames with strictly increasing ``index`` and ``t``,
            unique integer ids within a frame, finite ``uv`` of shape (N, 2).
            A frame with no points writes no row (the format cannot hold it),
            so it is absent when the file is read back.
    Raises:
        InputError: naming the frame that breaks one of these rules.
    """
    out = [HEADER]
    prev: FrameObservations | None = None
    for k, obs in enumerate(observations):
        name = f"observations[{k}] (frame {obs.index})"
        uv = np.asarray(obs.uv, dtype=float)
        ids = np.asarray(obs.ids)
        if uv.ndim != 2 or uv.shape[1] != 2 or ids.shape != (uv.shape[0],):
            raise InputError(f"{name}: expected ids (N,) and uv (N, 2), got {ids.shape} {uv.shape}")
        if not np.all(np.isfinite(uv)) or not np.isfinite(obs.t):
            raise InputError(f"{name}: contains NaN or inf")
        if ids.size and (not np.all(ids == np.round(ids)) or len(np.unique(ids)) != ids.size):
            raise InputError(f"{name}: ids must be unique integers")
        if obs.index < 0 or int(obs.index) != obs.index:
            raise InputError(f"{name}: frame index must be an integer >= 0")
        if prev is not None and (obs.index <= prev.index or obs.t <= prev.t):
            raise InputError(f"{name}: frame index and time must increase strictly")
        prev = obs
        head = f"{int(obs.index)},{float(obs.t)!r},"
        out.extend(
            f"{head}{i},{u!r},{v!r}"
            for i, u, v in zip(ids.astype(np.int64).tolist(), *(uv.T + 0.0).tolist(), strict=True)
        )
    atomic_write_text(path, "\n".join(out) + "\n")
