"""Exposure compensation: every image mapped to the first one's brightness and contrast.

Lucas-Kanade assumes brightness constancy: a patch looks the same in the next
image. A camera's auto exposure breaks it for every patch at once (a gain and an
offset that change from frame to frame, smoothly or in steps), and KLT then
follows the brightness change instead of the motion: tracks drift by pixels or
are lost. Mapping each image's mean and standard deviation onto the first
image's removes a global gain and offset.

The statistics also move a little with the content as the camera moves (about a
gray level and 1% over a second of the image experiment's renders); re-mapping
for that would itself be a brightness change. :class:`ExposureCompensation`
keeps its mapping while the image's statistics stay within
:data:`MEAN_TOLERANCE` and :data:`STD_TOLERANCE` of those it was made from: under
a constant exposure every image is tracked exactly as it was taken.
"""

from __future__ import annotations

import cv2
import numpy as np

#: A new mapping when the image mean moves by more than this (gray levels) ...
MEAN_TOLERANCE = 2.0
#: ... or its standard deviation by more than this fraction.
STD_TOLERANCE = 0.02
#: Least standard deviation (gray levels) of an image to take the exposure from.
MIN_STD = 0.5


def image_statistics(gray: np.ndarray) -> tuple[float, float]:
    """(mean, standard deviation) of the gray levels of ``gray``."""
    mean, std = cv2.meanStdDev(gray)
    return float(mean[0, 0]), float(std[0, 0])


def matched_exposure(
    gray: np.ndarray, statistics: tuple[float, float], target: tuple[float, float]
) -> np.ndarray:
    """``gray`` (H, W) uint8 under the gain and offset that take ``statistics``
    (mean, std) to ``target``: g' = target_std / std (g - mean) + target_mean, rounded
    and clipped to uint8."""
    scale = target[1] / statistics[1]
    offset = target[0] - scale * statistics[0]
    out = gray.astype(np.float32) * np.float32(scale) + np.float32(offset)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class ExposureCompensation:
    """:func:`matched_exposure` of a sequence onto its first textured image (std of at
    least ``MIN_STD``), one image at a time; the mapping is kept while the statistics
    stay within tolerance of those it was made from."""

    def __init__(self) -> None:
        self.target: tuple[float, float] | None = None  # the first textured image's
        self.statistics: tuple[float, float] | None = None  # of the mapping in use

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        mean, std = image_statistics(gray)
        if std < MIN_STD:
            return gray
        kept = self.statistics
        if (
            kept is None
            or abs(mean - kept[0]) > MEAN_TOLERANCE
            or abs(std - kept[1]) > STD_TOLERANCE * kept[1]
        ):
            self.statistics = kept = (mean, std)
        if self.target is None:
            self.target = kept
        return gray if kept == self.target else matched_exposure(gray, kept, self.target)
