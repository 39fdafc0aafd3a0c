"""Settings of the KLT tracker (:mod:`hvo_graph.frontend.tracking`), checked on creation."""

from __future__ import annotations

from dataclasses import dataclass

from hvo_graph.errors import InputError, as_integer, as_number

#: Frame-to-frame KLT keeping fewer than this fraction of the tracks calls for a
#: wide-baseline match (``TrackerConfig.wide_baseline``).
WIDE_BASELINE_FRACTION = 0.5


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
        wide_baseline: when frame-to-frame KLT keeps fewer than
            ``WIDE_BASELINE_FRACTION`` of the tracks (a jump: a large viewpoint
            change, a dropped or blurred stretch), match SIFT features of the two
            images for a coarse plane homography (MAGSAC) and align the tracks again
            under it (:mod:`hvo_graph.frontend.wide_baseline`); the result with more
            tracks is kept.
        reidentify_frames: when a frame loses more than half the tracks at once (at
            least 8), look for them again in each of this many later frames and
            resume the ones found under their old ids
            (:mod:`hvo_graph.frontend.reidentify`); 0: never.
        compensate_exposure: divide every image by its gain relative to the first
            image before tracking (:class:`~hvo_graph.frontend.exposure.ExposureCompensation`),
            for footage under auto exposure, which breaks KLT's brightness constancy.
            Off by default: where the content changes the mean gray level as the camera
            moves (a small view of a varied texture), the compensation itself is a
            brightness change (tight's position error 0.2 -> 1.4 mm on the quick renders).
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
    wide_baseline: bool = True
    reidentify_frames: int = 60
    compensate_exposure: bool = False

    def __post_init__(self) -> None:
        for name, minimum in (
            ("max_features", 1),
            ("block_size", 3),
            ("lk_window", 3),
            ("lk_levels", 0),
            ("lk_iterations", 1),
            ("min_tracked", 0),
            ("reidentify_frames", 0),
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
        for name in ("wide_baseline", "compensate_exposure"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name}: expected true or false, got {getattr(self, name)!r}")
