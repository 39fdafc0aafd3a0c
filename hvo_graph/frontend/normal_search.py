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

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend._points import normalized_by_id
from hvo_graph.geometry._fit import PlaneTransfer, euclidean
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.decomposition import decompose_homography, physically_valid_solutions
from hvo_graph.geometry.discrete import collinear, estimate_homography
from hvo_graph.geometry.plane_normal import NormalFit, refine_plane_normal
from hvo_graph.types import FrameObservations, Plane

__all__ = ["MAX_FRAMES", "MAX_POINTS", "sequence_normal"]

#: Frames fitted together (spread evenly over those sharing points with the first).
MAX_FRAMES: int = 200

#: Points of the first frame fitted (those seen in the most of those frames).
MAX_POINTS: int = 40

#: Frames looked at to find them (evenly spread): bounds the cost on long sequences.
MAX_SCANNED: int = 2000

#: Frames of most parallax whose decompositions propose starting normals.
TOP_FRAMES: int = 10

#: Most starting normals tried (the fit from each; the smallest cost wins).
MAX_STARTS: int = 4

#: Decompositions within this angle (degrees) agree on n*.
AGREEMENT_DEG: float = 5.0

#: False-alarm rate of the translation test over a whole sequence (:func:`tested`).
TRANSLATION_ALPHA: float = 1e-3
#: n*'s standard deviation (degrees) where no frame translates measurably.
UNOBSERVED_SIGMA_DEG: float = 90.0


def sequence_normal(
    observations: Sequence[FrameObservations],
    camera: CameraModel,
    distance: float,
    sigma: float,
    *,
    min_points: int = 4,
    min_parallax: float = 0.01,
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
        min_parallax: ||T|| / d* a frame's decomposition needs to propose a starting n*.
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
    votes = []  # per frame: (its inlier rows and points, valid solutions, parallax)
    for rows, m in frames:
        threshold = None if ransac_px is None or len(rows) < 6 else ransac_px / camera.mean_focal
        try:
            H, inliers = estimate_homography(m0[rows], m, ransac_threshold=threshold)
        except InputError:
            continue
        a, b = m0[rows[inliers]], m[inliers]
        valid = physically_valid_solutions(decompose_homography(euclidean(H, a, b)), a, b)
        if valid:
            votes.append(((rows[inliers], b), valid, float(np.linalg.norm(valid[0].translation))))
    # the start: the normals the frames of most parallax agree on (each decomposition has
    # a spurious twin; with little parallax it can win the vote, so the fit starts from
    # each distinct candidate and the smallest cost decides)
    top = sorted((v for v in votes if v[2] >= min_parallax), key=lambda v: -v[2])[:TOP_FRAMES]
    if not top:
        return None
    best: NormalFit | None = None
    for normal in _candidates([valid for _, valid, _ in top]):
        # each frame starts from its solution nearest to that n*
        starts = [max(valid, key=lambda s: float(s.normal @ normal)) for _, valid, _ in votes]
        motions = [(s.rotation, s.translation * distance) for s in starts]
        try:
            fit = refine_plane_normal(
                m0, [frame for frame, _, _ in votes], motions, normal, distance, sigma, huber=huber
            )
        except (InputError, np.linalg.LinAlgError):
            continue
        if best is None or fit.cost < best.cost:
            best = fit
    return None if best is None else tested(best, [f for f, _, _ in votes], distance, sigma)


def tested(
    fit: NormalFit, frames: list[tuple[np.ndarray, np.ndarray]], distance: float, sigma: float
) -> NormalFit:
    """``fit`` with its translation test: n* unobservable (its standard deviation set to
    :data:`UNOBSERVED_SIGMA_DEG`) unless some frame's translation stands out of the noise.

    Without translation H_d = R whatever n*, and the joint fit's curvature in n* comes
    from the noise the frames' motions absorb (a static camera: 16-19 degrees off with a
    standard deviation of 1 degree). Each frame's T_k is tested against its covariance
    (the frame's transfer fit at the joint n* and reference points, rotation free):
    chi^2_3 per frame without translation, so the largest must pass the chi^2_3 quantile
    of 1 - :data:`TRANSLATION_ALPHA` / frames (about 27 for 200 frames; a static camera
    gives 9-13, 3.5 cm of motion at d* = 2 m 42-55, the paper's 0.35 m thousands).
    """
    plane = Plane(distance, fit.normal)
    largest = 0.0
    for (rows, m), (R, T) in zip(frames, fit.motions, strict=True):
        transfer = PlaneTransfer(fit.reference[rows], m, plane, sigma)
        lin = transfer.linearize(R, T)
        covariance = np.linalg.inv(np.sum(lin.JtW @ lin.J, axis=0))[3:, 3:]
        largest = max(largest, float(T @ np.linalg.solve(covariance, T)))
    covariance = fit.covariance
    if largest <= chi2_3_quantile(1.0 - TRANSLATION_ALPHA / len(frames)):
        covariance = np.radians(UNOBSERVED_SIGMA_DEG) ** 2 * np.eye(2)
    return dataclasses.replace(fit, covariance=covariance, translation_chi2=largest)


def chi2_3_quantile(p: float) -> float:
    """The p-quantile of chi^2 with 3 degrees of freedom (bisection on its CDF,
    erf(sqrt(x/2)) - sqrt(2x/pi) exp(-x/2))."""
    lo, hi = 0.0, 200.0
    for _ in range(100):
        x = 0.5 * (lo + hi)
        cdf = math.erf(math.sqrt(x / 2.0)) - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)
        lo, hi = (x, hi) if cdf < p else (lo, x)
    return 0.5 * (lo + hi)


def _candidates(solutions: list) -> list[np.ndarray]:
    """Up to :data:`MAX_STARTS` distinct normals (more than :data:`AGREEMENT_DEG` apart)
    from the frames' valid decompositions, the most agreed on first: each is the mean of
    the frames' solutions within :data:`AGREEMENT_DEG` of it."""
    per_frame = [np.array([s.normal for s in valid]) for valid in solutions]
    cos_limit = np.cos(np.radians(AGREEMENT_DEG))
    scored = []
    for c in np.concatenate(per_frame):
        nearest = np.array([normals[np.argmax(normals @ c)] for normals in per_frame])
        agree = nearest[nearest @ c >= cos_limit]
        mean = agree.sum(axis=0) / np.linalg.norm(agree.sum(axis=0))
        scored.append(((len(agree), float((nearest @ c).sum())), mean))
    chosen: list[np.ndarray] = []
    for _, mean in sorted(scored, key=lambda x: x[0], reverse=True):
        if all(mean @ c < cos_limit for c in chosen):
            chosen.append(mean)
        if len(chosen) == MAX_STARTS:
            break
    return chosen
