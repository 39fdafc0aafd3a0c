"""Image sequences on disk: a folder of images (with an optional times.txt) or a video.

Frames are read lazily and converted to gray uint8 (:class:`ImageSequence`);
a folder is sorted by file name with digit runs compared by value (frame2
before frame10), its timestamps come from ``times.txt`` (one time per image,
seconds) or a frame rate given by the caller (never a guessed one); a video
gives each frame's own container timestamp unless a frame rate is passed.
Dataset layouts (TUM RGB-D, EuRoC, ROS bags) are in
:mod:`hvo_graph.io.datasets` and :mod:`hvo_graph.io.rosbag`, and
:func:`hvo_graph.io.sequences.open_recording` picks the reader.
:func:`as_gray_image` is the one conversion of an image array (gray, BGR or
BGRA, 8 or 16 bits) into what the tracker reads (:mod:`hvo_graph.frontend.tracking`).
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from hvo_graph.errors import InputError, as_number
from hvo_graph.geometry.camera import CameraModel

#: File name endings read as images (case-insensitive).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: File name endings read as videos (case-insensitive); FFmpeg opens some text files too.
VIDEO_EXTENSIONS = (
    ".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".ts", ".mts",
    ".m2ts", ".wmv", ".flv", ".ogv", ".3gp", ".mjpeg", ".mjpg", ".y4m", ".h264", ".h265",
)  # fmt: skip
#: Images of a folder read ahead of the one being worked on (a worker thread decodes them).
PREFETCH_FRAMES = 2
#: Optional timestamp file inside an image directory: one time (seconds) per image.
TIMES_FILE = "times.txt"


def as_gray_image(image: object, name: str, camera: CameraModel | None = None) -> np.ndarray:
    """Return ``image`` as a (H, W) uint8 gray image, or raise InputError.

    Args:
        image: (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA array, uint8
            or uint16 (scaled to 8 bits).
        name: how the error message names the image.
        camera: when given, the image must be camera.width x camera.height.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name}: expected an image array, got {type(image).__name__}")
    a = image
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise InputError(
            f"{name}: expected a (H, W) gray or (H, W, 3) BGR image, got shape {image.shape}"
        )
    if a.dtype == np.uint16:
        a = np.rint(a / 257.0).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise InputError(
            f"{name}: expected uint8 or uint16 pixels, got {a.dtype} "
            "(scale floats to 0..255 and convert with .astype(np.uint8))"
        )
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if camera is not None and a.shape != (camera.height, camera.width):
        raise InputError(
            f"{name}: image size {a.shape[1]}x{a.shape[0]} does not match the camera's "
            f"{camera.width}x{camera.height} (camera.width x camera.height)"
        )
    # A copy: the tracker keeps images, and callers may reuse their buffers.
    return np.array(a, order="C", copy=True) if a is image else np.ascontiguousarray(a)


class ImageSequence:
    """Frames read lazily from disk, gray uint8, in time order.

    Iterate to read them; ``len()`` is the number of frames and ``names[k]``
    names frame k in error messages (its file, or the video and frame number).
    Iterating raises InputError for an unreadable frame or one whose size
    differs from the first.
    """

    def __init__(self, names: list[str], width: int, height: int):
        self.names = names
        self.width = width
        self.height = height

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self) -> Iterator[np.ndarray]:
        raise NotImplementedError

    def _check_size(self, image: np.ndarray, name: str) -> np.ndarray:
        if image.shape[:2] != (self.height, self.width):
            raise InputError(
                f"{name}: image size {image.shape[1]}x{image.shape[0]} differs from the first "
                f"image's {self.width}x{self.height}"
            )
        return image


class _DirectoryImages(ImageSequence):
    def __init__(self, files: list[Path]):
        self.files = files
        # Read now for the size, and kept: the first pass would decode it again.
        self._first: np.ndarray | None = _read_image(files[0])
        super().__init__([str(f) for f in files], self._first.shape[1], self._first.shape[0])

    def __getitem__(self, k: int) -> np.ndarray:
        return self._check_size(_read_image(self.files[k]), self.names[k])

    def __iter__(self) -> Iterator[np.ndarray]:
        # The next files are read and decoded by a worker thread (OpenCV's decoders
        # release the GIL) while the caller works on this one; a file's error is raised
        # when the caller reaches it, as a plain loop would.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="hvo-images") as pool:
            ahead: deque[Future[np.ndarray]] = deque()
            for k in range(len(self.files)):
                while len(ahead) < PREFETCH_FRAMES and k + len(ahead) < len(self.files):
                    ahead.append(pool.submit(self._read, k + len(ahead)))
                yield ahead.popleft().result()

    def _read(self, k: int) -> np.ndarray:
        if k == 0 and self._first is not None:
            image, self._first = self._first, None
            return image
        return self[k]


class _VideoFrames(ImageSequence):
    def __init__(self, path: Path, count: int, width: int, height: int):
        self.path = path
        super().__init__([f"{path} frame {k}" for k in range(count)], width, height)

    def __iter__(self) -> Iterator[np.ndarray]:
        capture = cv2.VideoCapture(str(self.path))
        try:
            for name in self.names:
                ok, frame = capture.read()
                if not ok:
                    raise InputError(f"{name}: cannot decode this frame of the video")
                yield self._check_size(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), name)
        finally:
            capture.release()


def _read_image(path: Path) -> np.ndarray:
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror})") from None
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if image is None:
        raise InputError(f"{path}: cannot read the image (not a valid image file)")
    return image


