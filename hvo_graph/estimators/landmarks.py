"""Plane landmarks of the tightly coupled smoother: where a new one starts, and which
tracks get one when a frame sees more than the smoother keeps.
"""

from __future__ import annotations

import gtsam
import numpy as np

__all__ = ["DEFAULT_MAX_LANDMARKS", "back_project", "farthest_points"]

#: Most landmarks observed in one frame. ISAM2's cost per frame grows with the cube of
#: the landmarks in view (each is seen from every pose of the window, so their cliques
#: are dense) while their information grows linearly: 150 tracks cost ~7x what 64 cost
#: for a 1.4x lower error. None of the simulated scenes reaches it; an image sequence
#: with ~200 KLT tracks does.
DEFAULT_MAX_LANDMARKS: int = 64


def back_project(
    pose: gtsam.Pose3, m: np.ndarray, normal: np.ndarray, distance: float
) -> np.ndarray | None:
    """The point of the plane n^T X = d (in W) seen at normalized coordinates m from T_wc.

    Args:
        pose: T_wc.
        m: (2,) normalized image coordinates (x/z, y/z).
        normal, distance: n* (3,) and d* of the plane in W.
    Returns:
        (3,) the point in W, or None when the ray does not meet the plane in front.
    """
    R = pose.rotation().matrix()
    p = np.asarray(pose.translation(), dtype=float)
    ray = R @ np.array([m[0], m[1], 1.0])
    along = float(normal @ ray)
    if abs(along) < 1e-9:
        return None
    s = (distance - float(normal @ p)) / along
    return p + s * ray if s > 0 else None


def farthest_points(candidates: np.ndarray, used: np.ndarray, count: int) -> list[int]:
    """Greedy farthest-point selection: ``count`` of the candidates, each in turn the one
    farthest from every point used or already picked, so the selection spreads over
    the image.

    Args:
        candidates: (N, 2) image coordinates to pick from.
        used: (M, 2) coordinates already in use (M may be 0).
        count: how many to pick (fewer when N is smaller; none when <= 0).
    Returns:
        indices into ``candidates``, in the order picked (ties: the lowest index).
    """
    count = min(int(count), len(candidates))
    if count <= 0:
        return []
    nearest = np.full(len(candidates), np.inf)
    if len(used):
        gaps = candidates[:, None, :] - np.asarray(used)[None, :, :]
        nearest = np.sqrt((gaps**2).sum(axis=2)).min(axis=1)
    picks: list[int] = []
    for _ in range(count):
        pick = int(np.argmax(nearest))
        picks.append(pick)
        nearest = np.minimum(nearest, np.linalg.norm(candidates - candidates[pick], axis=1))
        nearest[pick] = -np.inf
    return picks
