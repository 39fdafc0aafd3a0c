"""The pixel noise of a tracked sequence, for camera files that do not give it.

Every covariance of the front end (H_d poses, H_c twists), its RANSAC threshold and
gates, and the smoothers' fitted process noise scale with the pixel noise sigma
(``noise.pixel_sigma``). A tracker's real noise is seldom known: KLT on real images
is 0.05-1 px, and a sigma 4x too small makes every covariance 16x too confident
(and the tightly coupled graph rejects good tracks as off the plane).

Along one track the image point moves smoothly with the camera, and the tracker's
noise is white from frame to frame, so the n-th finite difference of a track over
n + 1 consecutive, equally spaced frames,

    d_k = sum_j (-1)^(n-j) C(n, j) u_(k+j),

is noise with variance C(2n, n) sigma^2 plus the n-th derivative of the motion times
dt^n, which shrinks fast with n. With n = 5 the motion's share is below 3 % on
every simulated family (10-120 fps, hover to 2 Hz motion); the median absolute
difference, scaled for a Gaussian (1.4826), ignores jumps and re-detections.

Two checks keep the motion from passing for noise: the estimates of orders n - 1 and
n + 1 must agree (a share of motion still falls with the order; noise does not), and
the result must be one a tracker can have (at most :data:`MAX_SIGMA_PX`): views far
apart, as in a calibration set, move the points by more than any tracker's noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from math import comb, sqrt

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.types import FrameObservations

__all__ = [
    "DIFFERENCE_ORDER",
    "MAX_ORDER_RATIO",
    "MAX_SIGMA_PX",
    "MIN_DIFFERENCES",
    "PixelNoiseEstimate",
    "estimate_pixel_sigma",
]

#: Order n of the finite differences.
DIFFERENCE_ORDER: int = 5

#: Fewest differences (per coordinate) to estimate from: fewer give no estimate.
MIN_DIFFERENCES: int = 100

#: Largest ratio of the estimates of orders n - 1 and n + 1 taken as noise alone.
MAX_ORDER_RATIO: float = 1.25

#: Largest sigma read from tracks, pixels: above it the frames are too far apart.
MAX_SIGMA_PX: float = 3.0

#: Frames count as equally spaced when their intervals differ by at most this fraction.
SPACING_TOLERANCE: float = 0.01


@dataclass(frozen=True)
class PixelNoiseEstimate:
    """The pixel noise read from the tracks (:func:`estimate_pixel_sigma`).

    Attributes:
        sigma: standard deviation of each image coordinate, pixels.
        differences: the n-th differences it was read from (u and v counted apart).
    """

    sigma: float
    differences: int


def estimate_pixel_sigma(
    observations: Sequence[FrameObservations],
    *,
    order: int = DIFFERENCE_ORDER,
    min_differences: int = MIN_DIFFERENCES,
) -> PixelNoiseEstimate | None:
    """sigma of the tracks' pixel noise from their n-th differences (module docstring).

    Args:
        observations: the tracked frames, in order (a list, or a tracks file's
            :class:`~hvo_graph.io.tracks.TrackTable`).
        order: n, the order of the differences (>= 2).
        min_differences: fewest differences to estimate from.
    Returns:
        The estimate, or None when fewer than ``min_differences`` windows of n + 2
        consecutive, equally spaced frames see the same point, or when the motion
        between frames dominates the differences (module docstring).
    """
    if order < 2:
        raise InputError(f"order: expected an integer >= 2, got {order!r}")
    frame, t, ids, uv = _rows(observations)
    by_track = np.lexsort((frame, ids))
    frame, t, ids, uv = frame[by_track], t[by_track], ids[by_track], uv[by_track]
    estimates = [_sigma(frame, t, ids, uv, n, min_differences) for n in (order - 1, order + 1)]
    noise = _sigma(frame, t, ids, uv, order, min_differences)
    if noise is None or None in estimates:
        return None
    low, high = (e.sigma for e in estimates)  # type: ignore[union-attr]
    if max(low, high) > MAX_ORDER_RATIO * min(low, high) or noise.sigma > MAX_SIGMA_PX:
        return None
    return noise


def _sigma(
    frame: np.ndarray, t: np.ndarray, ids: np.ndarray, uv: np.ndarray, order: int, least: int
) -> PixelNoiseEstimate | None:
    """The estimate from the n-th differences of rows sorted by (track, frame)."""
    if len(ids) <= order:
        return None
    # window k spans rows k..k+n: one track, n + 1 consecutive frames, even spacing
    same = ids[order:] == ids[:-order]
    consecutive = frame[order:] - frame[:-order] == order
    gaps = np.lib.stride_tricks.sliding_window_view(np.diff(t), order)
    spread = gaps.max(axis=1) - gaps.min(axis=1)
    even = spread <= SPACING_TOLERANCE * np.abs(gaps.mean(axis=1))
    differences = np.diff(uv, n=order, axis=0)[same & consecutive & even]
    if len(differences) < least:
        return None
    median = float(np.median(np.abs(differences)))
    return PixelNoiseEstimate(1.4826 * median / sqrt(comb(2 * order, order)), differences.size)


def _rows(
    observations: Sequence[FrameObservations],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every observation as columns: (R,) frame number, (R,) time, (R,) id, (R, 2) uv."""
    rows = getattr(observations, "rows", None)
    if callable(rows):  # a tracks file's table: its columns as they are
        return rows()
    counts = [len(obs.ids) for obs in observations]
    if not sum(counts):
        return np.empty(0, np.int64), np.empty(0), np.empty(0, np.int64), np.empty((0, 2))
    frame = np.repeat([obs.index for obs in observations], counts)
    t = np.repeat([obs.t for obs in observations], counts)
    ids = np.concatenate([np.asarray(obs.ids, dtype=np.int64) for obs in observations])
    uv = np.concatenate([np.asarray(obs.uv, dtype=float).reshape(-1, 2) for obs in observations])
    return frame, t, ids, uv
