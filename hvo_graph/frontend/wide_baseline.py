"""Coarse plane homographies between two views far apart, and alignment guided by one.

Frame-to-frame KLT follows points only while they move a few pixels; across a
large viewpoint change (two photographs, a jump after a dropped or blurred
stretch) it loses them or locks onto a neighbouring corner. The images path then
takes a coarse plane homography H0 from the first view to the second and aligns
its own corners under it:

- **from features** (:func:`feature_homography`): SIFT keypoints of both images
  (``cv2.SIFT_create``), nearest neighbours with Lowe's ratio test, and a robust
  homography of the dominant plane (``cv2.findHomography`` with
  ``cv2.USAC_MAGSAC``);
- **from a target** (:func:`target_homography`): the corners of a chessboard,
  ChArUco or ArUco board (:mod:`hvo_graph.frontend.target`) found in both images.
  Repetitive patterns defeat descriptors (every inner corner of a chessboard looks
  the same), and a static background seen by both images can be a larger plane
  than the board; the board's own corners name the plane meant;
- **guided alignment** (:func:`guided_alignment`): Lucas-Kanade from the first
  image *warped by H0* (so the patches look as they do in the second view) to the
  second image, started at the prediction H0 m_a and kept when tracking back lands
  within the forward-backward threshold.

SIFT keypoints are only as precise as their scale (on OpenCV's graf1 -> graf3
pair their mean transfer error under the published homography is about 1.7 px);
the aligned corners are sub-pixel (about 0.4 px there), so H0 only starts the
alignment. Everything works in *pinhole* pixels (the image an ideal camera with
the same K would see: :func:`pinhole_image`), where the plane maps by a homography;
:func:`raw_pixels` maps the results back to the camera's distorted pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel

#: Lowe's ratio: a SIFT match is kept when its distance is below this times the second best.
RATIO = 0.8
#: Inlier threshold of the SIFT homography, pixels (the keypoints are coarse).
SIFT_RANSAC_PX = 3.0
#: Fewest consistent matches for a homography.
MIN_MATCHES = 8


def pinhole_image(camera: CameraModel | None, image: np.ndarray) -> np.ndarray:
    """The image as an ideal pinhole camera with the same K would see it (``cv2.undistort``
    or ``cv2.fisheye.undistortImage``); unchanged without a camera or distortion.

    Args:
        image: (H, W) or (H, W, 3) uint8.
    """
    if camera is None or not camera.has_distortion:
        return image
    if camera.is_fisheye:
        return cv2.fisheye.undistortImage(image, camera.K, camera.distortion, Knew=camera.K)
    return cv2.undistort(image, camera.K, camera.distortion)


def pinhole_pixels(camera: CameraModel | None, uv: np.ndarray) -> np.ndarray:
    """(N, 2) raw pixels -> pixels of the ideal pinhole camera with the same K."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if camera is None or not camera.has_distortion:
        return uv
    return (camera.pixel_to_normalized(uv) @ camera.K.T)[:, :2]


