"""The plane (n*, d*) of the first frame, from a target seen there or from the camera's height.

The estimators need the plane in the first camera frame F*: the unit normal n*
pointing away from the camera and the distance d*, with n*^T X = d* for the
plane's points X (camera frame, metres). A user rarely knows them; a target in
the first image gives them:

- **chessboard**: inner corners by ``cv2.findChessboardCorners``, refined by
  ``cv2.cornerSubPix``;
- **ChArUco board**: ``cv2.aruco.CharucoDetector`` (chessboard corners between
  ArUco markers; works when part of the board is hidden);
- **ArUco grid board**: ``cv2.aruco.ArucoDetector`` and the board's marker corners.

The board's pose comes from ``cv2.solvePnP`` (IPPE for planar points, then
Levenberg-Marquardt refinement); the board's plane z_b = 0 in the camera frame
is n* = R_cb e_z, d* = n*^T t_cb (n* flipped when that is negative). Without a
target, a camera at height h above a floor and tilted down by an angle a has
n* = [0, cos a, sin a], d* = h (camera frame: x right, y down, z forward).

A target is named by a compact specification, the same on every command::

    chessboard:9x6:0.025                     # inner corners across x down, square (m)
    charuco:7x5:0.04:0.03:DICT_5X5_100       # squares across x down, square, marker (m), dictionary
    aruco:5x7:0.04:0.01:DICT_6X6_250         # markers across x down, marker, gap (m), dictionary
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from hvo_graph.errors import InputError, as_number
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import IMAGE_EXTENSIONS, as_gray_image, load_image_sequence
from hvo_graph.types import Plane

#: Target kinds of :func:`parse_target`.
TARGET_KINDS = ("chessboard", "charuco", "aruco")

#: cornerSubPix: half window (pixels) and stopping rule of the corner refinement.
_SUBPIX_WINDOW = (5, 5)
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)

_FORMS = {
    "chessboard": "chessboard:COLSxROWS:SQUARE",
    "charuco": "charuco:COLSxROWS:SQUARE:MARKER:DICTIONARY",
    "aruco": "aruco:COLSxROWS:MARKER:GAP:DICTIONARY",
}


@dataclass(frozen=True)
class TargetSpec:
    """A planar calibration target.

    Attributes:
        kind: "chessboard", "charuco" or "aruco".
        columns, rows: chessboard: inner corners across and down; charuco: squares;
            aruco: markers.
        square: chessboard / charuco square side, metres (aruco: the marker side).
        marker: charuco / aruco marker side, metres (None for a chessboard).
        gap: aruco: the gap between markers, metres (None otherwise).
        dictionary: the ArUco dictionary name, e.g. "DICT_4X4_50" (None for a chessboard).
    """

    kind: str
    columns: int
    rows: int
    square: float
    marker: float | None = None
    gap: float | None = None
    dictionary: str | None = None


@dataclass(frozen=True)
class TargetPose:
    """A target's pose in one image and the plane it gives.

    Attributes:
        plane: d* (metres) and n* (unit, away from the camera) in this camera frame.
        rotation: (3, 3) R_cb, board axes in the camera frame.
        translation: (3,) t_cb, board origin in the camera frame, metres.
        image_points: (N, 2) detected corners, raw (distorted) pixels.
        object_points: (N, 3) the same corners on the board (z = 0), metres.
        rms_px: RMS reprojection error of the corners at the pose, pixels.
    """

    plane: Plane
    rotation: np.ndarray
    translation: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray
    rms_px: float


def parse_target(spec: str) -> TargetSpec:
    """Read a target specification (module docstring), e.g. ``"chessboard:9x6:0.025"``.

    Raises:
        InputError: naming the specification and the form expected.
    """
    parts = str(spec).strip().split(":")
    kind = parts[0].lower()
    if kind not in _FORMS:
        raise InputError(
            f"target {spec!r}: expected one of {', '.join(_FORMS[k] for k in TARGET_KINDS)}"
        )
    form = _FORMS[kind]
    if len(parts) != form.count(":") + 1:
        raise InputError(f"target {spec!r}: expected {form}")
    try:
        columns, rows = (int(x) for x in parts[1].lower().split("x"))
        sizes = [float(x) for x in parts[2 : 3 if kind == "chessboard" else 4]]
    except ValueError:
        raise InputError(f"target {spec!r}: expected {form}") from None
    least = 2 if kind != "aruco" else 1
    if columns < least or rows < least or (kind == "charuco" and columns * rows < 4):
        raise InputError(f"target {spec!r}: expected at least {least}x{least} in {form}")
    names = form.split(":")[2 : 2 + len(sizes)]  # SQUARE [MARKER] or MARKER GAP
    for name, value in zip(names, sizes, strict=True):
        as_number(value, f"target {spec!r}: {name}", above=0.0)
    if kind == "chessboard":
        return TargetSpec(kind, columns, rows, sizes[0])
    dictionary = parts[4].upper()
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise InputError(
            f"target {spec!r}: unknown ArUco dictionary {parts[4]!r} (e.g. DICT_4X4_50)"
        )
    if kind == "charuco":
        if sizes[1] >= sizes[0]:
            raise InputError(f"target {spec!r}: MARKER must be smaller than SQUARE")
        return TargetSpec(kind, columns, rows, sizes[0], marker=sizes[1], dictionary=dictionary)
    return TargetSpec(kind, columns, rows, sizes[0], marker=sizes[0], gap=sizes[1],
                      dictionary=dictionary)  # fmt: skip


def chessboard_points(columns: int, rows: int, square: float) -> np.ndarray:
    """(columns * rows, 3) inner corners of a chessboard on its plane z = 0, metres, in
    ``cv2.findChessboardCorners``'s order (row by row, x fastest)."""
    grid = np.mgrid[0:columns, 0:rows].T.reshape(-1, 2) * float(square)
    return np.column_stack((grid, np.zeros(len(grid))))


