"""Recorded layouts in: folder, video, TUM RGB-D, EuRoC/ASL and ROS 1/2 bags.

Each layout is written here from rendered frames of known poses (tests/layouts.py)
with irregular timestamps; the readers must give back the same pixels (lossless
layouts), the exact timestamps, and the calibration stored with the data, and
``hvo-graph estimate --images`` must run end to end on each.
"""

from __future__ import annotations

import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from layouts import (
    CAMERA,
    NUM_FRAMES,
    PLANE,
    POSES,
    STAMPS_NS,
    render,
    same_camera,
    tum_stamps,
    write_bag,
    write_euroc,
    write_tum,
    write_video,
)

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.io.config import SceneConfig, save_scene
from hvo_graph.io.sequences import detect_layout, open_recording
from hvo_graph.io.trajectory import read_tum

#: Seconds of each stamp, exactly rounded from the integer nanoseconds (independent of the
#: readers: a rational, then one rounding).
SECONDS = [float(Fraction(ns, 10**9)) for ns in STAMPS_NS]

LAYOUTS = (
    "an image folder (with times.txt or a frame rate), a video file, a TUM RGB-D folder "
    "with rgb.txt (or rgb.txt itself), a EuRoC/ASL folder (root, mav0/ or cam0/ with "
    "data.csv and data/), a ROS 1 .bag file or a ROS 2 bag folder (metadata.yaml)"
)


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    return render()


@pytest.fixture(scope="module")
def data(tmp_path_factory, frames) -> dict[str, Path]:
    """Every layout, written once for the module."""
    root = tmp_path_factory.mktemp("layouts")
    folder = root / "folder"
    folder.mkdir()
    import cv2

    for k, image in enumerate(frames):
        assert cv2.imwrite(str(folder / f"img{k}.png"), image)
    (folder / "times.txt").write_text("".join(f"{t!r}\n" for t in SECONDS))
    return {
        "folder": folder,
        "video": write_video(root / "clip.avi", frames, fps=20.0),
        "tum": write_tum(root / "tum", frames),
        "euroc": write_euroc(root / "euroc", frames),
        "ros1": write_bag(root / "seq.bag", frames, ros1=True, compressed=True),
        "ros2": write_bag(root / "seq_ros2", frames, ros1=False, compressed=False),
    }


def assert_same_pixels(recording, frames) -> None:
    decoded = list(recording.frames)
    assert len(decoded) == len(recording.frames) == NUM_FRAMES
    for a, b in zip(decoded, frames, strict=True):
        assert a.dtype == np.uint8 and np.array_equal(a, b)


# -- each reader -------------------------------------------------------------------------------


def test_tum_rgbd_folder_and_its_rgb_txt(data, frames):
    expected = [float(s) for s in tum_stamps()]  # the text as written, read as a float
    for path in (data["tum"], data["tum"] / "rgb.txt"):
        recording = open_recording(path)
        assert recording.layout == "tum" and recording.camera is None
        assert recording.times == expected
        assert_same_pixels(recording, frames)


@pytest.mark.parametrize("where", ["", "mav0", "mav0/cam0"])
def test_euroc_root_mav0_or_cam0_with_nanosecond_times_and_sensor_camera(data, frames, where):
    recording = open_recording(data["euroc"] / where)
    assert recording.layout == "euroc"
    assert recording.times == SECONDS
    assert same_camera(recording.camera, CAMERA)
    assert_same_pixels(recording, frames)


@pytest.mark.parametrize("bag", ["ros1", "ros2"])
def test_ros_bags_header_stamps_images_and_camera_info(data, frames, bag):
    # ROS 1: CompressedImage (PNG); ROS 2: raw rgb8 Image. Both: the header stamps, not the
    # recording times (3 ms later), and the camera of /cam0/camera_info.
    recording = open_recording(data[bag])
    assert recording.layout == "rosbag"
    assert recording.times == SECONDS
    assert same_camera(recording.camera, CAMERA)
    assert_same_pixels(recording, frames)


def test_a_dataset_image_folder_opens_the_dataset_with_its_times(data):
    tum = open_recording(data["tum"] / "rgb")
    assert (tum.layout, tum.times) == ("tum", [float(s) for s in tum_stamps()])
    euroc = open_recording(data["euroc"] / "mav0" / "cam0" / "data")
    assert (euroc.layout, euroc.times) == ("euroc", SECONDS)