def raw_pixels(camera: CameraModel | None, uv: np.ndarray) -> np.ndarray:
    """(N, 2) pinhole pixels -> the camera's raw (distorted) pixels."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if camera is None or not camera.has_distortion:
        return uv
    m = np.column_stack(((uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy))
    return camera.normalized_to_pixel(m)


def feature_homography(image_a: np.ndarray, image_b: np.ndarray) -> tuple[np.ndarray, int]:
    """The dominant plane's homography a -> b from SIFT matches (ratio test, MAGSAC).

    Args:
        image_a, image_b: (H, W) uint8 gray images (pinhole pixels when the camera has
            distortion).
    Returns:
        (3, 3) H0 with m_b ~ H0 m_a, and the number of matches consistent with it.
    Raises:
        InputError: too little texture, or fewer than ``MIN_MATCHES`` consistent matches.
    """
    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(image_a, None)
    kb, db = sift.detectAndCompute(image_b, None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        raise InputError("images: too little texture for a wide-baseline match")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    if len(good) < MIN_MATCHES:
        raise InputError(f"images: only {len(good)} distinctive matches between the two images")
    pa = np.array([ka[m.queryIdx].pt for m in good])
    pb = np.array([kb[m.trainIdx].pt for m in good])
    H, inliers = cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, SIFT_RANSAC_PX)
    count = 0 if inliers is None else int(inliers.sum())
    if H is None or count < MIN_MATCHES:
        raise InputError(f"images: only {count} matches agree on one plane")
    return H, count


def target_homography(
    found_a: tuple[np.ndarray, np.ndarray],
    found_b: tuple[np.ndarray, np.ndarray],
    camera: CameraModel | None = None,
) -> np.ndarray | None:
    """The board's homography a -> b (pinhole pixels) from its corners in both images.

    Args:
        found_a, found_b: :func:`~hvo_graph.frontend.target.detect_target` results,
            (N, 2) raw pixels and (N, 3) board points; corners are paired by their
            board point (ChArUco / ArUco boards may show different subsets).
        camera: the camera (distortion), or None for raw pixels.
    Returns:
        (3, 3) H0, or None when fewer than 4 corners are common to both.
    """
    (uv_a, xyz_a), (uv_b, xyz_b) = found_a, found_b
    index_b = {tuple(np.round(p, 9)): i for i, p in enumerate(np.asarray(xyz_b))}
    pairs = [(i, index_b[key]) for i, p in enumerate(np.asarray(xyz_a))
             if (key := tuple(np.round(p, 9))) in index_b]  # fmt: skip
    if len(pairs) < 4:
        return None
    ia, ib = (np.array(x) for x in zip(*pairs, strict=True))
    H, _ = cv2.findHomography(pinhole_pixels(camera, uv_a[ia]), pinhole_pixels(camera, uv_b[ib]))
    return H


def target_outline(
    found: tuple[np.ndarray, np.ndarray],
    margin: float,
    camera: CameraModel | None = None,
    samples: int = 16,
) -> np.ndarray | None:
    """The board's outline in the image: the bounding box of its detected board points,
    widened by ``margin`` (metres on the board), mapped by the board's homography.

    Args:
        found: (N, 2) raw pixels and (N, 3) board points (z = 0).
        margin: metres added on each side (e.g. one square: the chessboard's inner
            corners leave out its outer row of squares).
        camera: the camera (distortion: the outline's sides are sampled and bent).
        samples: points per side.
    Returns:
        (4 * samples, 2) raw pixels of the polygon, or None with fewer than 4 corners.
    """
    uv, xyz = found
    if len(uv) < 4:
        return None
    xy = np.asarray(xyz, dtype=np.float64)[:, :2]
    H, _ = cv2.findHomography(xy, pinhole_pixels(camera, uv))
    if H is None:
        return None
    (x0, y0), (x1, y1) = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    s = np.linspace(0.0, 1.0, samples, endpoint=False)
    sides = [
        np.column_stack((x0 + (x1 - x0) * s, np.full_like(s, y0))),
        np.column_stack((np.full_like(s, x1), y0 + (y1 - y0) * s)),
        np.column_stack((x1 - (x1 - x0) * s, np.full_like(s, y1))),
        np.column_stack((np.full_like(s, x0), y1 - (y1 - y0) * s)),
    ]
    outline = cv2.perspectiveTransform(np.vstack(sides).reshape(-1, 1, 2), H).reshape(-1, 2)
    return raw_pixels(camera, outline)


def guided_alignment(
    image_a: np.ndarray,
    image_b: np.ndarray,
    points_a: np.ndarray,
    homography: np.ndarray,
    *,
    window: int = 21,
    levels: int = 2,
    iterations: int = 30,
    epsilon: float = 0.01,
    fb_threshold_px: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Points of image a found in image b, starting from a coarse plane homography.

    Args:
        image_a, image_b: (H, W) uint8 gray, pinhole pixels (sizes may differ).
        points_a: (N, 2) pinhole pixels in image a.
        homography: (3, 3) H0, a -> b.
        window, levels, iterations, epsilon: Lucas-Kanade settings (a short pyramid
            suffices: the prediction is close).
        fb_threshold_px: largest forward-backward error of a kept point, pixels.
    Returns:
        (N, 2) pinhole pixels in image b and (N,) success (LK converged both ways,
        forward-backward check passed).
    """
    H0 = np.asarray(homography, dtype=np.float64).reshape(3, 3)
    size = (image_b.shape[1], image_b.shape[0])
    # Replicated borders: a black frame would be an edge that pulls the LK windows.
    warped = cv2.warpPerspective(
        image_a, H0, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    points = np.asarray(points_a, dtype=np.float64).reshape(-1, 1, 2)
    predicted = cv2.perspectiveTransform(points, H0).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, epsilon)
    common = {"winSize": (window, window), "maxLevel": levels, "criteria": criteria,
              "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}  # fmt: skip
    moved, st, _ = cv2.calcOpticalFlowPyrLK(warped, image_b, predicted, predicted.copy(), **common)
    back, st_back, _ = cv2.calcOpticalFlowPyrLK(image_b, warped, moved, moved.copy(), **common)
    moved, back = moved.reshape(-1, 2), back.reshape(-1, 2)
    fb = np.linalg.norm(back - predicted.reshape(-1, 2), axis=1)
    ok = (st.ravel() == 1) & (st_back.ravel() == 1) & (fb < fb_threshold_px)
    return moved.astype(np.float64), ok & np.all(np.isfinite(moved), axis=1)
