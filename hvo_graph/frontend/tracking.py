"""Image front end: image sequences -> feature tracks (the contract's tracks form).

Images come from arrays or from disk (:func:`hvo_graph.io.sequences.open_recording`
reads image folders, videos, TUM RGB-D, EuRoC and ROS bags).

The paper's future work (NOTES section 7) is running on real images with fast
feature detection and tracking. This module does that with OpenCV's KLT
tracker:

- **detection**: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``), away from
  the image border and from existing tracks;
- **tracking**: pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) from
  frame k-1 to frame k, kept only when tracking the result back to frame k-1
  lands within ``fb_threshold_px`` of the start (forward-backward check);
- **plane consistency**: a RANSAC homography between consecutive frames
  (``cv2.findHomography``), in undistorted pixels, drops tracks that do not
  move with the dominant plane (m_k ~ H m_{k-1} holds for plane points only);
- **re-alignment** (``refine_max_px``): each track is aligned once more
  against the image where it was first seen, warped into the current view by
  the plane homography. Frame-to-frame KLT drifts (its translation-only
  window is biased by the perspective deformation of the patch, and the bias
  adds up); the re-aligned track does not. On the rendered test sequence
  (320x240, 60 frames) this takes the median error of the tracks from
  ~0.2 px (growing to ~0.9 px after 40 frames) to ~0.01 px at any age;
- **replenishment**: when fewer than ``min_tracked`` tracks remain, new
  corners get new ids, so an id always names one physical point and a lost
  id never comes back.

Tracks are raw (distorted) pixels, as in tracks.csv: undistortion belongs to
the measurement front end (:mod:`hvo_graph.frontend.measure`), which turns these
tracks into pose (H_d) and velocity (H_c) measurements::

    from hvo_graph.frontend import measure_sequence, tracks_from_images

    tracks = tracks_from_images("images/", camera)
    frames = measure_sequence(tracks, camera, plane)

Poses come from H_d between each frame and its reference: the first frame,
or a later keyframe once the first frame's points have left the view
(``FrontEndConfig.keyframe_min_points``); replenished points become usable
for poses as soon as a keyframe that sees them is taken, and for the velocity
(H_c, consecutive frames) at once.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from hvo_graph.errors import InputError, as_integer, as_number
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import as_gray_image
from hvo_graph.io.sequences import open_recording
from hvo_graph.types import FrameObservations

#: Fewest tracks of one first-sight frame to fit their own re-alignment homography.
_MIN_GROUP_FIT = 8


@dataclass(frozen=True)
class TrackerConfig:
    """KLT tracker settings.

    Attributes:
        max_features: most tracks alive at once.
        quality_level: Shi-Tomasi threshold relative to the strongest corner
            (``cv2.goodFeaturesToTrack``'s qualityLevel).
        min_distance: smallest distance between a new corner and any other
            corner or live track, pixels.
        block_size: corner detection window, pixels.
        lk_window: side of the Lucas-Kanade window, pixels.
        lk_levels: pyramid levels above the full image (0: no pyramid).
        lk_iterations: most Lucas-Kanade iterations per level.
        lk_epsilon: Lucas-Kanade convergence threshold, pixels.
        fb_threshold_px: largest forward-backward error of a kept track, pixels.
        min_tracked: detect new corners when fewer tracks remain (0: detect in
            the first frame only).
        ransac_threshold_px: inlier threshold of the frame-to-frame homography
            RANSAC, undistorted pixels; None keeps every tracked point.
        border_margin_px: tracks closer than this to the border are dropped and
            no corner is detected there, pixels.
        refine_max_px: re-align every track against the image where it was
            first seen, warped by the plane homography (stops the drift of
            frame-to-frame KLT); tracks the re-alignment moves by more than
            this many pixels are dropped. None: plain frame-to-frame KLT.
    """

    max_features: int = 200
    quality_level: float = 0.01
    min_distance: float = 10.0
    block_size: int = 7
    lk_window: int = 21
    lk_levels: int = 3
    lk_iterations: int = 30
    lk_epsilon: float = 0.01
    fb_threshold_px: float = 0.5
    min_tracked: int = 100
    ransac_threshold_px: float | None = 1.0
    border_margin_px: float = 8.0
    refine_max_px: float | None = 1.0

    def __post_init__(self) -> None:
        for name, minimum in (
            ("max_features", 1),
            ("block_size", 3),
            ("lk_window", 3),
            ("lk_levels", 0),
            ("lk_iterations", 1),
            ("min_tracked", 0),
        ):
            as_integer(getattr(self, name), name, minimum)
        if self.min_tracked > self.max_features:
            raise InputError(
                f"min_tracked: expected at most max_features ({self.max_features}), "
                f"got {self.min_tracked}"
            )
        if not 0 < self.quality_level < 1:
            raise InputError(
                f"quality_level: expected a number in (0, 1), got {self.quality_level}"
            )
        for name in ("lk_epsilon", "fb_threshold_px"):
            as_number(getattr(self, name), name, above=0.0)
        for name in ("min_distance", "border_margin_px"):
            as_number(getattr(self, name), name, at_least=0.0)
        for name in ("ransac_threshold_px", "refine_max_px"):
            if getattr(self, name) is not None:
                as_number(getattr(self, name), name, above=0.0)


class FeatureTracker:
    """Streaming KLT tracker: one :meth:`process` call per image, in time order.

    Attributes:
        camera: the camera (image size; distortion for the RANSAC check).
        config: tracker settings.
    """

    def __init__(self, camera: CameraModel, config: TrackerConfig | None = None):
        self.camera = camera
        self.config = config or TrackerConfig()
        self._index = 0
        self._t: float | None = None
        self._image: np.ndarray | None = None
        # Live tracks: position in the last image, id, frame of first sight, position there.
        self._points = np.empty((0, 2), dtype=np.float32)
        self._ids = np.empty(0, dtype=np.int64)
        self._birth = np.empty(0, dtype=np.int64)
        self._birth_uv = np.empty((0, 2), dtype=np.float32)
        self._birth_images: dict[int, np.ndarray] = {}
        # Per first-sight frame b: homography from image b to the last image (raw pixels).
        self._warps: dict[int, np.ndarray] = {}
        self._next_id = 0
        c = self.config
        self._criteria = (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
            c.lk_iterations,
            c.lk_epsilon,
        )
        self._window = (c.lk_window, c.lk_window)

    def process(self, image: np.ndarray, t: float, name: str = "image") -> FrameObservations:
        """Track into one more image.

        Args:
            image: (H, W) gray or (H, W, 3) BGR / (H, W, 4) BGRA, uint8 or
                uint16, of the camera's size.
            t: time, seconds, greater than the previous image's.
            name: how error messages refer to the image (e.g. its file name).
        Returns:
            The frame's tracks: ids (N,) and raw pixel positions uv (N, 2).
        """
        gray = as_gray_image(image, name, self.camera)
        if not np.isfinite(t):
            raise InputError(f"{name}: expected a finite time, got {t}")
        if self._t is not None and not t > self._t:
            raise InputError(f"{name}: time {t} does not increase (previous {self._t})")
        if self._image is not None and len(self._points):
            keep, points = self._track(self._image, gray, self._points)
            if self.config.refine_max_px is not None:
                keep, points = self._realign(gray, keep, self._points, points)
            self._select(keep)
            self._points = points[keep]
        if len(self._points) < self.config.min_tracked or self._image is None:
            self._replenish(gray)
        # Keep first images only while a track born there lives (for re-alignment).
        alive = [int(b) for b in np.unique(self._birth)]
        self._birth_images = {b: self._birth_images[b] for b in alive}
        self._warps = {b: self._warps[b] for b in alive}
        obs = FrameObservations(
            index=self._index,
            t=float(t),
            ids=self._ids.copy(),
            uv=self._points.astype(float).reshape(-1, 2),
        )
        self._image, self._t = gray, float(t)
        self._index += 1
        return obs

    def _select(self, keep: np.ndarray) -> None:
        self._ids, self._birth, self._birth_uv = (
            self._ids[keep],
            self._birth[keep],
            self._birth_uv[keep],
        )

    def _lk(
        self,
        source: np.ndarray,
        target: np.ndarray,
        points: np.ndarray,
        guess: np.ndarray | None = None,
        levels: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pyramidal Lucas-Kanade: (N, 2) positions in ``target`` and (N,) success."""
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW if guess is not None else 0
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            source,
            target,
            points.reshape(-1, 1, 2).astype(np.float32),
            None if guess is None else guess.reshape(-1, 1, 2).astype(np.float32).copy(),
            winSize=self._window,
            maxLevel=self.config.lk_levels if levels is None else levels,
            criteria=self._criteria,
            flags=flags,
        )
        moved = moved.reshape(-1, 2)
        return moved, (status.ravel() == 1) & np.all(np.isfinite(moved), axis=1)

    def _track(
        self, previous: np.ndarray, current: np.ndarray, p0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Frame-to-frame KLT with the forward-backward, border and RANSAC checks.

        Returns:
            (N,) keep mask and (N, 2) positions in ``current`` of the points p0.
        """
        c = self.config
        p1, ok = self._lk(previous, current, p0)
        back, ok_back = self._lk(current, previous, p1)
        fb_error = np.linalg.norm(back - p0, axis=1)
        keep = ok & ok_back & (fb_error < c.fb_threshold_px)
        keep &= self.camera.in_view(np.where(ok[:, None], p1, -1e9), margin=c.border_margin_px)
        if c.ransac_threshold_px is not None and np.count_nonzero(keep) >= 4:
            idx = np.flatnonzero(keep)
            src = _undistorted_pixels(self.camera, p0[idx])
            dst = _undistorted_pixels(self.camera, p1[idx])
            H, inliers = cv2.findHomography(
                src, dst, cv2.RANSAC, c.ransac_threshold_px, maxIters=2000, confidence=0.999
            )
            if H is not None:  # None: degenerate configuration, nothing to judge against
                keep[idx[inliers.ravel() == 0]] = False
        return keep, p1.astype(np.float32)

    def _realign(
        self, current: np.ndarray, keep: np.ndarray, p0: np.ndarray, p1: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Re-align each track against the image where it was first seen.

        Frame-to-frame KLT drifts: its translation-only window is biased by the
        patch's perspective deformation, and the bias adds up frame after
        frame. For the tracks first seen in frame b, the plane homography G
        from image b to the current image warps image b into the current view,
        where the first patches look as they should now; LK from the warped
        image b at G(p_b) to the current image, started at the frame-to-frame
        result, then finds the points p_b themselves, without accumulated
        drift. G is the least-squares fit to the group's first and current
        positions when the group has enough points to pin it down, else the
        previous G chained with the frame-to-frame homography of all tracks.
        Only G's local shape matters (the warp makes the patches look right);
        its errors do not move the points. Tracks moved by more than
        ``refine_max_px`` are dropped (frame-to-frame and direct tracking
        disagree).
        """
        c = self.config
        assert c.refine_max_px is not None
        size = (self.camera.width, self.camera.height)
        p1 = p1.copy()
        step = None
        if np.count_nonzero(keep) >= 4:
            step, _ = cv2.findHomography(p0[keep], p1[keep], 0)
        for b in np.unique(self._birth[keep]).tolist():
            idx = np.flatnonzero(keep & (self._birth == b))
            first = self._birth_uv[idx]
            G = None
            if len(idx) >= _MIN_GROUP_FIT:
                G, _ = cv2.findHomography(first, p1[idx], 0)
            if G is None and step is not None:
                G = step @ self._warps[b]
            if G is None:
                continue  # nothing to warp with: keep the frame-to-frame result
            self._warps[b] = G
            # Replicated borders: a black frame would be an edge that pulls the LK windows.
            warped = cv2.warpPerspective(
                self._birth_images[int(b)],
                G,
                size,
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            predicted = cv2.perspectiveTransform(first.reshape(-1, 1, 2), G).reshape(-1, 2)
            # No pyramid: the frame-to-frame result is within a fraction of a pixel.
            aligned, ok = self._lk(warped, current, predicted, guess=p1[idx], levels=0)
            shift = np.linalg.norm(aligned - p1[idx], axis=1)
            ok &= shift < c.refine_max_px
            ok &= self.camera.in_view(
                np.where(ok[:, None], aligned, -1e9), margin=c.border_margin_px
            )
            p1[idx[ok]] = aligned[ok]
            keep[idx[~ok]] = False
        return keep, p1

    def _replenish(self, gray: np.ndarray) -> None:
        c = self.config
        wanted = c.max_features - len(self._points)
        if wanted <= 0:
            return
        mask = np.zeros(gray.shape, dtype=np.uint8)
        m = int(np.ceil(c.border_margin_px))
        mask[m : gray.shape[0] - m, m : gray.shape[1] - m] = 255
        radius = round(c.min_distance)
        for u, v in np.rint(self._points).astype(int):
            cv2.circle(mask, (int(u), int(v)), radius, 0, thickness=-1)
        corners = cv2.goodFeaturesToTrack(
            gray,
            maxCorners=wanted,
            qualityLevel=c.quality_level,
            minDistance=max(c.min_distance, 1.0),
            mask=mask,
            blockSize=c.block_size,
        )
        if corners is None:
            return
        corners = corners.reshape(-1, 2).astype(np.float32)
        new_ids = np.arange(self._next_id, self._next_id + len(corners), dtype=np.int64)
        self._next_id += len(corners)
        self._points = np.vstack((self._points, corners))
        self._ids = np.concatenate((self._ids, new_ids))
        self._birth = np.concatenate((self._birth, np.full(len(corners), self._index)))
        self._birth_uv = np.vstack((self._birth_uv, corners))
        self._birth_images[self._index] = gray
        self._warps[self._index] = np.eye(3)


def _undistorted_pixels(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of an ideal pinhole camera with the same K, where plane points map by a
    homography (they do not in distorted pixels)."""
    if not camera.has_distortion:
        return np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    m = camera.pixel_to_normalized(np.asarray(uv, dtype=float))
    return (m @ camera.K.T)[:, :2]


def track_images(
    images: Iterable[np.ndarray],
    times: Sequence[float],
    camera: CameraModel,
    config: TrackerConfig | None = None,
) -> list[FrameObservations]:
    """Track features through an image sequence.

    Args:
        images: K images in time order, (H, W) gray or (H, W, 3) BGR, uint8 or
            uint16, each camera.width x camera.height; any iterable (an
            :class:`~hvo_graph.io.images.ImageSequence` reads files lazily).
        times: (K,) timestamps, seconds, strictly increasing.
        camera: the calibrated camera.
        config: tracker settings.
    Returns:
        K :class:`FrameObservations` (index k, t = times[k], ids, raw pixel uv),
        ready for :func:`hvo_graph.frontend.measure_sequence` or a tracks CSV.
    """
    try:
        t = np.asarray(times, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError("times: expected a sequence of numbers (seconds)") from None
    for k in range(len(t)):
        if not np.isfinite(t[k]):
            raise InputError(f"times[{k}]: expected a finite number, got {t[k]}")
        if k and not t[k] > t[k - 1]:
            raise InputError(f"times[{k}]: {t[k]} does not increase (previous {t[k - 1]})")
    names = getattr(images, "names", None)
    tracker = FeatureTracker(camera, config)
    out = []
    for k, image in enumerate(images):
        if k >= len(t):
            raise InputError(f"images: more images than times ({len(t)})")
        name = names[k] if names is not None else f"images[{k}]"
        out.append(tracker.process(image, float(t[k]), name))
    if len(out) != len(t):
        raise InputError(f"images: {len(out)} images for {len(t)} times")
    return out


def tracks_from_images(
    path: str | Path,
    camera: CameraModel | None,
    *,
    fps: float | None = None,
    config: TrackerConfig | None = None,
    topic: str | None = None,
) -> list[FrameObservations]:
    """Feature tracks of a recorded sequence: :func:`~hvo_graph.io.sequences.open_recording`
    (image folder, video, TUM RGB-D, EuRoC, ROS bag) then :func:`track_images`.

    Args:
        path: what ``open_recording`` reads.
        camera: the calibrated camera (images must be its size); None takes the
            camera stored with the data (EuRoC sensor.yaml, a bag's CameraInfo).
        fps: frame rate of an image folder without times.txt (required there),
            or replacing a video's container timestamps.
        config: tracker settings.
        topic: the image topic of a bag with several.
    Returns:
        One :class:`FrameObservations` per image, raw pixels.
    """
    recording = open_recording(path, fps=fps, topic=topic, camera=camera)
    camera = camera if camera is not None else recording.camera
    if camera is None:
        raise InputError(f"camera: {path} carries no calibration; pass the camera")
    return track_images(recording.frames, recording.times, camera, config)
