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
the aligned corners are sub-pixel (about 0.4 px there). Corners are compared in
undistorted pixels for the homographies when the camera has distortion; the
points returned are raw pixels, as tracks are.

Repetitive patterns defeat step 1: on a chessboard every inner corner looks the
same, and a static background seen by both images is a larger plane than the
board. Such pairs need the target's own corners (:mod:`hvo_graph.frontend.target`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend.tracking import TrackerConfig
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import as_gray_image
from hvo_graph.types import FrameObservations

#: Lowe's ratio: a SIFT match is kept when its distance is below this times the second best.
RATIO = 0.8
#: Inlier threshold of the SIFT homography, pixels (the keypoints are coarse).
SIFT_RANSAC_PX = 3.0
#: Fewest consistent matches for a pair.
MIN_MATCHES = 8


@dataclass(frozen=True)
class PairMatches:
    """Corners of the first image and where they are in the second.

    Attributes:
        uv_a: (N, 2) raw pixels in the first image.
        uv_b: (N, 2) raw pixels of the same plane points in the second image.
        homography: (3, 3) first -> second image, fitted to the pairs (undistorted
            pixels when the camera has distortion, else raw pixels).
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


def _undistorted(camera: CameraModel | None, uv: np.ndarray) -> np.ndarray:
    if camera is None or not camera.has_distortion:
        return np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    m = camera.pixel_to_normalized(np.asarray(uv, dtype=float))
    return (m @ camera.K.T)[:, :2]


def _sift_homography(a: np.ndarray, b: np.ndarray, camera: CameraModel | None) -> tuple:
    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        raise InputError("images: too little texture for a wide-baseline match")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    if len(good) < MIN_MATCHES:
        raise InputError(f"images: only {len(good)} distinctive matches between the two images")
    pa = _undistorted(camera, np.array([ka[m.queryIdx].pt for m in good]))
    pb = _undistorted(camera, np.array([kb[m.trainIdx].pt for m in good]))
    H, inliers = cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, SIFT_RANSAC_PX)
    count = 0 if inliers is None else int(inliers.sum())
    if H is None or count < MIN_MATCHES:
        raise InputError(f"images: only {count} matches agree on one plane")
    return H, count


def match_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    camera: CameraModel | None = None,
    config: TrackerConfig | None = None,
) -> PairMatches:
    """Corners of ``image_a`` found in ``image_b`` across a wide baseline (module docstring).

    Args:
        image_a, image_b: (H, W) gray or (H, W, 3) BGR, uint8 (sizes may differ
            without a camera).
        camera: the calibrated camera (images must be its size), or None for raw pixels.
        config: the tracker's settings (corner detector, Lucas-Kanade window,
            forward-backward threshold, border margin, RANSAC threshold).
    Returns:
        The matched corners and the plane homography.
    Raises:
        InputError: too few distinctive or consistent matches.
    """
    c = config or TrackerConfig()
    a = as_gray_image(image_a, "image_a", camera)
    b = as_gray_image(image_b, "image_b", camera)
    H0, sift_count = _sift_homography(a, b, camera)
    corners = cv2.goodFeaturesToTrack(
        a, c.max_features, c.quality_level, max(c.min_distance, 1.0), blockSize=c.block_size
    )
    if corners is None:
        raise InputError("image_a: no corners to match")
    uv_a = corners.reshape(-1, 2).astype(np.float64)
    # Raw-pixel warp for the patches' appearance only; the alignment finds the points.
    G = H0 if camera is None or not camera.has_distortion else _raw_homography(uv_a, H0, camera)
    warped = cv2.warpPerspective(
        a, G, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    predicted = cv2.perspectiveTransform(uv_a.reshape(-1, 1, 2), G).reshape(-1, 2)
    uv_b, ok = _aligned(warped, b, predicted.astype(np.float32), c)
    size = b.shape[1], b.shape[0]
    margin = c.border_margin_px
    ok &= np.all((uv_b >= margin - 0.5) & (uv_b <= np.array(size) - 0.5 - margin), axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) < MIN_MATCHES:
        raise InputError(f"images: only {len(idx)} corners aligned in the second image")
    threshold = c.ransac_threshold_px if c.ransac_threshold_px is not None else 1.0
    src, dst = _undistorted(camera, uv_a[idx]), _undistorted(camera, uv_b[idx])
    H, inliers = cv2.findHomography(src, dst, cv2.RANSAC, threshold, maxIters=5000)
    if H is None or int(inliers.sum()) < MIN_MATCHES:
        raise InputError("images: the aligned corners agree on no plane")
    keep = idx[inliers.ravel() > 0]
    return PairMatches(uv_a[keep], uv_b[keep].astype(np.float64), H, sift_count)


def _raw_homography(uv_a: np.ndarray, H: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The raw-pixel homography closest to ``H`` (undistorted pixels) over the corners."""
    moved = cv2.perspectiveTransform(_undistorted(camera, uv_a).reshape(-1, 1, 2), H)
    moved = moved.reshape(-1, 2)
    m = np.column_stack(
        ((moved[:, 0] - camera.cx) / camera.fx, (moved[:, 1] - camera.cy) / camera.fy)
    )
    raw = camera.normalized_to_pixel(m)
    G, _ = cv2.findHomography(uv_a, raw, 0)
    return G if G is not None else H


def _aligned(
    warped: np.ndarray, target: np.ndarray, predicted: np.ndarray, c: TrackerConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Lucas-Kanade warped -> target from the prediction, with the forward-backward check."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, c.lk_iterations, c.lk_epsilon)
    window = (c.lk_window, c.lk_window)
    start = predicted.reshape(-1, 1, 2)
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    levels = min(c.lk_levels, 2)  # the prediction is close: a short pyramid suffices
    moved, st, _ = cv2.calcOpticalFlowPyrLK(
        warped, target, start, start.copy(), winSize=window, maxLevel=levels,
        criteria=criteria, flags=flags,
    )  # fmt: skip
    back, st_back, _ = cv2.calcOpticalFlowPyrLK(
        target, warped, moved, moved.copy(), winSize=window, maxLevel=levels,
        criteria=criteria, flags=flags,
    )  # fmt: skip
    moved, back = moved.reshape(-1, 2), back.reshape(-1, 2)
    fb = np.linalg.norm(back - predicted, axis=1)
    ok = (st.ravel() == 1) & (st_back.ravel() == 1) & (fb < c.fb_threshold_px)
    return moved.astype(np.float64), ok & np.all(np.isfinite(moved), axis=1)
