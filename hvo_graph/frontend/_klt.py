"""Work-saving pieces of the KLT tracker (:mod:`hvo_graph.frontend.tracking`).

Each computes what the tracker needs and no more, with the same result as the
plain way:

- :func:`forward_backward`: the forward search starts at a prediction, with the
  pyramid levels its error needs (the plain search for what it loses), and the
  backward search of the check uses only the levels the forward displacement needs
  (:func:`back_levels`);
- :func:`align_to_first_sight` (:func:`window_box`, :func:`warp_box`): the
  re-alignment warps the image of first sight only where its Lucas-Kanade windows
  read, not the whole frame.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from hvo_graph.frontend.tracker_config import TrackerConfig
from hvo_graph.frontend.wide_baseline import pinhole_pixels, raw_pixels
from hvo_graph.geometry.camera import CameraModel

#: Lucas-Kanade as the tracker calls it: (source, target, points, guess, levels) ->
#: (N, 2) positions in target and (N,) success.
LucasKanade = Callable[
    [np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, int | None],
    tuple[np.ndarray, np.ndarray],
]


def pyramid_levels(d: float, window: int, levels: int) -> int:
    """Pyramid levels LK needs to recover a displacement of up to d pixels: the top level
    used sees d / 2^L within an eighth of the window (on rendered textures, one level
    recovers about twice that); ``levels`` (the most) when d is unknown or too large.

    Args:
        d: the largest displacement, pixels (nan: unknown).
        window: side of the LK window, pixels.
        levels: the tracker's pyramid levels.
    """
    capture = window / 8.0
    if not np.isfinite(d):
        return levels
    if d <= capture:
        return 0
    return min(levels, int(np.ceil(np.log2(d / capture))))


def back_levels(p0: np.ndarray, p1: np.ndarray, window: int, levels: int) -> int:
    """Pyramid levels of the backward search: as many as the forward displacement needs.

    A pyramid lets LK recover a displacement larger than its window; going back, the
    displacement is known (the forward one, at most d pixels over the frame's points),
    so the levels whose only use would be a larger one are skipped
    (:func:`pyramid_levels`). The search still starts at p1 with no motion, so the
    check stays independent of the forward result; with fast motion it is the full
    pyramid.

    Args:
        p0, p1: (N, 2) the points and where the forward search found them, pixels.
        window: side of the LK window, pixels.
        levels: the tracker's pyramid levels (the most returned).
    """
    if not len(p0):
        return levels
    return pyramid_levels(float(np.max(np.linalg.norm(p1 - p0, axis=1))), window, levels)


def forward_backward(
    lk: LucasKanade,
    previous: np.ndarray,
    current: np.ndarray,
    p0: np.ndarray,
    config: TrackerConfig,
    in_view: Callable[[np.ndarray], np.ndarray],
    guess: np.ndarray | None = None,
    levels: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame-to-frame LK with the forward-backward check (and the border gate).

    With a ``guess`` (a prediction of the points in ``current``) the forward search
    starts there with ``levels`` pyramid levels (as many as the prediction's error
    needs); the points it loses, or whose check fails, are searched for again the
    plain way (no guess, the full pyramid), so a wrong prediction costs time, never a
    track the plain search keeps.

    Args:
        lk: the tracker's Lucas-Kanade.
        previous, current: (H, W) uint8 images.
        p0: (N, 2) points in ``previous``, pixels.
        config: the tracker's settings (window, levels, ``fb_threshold_px``).
        in_view: (N, 2) pixels -> (N,) inside the image, away from its border.
        guess, levels: the prediction (N, 2) and the forward search's levels.
    Returns:
        (N, 2) positions in ``current`` and (N,) keep: found both ways, in view.
    """
    p1, ok = lk(previous, current, p0, guess, config.lk_levels if guess is None else levels)
    keep = ok & in_view(p1)
    _check_back(lk, previous, current, p0, p1, keep, config)
    retry = np.flatnonzero(~keep) if guess is not None else np.empty(0, dtype=np.int64)
    if len(retry):
        p1_again, ok_again = lk(previous, current, p0[retry], None, None)
        keep_again = ok_again & in_view(p1_again)
        _check_back(lk, previous, current, p0[retry], p1_again, keep_again, config)
        p1[retry], keep[retry] = p1_again, keep_again
    return p1, keep


def _check_back(
    lk: LucasKanade,
    previous: np.ndarray,
    current: np.ndarray,
    p0: np.ndarray,
    p1: np.ndarray,
    keep: np.ndarray,
    config: TrackerConfig,
) -> None:
    """Clear ``keep`` where tracking p1 back does not land within ``fb_threshold_px`` of
    p0. Only the kept points go back: each point is tracked on its own, so the others'
    results are the same."""
    idx = np.flatnonzero(keep)
    if len(idx):
        levels = back_levels(p0[idx], p1[idx], config.lk_window, config.lk_levels)
        back, ok_back = lk(current, previous, p1[idx], None, levels)
        keep[idx] = ok_back & (np.linalg.norm(back - p0[idx], axis=1) < config.fb_threshold_px)


def plane_check(
    p0: np.ndarray,
    p1: np.ndarray,
    keep: np.ndarray,
    threshold: float | None,
    to_pinhole: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray | None:
    """Clear ``keep`` where a track does not move with the dominant plane.

    A RANSAC homography of the kept tracks p0 -> p1 in pinhole pixels (``to_pinhole``),
    where plane points map by one, with the inlier ``threshold`` (pixels; None: no
    check). Returns that homography (3, 3), or None."""
    if threshold is None or np.count_nonzero(keep) < 4:
        return None
    idx = np.flatnonzero(keep)
    H, inliers = cv2.findHomography(
        to_pinhole(p0[idx]), to_pinhole(p1[idx]), cv2.RANSAC, threshold, maxIters=2000,
        confidence=0.999,
    )  # fmt: skip
    if H is not None:  # None: degenerate configuration, nothing to judge against
        keep[idx[inliers.ravel() == 0]] = False
    return H


def predict(
    p0: np.ndarray,
    motion: tuple[np.ndarray | None, float],
    lens: CameraModel | None,
    config: TrackerConfig,
) -> tuple[np.ndarray | None, int | None]:
    """Where the points p0 (N, 2, raw pixels) should be in the next image if the plane
    moves across the view as in the last step, and the forward search's pyramid levels.

    Args:
        motion: the last step's homography (3, 3, pinhole pixels) and the largest
            distance between a kept track and its prediction then (pixels; nan:
            unknown), or (None, nan).
        lens: the camera when it has distortion, else None.
    Returns:
        (N, 2) raw pixels and the levels for twice the last error (:func:`pyramid_levels`),
        or (None, None) without a step to repeat.
    """
    H, miss = motion
    if H is None:
        return None, None
    q = cv2.perspectiveTransform(pinhole_pixels(lens, p0).reshape(-1, 1, 2), H)
    return raw_pixels(lens, q.reshape(-1, 2)), pyramid_levels(
        2.0 * miss, config.lk_window, config.lk_levels
    )


def prediction_miss(p1: np.ndarray, guess: np.ndarray | None, keep: np.ndarray) -> float:
    """The largest distance between a kept track p1 and its prediction (nan: none)."""
    if guess is None:
        return np.nan
    return float(np.max(np.linalg.norm(p1[keep] - guess[keep], axis=1), initial=0.0))


def window_box(
    points: np.ndarray, window: int, refine_max_px: float, width: int, height: int
) -> tuple[int, int, int, int]:
    """The part of the view that the re-alignment's LK windows at ``points`` can read.

    LK reads the template only in the window around each starting point (plus one
    pixel for the bilinear interpolation and one for the Scharr derivative) and the
    current image around its estimate, which is dropped once it is more than
    ``refine_max_px`` from where it started.

    Args:
        points: (N, 2) the starting points and the estimates, pixels.
        window: side of the LK window, pixels.
        refine_max_px: the re-alignment's largest move, pixels.
        width, height: the image size, pixels.
    Returns:
        x0, y0, x1, y1: the box's columns x0..x1-1 and rows y0..y1-1, inside the image.
    """
    reach = window // 2 + 3 + int(np.ceil(refine_max_px))
    finite = points[np.all(np.isfinite(points), axis=1)]
    if not len(finite):
        return 0, 0, width, height
    low = np.floor(finite.min(axis=0)) - reach
    high = np.ceil(finite.max(axis=0)) + reach + 1
    x0, y0 = (int(v) for v in np.clip(low, 0, (width - 1, height - 1)))
    x1, y1 = (int(v) for v in np.clip(high, (x0 + 1, y0 + 1), (width, height)))
    return x0, y0, x1, y1


def warp_box(image: np.ndarray, G: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """``image`` warped by the homography G, only inside ``box`` of the target view.

    Args:
        image: (H, W) uint8.
        G: (3, 3) image -> target view, pixels.
        box: x0, y0, x1, y1 (:func:`window_box`).
    Returns:
        (y1 - y0, x1 - x0) uint8: pixel (x, y) of the target view at [y - y0, x - x0].
    """
    x0, y0, x1, y1 = box
    shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
    # Replicated borders: a black frame would be an edge that pulls the LK windows.
    return cv2.warpPerspective(
        image, shift @ G, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip


def align_to_first_sight(
    first_image: np.ndarray,
    current: np.ndarray,
    G: np.ndarray,
    first: np.ndarray,
    guess: np.ndarray,
    config: TrackerConfig,
    lk: LucasKanade,
) -> tuple[np.ndarray, np.ndarray]:
    """Points of their image of first sight found again in the current image.

    The image of first sight, warped by the plane homography G into the current view,
    looks as the current image does around each point; LK from it at G(first), started
    at the frame-to-frame result, finds the points themselves. Only the box that LK
    reads is warped (:func:`window_box`).

    Args:
        first_image: (H, W) uint8, the image of first sight (pinhole pixels).
        current: (H, W) uint8, the current image (pinhole pixels).
        G: (3, 3) first image -> current image.
        first: (N, 2) the points in the first image, pinhole pixels.
        guess: (N, 2) the frame-to-frame result in the current image, pinhole pixels.
        config: the tracker's settings (LK window, ``refine_max_px``).
        lk: the tracker's Lucas-Kanade.
    Returns:
        (N, 2) pinhole pixels in the current image and (N,) success: LK converged within
        ``refine_max_px`` of the guess.
    """
    assert config.refine_max_px is not None
    height, width = current.shape[:2]
    predicted = cv2.perspectiveTransform(first.reshape(-1, 1, 2), G).reshape(-1, 2)
    box = x0, y0, x1, y1 = window_box(
        np.vstack((predicted, guess)), config.lk_window, config.refine_max_px, width, height
    )
    corner = np.array([x0, y0], dtype=np.float64)
    # No pyramid: the frame-to-frame result is within a fraction of a pixel.
    aligned, ok = lk(
        warp_box(first_image, G, box), current[y0:y1, x0:x1], predicted - corner,
        guess - corner, 0,
    )  # fmt: skip
    aligned = aligned + corner
    return aligned, ok & (np.linalg.norm(aligned - guess, axis=1) < config.refine_max_px)
