"""Compact per-frame bookkeeping of the estimators (long runs: 100,000 frames and more).

Per-frame Python objects cost far more than their numbers: a
:class:`~hvo_graph.types.StateEstimate` with its three arrays ~0.7 kB, a dict
entry ~0.1 kB. These keep the numbers in arrays, or read an existing list.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator, Sequence

import numpy as np

from hvo_graph.types import StateEstimate, Trajectory

__all__ = ["GrowingRows", "SortedIndices", "StateLog"]


class StateLog:
    """Per-frame estimates in growing arrays (a list of :class:`StateEstimate` objects
    cost ~0.7 kB per frame: 70 MB over 100,000 frames; here 152 bytes, or 1.3 kB with
    a 12 x 12 covariance). Reads like a list: ``len``, truth, ``log[i]``, iteration.
    """

    def __init__(self) -> None:
        self._n = 0
        self._index = np.empty(16, dtype=np.int64)
        self._values = np.empty((16, 19))  # t, rotation (9), position (3), twist (6)
        self._covariance: np.ndarray | None = None  # (capacity, 12, 12) once one has one
        self._with_covariance = 0

    def __len__(self) -> int:
        return self._n

    def append(self, state: StateEstimate) -> None:
        """Keep a copy of ``state``."""
        if self._n == len(self._index):
            # Grown in place (realloc: the kept pages are remapped, not copied and faulted
            # in again as a concatenation would; a third of the cost on 30,000 frames). The
            # arrays own their data and no view of them outlives a call.
            capacity = 2 * len(self._index)
            self._index.resize(capacity, refcheck=False)
            self._values.resize((capacity, 19), refcheck=False)
            if self._covariance is not None:
                self._covariance.resize((capacity, 12, 12), refcheck=False)
        row = self._values[self._n]
        row[0] = state.t
        rotation = state.rotation
        row[1:10] = rotation.reshape(9) if isinstance(rotation, np.ndarray) else np.ravel(rotation)
        row[10:13] = state.position
        row[13:19] = state.twist
        self._index[self._n] = state.index
        if state.covariance is not None:
            if self._covariance is None:
                self._covariance = np.empty((len(self._index), 12, 12))
            self._covariance[self._n] = state.covariance
            self._with_covariance += 1
        self._n += 1

    def extend(
        self,
        index: np.ndarray,
        t: np.ndarray,
        rotations: np.ndarray,
        positions: np.ndarray,
        twists: np.ndarray,
        covariances: np.ndarray | None,
    ) -> None:
        """Append n states at once: what n :meth:`append` calls of their
        :class:`StateEstimate` would keep. Shapes (n,), (n,), (n, 3, 3), (n, 3), (n, 6),
        (n, 12, 12) or None (states without a covariance)."""
        n = len(index)
        need = self._n + n
        if need > len(self._index):
            capacity = max(2 * len(self._index), need)
            self._index.resize(capacity, refcheck=False)
            self._values.resize((capacity, 19), refcheck=False)
            if self._covariance is not None:
                self._covariance.resize((capacity, 12, 12), refcheck=False)
        if self._covariance is None and covariances is not None:
            self._covariance = np.empty((len(self._index), 12, 12))
        rows = slice(self._n, need)
        self._index[rows] = index
        self._values[rows, 0] = t
        self._values[rows, 1:10] = rotations.reshape(n, 9)
        self._values[rows, 10:13] = positions
        self._values[rows, 13:19] = twists
        if covariances is not None:
            self._covariance[rows] = covariances  # type: ignore[index]
            self._with_covariance += n
        self._n = need

    def last(self) -> tuple[int, float]:
        """(index, t) of the latest state (the log must not be empty)."""
        return int(self._index[self._n - 1]), float(self._values[self._n - 1, 0])

    def _state(self, i: int) -> StateEstimate:
        row = self._values[i]
        full = self._covariance is not None and self._with_covariance == self._n
        return StateEstimate(
            index=int(self._index[i]),
            t=float(row[0]),
            rotation=row[1:10].reshape(3, 3).copy(),
            position=row[10:13].copy(),
            twist=row[13:19].copy(),
            covariance=self._covariance[i].copy() if full else None,  # type: ignore[index]
        )

    def __getitem__(self, i: int) -> StateEstimate:
        if not -self._n <= i < self._n:
            raise IndexError(f"state {i} of {self._n}")
        return self._state(i % self._n)

    def __iter__(self) -> Iterator[StateEstimate]:
        return (self._state(i) for i in range(self._n))

    def find(self, index: int) -> StateEstimate | None:
        """The latest state of frame ``index``, or None."""
        hits = np.flatnonzero(self._index[: self._n] == index)
        return self._state(int(hits[-1])) if len(hits) else None

    def trajectory(self) -> Trajectory:
        """Every state as a :class:`Trajectory` (covariances when every state has one)."""
        n, values = self._n, self._values[: self._n]
        full = self._covariance is not None and self._with_covariance == n
        return Trajectory(
            t=values[:, 0].copy(),
            rotations=values[:, 1:10].reshape(n, 3, 3).copy(),
            positions=values[:, 10:13].copy(),
            twists=values[:, 13:19].copy(),
            covariances=self._covariance[:n].copy() if full else None,  # type: ignore[index]
        )


class SortedIndices:
    """``in`` for an increasing list of ints (frame indices), by bisection: no per-frame
    set or dict entry. The list is shared, not copied: appends show."""

    def __init__(self, values: list[int]) -> None:
        self.values = values

    def __contains__(self, value: object) -> bool:
        i = bisect.bisect_left(self.values, value)  # type: ignore[call-overload]
        return i < len(self.values) and self.values[i] == value


class GrowingRows:
    """A growing 2-D array (capacity doubles): rows appended one or many at a time;
    ``view()`` the rows so far.

    Args:
        width: values per row; dtype: their type.
    """

    def __init__(self, width: int, dtype: type = float) -> None:
        self.data = np.empty((16, width), dtype=dtype)
        self.size = 0

    def append(self, row: Sequence[float] | np.ndarray) -> None:
        """Add one row."""
        if self.size == len(self.data):
            self.data = np.concatenate([self.data, np.empty_like(self.data)])
        self.data[self.size] = row
        self.size += 1

    def extend(self, rows: np.ndarray) -> None:
        """Add the rows of a (n, width) array."""
        while self.size + len(rows) > len(self.data):
            self.data = np.concatenate([self.data, np.empty_like(self.data)])
        self.data[self.size : self.size + len(rows)] = rows
        self.size += len(rows)

    def view(self) -> np.ndarray:
        """The (size, width) rows so far (a view: valid until the next append)."""
        return self.data[: self.size]
