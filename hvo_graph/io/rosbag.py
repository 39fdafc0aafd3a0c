"""ROS 1 and ROS 2 bags read as image sequences, through the pure-Python ``rosbags`` package.

Install it with the ``bags`` extra (``pip install "hvo_graph[bags]"``); without
it, opening a bag is a one-line error naming the extra.

- **Images**: ``sensor_msgs/Image`` (mono8, mono16, bgr8, rgb8, bgra8, rgba8,
  8UC1, 8UC3, 16UC1) or ``sensor_msgs/CompressedImage`` (JPEG, PNG), on one
  topic: the only image topic of the bag, or the one named by ``topic``.
- **Timestamps**: each message's ``header.stamp`` (the sensor's time), in
  seconds as sec + nanosec / 10^9 (exactly rounded); a zero stamp (driver
  left it unset) takes the time the bag recorded the message.
- **Camera**: the first ``sensor_msgs/CameraInfo`` (K, D, distortion_model
  plumb_bob / rational_polynomial / equidistant, width, height) of the image
  topic's namespace, nearest first (``/cam/image_raw/compressed`` ->
  ``/cam/image_raw/camera_info``, ``/cam/camera_info``, ``/camera_info``);
  none when absent or uncalibrated (K = 0).

A ROS 1 bag is a ``.bag`` file; a ROS 2 bag a folder with ``metadata.yaml``
(or one of its ``.db3`` / ``.mcap`` files).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import ImageSequence, as_gray_image

#: Message types read as images, and as the camera (ROS 2 names, as rosbags gives them).
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: Raw image encodings read: name -> (channels, dtype, conversion to BGR or None).
ENCODINGS: dict[str, tuple[int, str, int | None]] = {
    "mono8": (1, "u1", None),
    "8UC1": (1, "u1", None),
    "mono16": (1, "u2", None),
    "16UC1": (1, "u2", None),
    "bgr8": (3, "u1", None),
    "8UC3": (3, "u1", None),
    "rgb8": (3, "u1", cv2.COLOR_RGB2BGR),
    "bgra8": (4, "u1", None),
    "8UC4": (4, "u1", None),
    "rgba8": (4, "u1", cv2.COLOR_RGBA2BGRA),
}
_DISTORTION_MODELS = {
    "": "radtan",
    "plumb_bob": "radtan",
    "rational_polynomial": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
}


def is_bag(path: Path) -> bool:
    """Whether ``path`` looks like a ROS 1 (.bag) or ROS 2 (folder with metadata.yaml) bag."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    suffix = path.suffix.lower()
    return suffix == ".bag" or (
        suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file()
    )


