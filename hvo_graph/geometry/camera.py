"""Pinhole camera with optional OpenCV lens distortion: radial-tangential or equidistant.

Normalized image coordinates are m = [x/z, y/z, 1]^T (the paper's m), i.e.
pixels mapped through K^-1 after undistortion. Distortion goes through
OpenCV, never by hand: ``cv2.undistortPoints`` / ``cv2.projectPoints`` for
the radial-tangential model ("radtan", OpenCV's standard model, ROS's
plumb_bob), ``cv2.fisheye.undistortPoints`` / ``cv2.fisheye.distortPoints``
for the equidistant (fisheye) model ("equidistant", OpenCV's ``cv2.fisheye``,
Kalibr's equidistant).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from hvo_graph.errors import InputError, as_number, as_points

#: OpenCV's default stops undistortion after 5 fixed-point iterations, which leaves
#: errors of ~1e-5 (normalized; ~0.01 px) under strong distortion; iterate to convergence.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)

#: Lens distortion models: OpenCV's standard (radial-tangential) and cv2.fisheye (equidistant).
DISTORTION_MODELS = ("radtan", "equidistant")


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics fx, fy, cx, cy (pixels), image size and OpenCV distortion.

    Attributes:
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (OpenCV convention: the centre of the
            top-left pixel is (0, 0)).
        width, height: image size in pixels.
        distortion: "radtan": (4|5|8|12|14,) k1 k2 p1 p2 [k3 ...] (OpenCV
            order), zeros for none; "equidistant": (4,) k1 k2 k3 k4 of
            theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8).
        distortion_model: "radtan" (default) or "equidistant" (fisheye).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "radtan"

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            as_number(getattr(self, name), f"camera.{name}", above=0.0)
        for name in ("cx", "cy"):
            as_number(getattr(self, name), f"camera.{name}")
        for name in ("width", "height"):
            value = getattr(self, name)
            # as_number first: int() of inf or NaN would raise OverflowError/ValueError.
            x = as_number(value, f"camera.{name}", above=0.0, what="an integer")
            if int(x) != x:
                raise InputError(f"camera.{name}: expected a positive integer, got {value}")
        if self.distortion_model not in DISTORTION_MODELS:
            raise InputError(
                "camera.distortion_model: expected one of "
                f"{', '.join(DISTORTION_MODELS)}, got {self.distortion_model!r}"
            )
        dist = np.asarray(self.distortion, dtype=float).ravel()
        if self.distortion_model == "equidistant":
            if dist.size != 4 or not np.all(np.isfinite(dist)):
                raise InputError(
                    "camera.distortion: expected 4 finite equidistant (fisheye) coefficients "
                    f"k1 k2 k3 k4, got {dist.size}"
                )
        elif dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise InputError(
                "camera.distortion: expected 4, 5, 8, 12 or 14 finite OpenCV coefficients "
                f"(k1 k2 p1 p2 [k3 ...]), got {dist.size}"
            )
        object.__setattr__(self, "distortion", dist)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """Whether pixels differ from the pinhole projection (always, for equidistant: its
        theta_d = theta even with zero coefficients is not the pinhole's tan(theta))."""
        return self.is_fisheye or bool(np.any(self.distortion != 0.0))

    @property
    def is_fisheye(self) -> bool:
        """Whether the lens follows the equidistant (cv2.fisheye) model."""
        return self.distortion_model == "equidistant"

    @property
    def mean_focal(self) -> float:
        """(fx + fy) / 2: converts a pixel sigma into normalized units."""
        return 0.5 * (self.fx + self.fy)

    def pixel_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistort and normalize pixels.

        Args:
            uv: (N, 2) pixel coordinates.
        Returns:
            (N, 3) normalized homogeneous coordinates m = [x, y, 1].
        """
        uv = as_points(uv, "uv", dim=2)
        if self.is_fisheye:
            xy = cv2.fisheye.undistortPoints(
                uv.reshape(-1, 1, 2), self.K, self.distortion, None, None, None, _UNDISTORT_CRITERIA
            ).reshape(-1, 2)
        elif self.has_distortion:
            xy = cv2.undistortPoints(
                uv.reshape(-1, 1, 2), self.K, self.distortion, None, None, None, _UNDISTORT_CRITERIA
            ).reshape(-1, 2)
        else:
            xy = np.column_stack(((uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy))
        return np.column_stack((xy, np.ones(len(xy))))

    def normalized_to_pixel(self, m: np.ndarray) -> np.ndarray:
        """Distort and map normalized coordinates to pixels.

        Args:
            m: (N, 2) or (N, 3) normalized coordinates (a third column must be 1).
        Returns:
            (N, 2) pixel coordinates.
        """
        m = as_points(m, "m")
        if m.shape[1] == 3 and not np.all(m[:, 2] > 0):
            raise InputError("m: third column must be > 0 (points in front of the camera)")
        xy = m[:, :2] / m[:, 2:3] if m.shape[1] == 3 else m
        if self.is_fisheye:
            uv = cv2.fisheye.distortPoints(xy.reshape(-1, 1, 2), self.K, self.distortion)
            return uv.reshape(-1, 2)
        if self.has_distortion:
            pts = np.column_stack((xy, np.ones(len(xy))))
            uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.distortion)
            return uv.reshape(-1, 2)
        return np.column_stack((self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project camera-frame 3D points to pixels.

        Args:
            points: (N, 3) points in the camera frame, z > 0.
        Returns:
            (N, 2) pixel coordinates.
        Raises:
            InputError: when a point is not in front of the camera.
        """
        points = as_points(points, "points", dim=3)
        if np.any(points[:, 2] <= 0):
            raise InputError("points: a point is behind the camera (z <= 0)")
        return self.normalized_to_pixel(points / points[:, 2:3])

    def in_view(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixels inside the image, at least ``margin`` pixels from its border."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return (
            (uv[:, 0] >= -0.5 + margin)
            & (uv[:, 0] <= self.width - 0.5 - margin)
            & (uv[:, 1] >= -0.5 + margin)
            & (uv[:, 1] <= self.height - 0.5 - margin)
        )
