"""Re-identification: tracks lost together are found again when their points come back.

A motion-blur passage, an occlusion or the target leaving the view loses most
tracks at once. Without re-identification the points seen again afterwards get
new ids, and the pose front end has to start a new reference, tied to the old
one only through the motion model across the gap. The tracker
(:mod:`hvo_graph.frontend.tracking`) instead keeps the lost tracks (their ids,
their positions in the last image that saw them, and that image) for
``TrackerConfig.reidentify_frames`` frames, and in each later image looks for
them under a coarse plane homography from that image (the target's corners,
else SIFT + MAGSAC: :mod:`hvo_graph.frontend.wide_baseline`), aligned by
Lucas-Kanade and checked for one plane. Found tracks resume under their old ids,
so poses are measured against the old reference again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend.tracker_config import TrackerConfig
from hvo_graph.frontend.wide_baseline import (
    MIN_MATCHES,
    feature_homography,
    guided_alignment,
    raw_pixels,
    target_homography,
)
from hvo_graph.geometry.camera import CameraModel


@dataclass
class LostTracks:
    """Tracks lost together, as the last image that saw them had them.

    Attributes:
        index: that image's frame index.
        image: (H, W) uint8, that image undistorted (pinhole).
        found: the target's corners there ((N, 2) raw pixels, (N, 3) board points) or None.
        ids: (M,) the lost tracks' ids.
        uv: (M, 2) their pinhole pixels in that image.
        birth: (M,) frame of each track's first sight.
        birth_uv: (M, 2) pinhole pixels there.
        birth_images: first-sight frame -> its undistorted image.
        warps: first-sight frame -> (3, 3) homography from it to ``image`` (pinhole pixels).
    """

    index: int
    image: np.ndarray
    found: tuple[np.ndarray, np.ndarray] | None
    ids: np.ndarray
    uv: np.ndarray
    birth: np.ndarray
    birth_uv: np.ndarray
    birth_images: dict[int, np.ndarray] = field(default_factory=dict)
    warps: dict[int, np.ndarray] = field(default_factory=dict)


def find_again(
    lost: LostTracks,
    pinhole: np.ndarray,
    found: tuple[np.ndarray, np.ndarray] | None,
    camera: CameraModel,
    config: TrackerConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Look for the lost tracks in the current image.

    Args:
        lost: the lost tracks.
        pinhole: (H, W) uint8, the current image undistorted.
        found: the target's corners in the current image, or None.
        camera: the camera.
        config: the tracker's settings (LK window, thresholds, border margin).
    Returns:
        (M,) mask of the tracks found, (M, 2) their raw pixels in the current image
        (valid where found) and the (3, 3) homography H0 lost image -> current image
        (pinhole pixels); None when fewer than ``MIN_MATCHES`` are found on one plane.
    """
    H0 = None
    if found is not None and lost.found is not None:
        H0 = target_homography(lost.found, found, camera)
    if H0 is None:
        try:
            H0, _ = feature_homography(lost.image, pinhole)
        except InputError:  # nothing recognisable yet
            return None
    c = config
    q, ok = guided_alignment(
        lost.image, pinhole, lost.uv, H0, window=c.lk_window, levels=min(c.lk_levels, 2),
        iterations=c.lk_iterations, epsilon=c.lk_epsilon, fb_threshold_px=c.fb_threshold_px,
    )  # fmt: skip
    uv = np.full_like(q, -1e9)
    uv[ok] = raw_pixels(camera, q[ok])
    ok &= camera.in_view(uv, margin=c.border_margin_px)
    if np.count_nonzero(ok) < MIN_MATCHES:
        return None
    idx = np.flatnonzero(ok)
    threshold = c.ransac_threshold_px if c.ransac_threshold_px is not None else 1.0
    H, inliers = cv2.findHomography(lost.uv[idx], q[idx], cv2.RANSAC, threshold, maxIters=2000)
    if H is None:
        return None
    ok[idx[inliers.ravel() == 0]] = False
    if np.count_nonzero(ok) < MIN_MATCHES:
        return None
    return ok, uv, H0
