"""One entry point for recorded image sequences: the reader is chosen from what the path holds.

:func:`open_recording` recognises, in this order:

==============  ==========================================================  ==================
layout          path                                                        timestamps
==============  ==========================================================  ==================
``rosbag``      a ROS 1 ``.bag``; a ROS 2 bag folder (``metadata.yaml``)    header stamps
``euroc``       EuRoC / ASL root, ``mav0/`` or ``cam0/`` (``data.csv``)     data.csv, ns
``tum``         a TUM RGB-D folder with ``rgb.txt``, or that ``rgb.txt``    rgb.txt, s
``folder``      a folder of images                                          times.txt or fps
``video``       a video file (:data:`~hvo_graph.io.images.VIDEO_EXTENSIONS`) container, or fps
==============  ==========================================================  ==================

Every layout gives real timestamps; a rate is never guessed: a folder
without ``times.txt`` needs ``fps``, and ``fps`` is refused where the data
has its own times (except a video, where it replaces the container's
timestamps). EuRoC (``sensor.yaml``) and bags (``CameraInfo``) also give the
camera. Anything else is a one-line error naming the path and these layouts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hvo_graph.errors import InputError, as_number
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.datasets import (
    EUROC_DATA,
    TUM_LIST,
    euroc_camera_folder,
    read_euroc,
    read_tum_rgb,
)
from hvo_graph.io.images import (
    IMAGE_EXTENSIONS,
    TIMES_FILE,
    VIDEO_EXTENSIONS,
    ImageSequence,
    check_camera_size,
    image_files,
    load_image_sequence,
)
from hvo_graph.io.rosbag import is_bag, read_rosbag

#: The layouts :func:`open_recording` reads.
LAYOUTS = ("folder", "video", "tum", "euroc", "rosbag")
#: How error messages describe them.
LAYOUTS_UNDERSTOOD = (
    f"an image folder (with {TIMES_FILE} or a frame rate), a video file, "
    f"a TUM RGB-D folder with {TUM_LIST} (or {TUM_LIST} itself), "
    "a EuRoC/ASL folder (root, mav0/ or cam0/ with data.csv and data/), "
    "a ROS 1 .bag file or a ROS 2 bag folder (metadata.yaml)"
)


@dataclass(frozen=True)
class Recording:
    """An image sequence with its timestamps and, when the data carries one, its camera.

    Attributes:
        path: what was opened.
        layout: one of :data:`LAYOUTS`.
        frames: the K frames, read lazily (gray uint8; ``names[k]`` names frame k).
        times: (K,) timestamps, seconds, strictly increasing.
        camera: the calibration stored with the data (EuRoC sensor.yaml, a
            bag's CameraInfo), else None.
    """

    path: Path
    layout: str
    frames: ImageSequence
    times: list[float]
    camera: CameraModel | None = None


def detect_layout(path: str | Path) -> str:
    """The layout of ``path`` (one of :data:`LAYOUTS`), or InputError naming those understood."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory (expected {LAYOUTS_UNDERSTOOD})")
    if is_bag(path):
        return "rosbag"
    if path.is_dir():
        if euroc_camera_folder(path) is not None:
            return "euroc"
        if (path / TUM_LIST).is_file():
            return "tum"
        if image_files(path):
            return "folder"
        raise InputError(
            f"{path}: no images and no known layout in the folder (expected {LAYOUTS_UNDERSTOOD})"
        )
    suffix = path.suffix.lower()
    if path.name == TUM_LIST:
        return "tum"
    if suffix in VIDEO_EXTENSIONS:
        return "video"
    if suffix in IMAGE_EXTENSIONS:
        raise InputError(f"{path}: a single image (expected {LAYOUTS_UNDERSTOOD})")
    raise InputError(f"{path}: not a layout this program reads (expected {LAYOUTS_UNDERSTOOD})")


def _dataset_of_image_folder(path: Path) -> Path:
    """A dataset's own image folder stands for the dataset, whose list has the times: TUM's
    ``rgb/`` (beside rgb.txt) and EuRoC's ``cam0/data/`` (beside data.csv)."""
    if not path.is_dir() or (path / TIMES_FILE).exists():
        return path
    if (path.parent / TUM_LIST).is_file():
        return path.parent
    if path.name == EUROC_DATA and euroc_camera_folder(path.parent) is not None:
        return path.parent
    return path


def open_recording(
    path: str | Path,
    *,
    fps: float | None = None,
    topic: str | None = None,
    camera: CameraModel | None = None,
) -> Recording:
    """Open an image sequence in any of :data:`LAYOUTS`, chosen from what ``path`` holds.

    A dataset's own image folder (TUM's ``rgb/``, EuRoC's ``cam0/data/``)
    opens the dataset, so that its listed times are used.

    Args:
        path: the file or folder (see the module's table).
        fps: frames per second, > 0: required by an image folder without
            times.txt; replaces a video's container timestamps
            (t_k = k / fps); refused by the other layouts.
        topic: the image topic of a bag (required when it has several);
            refused by the other layouts.
        camera: when given, the frames must be camera.width x camera.height.
    Returns:
        The :class:`Recording`.
    """
    path = _dataset_of_image_folder(Path(path))
    if fps is not None:
        as_number(fps, "fps", above=0.0, what="a number")
    layout = detect_layout(path)
    if topic is not None and layout != "rosbag":
        raise InputError(f"topic: only for ROS bags; {path} is {_NAMES[layout]}")
    if fps is not None and layout in ("tum", "euroc", "rosbag"):
        raise InputError(
            f"fps: {path} is {_NAMES[layout]}, which gives its own timestamps; leave fps unset"
        )
    own_camera = None
    if layout == "rosbag":
        frames, times, own_camera = read_rosbag(path, topic)
    elif layout == "euroc":
        frames, times, own_camera = read_euroc(path)
    elif layout == "tum":
        frames, times = read_tum_rgb(path)
    else:
        frames, times = load_image_sequence(path, fps=fps)
    check_camera_size(frames, camera if camera is not None else own_camera)
    return Recording(path, layout, frames, times, own_camera)


_NAMES = {
    "folder": "an image folder",
    "video": "a video",
    "tum": "a TUM RGB-D sequence",
    "euroc": "a EuRoC/ASL sequence",
    "rosbag": "a ROS bag",
}