def test_a_ros2_bag_opens_from_its_storage_file(data):
    (db,) = [p for p in data["ros2"].iterdir() if p.suffix in (".db3", ".mcap")]
    assert open_recording(db).times == SECONDS


def test_video_container_timestamps_or_a_given_rate(data):
    recording = open_recording(data["video"])
    assert recording.layout == "video" and len(recording.frames) == NUM_FRAMES
    assert recording.times == pytest.approx([k / 20.0 for k in range(NUM_FRAMES)], abs=1e-12)
    assert open_recording(data["video"], fps=10.0).times == [k / 10.0 for k in range(8)]


def test_image_folder_with_times(data, frames):
    recording = open_recording(data["folder"])
    assert (recording.layout, recording.times) == ("folder", SECONDS)
    assert_same_pixels(recording, frames)


# -- end to end --------------------------------------------------------------------------------


def camera_args(tmp_path: Path) -> list[str]:
    scene = tmp_path / "camera.yaml"
    save_scene(scene, SceneConfig(CAMERA, PLANE))
    return ["--camera", str(scene)]


def plane_args() -> list[str]:
    n = ",".join(repr(float(x)) for x in PLANE.normal)
    return ["--plane-distance", repr(PLANE.distance), "--plane-normal", n]


@pytest.mark.parametrize(
    ("layout", "subpath", "uses_own_camera"),
    [
        ("folder", "", False),
        ("video", "", False),
        ("tum", "rgb.txt", False),
        ("euroc", "", True),
        ("ros1", "", True),
        ("ros2", "", True),
    ],
)
def test_estimate_runs_on_each_layout(tmp_path, data, layout, subpath, uses_own_camera):
    out = tmp_path / "out"
    path = data[layout] / subpath if subpath else data[layout]
    cam = plane_args() if uses_own_camera else camera_args(tmp_path)
    args = ["estimate", *cam, "--images", str(path), "--method", "measurements"]
    assert main([*args, "--out", str(out)]) == 0
    estimate = read_tum(out / "trajectory.txt")
    expected = {
        "folder": SECONDS,
        "video": [k / 20.0 for k in range(NUM_FRAMES)],
        "tum": [float(s) for s in tum_stamps()],
    }.get(layout, SECONDS)
    if layout == "video":
        assert estimate.t == pytest.approx(expected, abs=1e-12)
    else:
        assert list(estimate.t) == expected  # exact: written at full precision
    truth = np.array([p.translation() for p in POSES])
    tolerance = 0.02 if layout == "video" else 0.005  # metres at 2 m; MJPG is lossy
    assert np.abs(np.asarray(estimate.positions) - truth).max() < tolerance


# -- bad layouts -------------------------------------------------------------------------------


def error(path, **kwargs) -> str:
    with pytest.raises(InputError) as info:
        open_recording(path, **kwargs)
    return str(info.value)


def test_unknown_paths_name_the_layouts_understood(tmp_path):
    (tmp_path / "notes.txt").write_text("1.0 a.png\n")
    (tmp_path / "empty").mkdir()
    assert error(tmp_path / "nowhere") == (
        f"{tmp_path / 'nowhere'}: no such file or directory (expected {LAYOUTS})"
    )
    assert error(tmp_path / "notes.txt") == (
        f"{tmp_path / 'notes.txt'}: not a layout this program reads (expected {LAYOUTS})"
    )
    assert error(tmp_path / "empty") == (
        f"{tmp_path / 'empty'}: no images and no known layout in the folder (expected {LAYOUTS})"
    )


def test_rates_and_topics_only_where_they_apply(data, frames, tmp_path):
    assert error(data["tum"], fps=30.0) == (
        f"fps: {data['tum']} is a TUM RGB-D sequence, which gives its own timestamps; "
        "leave fps unset"
    )
    assert error(data["euroc"], fps=30.0).startswith(f"fps: {data['euroc']} is a EuRoC/ASL")
    assert error(data["folder"], topic="/cam0/image_raw") == (
        f"topic: only for ROS bags; {data['folder']} is an image folder"
    )
    assert error(data["ros2"], fps=20.0) == (
        f"fps: {data['ros2']} is a ROS bag, which gives its own timestamps; leave fps unset"
    )


