"""The front end's per-frame points: normalized coordinates by track id, and the points
two frames share."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import FrameObservations, Plane, PointObservations

#: Huber threshold (whitened residual norm) of the refinement the gate judges by: an
#: off-plane track must not pull the pose towards itself and push good points out.
HUBER = 2.0


@dataclass(frozen=True)
class TrackedFrame:
    """What the front end keeps of one processed frame."""

    index: int
    t: float
    ids: np.ndarray  # (N,) sorted
    m: np.ndarray  # (N, 3) normalized, rows in ids order
    R: np.ndarray | None  # (3, 3) motion reference -> this frame (X = R X* + T)
    T: np.ndarray | None  # (3,)


def normalized_by_id(camera: CameraModel, obs: FrameObservations) -> tuple[np.ndarray, np.ndarray]:
    """Sorted ids and their normalized coordinates."""
    ids = np.asarray(obs.ids)
    uv = np.asarray(obs.uv, dtype=float)
    if len(ids) > 1 and not np.all(ids[1:] > ids[:-1]):  # not already sorted and unique
        order = np.argsort(ids, kind="stable")
        ids, uv = ids[order], uv[order]
        if np.any(ids[1:] == ids[:-1]):
            raise InputError(f"frame {obs.index}: a point id appears twice")
    m = camera.pixel_to_normalized(uv) if len(ids) else None
    return ids, (m if m is not None else np.empty((0, 3)))


def _same_ids(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two sorted id arrays are equal (the usual case: the same tracks)."""
    return a is b or (len(a) == len(b) and bool(np.all(a == b)))


def shared_count(a: np.ndarray, b: np.ndarray) -> int:
    """How many ids two sorted, unique id arrays share."""
    if _same_ids(a, b):
        return len(a)
    return len(np.intersect1d(a, b, assume_unique=True))


def common_points(
    a: TrackedFrame, ids: np.ndarray, m: np.ndarray, *, with_ids: bool = False
) -> tuple[np.ndarray, ...]:
    """The rows of ``a.m`` and ``m`` of the ids both have (and those ids, if asked)."""
    if _same_ids(a.ids, ids):
        return (a.m, m, ids) if with_ids else (a.m, m)
    shared, ia, ib = np.intersect1d(a.ids, ids, assume_unique=True, return_indices=True)
    return (a.m[ia], m[ib], shared) if with_ids else (a.m[ia], m[ib])


def any_collinear(tolerance: float, *point_sets: np.ndarray) -> bool:
    """Whether any of the point sets (each (N, 3), the same N >= 3) lies on one line within
    ``tolerance`` (RMS distance): :func:`~hvo_graph.geometry.discrete.collinear`, with one
    batched SVD."""
    xy = np.stack([m[:, :2] for m in point_sets])
    xy = xy - xy.mean(axis=1, keepdims=True)
    smallest = np.linalg.svd(xy, compute_uv=False)[:, -1]
    return bool(np.any(smallest / np.sqrt(xy.shape[1]) < tolerance))


class CollinearMemo:
    """:func:`any_collinear` of one point set at a time, remembered for the last three
    arrays (by identity): a reference's points recur in every pose measured against it,
    and a frame's points in the next frame's velocity.

    Args:
        tolerance: RMS distance from the best line, normalized units.
    """

    def __init__(self, tolerance: float) -> None:
        self.tolerance = tolerance
        self._kept: list[tuple[np.ndarray, bool]] = []

    def __call__(self, m: np.ndarray) -> bool:
        for array, result in self._kept:
            if array is m:
                return result
        result = any_collinear(self.tolerance, m)
        self._kept = [(m, result), *self._kept[:2]]
        return result


def kept_points(
    ids: np.ndarray,
    m: np.ndarray,
    rejected: list[int],
    sigma: float,
    normal: np.ndarray | None,
    plane: Plane,
) -> PointObservations | None:
    """The frame's points less those its gate ``rejected``: ids (N,), m (N, 2) = (x/z, y/z)
    from the homogeneous (N, 3), their sigma (normalized units), n* and d*; None while
    n* is unknown (for estimators that fuse pixels)."""
    if normal is None:
        return None
    keep = ~np.isin(ids, rejected) if rejected else np.ones(len(ids), dtype=bool)
    return PointObservations(
        ids=ids[keep],
        m=m[keep, :2] / m[keep, 2:3],
        sigma=sigma,
        normal=normal,
        distance=plane.distance,
    )
