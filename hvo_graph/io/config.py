"""The camera-and-scene YAML file of the contract (format in docs/conventions.md, "Files").

.. code-block:: yaml

    camera:
      fx: 800.0          # pixels
      fy: 800.0
      cx: 320.0
      cy: 240.0
      width: 640         # pixels
      height: 480
      distortion: [0.0, 0.0, 0.0, 0.0, 0.0]   # optional; OpenCV order k1 k2 p1 p2 k3
      distortion_model: radtan  # optional: radtan (default) or equidistant (fisheye, k1..k4)
    plane:
      distance: 2.0      # d* > 0, metres
      normal: [0.0, 0.0, 1.0]   # optional n*, unit normal in the first camera frame
    noise:
      pixel_sigma: 0.2236       # optional, pixels

Unknown keys, missing required keys and values of the wrong type are errors
that name the file, the line and the dotted key (``camera.yaml:3: unknown key
'camera.fz'``). Duplicate keys are errors too (plain YAML loaders silently keep
the last one). A number written like ``1e-3`` (a string in YAML 1.1) is read
as a number.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import yaml

from hvo_graph.errors import InputError, as_number
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io._common import PathLike, atomic_write_text, fmt, read_text
from hvo_graph.types import Plane

_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
_SECTIONS = {
    "camera": (_CAMERA_KEYS, ("distortion", "distortion_model")),
    "plane": (("distance",), ("normal",)),
    "noise": ((), ("pixel_sigma",)),
}
_REQUIRED_SECTIONS = ("camera", "plane")


@dataclass(frozen=True)
class SceneConfig:
    """What the estimator needs to know about the camera and the scene.

    Attributes:
        camera: intrinsics, image size, distortion.
        plane: d* and, when known, n* (in the first camera frame F*).
        pixel_sigma: std of the feature coordinates in pixels, or None when unknown.
    """

    camera: CameraModel
    plane: Plane
    pixel_sigma: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.camera, CameraModel):
            raise InputError(f"camera: expected a CameraModel, got {type(self.camera).__name__}")
        if not isinstance(self.plane, Plane):
            raise InputError(f"plane: expected a Plane, got {type(self.plane).__name__}")
        if self.pixel_sigma is not None:
            as_number(self.pixel_sigma, "noise.pixel_sigma", at_least=0.0)


class _Reader:
    """Walks the composed YAML node tree, keeping line numbers for messages."""

    def __init__(self, path: PathLike) -> None:
        self.path = path
        self._constructor = yaml.SafeLoader("")

    def error(self, node: yaml.Node | None, message: str) -> InputError:
        where = f"{self.path}:{node.start_mark.line + 1}" if node is not None else f"{self.path}"
        return InputError(f"{where}: {message}")

    def mapping(self, node: yaml.Node, key: str) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """{name: (key node, value node)} of a mapping; rejects duplicates and non-string keys."""
        if not isinstance(node, yaml.MappingNode):
            what = f"{key}: expected" if key else "expected a YAML file of"
            raise self.error(node, f"{what} a mapping of keys to values")
        out: dict[str, tuple[yaml.Node, yaml.Node]] = {}
        for knode, vnode in node.value:
            name = self._constructor.construct_object(knode, deep=True)
            dotted = f"{key}.{name}" if key else str(name)
            if not isinstance(name, str):
                raise self.error(knode, f"unknown key '{dotted}'")
            if name in out:
                raise self.error(knode, f"duplicate key '{dotted}'")
            out[name] = (knode, vnode)
        return out

    def check_keys(
        self,
        entries: dict[str, tuple[yaml.Node, yaml.Node]],
        node: yaml.Node,
        prefix: str,
        required: tuple[str, ...],
        optional: tuple[str, ...],
    ) -> None:
        for name, (knode, _) in entries.items():
            if name not in required and name not in optional:
                dotted = f"{prefix}.{name}" if prefix else name
                allowed = ", ".join(required + optional)
                raise self.error(knode, f"unknown key '{dotted}' (expected one of: {allowed})")
        for name in required:
            if name not in entries:
                dotted = f"{prefix}.{name}" if prefix else name
                raise self.error(node, f"missing required key '{dotted}'")

    def number(self, node: yaml.Node, key: str) -> float:
        value = self._constructor.construct_object(node, deep=True)
        if isinstance(value, str):  # YAML 1.1 reads 1e-3 as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(node, f"{key}: expected a number, got {value!r}")
        if not np.isfinite(value):
            raise self.error(node, f"{key}: expected a finite number, got {value!r}")
        return float(value)

    def integer(self, node: yaml.Node, key: str) -> int:
        value = self.number(node, key)
        if value != int(value):
            raise self.error(node, f"{key}: expected an integer, got {value!r}")
        return int(value)

    def numbers(self, node: yaml.Node, key: str) -> list[float]:
        if not isinstance(node, yaml.SequenceNode):
            raise self.error(node, f"{key}: expected a list of numbers")
        return [self.number(item, f"{key}[{i}]") for i, item in enumerate(node.value)]


#: A file's n* must have a length within this of 1 (three written decimals are enough);
#: it is then normalized. Anything else is a mistake, not a direction to guess.
UNIT_NORMAL_TOLERANCE = 1e-3


def _check_unit(r: _Reader, node: yaml.Node, normal: np.ndarray) -> None:
    if normal.shape != (3,):
        return  # Plane names the wrong length
    norm = float(np.linalg.norm(normal))
    if abs(norm - 1.0) > UNIT_NORMAL_TOLERANCE:
        hint = (
            f"; did you mean [{', '.join(f'{x:.4g}' for x in normal / norm)}]?" if norm > 0 else ""
        )
        raise r.error(
            node, f"plane.normal: expected a unit vector (length 1), got length {norm:.6g}{hint}"
        )


def load_scene(path: PathLike) -> SceneConfig:
    """Read the contract's camera/scene YAML.

    Args:
        path: the YAML file.
    Returns:
        The camera, the plane (d*, optional n*) and the optional pixel noise.
    Raises:
        InputError: naming the file, line and key of the first problem.
        OSError: when the file cannot be read.
    """
    camera, plane, pixel_sigma = _read_scene(path, plane_required=True)
    assert plane is not None
    return SceneConfig(camera=camera, plane=plane, pixel_sigma=pixel_sigma)


def load_camera(path: PathLike) -> tuple[CameraModel, Plane | None, float | None]:
    """Read the contract's camera YAML where the ``plane`` section may be left out (it is
    about to be derived, e.g. by ``hvo-graph plane``); the same checks otherwise.

    Returns:
        The camera, the plane when the file gives one (else None), the pixel noise or None.
    """
    return _read_scene(path, plane_required=False)


def _read_scene(
    path: PathLike, *, plane_required: bool
) -> tuple[CameraModel, Plane | None, float | None]:
    text = read_text(path)
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else f"{path}"
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise InputError(f"{where}: not valid YAML: {problem}") from None
    r = _Reader(path)
    if root is None:
        raise InputError(f"{path}:1: expected a mapping with keys 'camera' and 'plane', got none")
    top = r.mapping(root, "")
    required = _REQUIRED_SECTIONS if plane_required else ("camera",)
    optional = ("noise",) if plane_required else ("plane", "noise")
    r.check_keys(top, root, "", required, optional)

    sections: dict[str, dict[str, tuple[yaml.Node, yaml.Node]]] = {}
    for name, (knode, vnode) in top.items():
        if name == "noise" and isinstance(vnode, yaml.ScalarNode) and vnode.tag.endswith(":null"):
            sections[name] = {}
            continue
        entries = r.mapping(vnode, name)
        required, optional = _SECTIONS[name]
        r.check_keys(entries, knode, name, required, optional)
        sections[name] = entries

    cam = sections["camera"]
    values = {k: r.number(cam[k][1], f"camera.{k}") for k in ("fx", "fy", "cx", "cy")}
    sizes = {k: r.integer(cam[k][1], f"camera.{k}") for k in ("width", "height")}
    model = "radtan"
    if "distortion_model" in cam:
        model = r._constructor.construct_object(cam["distortion_model"][1], deep=True)
    distortion = np.zeros(4 if model == "equidistant" else 5)
    if "distortion" in cam:
        distortion = np.array(r.numbers(cam["distortion"][1], "camera.distortion"))
    try:
        camera = CameraModel(**values, **sizes, distortion=distortion, distortion_model=model)
    except InputError as exc:  # CameraModel names the key: "camera.<key>: ..."
        key = str(exc).split(":")[0].removeprefix("camera.")
        raise r.error(cam[key][1] if key in cam else top["camera"][0], str(exc)) from None

    plane = None
    if "plane" in sections:
        plane = _read_plane(r, sections["plane"])
    pixel_sigma = None
    noise = sections.get("noise", {})
    if "pixel_sigma" in noise:
        node = noise["pixel_sigma"][1]
        pixel_sigma = r.number(node, "noise.pixel_sigma")
        if pixel_sigma < 0:
            raise r.error(node, f"noise.pixel_sigma: expected a number >= 0, got {pixel_sigma}")
    return camera, plane, pixel_sigma


def _read_plane(r: _Reader, pl: dict[str, tuple[yaml.Node, yaml.Node]]) -> Plane:
    distance = r.number(pl["distance"][1], "plane.distance")
    normal = None
    if "normal" in pl and not (
        isinstance(pl["normal"][1], yaml.ScalarNode) and pl["normal"][1].tag.endswith(":null")
    ):
        normal = np.array(r.numbers(pl["normal"][1], "plane.normal"))
        _check_unit(r, pl["normal"][1], normal)
    try:
        plane = Plane(distance=distance, normal=normal)
    except InputError as exc:
        key = "distance" if str(exc).startswith("plane.distance") else "normal"
        node = pl[key][1]
        raise r.error(node, str(exc)) from None
    return plane


def save_scene(path: PathLike, scene: SceneConfig) -> None:
    """Write ``scene`` as the contract's YAML (atomically, floats at full precision).

    ``plane.normal`` is omitted when unknown (None); ``noise`` when
    ``pixel_sigma`` is None.
    """
    if not isinstance(scene, SceneConfig):
        raise InputError(f"scene: expected a SceneConfig, got {type(scene).__name__}")
    cam, plane = scene.camera, scene.plane

    def seq(values: np.ndarray) -> str:
        return "[" + ", ".join(fmt(x) for x in np.asarray(values, dtype=float)) + "]"

    lines = [
        "# hvo_graph camera and scene (units: pixels, metres)",
        "camera:",
        *(f"  {k}: {fmt(getattr(cam, k))}" for k in ("fx", "fy", "cx", "cy")),
        f"  width: {int(cam.width)}",
        f"  height: {int(cam.height)}",
        *(
            [
                f"  distortion: {seq(cam.distortion)}  # fisheye k1 k2 k3 k4",
                "  distortion_model: equidistant",
            ]
            if cam.is_fisheye
            else [f"  distortion: {seq(cam.distortion)}  # OpenCV order k1 k2 p1 p2 k3"]
        ),
        "plane:",
        f"  distance: {fmt(plane.distance)}  # d*, metres",
    ]
    if plane.normal is not None:
        lines.append(f"  normal: {seq(plane.normal)}  # n*, first camera frame")
    if scene.pixel_sigma is not None:
        lines += ["noise:", f"  pixel_sigma: {fmt(scene.pixel_sigma)}  # pixels"]
    atomic_write_text(path, "\n".join(lines) + "\n")