def test_bad_tum_lists(tmp_path, frames):
    root = write_tum(tmp_path / "tum", frames[:3])
    listing = root / "rgb.txt"
    lines = listing.read_text().splitlines()
    listing.write_text("\n".join([*lines[:4], lines[3]]) + "\n")
    assert error(root) == f"{listing}:5: time {float(tum_stamps()[0])} does not increase " + (
        f"(previous {float(tum_stamps()[0])})"
    )
    listing.write_text("1.0 rgb/missing.png\n")
    assert error(root) == f"{listing}:1: image {root / 'rgb' / 'missing.png'} does not exist"
    listing.write_text("# timestamp filename\n1.0\n")
    assert error(listing) == (
        f"{listing}:2: expected 'timestamp filename' (TUM RGB-D rgb.txt), got '1.0'"
    )


def test_bad_euroc_csv(tmp_path, frames):
    root = write_euroc(tmp_path / "e", frames[:2])
    csv = root / "mav0" / "cam0" / "data.csv"
    csv.write_text("#timestamp [ns],filename\n1.5,a.png\n")
    assert error(root) == (
        f"{csv}:2: expected 'timestamp [ns],filename' with an integer timestamp, got '1.5,a.png'"
    )
    (root / "mav0" / "cam0" / "sensor.yaml").write_text("sensor_type: imu\n")
    csv.write_text(f"#timestamp [ns],filename\n{STAMPS_NS[0]},{STAMPS_NS[0]}.png\n")
    sensor = root / "mav0" / "cam0" / "sensor.yaml"
    assert error(root) == f"{sensor}: sensor_type: expected camera, got 'imu'"


def test_a_bag_with_several_image_topics_needs_a_topic(tmp_path, frames):
    bag = write_bag(
        tmp_path / "two.bag",
        frames[:2],
        ros1=True,
        compressed=True,
        topics=("/cam0/image_raw", "/cam1/image_raw"),
    )
    assert error(bag) == (
        f"{bag}: 2 image topics, choose one with --topic: /cam0/image_raw, /cam1/image_raw"
    )
    assert error(bag, topic="/cam2/image_raw") == (
        f"topic: /cam2/image_raw is not an image topic of {bag} "
        "(image topics: /cam0/image_raw, /cam1/image_raw)"
    )
    # The chosen topic: its own camera_info (same namespace) for cam0, none for cam1.
    assert same_camera(open_recording(bag, topic="/cam0/image_raw").camera, CAMERA)
    cam1 = open_recording(bag, topic="/cam1/image_raw")
    assert cam1.times == SECONDS[:2] and cam1.camera is None


def test_a_missing_rosbags_package_is_one_line_naming_the_extra(data, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails
    assert error(data["ros1"]) == (
        f'{data["ros1"]}: reading ROS bags needs the rosbags package: pip install "hvo_graph[bags]"'
    )


def test_layouts_are_detected_from_the_path(data):
    assert [detect_layout(data[k]) for k in ("folder", "video", "tum", "euroc", "ros1")] == [
        "folder",
        "video",
        "tum",
        "euroc",
        "rosbag",
    ]


def test_a_config_file_can_give_the_frame_rate_and_run_json_names_the_layout(tmp_path, frames):
    import json

    import cv2

    folder = tmp_path / "seq"
    folder.mkdir()
    for k, image in enumerate(frames[:4]):
        assert cv2.imwrite(str(folder / f"{k}.png"), image)
    config = tmp_path / "run.yaml"
    config.write_text("fps: 25\n")
    out = tmp_path / "out"
    args = ["estimate", *camera_args(tmp_path), "--images", str(folder), "--config", str(config)]
    assert main([*args, "--method", "measurements", "--out", str(out)]) == 0
    assert list(read_tum(out / "trajectory.txt").t) == [k / 25.0 for k in range(4)]
    inputs = json.loads((out / "run.json").read_text())["inputs"]
    assert (inputs["images"], inputs["layout"]) == (str(folder), "folder")


def test_a_broken_video_and_a_bag_without_images(tmp_path, frames):
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video at all" * 10)
    assert error(broken) == f"{broken}: cannot open as a video"
    bag = write_bag(tmp_path / "info.bag", frames[:1], ros1=True, compressed=True, topics=())
    assert error(bag) == (
        f"{bag}: no sensor_msgs/Image or CompressedImage topic in the bag "
        "(topics: /cam0/camera_info)"
    )
