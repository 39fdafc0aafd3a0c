"""Camera calibration files from other tools, read into a :class:`CameraModel`.

:func:`load_calibration` recognises, by content:

- the project's camera/scene YAML (:func:`hvo_graph.io.config.load_scene`:
  camera, plane and noise);
- OpenCV FileStorage YAML or XML (``cv2.FileStorage``, as written by OpenCV's
  calibration tools): ``camera_matrix``, ``distortion_coefficients``,
  ``image_width`` / ``image_height`` (or ``image_size: [w, h]``); a
  ``distortion_model: equidistant`` (or ``fisheye``) or ``fisheye_model: 1``
  entry selects the fisheye model;
- a ROS ``camera_info`` YAML (``camera_calibration_parsers``):
  ``image_width``, ``image_height``, ``camera_matrix.data``,
  ``distortion_model`` (plumb_bob, rational_polynomial, equidistant),
  ``distortion_coefficients.data``;
- a Kalibr camchain YAML: ``cam0`` (the first camera) with
  ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``,
  ``resolution: [w, h]``, ``distortion_model`` (radtan, equidistant, none),
  ``distortion_coeffs``;
- a EuRoC / ASL ``sensor.yaml``: ``intrinsics: [fu, fv, cu, cv]``,
  ``resolution: [w, h]``, ``distortion_model`` (radial-tangential,
  equidistant), ``distortion_coefficients``.

Radial-tangential coefficients are OpenCV's order (k1 k2 p1 p2 [k3 ...]);
equidistant ones are k1 k2 k3 k4 of ``cv2.fisheye``. Calibration files carry
no plane (n*, d*): the caller supplies it (``hvo-graph estimate
--plane-distance``, docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import yaml

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io._common import PathLike, read_text
from hvo_graph.io.config import SceneConfig, load_scene

#: The calibration formats read, as error messages list them.
CALIBRATION_FORMATS = (
    "the hvo-graph camera/scene YAML",
    "an OpenCV FileStorage YAML/XML (camera_matrix, distortion_coefficients)",
    "a ROS camera_info YAML",
    "a Kalibr camchain YAML",
    "a EuRoC sensor.yaml",
)

#: Distortion model names of the formats read -> :data:`CameraModel.distortion_model`.
_MODELS = {
    "": "radtan",
    "none": "radtan",
    "radtan": "radtan",
    "radial-tangential": "radtan",
    "plumb_bob": "radtan",
    "rational_polynomial": "radtan",
    "pinhole": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
    "equi": "equidistant",
}


@dataclass(frozen=True)
class Calibration:
    """A camera read from a calibration file.

    Attributes:
        camera: intrinsics, image size and distortion.
        format: which format the file was: "scene" (the project's YAML),
            "opencv", "ros", "kalibr" or "euroc".
        scene: the whole scene (camera, plane, noise) when the file is the
            project's camera/scene YAML, else None (the plane must come from
            elsewhere).
    """

    camera: CameraModel
    format: str
    scene: SceneConfig | None = None


def load_calibration(path: PathLike) -> Calibration:
    """Read a camera calibration in any of the formats listed in this module's doc.

    Args:
        path: the file.
    Returns:
        The camera, the format recognised and, for the project's YAML, the scene.
    Raises:
        InputError: naming the file and the key of the first problem, or the
            formats understood when the file is none of them.
        OSError: when the file cannot be read.
    """
    text = read_text(path)
    head = text.lstrip()[:200]
    if head.startswith(("%YAML", "<?xml", "<opencv_storage")) or "!!opencv-matrix" in text:
        return Calibration(_opencv(path), "opencv")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if isinstance(data, dict):
        if isinstance(data.get("camera"), dict):
            scene = load_scene(path)
            return Calibration(scene.camera, "scene", scene)
        if "camera_matrix" in data and "image_width" in data:
            return Calibration(_ros(path, data), "ros")
        if isinstance(data.get("cam0"), dict):
            return Calibration(_kalibr(path, data["cam0"]), "kalibr")
        if "intrinsics" in data and "resolution" in data:
            return Calibration(_euroc(path, data), "euroc")
    raise InputError(
        f"{path}: not a camera calibration this program reads (expected "
        + ", ".join(CALIBRATION_FORMATS[:-1])
        + f" or {CALIBRATION_FORMATS[-1]})"
    )


def load_euroc_sensor(path: PathLike) -> CameraModel:
    """The camera of a EuRoC / ASL ``sensor.yaml`` (intrinsics, resolution, distortion)."""
    text = read_text(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a EuRoC sensor.yaml mapping")
    return _euroc(path, data)


def _numbers(path: PathLike, value: object, key: str, count: int | tuple[int, ...]) -> np.ndarray:
    counts = (count,) if isinstance(count, int) else count
    expected = " or ".join(map(str, counts))
    try:
        array = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{path}: {key}: expected a list of {expected} numbers") from None
    if array.size not in counts or not np.all(np.isfinite(array)):
        raise InputError(
            f"{path}: {key}: expected {expected} finite numbers, got {np.asarray(value).size}"
        )
    return array


def _get(path: PathLike, data: dict, key: str, prefix: str = "") -> object:
    if key not in data:
        raise InputError(f"{path}: missing required key '{prefix}{key}'")
    return data[key]


def _model(path: PathLike, name: object, key: str) -> str:
    model = _MODELS.get(str(name or "").strip().lower())
    if model is None:
        known = ", ".join(k for k in _MODELS if k)
        raise InputError(f"{path}: {key}: unsupported distortion model {name!r} (expected {known})")
    return model


def _camera(
    path: PathLike, K: np.ndarray, size: np.ndarray, dist: np.ndarray, model: str
) -> CameraModel:
    if K[0, 1] != 0.0:
        raise InputError(f"{path}: camera matrix has a skew term {K[0, 1]}; expected 0")
    if model == "equidistant" and dist.size == 0:
        dist = np.zeros(4)
    if model == "radtan" and dist.size < 4:
        dist = np.concatenate((dist, np.zeros(5 - dist.size)))
    if size[0] != int(size[0]) or size[1] != int(size[1]):
        raise InputError(f"{path}: image size must be whole pixels, got {size[0]} x {size[1]}")
    try:
        return CameraModel(
            float(K[0, 0]),
            float(K[1, 1]),
            float(K[0, 2]),
            float(K[1, 2]),
            int(size[0]),
            int(size[1]),
            dist,
            model,
        )
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def _opencv(path: PathLike) -> CameraModel:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not storage.isOpened():
            raise InputError(f"{path}: cannot parse as an OpenCV FileStorage YAML/XML file")
        K = _fs_matrix(path, storage, ("camera_matrix", "cameraMatrix", "K"), required=True)
        if K.shape != (3, 3):
            raise InputError(f"{path}: camera_matrix: expected a 3x3 matrix, got {K.shape}")
        dist = _fs_matrix(
            path, storage, ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
        ).ravel()
        size = _fs_size(path, storage)
        name = storage.getNode("distortion_model")
        model = _model(path, name.string() if name.isString() else "", "distortion_model")
        fisheye = storage.getNode("fisheye_model")
        if not fisheye.empty() and fisheye.real() != 0:
            model = "equidistant"
    finally:
        storage.release()
    return _camera(path, K, size, dist, model)


def _fs_matrix(
    path: PathLike, storage: cv2.FileStorage, keys: tuple[str, ...], required: bool = False
) -> np.ndarray:
    for key in keys:
        node = storage.getNode(key)
        if node.empty():
            continue
        matrix = node.mat() if node.isMap() else None
        if matrix is None and node.isSeq():
            matrix = np.array([node.at(i).real() for i in range(node.size())])
        if matrix is None or not np.all(np.isfinite(matrix)):
            raise InputError(f"{path}: {key}: expected a matrix of finite numbers")
        return np.asarray(matrix, dtype=float)
    if required:
        raise InputError(f"{path}: missing required key '{keys[0]}'")
    return np.zeros(0)


def _fs_size(path: PathLike, storage: cv2.FileStorage) -> np.ndarray:
    width, height = storage.getNode("image_width"), storage.getNode("image_height")
    if not width.empty() and not height.empty():
        return np.array([width.real(), height.real()])
    size = storage.getNode("image_size")
    if size.isSeq() and size.size() == 2:
        return np.array([size.at(0).real(), size.at(1).real()])
    raise InputError(
        f"{path}: missing required key 'image_width' and 'image_height' (or 'image_size: [w, h]')"
    )


def _ros(path: PathLike, data: dict) -> CameraModel:
    matrix = _get(path, data, "camera_matrix")
    values = matrix.get("data") if isinstance(matrix, dict) else matrix
    K = _numbers(path, values, "camera_matrix.data", 9).reshape(3, 3)
    size = np.array(
        [
            _numbers(path, _get(path, data, "image_width"), "image_width", 1)[0],
            _numbers(path, _get(path, data, "image_height"), "image_height", 1)[0],
        ]
    )
    model = _model(path, data.get("distortion_model", ""), "distortion_model")
    dist_node = data.get("distortion_coefficients", {"data": []})
    dist_values = dist_node.get("data", []) if isinstance(dist_node, dict) else dist_node
    counts = (0, 4) if model == "equidistant" else (0, 4, 5, 8, 12, 14)
    dist = _numbers(path, dist_values or [], "distortion_coefficients.data", counts)
    return _camera(path, K, size, dist, model)


def _pinhole(path: PathLike, data: dict, prefix: str, dist_key: str) -> CameraModel:
    camera_model = str(data.get("camera_model", "pinhole"))
    if camera_model != "pinhole":
        raise InputError(
            f"{path}: {prefix}camera_model: unsupported projection {camera_model!r} "
            "(expected pinhole)"
        )
    fu, fv, cu, cv = _numbers(
        path, _get(path, data, "intrinsics", prefix), f"{prefix}intrinsics", 4
    )
    size = _numbers(path, _get(path, data, "resolution", prefix), f"{prefix}resolution", 2)
    model = _model(path, data.get("distortion_model", ""), f"{prefix}distortion_model")
    counts = (0, 4) if model == "equidistant" else (0, 4, 5, 8, 12, 14)
    dist = _numbers(path, data.get(dist_key) or [], f"{prefix}{dist_key}", counts)
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return _camera(path, K, size, dist, model)


def _kalibr(path: PathLike, cam0: dict) -> CameraModel:
    return _pinhole(path, cam0, "cam0.", "distortion_coeffs")


def _euroc(path: PathLike, data: dict) -> CameraModel:
    sensor = data.get("sensor_type", "camera")
    if sensor != "camera":
        raise InputError(f"{path}: sensor_type: expected camera, got {sensor!r}")
    return _pinhole(path, data, "", "distortion_coefficients")
