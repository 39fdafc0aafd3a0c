"""The front end's per-frame points: normalized coordinates by track id, and the points
two frames share."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import FrameObservations, Plane, PointObservations


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
    order = np.argsort(obs.ids, kind="stable")
    ids = np.asarray(obs.ids)[order]
    if len(ids) > 1 and np.any(ids[1:] == ids[:-1]):
        raise InputError(f"frame {obs.index}: a point id appears twice")
    m = camera.pixel_to_normalized(np.asarray(obs.uv, dtype=float)[order]) if len(ids) else None
    return ids, (m if m is not None else np.empty((0, 3)))


def common_points(
    a: TrackedFrame, ids: np.ndarray, m: np.ndarray, *, with_ids: bool = False
) -> tuple[np.ndarray, ...]:
    """The rows of ``a.m`` and ``m`` of the ids both have (and those ids, if asked)."""
    shared, ia, ib = np.intersect1d(a.ids, ids, assume_unique=True, return_indices=True)
    return (a.m[ia], m[ib], shared) if with_ids else (a.m[ia], m[ib])


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