def _aruco_board(spec: TargetSpec) -> object:
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    size = (spec.columns, spec.rows)
    if spec.kind == "charuco":
        return cv2.aruco.CharucoBoard(size, spec.square, spec.marker, dictionary)
    return cv2.aruco.GridBoard(size, spec.marker, spec.gap, dictionary)


def target_board(spec: TargetSpec) -> object:
    """The OpenCV board of a ChArUco / ArUco specification (``cv2.aruco.CharucoBoard`` or
    ``GridBoard``), e.g. to print it with ``generateImage``."""
    if spec.kind == "chessboard":
        raise InputError("target: a chessboard has no ArUco board")
    return _aruco_board(spec)


def detect_target(image: np.ndarray, spec: TargetSpec) -> tuple[np.ndarray, np.ndarray] | None:
    """Find the target's corners in an image.

    Args:
        image: (H, W) gray or (H, W, 3) BGR, uint8.
        spec: the target.
    Returns:
        (N, 2) raw pixels and (N, 3) the matching board points (metres, z = 0), or None
        when the target is not found (fewer than 4 corners).
    """
    gray = as_gray_image(image, "image")
    if gray.dtype != np.uint8:
        gray = cv2.convertScaleAbs(gray, alpha=255.0 / max(float(gray.max()), 1.0))
    if spec.kind == "chessboard":
        size = (spec.columns, spec.rows)
        found, corners = cv2.findChessboardCorners(
            gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        )
        if not found:
            return None
        corners = cv2.cornerSubPix(gray, corners, _SUBPIX_WINDOW, (-1, -1), _SUBPIX_CRITERIA)
        return corners.reshape(-1, 2).astype(float), chessboard_points(*size, spec.square)
    board = _aruco_board(spec)
    if spec.kind == "charuco":
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
        if ids is None or len(ids) < 4:
            return None
        objects = board.getChessboardCorners()[ids.ravel()]
        return corners.reshape(-1, 2).astype(float), np.asarray(objects, dtype=float)
    corners, ids, _ = cv2.aruco.ArucoDetector(board.getDictionary()).detectMarkers(gray)
    if ids is None or not len(ids):
        return None
    objects, pixels = board.matchImagePoints(corners, ids)
    if objects is None or len(objects) < 4:
        return None
    return pixels.reshape(-1, 2).astype(float), objects.reshape(-1, 3).astype(float)