def _open(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise InputError(
            f'{path}: reading ROS bags needs the rosbags package: pip install "hvo_graph[bags]"'
        ) from None
    bag = path.parent if path.suffix.lower() in (".db3", ".mcap") else path
    reader = AnyReader([bag])
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own error types for a damaged bag
        raise InputError(f"{path}: cannot read the bag ({exc})") from None
    return reader


def _stamp_ns(msg: Any, recorded_ns: int) -> int:
    stamp = msg.header.stamp
    nanosec = getattr(stamp, "nanosec", None)
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nsec if nanosec is None else nanosec)
    return ns if ns else int(recorded_ns)


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo field: ROS 2 spells them k, d; ROS 1 K, D."""
    return getattr(msg, name, None) if hasattr(msg, name) else getattr(msg, name.upper())


def _camera_info(path: Path, msg: Any, topic: str) -> CameraModel | None:
    K = np.asarray(_field(msg, "k"), dtype=float).reshape(3, 3)
    if K[0, 0] == 0.0:  # an uncalibrated driver publishes K = 0
        return None
    model = _DISTORTION_MODELS.get(str(msg.distortion_model).lower())
    if model is None:
        raise InputError(
            f"{path}: {topic}: unsupported distortion model {msg.distortion_model!r} "
            f"(expected {', '.join(m for m in _DISTORTION_MODELS if m)})"
        )
    dist = np.asarray(_field(msg, "d"), dtype=float).ravel()
    if dist.size == 0:
        dist = np.zeros(4 if model == "equidistant" else 5)
    try:
        fx, fy, cx, cy = (float(x) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        return CameraModel(fx, fy, cx, cy, int(msg.width), int(msg.height), dist, model)
    except InputError as exc:
        raise InputError(f"{path}: {topic}: {exc}") from None


def decode_image(msg: Any, msgtype: str, name: str) -> np.ndarray:
    """A sensor_msgs Image or CompressedImage message as a (H, W) gray uint8 image."""
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InputError(f"{name}: cannot decode the compressed image ({msg.format})")
        return as_gray_image(image, name)
    encoding = ENCODINGS.get(msg.encoding)
    if encoding is None:
        raise InputError(
            f"{name}: image encoding {msg.encoding!r} not supported (expected one of "
            f"{', '.join(ENCODINGS)})"
        )
    channels, kind, conversion = encoding
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row = width * channels * dtype.itemsize
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if step < row or data.size < step * height:
        raise InputError(
            f"{name}: {data.size} bytes do not hold a {width}x{height} {msg.encoding} image "
            f"with step {step}"
        )
    rows = data[: step * height].reshape(height, step)[:, :row]
    image = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)
    image = image.astype(dtype.newbyteorder("="))
    if conversion is not None:
        image = cv2.cvtColor(image, conversion)
    return as_gray_image(image, name)


class _BagFrames(ImageSequence):
    def __init__(self, path: Path, topic: str, count: int, width: int, height: int):
        self.path, self.topic = path, topic
        super().__init__([f"{path} {topic} message {k}" for k in range(count)], width, height)

    def __iter__(self) -> Iterator[np.ndarray]:
        reader = _open(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
                msg = reader.deserialize(raw, conn.msgtype)
                yield self._check_size(
                    decode_image(msg, conn.msgtype, self.names[k]), self.names[k]
                )
        finally:
            reader.close()


def _image_topic(path: Path, connections: list[Any], topic: str | None) -> str:
    topics = sorted({c.topic for c in connections if c.msgtype in IMAGE_TYPES})
    if topic is not None:
        if topic not in topics:
            listed = ", ".join(topics) or "none"
            raise InputError(
                f"topic: {topic} is not an image topic of {path} (image topics: {listed})"
            )
        return topic
    if not topics:
        every = ", ".join(sorted({c.topic for c in connections})) or "none"
        raise InputError(
            f"{path}: no sensor_msgs/Image or CompressedImage topic in the bag (topics: {every})"
        )
    if len(topics) > 1:
        raise InputError(
            f"{path}: {len(topics)} image topics, choose one with --topic: {', '.join(topics)}"
        )
    return topics[0]


def _info_connection(connections: list[Any], topic: str) -> Any | None:
    """The CameraInfo of the image topic's namespace, nearest first: /cam/image_raw/compressed
    -> /cam/image_raw/camera_info, /cam/camera_info, /camera_info."""
    infos = {c.topic: c for c in connections if c.msgtype == CAMERA_INFO_TYPE}
    parts = topic.strip("/").split("/")
    for n in range(len(parts) - 1, -1, -1):
        name = "/" + "/".join([*parts[:n], "camera_info"])
        if name in infos:
            return infos[name]
    return None


def read_rosbag(
    path: str | Path, topic: str | None = None
) -> tuple[ImageSequence, list[float], CameraModel | None]:
    """Read the images of a ROS 1 or ROS 2 bag, their header stamps and the CameraInfo camera.

    Args:
        path: a ``.bag`` file, a ROS 2 bag folder, or a file of one.
        topic: the image topic; required when the bag has several.
    Returns:
        The frames (gray uint8, decoded lazily), their times in seconds and
        the camera of the topic's CameraInfo (None when absent).
    """
    path = Path(path)
    reader = _open(path)
    try:
        connections = list(reader.connections)
        topic = _image_topic(path, connections, topic)
        conns = [c for c in connections if c.topic == topic]
        stamps: list[int] = []
        first = None
        for conn, recorded, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            stamps.append(_stamp_ns(msg, recorded))
            if first is None:
                first = decode_image(msg, conn.msgtype, f"{path} {topic} message 0")
        info = _info_connection(connections, topic)
        camera = None
        if info is not None:
            for conn, _, raw in reader.messages(connections=[info]):
                camera = _camera_info(path, reader.deserialize(raw, conn.msgtype), info.topic)
                break
    finally:
        reader.close()
    if first is None:
        raise InputError(f"{path}: topic {topic} has no messages")
    for k in range(1, len(stamps)):
        if not stamps[k] > stamps[k - 1]:
            raise InputError(
                f"{path} {topic} message {k}: header stamp {stamps[k] / 1e9} s does not "
                f"increase (previous {stamps[k - 1] / 1e9} s)"
            )
    times = [ns / 1_000_000_000 for ns in stamps]
    frames = _BagFrames(path, topic, len(stamps), first.shape[1], first.shape[0])
    return frames, times, camera
