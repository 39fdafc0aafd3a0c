"""n* of a whole recorded sequence, before its frames are measured.

A streaming front end must take n* from the first two frames whose H_d
decompositions agree, with the parallax of the start of the sequence: on the
paper's scenario that is 5-10 degrees off, and every pose after it is tilted and
good points are gated out. A recorded sequence offers more: every frame that
shares points with the first one sees the same n*. :func:`sequence_normal` picks
up to :data:`MAX_FRAMES` of them spread over the sequence, starts n* from the
decompositions that agree most, and refines it over all those frames at once
(:func:`~hvo_graph.geometry.plane_normal.refine_plane_normal`, Huber-weighted).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend._points import normalized_by_id
from hvo_graph.geometry._fit import euclidean
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.decomposition import decompose_homography, physically_valid_solutions
from hvo_graph.geometry.discrete import collinear, estimate_homography
from hvo_graph.geometry.plane_normal import NormalFit, refine_plane_normal
from hvo_graph.types import FrameObservations

__all__ = ["MAX_FRAMES", "MAX_POINTS", "sequence_normal"]

#: Frames fitted together (spread evenly over those sharing points with the first).
MAX_FRAMES: int = 200

#: Points of the first frame fitted (those seen in the most of those frames).
MAX_POINTS: int = 40

#: Frames looked at to find them (evenly spread): bounds the cost on long sequences.
MAX_SCANNED: int = 2000

#: Decompositions within this angle (degrees) agree on n*.
AGREEMENT_DEG: float = 5.0


def sequence_normal(
    observations: Sequence[FrameObservations],
    camera: CameraModel,
    distance: float,
    sigma: float,
    *,
    min_points: int = 4,
    min_parallax: float = 0.05,
    ransac_px: float | None = None,
    huber: float | None = 2.0,
) -> NormalFit | None:
    """n* in the first frame from the frames that share points with it.

    Args:
        observations: the whole sequence, in order.
        camera: the calibrated camera.
        distance: d*, metres.
        sigma: pixel noise in normalized units.
        min_points: fewest points a frame must share with the first.
        min_parallax: ||T|| / d* a frame's decomposition needs to vote for n*.
        ransac_px: RANSAC threshold on each frame's H_d (pixels; None: none).
        huber: Huber threshold of the joint fit (whitened residual norm).
    Returns:
        The joint fit, or None when no frame has the parallax (or the points) to tell n*.
    """
    if not observations:
        return None
    ids0, m0 = normalized_by_id(camera, observations[0])
    if len(ids0) < min_points:
        return None
    stride = max(1, (len(observations) - 1) // MAX_SCANNED)
    frames: list[tuple[np.ndarray, np.ndarray]] = []  # (rows into the first frame, m)
    for obs in observations[1::stride]:
        ids, m = normalized_by_id(camera, obs)
        _, rows, cols = np.intersect1d(ids0, ids, assume_unique=True, return_indices=True)
        if len(rows) >= min_points and not collinear(m[cols], 3 * sigma):
            frames.append((rows, m[cols]))
    if len(frames) > MAX_FRAMES:
        frames = [frames[i] for i in np.linspace(0, len(frames) - 1, MAX_FRAMES).astype(int)]
    if len(ids0) > MAX_POINTS:  # the longest-seen points: the fit's cost grows with P^2
        seen = np.bincount(np.concatenate([rows for rows, _ in frames] or [[]]).astype(int))
        seen = np.pad(seen, (0, len(ids0) - len(seen)))
        keep = np.zeros(len(ids0), dtype=bool)
        keep[np.argsort(-seen, kind="stable")[:MAX_POINTS]] = True
        renumber = np.cumsum(keep) - 1
        frames = [(renumber[rows[keep[rows]]], m[keep[rows]]) for rows, m in frames]
        frames = [(rows, m) for rows, m in frames if len(rows) >= min_points]
        m0 = m0[keep]
    votes = []  # per frame with parallax: (its inlier rows and points, valid solutions)
    for rows, m in frames:
        threshold = None if ransac_px is None or len(rows) < 6 else ransac_px / camera.mean_focal
        try:
            H, inliers = estimate_homography(m0[rows], m, ransac_threshold=threshold)
        except InputError:
            continue
        a, b = m0[rows[inliers]], m[inliers]
        valid = physically_valid_solutions(decompose_homography(euclidean(H, a, b)), a, b)
        if valid and np.linalg.norm(valid[0].translation) >= min_parallax:
            votes.append(((rows[inliers], b), valid))
    if not votes:
        return None
    normal = _most_agreed(votes)
    # each frame starts from its solution nearest to that n*
    starts = [max(valid, key=lambda s: float(s.normal @ normal)) for _, valid in votes]
    motions = [(s.rotation, s.translation * distance) for s in starts]
    try:
        return refine_plane_normal(
            m0, [frame for frame, _ in votes], motions, normal, distance, sigma, huber=huber
        )
    except (InputError, np.linalg.LinAlgError):
        return None


def _most_agreed(votes: list) -> np.ndarray:
    """The candidate normal that the most frames have a solution within
    :data:`AGREEMENT_DEG` of (ties: the larger summed cosine), averaged with those."""
    candidates = np.array([s.normal for _, valid in votes for s in valid])
    per_frame = [np.array([s.normal for s in valid]) for _, valid in votes]
    cos_limit = np.cos(np.radians(AGREEMENT_DEG))
    best, best_score = candidates[0], (-1, -np.inf)
    for c in candidates:
        nearest = np.array([np.max(normals @ c) for normals in per_frame])
        score = (int(np.sum(nearest >= cos_limit)), float(nearest.sum()))
        if score > best_score:
            best, best_score = c, score
    agreeing = [normals[np.argmax(normals @ best)] for normals in per_frame]
    agreeing = [n for n in agreeing if n @ best >= cos_limit]
    mean = np.sum(agreeing, axis=0)
    return mean / np.linalg.norm(mean)
