"""Wide-baseline pairs: the images path's corners matched across a large viewpoint change.

Frame-to-frame KLT (:mod:`hvo_graph.frontend.tracking`) follows points between
neighbouring video frames; it cannot jump between two photographs taken far
apart. For such a pair:

1. **initial homography**: SIFT keypoints of both images (``cv2.SIFT_create``),
   nearest neighbours with Lowe's ratio test, and a robust homography
   (``cv2.findHomography`` with ``cv2.USAC_MAGSAC``) of the dominant plane;
2. **the images path's own features**: Shi-Tomasi corners of the first image
   (the tracker's detector and settings), predicted in the second image by that
   homography;
3. **alignment**: Lucas-Kanade from the first image *warped by the homography*
   (so the patches look as they do in the second view) to the second image,
   started at the prediction, kept when tracking back lands within the
   forward-backward threshold (as the tracker's re-alignment does);
4. **plane consistency**: a RANSAC homography of the aligned corners drops the
   ones off the dominant plane.

SIFT's keypoints are only as precise as their scale (on OpenCV's graf1 -> graf3
pair their mean transfer error under the published homography is about 1.7 px);
the aligned corners are sub-pixel (about 0.4 px there). With lens distortion both
images are first undistorted (``cv2.undistort``, same K), where the plane maps by a
homography; the points returned are raw pixels again, as tracks are.

Repetitive patterns defeat step 1: on a chessboard every inner corner looks the
same, and a static background seen by both images is a larger plane than the
board. For such pairs the homography of the target's corners
(:mod:`hvo_graph.frontend.target`) replaces step 1 (``initial_homography``); the
corners, their positions and everything measured from them are still this path's.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend.tracking import TrackerConfig
from hvo_graph.frontend.wide_baseline import (
    MIN_MATCHES,
    feature_homography,
    guided_alignment,
    pinhole_image,
    raw_pixels,
)
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import as_gray_image
from hvo_graph.types import FrameObservations


@dataclass(frozen=True)
class PairMatches:
    """Corners of the first image and where they are in the second.

    Attributes:
        uv_a: (N, 2) raw pixels in the first image.
        uv_b: (N, 2) raw pixels of the same plane points in the second image.
        homography: (3, 3) first -> second image, fitted to the pairs (in undistorted
            pixels when the camera has distortion).
        sift_matches: SIFT matches consistent with the initial homography.
    """

    uv_a: np.ndarray
    uv_b: np.ndarray
    homography: np.ndarray
    sift_matches: int

    def observations(self, times: tuple[float, float] = (0.0, 1.0)) -> list[FrameObservations]:
        """The pair as a two-frame sequence (ids 0..N-1 in both frames)."""
        ids = np.arange(len(self.uv_a), dtype=np.int64)
        return [
            FrameObservations(0, float(times[0]), ids, self.uv_a.copy()),
            FrameObservations(1, float(times[1]), ids.copy(), self.uv_b.copy()),
        ]


def match_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    camera: CameraModel | None = None,
    config: TrackerConfig | None = None,
    initial_homography: np.ndarray | None = None,
) -> PairMatches:
    """Corners of ``image_a`` found in ``image_b`` across a wide baseline (module docstring).

    Args:
        image_a, image_b: (H, W) gray or (H, W, 3) BGR, uint8 (sizes may differ
            without a camera).
        camera: the calibrated camera (images must be its size), or None for raw pixels.
        config: the tracker's settings (corner detector, Lucas-Kanade window,
            forward-backward threshold, border margin, RANSAC threshold).
        initial_homography: (3, 3) a first guess of the plane homography a -> b
            (undistorted pixels when the camera has distortion) in place of the SIFT
            step, e.g. from a target's corners where SIFT cannot tell them apart.
    Returns:
        The matched corners and the plane homography.
    Raises:
        InputError: too few distinctive or consistent matches.
    """
    c = config or TrackerConfig()
    a = pinhole_image(camera, as_gray_image(image_a, "image_a", camera))
    b = pinhole_image(camera, as_gray_image(image_b, "image_b", camera))
    if initial_homography is None:
        H0, sift_count = feature_homography(a, b)
    else:
        H0, sift_count = np.asarray(initial_homography, dtype=float).reshape(3, 3), 0
    corners = cv2.goodFeaturesToTrack(
        a, c.max_features, c.quality_level, max(c.min_distance, 1.0), blockSize=c.block_size
    )
    if corners is None:
        raise InputError("image_a: no corners to match")
    uv_a = corners.reshape(-1, 2).astype(np.float64)
    uv_b, ok = guided_alignment(
        a, b, uv_a, H0, window=c.lk_window, levels=min(c.lk_levels, 2),
        iterations=c.lk_iterations, epsilon=c.lk_epsilon, fb_threshold_px=c.fb_threshold_px,
    )  # fmt: skip
    size = np.array([b.shape[1], b.shape[0]])
    margin = c.border_margin_px
    ok &= np.all((uv_b >= margin - 0.5) & (uv_b <= size - 0.5 - margin), axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) < MIN_MATCHES:
        raise InputError(f"images: only {len(idx)} corners aligned in the second image")
    threshold = c.ransac_threshold_px if c.ransac_threshold_px is not None else 1.0
    H, inliers = cv2.findHomography(uv_a[idx], uv_b[idx], cv2.RANSAC, threshold, maxIters=5000)
    if H is None or int(inliers.sum()) < MIN_MATCHES:
        raise InputError("images: the aligned corners agree on no plane")
    keep = idx[inliers.ravel() > 0]
    return PairMatches(
        raw_pixels(camera, uv_a[keep]), raw_pixels(camera, uv_b[keep]), H, sift_count
    )
