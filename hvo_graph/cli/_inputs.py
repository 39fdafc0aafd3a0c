"""What the subcommands that read recordings share: the scene (camera + plane) from
``--camera`` or the recording's calibration and the plane flags, and tracking with a
progress bar."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING

from hvo_graph.cli._common import progress
from hvo_graph.errors import InputError

if TYPE_CHECKING:  # the heavy modules are imported when a command runs
    import numpy as np

    from hvo_graph.io.config import SceneConfig
    from hvo_graph.io.images import ImageSequence
    from hvo_graph.io.sequences import Recording
    from hvo_graph.report.progress import ProgressBar
    from hvo_graph.types import FrameObservations


def normal_argument(text: str) -> list[float]:
    """``--plane-normal``: three comma-separated numbers (normalised by Plane)."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers NX,NY,NZ, got {text!r}")
    return values


def scene_from_arguments(args: argparse.Namespace, recording: Recording | None) -> SceneConfig:
    """The camera and the plane: the camera/scene YAML, or a calibration (the --camera file's,
    else the recording's) with the plane flags."""
    import numpy as np

    from hvo_graph.io.calibration import load_calibration
    from hvo_graph.io.config import SceneConfig
    from hvo_graph.types import Plane

    given = [f for f in ("plane_distance", "plane_normal") if getattr(args, f) is not None]
    if args.camera is not None:
        calibration = load_calibration(args.camera)
        if calibration.scene is not None:
            if given:
                raise InputError(
                    f"--{given[0].replace('_', '-')}: {args.camera} already gives the plane "
                    "(plane.distance); leave the plane flags out or edit the file"
                )
            return calibration.scene
        camera, source = calibration.camera, f"{args.camera} (a calibration file)"
    elif recording is not None and recording.camera is not None:
        camera, source = recording.camera, f"the calibration stored in {args.images}"
    else:
        where = f"; {args.images} carries no calibration" if args.images is not None else ""
        raise InputError(f"--camera: required (camera/scene YAML or calibration file){where}")
    if args.plane_distance is None:
        raise InputError(
            f"--plane-distance: required with {source}, which gives no plane: d*, metres "
            "from the first frame's optical centre to the plane"
        )
    normal = None if args.plane_normal is None else np.asarray(args.plane_normal)
    try:
        plane = Plane(distance=args.plane_distance, normal=normal)
    except InputError as exc:
        raise InputError(f"--plane-normal: {exc}") from None
    return SceneConfig(camera=camera, plane=plane)


def track_recording(
    args: argparse.Namespace, scene: SceneConfig, recording: Recording
) -> list[FrameObservations]:
    from hvo_graph.frontend.target import parse_target
    from hvo_graph.frontend.tracking import TrackerConfig, track_images
    from hvo_graph.io.images import check_camera_size
    from hvo_graph.report.progress import ProgressBar

    features = {} if args.max_features is None else {"max_features": args.max_features}
    if features:
        features["min_tracked"] = min(args.max_features // 2, 100)
    config = TrackerConfig(**features, compensate_exposure=bool(args.compensate_exposure))
    check_camera_size(recording.frames, scene.camera)
    progress(f"tracking features in {args.images} ({_LAYOUT_NAMES[recording.layout]})")
    # A bar with frames/s on a terminal; nothing when stderr is a pipe or a file.
    with ProgressBar(
        len(recording.frames),
        label="tracking",
        enabled=sys.stderr.isatty(),
        rate_unit="frames",
    ) as bar:
        # --plane auto: the target defines the plane, so the tracker follows it alone.
        target = parse_target(args.target) if getattr(args, "plane", None) == "auto" else None
        frames = _Counted(recording.frames, bar)
        return track_images(frames, recording.times, scene.camera, config, target)


#: How the progress note names each layout of hvo_graph.io.sequences.
_LAYOUT_NAMES = {
    "folder": "image folder",
    "video": "video",
    "tum": "TUM RGB-D",
    "euroc": "EuRoC/ASL",
    "rosbag": "ROS bag",
}


class _Counted:
    """The frames of a sequence, counting each one read on a progress bar (keeps ``names``)."""

    def __init__(self, frames: ImageSequence, bar: ProgressBar) -> None:
        self.frames, self.bar = frames, bar
        self.names = frames.names

    def __iter__(self) -> Iterator[np.ndarray]:
        for frame in self.frames:
            yield frame
            self.bar.update()