def board_margin(spec: TargetSpec) -> float:
    """How far the board's plane reaches beyond the points :func:`detect_target` finds,
    metres: one square around a chessboard's or ChArUco board's inner corners, the gap
    around an ArUco grid's marker corners."""
    return float(spec.gap or 0.0) if spec.kind == "aruco" else float(spec.square)


def board_pose(
    image_points: np.ndarray, object_points: np.ndarray, camera: CameraModel
) -> TargetPose:
    """The pose of a planar board from its corners (``cv2.solvePnP``: IPPE, then LM).

    Args:
        image_points: (N, 2) raw pixels, N >= 4.
        object_points: (N, 3) board points, z = 0, metres.
        camera: the calibrated camera (distortion included).
    Returns:
        The pose, the plane (n*, d*) in this camera frame and the reprojection RMS.
    """
    uv = np.asarray(image_points, dtype=np.float64).reshape(-1, 1, 2)
    xyz = np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3)
    if len(uv) < 4 or len(uv) != len(xyz):
        raise InputError(f"target: expected at least 4 matching corners, got {len(uv)}")
    ok, rvec, tvec = cv2.solvePnP(xyz, uv, camera.K, camera.distortion, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise InputError("target: solvePnP found no pose for the corners")
    rvec, tvec = cv2.solvePnPRefineLM(xyz, uv, camera.K, camera.distortion, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.ravel()
    normal = R[:, 2].copy()
    distance = float(normal @ t)
    if distance < 0:  # the board's z axis points at the camera: n* must point away
        normal, distance = -normal, -distance
    if distance <= 0:
        raise InputError("target: the board plane passes through the camera centre")
    projected, _ = cv2.projectPoints(xyz, rvec, tvec, camera.K, camera.distortion)
    rms = float(np.sqrt(np.mean(np.sum((projected - uv).reshape(-1, 2) ** 2, axis=1))))
    return TargetPose(Plane(distance, normal), R, t, uv.reshape(-1, 2), xyz.reshape(-1, 3), rms)


def plane_from_target(image: np.ndarray, camera: CameraModel, spec: TargetSpec) -> TargetPose:
    """n*, d* in this image's camera frame from the target it shows.

    Raises:
        InputError: the target is not found in the image.
    """
    found = detect_target(image, spec)
    if found is None:
        raise InputError(f"target: no {spec.kind} {spec.columns}x{spec.rows} found in the image")
    return board_pose(*found, camera)


def plane_from_height(height: float, tilt_deg: float) -> Plane:
    """The floor's plane for a camera ``height`` metres above it, its optical axis tilted
    ``tilt_deg`` degrees below the horizon (0: level, 90: straight down), no roll.

    Returns:
        Plane(d* = height, n* = [0, cos a, sin a]) in the camera frame (y down).
    """
    h = as_number(height, "height", above=0.0)
    a = as_number(tilt_deg, "tilt", what="degrees")
    if not -90.0 < a <= 90.0:
        raise InputError(f"tilt: expected degrees in (-90, 90], got {tilt_deg}")
    r = np.deg2rad(a)
    return Plane(h, np.array([0.0, np.cos(r), np.sin(r)]))


def first_image(path: str | Path, camera: CameraModel) -> np.ndarray:
    """The first frame a sequence starts with: an image file itself, the first image of a
    folder (in the order ``estimate --images`` reads it) or a video's first frame.

    Returns:
        (H, W) gray uint8 image, the camera's size.
    """
    path = Path(path)
    if path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS:
        data = np.fromfile(path, dtype=np.uint8)
        image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
        if image is None:
            raise InputError(f"{path}: cannot read the image (not a valid image file)")
        return as_gray_image(image, str(path), camera)
    frames, _ = load_image_sequence(path, camera=camera)
    for image in frames:
        return as_gray_image(image, str(path), camera)
    raise InputError(f"{path}: no frames")
