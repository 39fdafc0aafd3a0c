"""Image front end: image sequences -> feature tracks (the contract's tracks form).

Images come from arrays or from disk (:func:`hvo_graph.io.sequences.open_recording`
reads image folders, videos, TUM RGB-D, EuRoC and ROS bags).

The paper's future work (NOTES section 7): real images, with OpenCV's KLT tracker:

- **detection**: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``), away from
  the image border and from existing tracks (with a target: on the board only);
- **tracking**: pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) from
  frame k-1 to frame k with a forward-backward check (``fb_threshold_px``),
  started where the last step's plane motion moves each point;
- **wide baseline** (``wide_baseline``, or a target seen in both frames): a
  coarse plane homography guides the alignment when KLT cannot follow
  (:mod:`hvo_graph.frontend.wide_baseline`);
- **plane consistency**: a RANSAC homography between consecutive frames, in
  undistorted pixels, drops tracks that do not move with the dominant plane;
- **re-alignment** (``refine_max_px``): each track is aligned once more
  against the image where it was first seen, warped into the current view by
  the plane homography, so frame-to-frame drift does not add up (on the
  rendered test sequence, 320x240, 60 frames: median error ~0.01 px at any age
  instead of ~0.2 px growing to ~0.9 px);
- **replenishment**: when fewer than ``min_tracked`` tracks remain, new
  corners get new ids, so an id always names one physical point;
- **re-identification** (``reidentify_frames``): tracks lost together are
  looked for again and resume under their old ids
  (:mod:`hvo_graph.frontend.reidentify`).

Tracks are raw (distorted) pixels, as in tracks.csv: undistortion belongs to
the measurement front end (:mod:`hvo_graph.frontend.measure`), which turns these
tracks into pose (H_d) and velocity (H_c) measurements::

    from hvo_graph.frontend import measure_sequence, tracks_from_images

    tracks = tracks_from_images("images/", camera)
    frames = measure_sequence(tracks, camera, plane)

Poses come from H_d between each frame and its reference (the first frame, or
a keyframe once its points have left the view: ``FrontEndConfig.keyframe_min_points``);
replenished points serve poses once a keyframe sees them, velocities (H_c) at once.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.frontend._klt import (
    align_to_first_sight,
    forward_backward,
    plane_check,
    predict,
    prediction_miss,
)
from hvo_graph.frontend.exposure import ExposureCompensation
from hvo_graph.frontend.reidentify import LostTracks, find_again
from hvo_graph.frontend.target import TargetSpec, board_margin, detect_target
from hvo_graph.frontend.tracker_config import WIDE_BASELINE_FRACTION, TrackerConfig
from hvo_graph.frontend.wide_baseline import (
    MIN_MATCHES,
    feature_homography,
    guided_alignment,
    pinhole_image,
    pinhole_pixels,
    raw_pixels,
    target_homography,
    target_outline,
)
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import as_gray_image
from hvo_graph.io.sequences import open_recording
from hvo_graph.types import FrameObservations

#: Fewest tracks of one first-sight frame to fit their own re-alignment homography.
_MIN_GROUP_FIT = 8


class FeatureTracker:
    """Streaming KLT tracker: one :meth:`process` call per image, in time order.

    With a ``target`` (the chessboard, ChArUco or ArUco board that defines the
    plane, e.g. the one ``--plane auto`` measures n*, d* on) the board is looked
    for in every image: new corners only inside its outline (widened by one square;
    none where it is not found), so a static background never competes with it, and
    when it is seen in two consecutive images the homography of its corners guides
    the alignment of every track (a start that cannot slip by a square, however far
    the views are apart). The tracks remain the tracker's own Shi-Tomasi corners
    aligned by Lucas-Kanade.

    Attributes:
        camera: the camera (image size; distortion for the RANSAC check).
        config: tracker settings.
        target: the board that defines the plane, or None.
    """

    def __init__(
        self,
        camera: CameraModel,
        config: TrackerConfig | None = None,
        target: TargetSpec | None = None,
    ):
        self.camera = camera
        self.config = config or TrackerConfig()
        self.target = target
        # The pinhole <-> raw pixel maps' camera; None without distortion (no per-call check).
        self._lens = camera if camera.has_distortion else None
        # The target's corners in the last image (raw pixels, board points), or None.
        self._found: tuple[np.ndarray, np.ndarray] | None = None
        self._index = 0
        self._t: float | None = None
        self._image: np.ndarray | None = None
        self._pinhole: np.ndarray | None = None  # the last image undistorted
        self._lost: LostTracks | None = None  # tracks lost together, still looked for
        # Live tracks: position in the last image (raw pixels), id, frame of first sight,
        # position there (pinhole pixels).
        self._points = np.empty((0, 2), dtype=np.float32)
        self._ids = np.empty(0, dtype=np.int64)
        self._birth = np.empty(0, dtype=np.int64)
        self._birth_uv = np.empty((0, 2), dtype=np.float32)
        self._birth_images: dict[int, np.ndarray] = {}
        # Per first-sight frame b: the homography from image b to the last (pinhole pixels).
        self._warps: dict[int, np.ndarray] = {}
        self._next_id = 0
        self._exposure = ExposureCompensation() if self.config.compensate_exposure else None
        # The last frame-to-frame plane homography of plain KLT (pinhole pixels) and the
        # largest distance between a kept track and its prediction; (None, nan): none.
        self._motion: tuple[np.ndarray | None, float] = (None, np.nan)
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
        found = detect_target(gray, self.target) if self.target is not None else None
        gray = self._exposure(gray) if self._exposure is not None else gray
        pinhole = pinhole_image(self._lens, gray)
        motion, self._motion = self._motion, (None, np.nan)  # set again by plain KLT
        if self._image is not None and len(self._points):
            keep, points = self._follow(gray, pinhole, self._points, found, motion)
            if self.config.refine_max_px is not None:
                keep, points = self._realign(pinhole, keep, self._points, points)
            self._remember(keep)
            self._select(keep)
            self._points = points[keep]
        if self._lost is not None:
            self._reidentify(pinhole, found)
        if len(self._points) < self.config.min_tracked or self._image is None:
            self._replenish(gray, pinhole, found)
        self._found, self._pinhole = found, pinhole
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

    def _remember(self, keep: np.ndarray) -> None:
        """Keep the tracks this frame lost, when it lost most of them at once."""
        lost, frames = ~keep, self.config.reidentify_frames
        n = np.count_nonzero(lost)  # a loss: more than half the tracks, at least 8, at once
        if not frames or n < MIN_MATCHES or n <= (1.0 - WIDE_BASELINE_FRACTION) * len(keep):
            return
        old = self._lost  # a larger loss still looked for is not replaced by a smaller one
        if old is not None and self._index - old.index <= frames and len(old.ids) > n:
            return
        births = [int(b) for b in np.unique(self._birth[lost])]
        assert self._pinhole is not None  # set by the previous frame
        self._lost = LostTracks(
            self._index - 1, self._pinhole, self._found, self._ids[lost],
            pinhole_pixels(self._lens, self._points[lost]), self._birth[lost],
            self._birth_uv[lost], {b: self._birth_images[b] for b in births},
            {b: self._warps[b] for b in births},
        )  # fmt: skip

    def _reidentify(self, pinhole: np.ndarray, found: tuple[np.ndarray, np.ndarray] | None):
        """Resume the lost tracks found in this image under their old ids."""
        lost = self._lost
        assert lost is not None  # the caller checks
        if self._index - lost.index > self.config.reidentify_frames:
            self._lost = None
            return
        if lost.index == self._index - 1 and self.config.wide_baseline:
            return  # the wide-baseline step has just tried this very pair
        result = find_again(lost, pinhole, found, self.camera, self.config)
        if result is None:
            return
        ok, uv, H0 = result
        self._lost = None
        self._points = np.vstack((self._points, uv[ok].astype(np.float32)))
        self._ids = np.concatenate((self._ids, lost.ids[ok]))
        self._birth = np.concatenate((self._birth, lost.birth[ok]))
        self._birth_uv = np.vstack((self._birth_uv, lost.birth_uv[ok]))
        for b in np.unique(lost.birth[ok]).tolist():
            self._birth_images.setdefault(b, lost.birth_images[b])
            self._warps.setdefault(b, H0 @ lost.warps[b])

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
            None if guess is None else guess.reshape(-1, 1, 2).astype(np.float32),
            winSize=self._window,
            maxLevel=self.config.lk_levels if levels is None else levels,
            criteria=self._criteria,
            flags=flags,
        )
        moved = moved.reshape(-1, 2)
        return moved, (status.ravel() == 1) & np.all(np.isfinite(moved), axis=1)

    def _follow(
        self,
        current: np.ndarray,
        pinhole: np.ndarray,
        p0: np.ndarray,
        found: tuple[np.ndarray, np.ndarray] | None,
        motion: tuple[np.ndarray | None, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        """The tracks p0 of the last image in ``current`` (``pinhole``: undistorted):
        guided by the target's homography when the target is seen in both images, else
        frame-to-frame KLT, and a SIFT homography (``wide_baseline``) when KLT loses
        most of them.

        Returns:
            (N,) keep mask and (N, 2) raw pixel positions in ``current``.
        """
        assert self._image is not None and self._pinhole is not None
        if found is not None and self._found is not None:
            H0 = target_homography(self._found, found, self.camera)
            if H0 is not None:
                return self._track_guided(self._pinhole, pinhole, p0, H0)
        keep, p1 = self._track(self._image, current, p0, motion)
        if not self.config.wide_baseline:
            return keep, p1
        if np.count_nonzero(keep) >= WIDE_BASELINE_FRACTION * len(p0):
            return keep, p1
        try:
            H0, _ = feature_homography(self._pinhole, pinhole)
        except InputError:  # too little texture or agreement: keep what KLT kept
            return keep, p1
        keep_g, p1_g = self._track_guided(self._pinhole, pinhole, p0, H0)
        if np.count_nonzero(keep_g) > np.count_nonzero(keep):
            self._motion = (None, np.nan)  # not plain KLT's step
            return keep_g, p1_g
        return keep, p1

    def _track(
        self,
        previous: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray,
        motion: tuple[np.ndarray | None, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Frame-to-frame KLT with the forward-backward, border and RANSAC checks; the
        forward search starts where the last frame's plane motion moves each point.

        Returns:
            (N,) keep mask and (N, 2) positions in ``current`` of the points p0.
        """
        c, to_pinhole = self.config, partial(pinhole_pixels, self._lens)
        guess, levels = predict(p0, motion, self._lens, c)
        in_view = partial(self.camera.in_view, margin=c.border_margin_px)
        p1, keep = forward_backward(self._lk, previous, current, p0, c, in_view, guess, levels)
        H = plane_check(p0, p1, keep, c.ransac_threshold_px, to_pinhole)
        self._motion = (None, np.nan) if H is None else (H, prediction_miss(p1, guess, keep))
        return keep, p1.astype(np.float32)

    def _track_guided(
        self, previous: np.ndarray, current: np.ndarray, p0: np.ndarray, H0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The tracks aligned from ``previous`` warped by the coarse homography H0
        (undistorted images and pinhole pixels, previous -> current), with the border and
        RANSAC checks."""
        c = self.config
        q1, ok = guided_alignment(
            previous,
            current,
            pinhole_pixels(self._lens, p0),
            H0,
            window=c.lk_window,
            levels=min(c.lk_levels, 2),
            iterations=c.lk_iterations,
            epsilon=c.lk_epsilon,
            fb_threshold_px=c.fb_threshold_px,
        )
        p1 = np.full_like(q1, -1e9)
        p1[ok] = raw_pixels(self._lens, q1[ok])
        keep = ok & self.camera.in_view(p1, margin=c.border_margin_px)
        plane_check(p0, p1, keep, c.ransac_threshold_px, partial(pinhole_pixels, self._lens))
        return keep, p1.astype(np.float32)

    def _realign(
        self, current: np.ndarray, keep: np.ndarray, p0: np.ndarray, p1: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Re-align each track against the image where it was first seen (frame-to-frame
        KLT's window is biased by the patch's perspective deformation, and the bias adds up).

        For the tracks first seen in frame b, the plane homography G from image b
        to the current one (undistorted) warps image b into the current view; LK from
        it at G(p_b), started at the frame-to-frame result, finds the points p_b
        themselves. G is the fit to the group's first and current positions (enough
        points), else the previous G chained with all tracks' frame-to-frame
        homography; only its local shape matters. Tracks moved by more than
        ``refine_max_px`` are dropped."""
        c = self.config
        assert c.refine_max_px is not None
        p1 = p1.copy()
        # In pinhole pixels (the undistorted images), where the plane maps by a homography.
        q0 = np.zeros((len(p0), 2))
        q1 = np.zeros((len(p1), 2))
        q0[keep], q1[keep] = (pinhole_pixels(self._lens, p[keep]) for p in (p0, p1))
        kept = keep.copy()  # keep loses the groups' failures below; step uses all tracks
        step: np.ndarray | None = None  # all tracks' frame-to-frame homography, when needed
        for b in np.unique(self._birth[keep]).tolist():
            idx = np.flatnonzero(keep & (self._birth == b))
            first = self._birth_uv[idx].astype(np.float64)
            G = None
            if len(idx) >= _MIN_GROUP_FIT:
                G, _ = cv2.findHomography(first, q1[idx], 0)
            if G is None and step is None and np.count_nonzero(kept) >= 4:
                step, _ = cv2.findHomography(q0[kept], q1[kept], 0)
            if G is None and step is not None:
                G = step @ self._warps[b]
            if G is None:
                continue  # nothing to warp with: keep the frame-to-frame result
            self._warps[b] = G
            aligned, ok = align_to_first_sight(
                self._birth_images[int(b)], current, G, first, q1[idx], c, self._lk
            )
            moved = np.full_like(aligned, -1e9)
            moved[ok] = raw_pixels(self._lens, aligned[ok])
            ok &= self.camera.in_view(moved, margin=c.border_margin_px)
            p1[idx[ok]] = moved[ok]
            keep[idx[~ok]] = False
        return keep, p1

    def _replenish(
        self, gray: np.ndarray, pinhole: np.ndarray, found: tuple[np.ndarray, np.ndarray] | None
    ) -> None:
        c = self.config
        wanted = c.max_features - len(self._points)
        if wanted <= 0:
            return
        mask = np.zeros(gray.shape, dtype=np.uint8)
        m = int(np.ceil(c.border_margin_px))
        mask[m : gray.shape[0] - m, m : gray.shape[1] - m] = 255
        if self.target is not None:
            # Only the board is the plane: no corners where it is not seen.
            outline = (
                None
                if found is None
                else target_outline(found, board_margin(self.target), self.camera)
            )
            if outline is None:
                return
            board = np.zeros_like(mask)
            cv2.fillPoly(board, [np.rint(outline).astype(np.int32)], 255)
            mask &= board
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
        self._birth_uv = np.vstack((self._birth_uv, pinhole_pixels(self._lens, corners)))
        self._birth_images[self._index] = pinhole
        self._warps[self._index] = np.eye(3)


def track_images(
    images: Iterable[np.ndarray],
    times: Sequence[float],
    camera: CameraModel,
    config: TrackerConfig | None = None,
    target: TargetSpec | None = None,
) -> list[FrameObservations]:
    """Track features through an image sequence.

    Args:
        images: K images in time order, (H, W) gray or (H, W, 3) BGR, uint8 or
            uint16, each camera.width x camera.height; any iterable (an
            :class:`~hvo_graph.io.images.ImageSequence` reads files lazily).
        times: (K,) timestamps, seconds, strictly increasing.
        camera: the calibrated camera.
        config: tracker settings.
        target: the board that defines the plane (:class:`FeatureTracker`), or None.
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
    tracker = FeatureTracker(camera, config, target)
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
    target: TargetSpec | None = None,
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
        target: the board that defines the plane (:class:`FeatureTracker`), or None.
    Returns:
        One :class:`FrameObservations` per image, raw pixels.
    """
    recording = open_recording(path, fps=fps, topic=topic, camera=camera)
    camera = camera if camera is not None else recording.camera
    if camera is None:
        raise InputError(f"camera: {path} carries no calibration; pass the camera")
    return track_images(recording.frames, recording.times, camera, config, target)
