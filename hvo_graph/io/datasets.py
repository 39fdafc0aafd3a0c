"""Dataset layouts read as image sequences with their recorded timestamps.

- **TUM RGB-D** (``rgb.txt``): lines ``timestamp filename`` (seconds; the file
  name relative to the folder holding rgb.txt, e.g. ``rgb/1305031102.175304.png``),
  ``#`` comments. The dataset ships no calibration file.
- **EuRoC / ASL** (``mav0/cam0/``): ``data.csv`` with lines
  ``timestamp [ns],filename`` (``#`` header), images in ``data/``, and the
  camera in ``sensor.yaml`` (:func:`hvo_graph.io.calibration.load_euroc_sensor`).
  Nanoseconds become seconds by an exactly rounded division (t = ns / 10^9).

Both return frames read lazily (:class:`~hvo_graph.io.images.ImageSequence`)
and times in seconds, strictly increasing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.calibration import load_euroc_sensor
from hvo_graph.io.images import ImageSequence, images_from_files

#: The TUM RGB-D image list.
TUM_LIST = "rgb.txt"
#: EuRoC / ASL camera folder contents: timestamps, images, calibration.
EUROC_CSV = "data.csv"
EUROC_DATA = "data"
EUROC_SENSOR = "sensor.yaml"


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the file ({exc})") from None


def _check_increasing(path: Path, lineno: int, value: float, times: list[float]) -> None:
    if not np.isfinite(value):
        raise InputError(f"{path}:{lineno}: expected a finite time, got {value}")
    if times and not value > times[-1]:
        raise InputError(f"{path}:{lineno}: time {value} does not increase (previous {times[-1]})")


def _existing(path: Path, lineno: int, file: Path) -> Path:
    if not file.is_file():
        raise InputError(f"{path}:{lineno}: image {file} does not exist")
    return file


def read_tum_rgb(path: str | Path) -> tuple[ImageSequence, list[float]]:
    """Read a TUM RGB-D sequence: its ``rgb.txt`` (or the folder holding it).

    Args:
        path: the rgb.txt file, or the dataset folder containing it.
    Returns:
        The frames (gray uint8, read lazily) and their times, seconds.
    """
    path = Path(path)
    listing = path / TUM_LIST if path.is_dir() else path
    root = listing.parent
    files: list[Path] = []
    times: list[float] = []
    for lineno, line in enumerate(_read_lines(listing), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.split()
        if len(fields) != 2:
            raise InputError(
                f"{listing}:{lineno}: expected 'timestamp filename' (TUM RGB-D rgb.txt), "
                f"got {text!r}"
            )
        try:
            t = float(fields[0])
        except ValueError:
            raise InputError(
                f"{listing}:{lineno}: expected a timestamp in seconds, got {fields[0]!r}"
            ) from None
        _check_increasing(listing, lineno, t, times)
        files.append(_existing(listing, lineno, root / fields[1]))
        times.append(t)
    if not files:
        raise InputError(f"{listing}: no images listed (expected lines 'timestamp filename')")
    return images_from_files(files), times


def euroc_camera_folder(path: str | Path) -> Path | None:
    """The camera folder (holding data.csv) of a EuRoC / ASL path, or None if it is not one.

    Accepts the dataset root (``ROOT/mav0/cam0``), ``mav0/`` (its ``cam0``)
    or the camera folder itself (``cam0/``, ``cam1/``).
    """
    path = Path(path)
    for folder in (path, path / "cam0", path / "mav0" / "cam0"):
        if (folder / EUROC_CSV).is_file() and (folder / EUROC_DATA).is_dir():
            return folder
    return None


def read_euroc(path: str | Path) -> tuple[ImageSequence, list[float], CameraModel | None]:
    """Read a EuRoC / ASL camera: data.csv timestamps (ns), data/ images, sensor.yaml camera.

    Args:
        path: the dataset root, its ``mav0/`` or a camera folder (see
            :func:`euroc_camera_folder`).
    Returns:
        The frames (gray uint8, read lazily), their times in seconds, and the
        camera of ``sensor.yaml`` (None when the folder has none).
    """
    folder = euroc_camera_folder(path)
    if folder is None:
        raise InputError(
            f"{path}: not a EuRoC / ASL camera folder (expected mav0/cam0/{EUROC_CSV} "
            f"and mav0/cam0/{EUROC_DATA}/)"
        )
    csv = folder / EUROC_CSV
    files: list[Path] = []
    times: list[float] = []
    for lineno, line in enumerate(_read_lines(csv), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        if len(fields) != 2 or not fields[0].isdigit():
            raise InputError(
                f"{csv}:{lineno}: expected 'timestamp [ns],filename' with an integer "
                f"timestamp, got {text!r}"
            )
        t = int(fields[0]) / 1_000_000_000  # int / int: correctly rounded
        _check_increasing(csv, lineno, t, times)
        files.append(_existing(csv, lineno, folder / EUROC_DATA / fields[1]))
        times.append(t)
    if not files:
        raise InputError(f"{csv}: no images listed (expected lines 'timestamp [ns],filename')")
    sensor = folder / EUROC_SENSOR
    camera = load_euroc_sensor(sensor) if sensor.is_file() else None
    return images_from_files(files), times, camera
