"""Small rendered sequences written in each recorded layout the readers understand.

The frames are rendered views of a textured plane (hvo_graph.sim.render) from
known poses; each writer lays them out as the dataset's own tools do (TUM
RGB-D rgb.txt, EuRoC mav0/cam0, ROS 1/2 bags written with rosbags' writers),
with irregular timestamps so that a guessed rate could not pass.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import gtsam
import numpy as np

from hvo_graph.geometry.camera import CameraModel
from hvo_graph.sim.render import render_plane_images
from hvo_graph.types import Plane

CAMERA = CameraModel(fx=310.0, fy=295.0, cx=158.3, cy=121.7, width=320, height=240)
NORMAL = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
PLANE = Plane(2.0, NORMAL)
TWIST = np.array([0.05, -0.1, 0.15, 0.8, -0.2, 0.15])  # body [w; v] per second
NUM_FRAMES = 8
#: Irregular steps (s): 20 Hz with jitter, as a real driver stamps frames.
STEPS = [0.05, 0.0501, 0.0498, 0.05, 0.0502, 0.0499, 0.05]
#: Nanosecond stamps from a EuRoC-like start (MH_01's first cam0 stamp).
START_NS = 1403636579763555584
STAMPS_NS = [START_NS + round(1e9 * sum(STEPS[:k])) for k in range(NUM_FRAMES)]
POSES = [gtsam.Pose3.Expmap(TWIST * k / 20.0) for k in range(NUM_FRAMES)]


def render() -> list[np.ndarray]:
    """The NUM_FRAMES gray uint8 frames (320x240)."""
    return render_plane_images(CAMERA, PLANE, POSES, noise_sigma=1.0, seed=3)


def tum_stamps() -> list[str]:
    """TUM RGB-D style timestamps, seconds with 6 decimals (as the dataset writes them)."""
    return [f"{ns // 10**9}.{(ns % 10**9) // 1000:06d}" for ns in STAMPS_NS]


def write_tum(root: Path, frames: list[np.ndarray]) -> Path:
    """ROOT/rgb/<stamp>.png and ROOT/rgb.txt (with the dataset's three comment lines)."""
    (root / "rgb").mkdir(parents=True)
    lines = ["# color images", "# file: 'rgbd_dataset_test.bag'", "# timestamp filename"]
    for stamp, image in zip(tum_stamps()[: len(frames)], frames, strict=True):
        assert cv2.imwrite(str(root / "rgb" / f"{stamp}.png"), image)
        lines.append(f"{stamp} rgb/{stamp}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    # The dataset's other lists sit beside rgb.txt and must not confuse the reader.
    (root / "depth.txt").write_text("# depth maps\n")
    return root


EUROC_SENSOR = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [{width}, {height}]
camera_model: pinhole
intrinsics: [{fx}, {fy}, {cx}, {cy}] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [0.0, 0.0, 0.0, 0.0]
"""


def write_euroc(root: Path, frames: list[np.ndarray]) -> Path:
    """ROOT/mav0/cam0/{data.csv, data/<ns>.png, sensor.yaml}, as the ASL format has them."""
    cam0 = root / "mav0" / "cam0"
    (cam0 / "data").mkdir(parents=True)
    lines = ["#timestamp [ns],filename"]
    for ns, image in zip(STAMPS_NS[: len(frames)], frames, strict=True):
        assert cv2.imwrite(str(cam0 / "data" / f"{ns}.png"), image)
        lines.append(f"{ns},{ns}.png")
    (cam0 / "data.csv").write_text("\r\n".join(lines) + "\r\n")  # the dataset's line ends
    c = CAMERA
    (cam0 / "sensor.yaml").write_text(
        EUROC_SENSOR.format(width=c.width, height=c.height, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy)
    )
    return root


def _header(types: dict, ns: int, ros1: bool, k: int) -> object:
    stamp = types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    if ros1:
        return types["std_msgs/msg/Header"](seq=k, stamp=stamp, frame_id="cam")
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")


def _camera_info(types: dict, ns: int, ros1: bool) -> object:
    c = CAMERA
    K = np.array([c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0])
    P = np.array([c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    arrays = {"d": np.zeros(5), "k": K, "r": np.eye(3).ravel(), "p": P}
    if ros1:
        arrays = {name.upper(): value for name, value in arrays.items()}
    return types["sensor_msgs/msg/CameraInfo"](
        header=_header(types, ns, ros1, 0),
        height=c.height,
        width=c.width,
        distortion_model="plumb_bob",
        binning_x=0,
        binning_y=0,
        roi=roi,
        **arrays,
    )


def write_bag(
    path: Path,
    frames: list[np.ndarray],
    *,
    ros1: bool,
    compressed: bool,
    topics: tuple[str, ...] = ("/cam0/image_raw",),
    camera_info: bool = True,
) -> Path:
    """A ROS 1 (.bag) or ROS 2 (folder) bag: frames on each topic, header stamps STAMPS_NS,
    recorded 3 ms after their stamps, and one CameraInfo on /cam0/camera_info."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=9)
    msgtype = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with writer:
        conns = [writer.add_connection(t, msgtype, typestore=store) for t in topics]
        if camera_info:
            info_type = "sensor_msgs/msg/CameraInfo"
            info = writer.add_connection("/cam0/camera_info", info_type, typestore=store)
            msg = _camera_info(types, STAMPS_NS[0], ros1)
            writer.write(info, STAMPS_NS[0], serialize(msg, info_type))
        for k, (ns, image) in enumerate(zip(STAMPS_NS[: len(frames)], frames, strict=True)):
            header = _header(types, ns, ros1, k)
            if compressed:
                ok, png = cv2.imencode(".png", image)
                assert ok
                msg = types[msgtype](
                    header=header, format="mono8; png compressed", data=png.ravel()
                )
            else:
                # Color, as most drivers publish: the reader converts to gray.
                rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
                msg = types[msgtype](
                    header=header,
                    height=image.shape[0],
                    width=image.shape[1],
                    encoding="rgb8",
                    is_bigendian=0,
                    step=3 * image.shape[1],
                    data=rgb.ravel(),
                )
            for conn in conns:
                writer.write(conn, ns + 3_000_000, serialize(msg, msgtype))
    return path


def write_video(path: Path, frames: list[np.ndarray], fps: float = 20.0) -> Path:
    """An MJPG AVI at ``fps``."""
    h, w = frames[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h), False)
    for image in frames:
        writer.write(image)
    writer.release()
    return path


def same_camera(a: CameraModel | None, b: CameraModel) -> bool:
    """Equal intrinsics, size, model and coefficients (trailing zero coefficients ignored:
    radial-tangential k1 k2 p1 p2 is k1 k2 p1 p2 k3 with k3 = 0)."""
    if a is None:
        return False

    def coefficients(c: CameraModel) -> np.ndarray:
        d = np.asarray(c.distortion, dtype=float)
        return np.pad(d, (0, 14 - d.size))

    return (
        (a.fx, a.fy, a.cx, a.cy, a.width, a.height, a.distortion_model)
        == (b.fx, b.fy, b.cx, b.cy, b.width, b.height, b.distortion_model)
    ) and np.array_equal(coefficients(a), coefficients(b))
