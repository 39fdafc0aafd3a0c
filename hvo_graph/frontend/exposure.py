"""Exposure compensation: every image brought to the first one's brightness.

Lucas-Kanade assumes brightness constancy: a patch looks the same in the next
image. A camera's auto exposure breaks it for every patch at once: exposure time
and analog gain scale the light, and the image by a common factor (gamma keeps
it a factor), from frame to frame, smoothly or in steps. KLT then follows the
brightness change instead of the motion: tracks drift by pixels or are lost.
Dividing each image by its gain relative to the first image, the ratio of the
mean gray levels, restores constancy.

Only the mean is used: a blur or a defocus lowers the contrast at the same mean,
and stretching it back would track through images where no corner survives.
The mean also moves a little with the content as the camera moves (about a
gray level over a second of the image experiment's renders); re-scaling for
that would itself be a brightness change. :class:`ExposureCompensation` keeps
its gain while the image's mean stays within :data:`GAIN_TOLERANCE` of the one
it was taken from: under a constant exposure every image is tracked as taken.
"""

from __future__ import annotations

import cv2
import numpy as np

#: A new gain when the image mean moves by more than this fraction.
GAIN_TOLERANCE = 0.02
#: Least mean gray level of an image to take the exposure from.
MIN_MEAN = 1.0


def scaled_image(gray: np.ndarray, factor: float) -> np.ndarray:
    """``gray`` (H, W) uint8 times ``factor``, rounded and clipped to uint8."""
    return cv2.convertScaleAbs(gray, alpha=float(factor))


class ExposureCompensation:
    """Each image of a sequence, one at a time, divided by its gain relative to the
    first image with a mean of at least ``MIN_MEAN`` (the ratio of the means); the gain
    is kept while the mean stays within ``GAIN_TOLERANCE`` of the one it came from."""

    def __init__(self) -> None:
        self.reference_mean: float | None = None  # the first image's
        self.mean: float | None = None  # of the gain in use

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        mean = float(cv2.mean(gray)[0])
        if mean < MIN_MEAN:
            return gray
        if self.mean is None or abs(mean - self.mean) > GAIN_TOLERANCE * self.mean:
            self.mean = mean
        if self.reference_mean is None:
            self.reference_mean = mean
        if self.mean == self.reference_mean:
            return gray
        return scaled_image(gray, self.reference_mean / self.mean)