def _natural_key(path: Path) -> list[object]:
    """Sort key comparing digit runs by value: frame2.png before frame10.png."""
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", path.name)]


def read_times(path: str | Path, count: int) -> list[float]:
    """Read a timestamp file: one time in seconds per line, strictly increasing.

    Blank lines and lines starting with '#' are skipped.

    Args:
        path: the file (e.g. ``DIR/times.txt``).
        count: the number of images the times belong to.
    Returns:
        ``count`` times, seconds.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the file ({exc})") from None
    times: list[float] = []
    for lineno, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        try:
            value = float(text)
        except ValueError:
            raise InputError(
                f"{path}:{lineno}: expected one time in seconds, got {text!r}"
            ) from None
        if not np.isfinite(value):
            raise InputError(f"{path}:{lineno}: expected a finite time, got {text!r}")
        if times and not value > times[-1]:
            raise InputError(
                f"{path}:{lineno}: time {value} does not increase (previous {times[-1]})"
            )
        times.append(value)
    if len(times) != count:
        raise InputError(f"{path}: {len(times)} times for {count} images; expected one per image")
    return times


def image_files(path: Path) -> list[Path]:
    """The image files of a directory (:data:`IMAGE_EXTENSIONS`, any case), in name order
    with digit runs compared by value (frame2 before frame10)."""
    return sorted(
        (f for f in path.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS and f.is_file()),
        key=_natural_key,
    )


def images_from_files(files: list[Path]) -> ImageSequence:
    """Frames read lazily from a list of image files (the first one is read now)."""
    return _DirectoryImages(files)


def check_camera_size(frames: ImageSequence, camera: CameraModel | None) -> None:
    """Raise InputError naming the first frame when its size is not the camera's."""
    if camera is not None and (frames.width, frames.height) != (camera.width, camera.height):
        raise InputError(
            f"{frames.names[0]}: image size {frames.width}x{frames.height} does not match the "
            f"camera's {camera.width}x{camera.height} (camera.width x camera.height)"
        )


def load_image_sequence(
    path: str | Path, *, fps: float | None = None, camera: CameraModel | None = None
) -> tuple[ImageSequence, list[float]]:
    """Open a directory of images or a video file, with timestamps.

    A directory: every file ending in .png, .jpg, .jpeg, .bmp, .tif or .tiff
    (any case), sorted by file name with digit runs compared by value
    (frame2 before frame10; zero-padded names sort as usual). Timestamps come
    from ``PATH/times.txt`` when present (see :func:`read_times`; ``fps``
    must then be None), else t_k = k / fps; without times.txt ``fps`` is
    required (a guessed rate would scale every velocity).

    A video file (a name ending in one of :data:`VIDEO_EXTENSIONS`, decoded
    by ``cv2.VideoCapture``): each frame's container timestamp
    (``CAP_PROP_POS_MSEC``, so variable frame rates are kept), or
    t_k = k / fps when ``fps`` is given.

    Args:
        path: the directory or video file.
        fps: frames per second, > 0.
        camera: when given, the first image must be camera.width x camera.height.
    Returns:
        The frames (read lazily; gray uint8) and their K times in seconds.
    """
    path = Path(path)
    if fps is not None:
        as_number(fps, "fps", above=0.0, what="a number")
    if not path.exists():
        raise InputError(f"{path}: no such directory or video file")
    if path.is_dir():
        files = image_files(path)
        if not files:
            raise InputError(
                f"{path}: no images in the directory (expected files ending in "
                f"{', '.join(IMAGE_EXTENSIONS)})"
            )
        frames: ImageSequence = _DirectoryImages(files)
        times_file = path / TIMES_FILE
        if times_file.exists():
            if fps is not None:
                raise InputError(f"fps: {times_file} already gives the timestamps; leave fps unset")
            times = read_times(times_file, len(files))
        elif fps is None:
            raise InputError(
                f"{path}: no {TIMES_FILE} in the folder to give the images' timestamps; pass the "
                f"frame rate (--fps) or write {TIMES_FILE} (one time in seconds per image)"
            )
        else:
            times = [k / fps for k in range(len(files))]
    elif path.suffix.lower() in IMAGE_EXTENSIONS:
        raise InputError(f"{path}: a single image; expected a directory of images or a video file")
    elif path.suffix.lower() in VIDEO_EXTENSIONS:
        frames, stamps = _open_video(path)
        times = stamps if fps is None else [k / fps for k in range(len(frames))]
    else:
        raise InputError(
            f"{path}: not a video file (expected a name ending in {', '.join(VIDEO_EXTENSIONS)}) "
            "nor a directory of images"
        )
    check_camera_size(frames, camera)
    return frames, times


def _open_video(path: Path) -> tuple[ImageSequence, list[float]]:
    """The frames of a video and their container timestamps, seconds."""
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise InputError(f"{path}: cannot open as a video")
        # Count by decoding: CAP_PROP_FRAME_COUNT is an estimate for many containers.
        ok, frame = capture.read()
        if not ok:
            raise InputError(f"{path}: the video has no readable frame")
        height, width = frame.shape[:2]
        stamps = [capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0]
        while capture.grab():
            stamps.append(capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
    finally:
        capture.release()
    for k in range(1, len(stamps)):
        if not (np.isfinite(stamps[k]) and stamps[k] > stamps[k - 1]):
            raise InputError(
                f"{path} frame {k}: the container's timestamp {stamps[k]} s does not increase "
                f"(previous {stamps[k - 1]} s); pass the frame rate (--fps)"
            )
    return _VideoFrames(path, len(stamps), width, height), stamps
