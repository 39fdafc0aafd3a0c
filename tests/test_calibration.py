"""Calibration files from other tools (OpenCV, ROS, Kalibr, EuRoC) and the fisheye lens model.

The equidistant model is checked against OpenCV's own cv2.fisheye.projectPoints;
the files are written as each tool writes them (OpenCV's through cv2.FileStorage
itself), and the camera read back must be the one written.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from layouts import CAMERA, NUM_FRAMES, PLANE, POSES, same_camera

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.calibration import load_calibration
from hvo_graph.io.config import SceneConfig, load_scene, save_scene
from hvo_graph.io.trajectory import read_tum
from hvo_graph.sim.render import render_plane_images

K = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
RADTAN = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
EQUI = np.array(
    [-0.013721808247486035, 0.020727425669427896, -0.012786476702685545, 0.0025242267320687625]
)


def euroc_cam(dist: np.ndarray = RADTAN, model: str = "radtan") -> CameraModel:
    return CameraModel(458.654, 457.296, 367.215, 248.375, 752, 480, dist, model)


# -- the equidistant (fisheye) model against OpenCV ---------------------------------------------


def fisheye_points(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Points up to ~60 deg off axis and their pixels by cv2.fisheye.projectPoints."""
    rng = np.random.default_rng(4)
    X = np.column_stack((rng.uniform(-1.7, 1.7, (200, 2)), rng.uniform(1.0, 2.0, 200)))
    uv, _ = cv2.fisheye.projectPoints(
        X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.distortion
    )
    return X, uv.reshape(-1, 2)


def test_equidistant_projection_matches_opencv_fisheye_and_round_trips():
    camera = euroc_cam(EQUI, "equidistant")
    X, uv = fisheye_points(camera)
    assert np.abs(camera.project(X) - uv).max() < 1e-9
    m = camera.pixel_to_normalized(uv)
    assert np.abs(m[:, :2] - X[:, :2] / X[:, 2:]).max() < 1e-12
    # Zero coefficients are still the equidistant lens (r = f theta), not a pinhole.
    plain = euroc_cam(np.zeros(4), "equidistant")
    assert plain.has_distortion
    x = np.array([[1.0, 0.0, 1.0]])  # 45 deg off axis
    assert plain.normalized_to_pixel(x)[0, 0] == pytest.approx(367.215 + 458.654 * np.pi / 4)


def test_fisheye_camera_round_trips_through_the_scene_yaml(tmp_path):
    scene = SceneConfig(euroc_cam(EQUI, "equidistant"), PLANE)
    save_scene(tmp_path / "c.yaml", scene)
    assert "distortion_model: equidistant" in (tmp_path / "c.yaml").read_text()
    assert same_camera(load_scene(tmp_path / "c.yaml").camera, scene.camera)


def test_bad_fisheye_settings():
    with pytest.raises(InputError) as info:
        CameraModel(1.0, 1.0, 0.0, 0.0, 10, 10, np.zeros(5), "equidistant")
    assert str(info.value) == (
        "camera.distortion: expected 4 finite equidistant (fisheye) coefficients k1 k2 k3 k4, got 5"
    )
    with pytest.raises(InputError) as info:
        CameraModel(1.0, 1.0, 0.0, 0.0, 10, 10, np.zeros(4), "omni")
    assert str(info.value) == (
        "camera.distortion_model: expected one of radtan, equidistant, got 'omni'"
    )


# -- files of other tools ----------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_filestorage_yaml_and_xml(tmp_path, suffix):
    path = tmp_path / f"left_intrinsics{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 752)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.append(RADTAN, 0.0).reshape(1, 5))
    fs.release()
    calibration = load_calibration(path)
    assert calibration.format == "opencv" and calibration.scene is None
    assert same_camera(calibration.camera, euroc_cam())


def test_opencv_fisheye_calibration(tmp_path):
    # As OpenCV's calibration sample writes a fisheye result (image_size as a sequence).
    path = tmp_path / "fisheye.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", EQUI.reshape(4, 1))
    fs.write("fisheye_model", 1)
    fs.release()
    path.write_text(path.read_text() + "image_size: [ 752, 480 ]\n")
    assert same_camera(load_calibration(path).camera, euroc_cam(EQUI, "equidistant"))


ROS_CAMERA_INFO = """\
image_width: 752
image_height: 480
camera_name: cam0
camera_matrix:
  rows: 3
  cols: 3
  data: [458.654, 0, 367.215, 0, 457.296, 248.375, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [458.654, 0, 367.215, 0, 0, 457.296, 248.375, 0, 0, 0, 1, 0]
"""

KALIBR_CAMCHAIN = """\
cam0:
  T_cam_imu:
  - [1.0, 0.0, 0.0, 0.0]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.013721808247486035, 0.020727425669427896, -0.012786476702685545,
    0.0025242267320687625]
  distortion_model: equidistant
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
cam1:
  camera_model: pinhole
  distortion_coeffs: [0.0, 0.0, 0.0, 0.0]
  distortion_model: radtan
  intrinsics: [400.0, 400.0, 376.0, 240.0]
  resolution: [752, 480]
  rostopic: /cam1/image_raw
"""

EUROC_SENSOR = """\
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


@pytest.mark.parametrize(
    ("name", "text", "fmt", "expected"),
    [
        ("camera_info.yaml", ROS_CAMERA_INFO, "ros", euroc_cam()),
        ("camchain.yaml", KALIBR_CAMCHAIN, "kalibr", euroc_cam(EQUI, "equidistant")),
        ("sensor.yaml", EUROC_SENSOR, "euroc", euroc_cam()),
    ],
)
def test_ros_kalibr_and_euroc_files(tmp_path, name, text, fmt, expected):
    (tmp_path / name).write_text(text)
    calibration = load_calibration(tmp_path / name)
    assert calibration.format == fmt
    assert same_camera(calibration.camera, expected)


def test_the_scene_yaml_is_read_whole(tmp_path):
    save_scene(tmp_path / "s.yaml", SceneConfig(CAMERA, PLANE, 0.3))
    calibration = load_calibration(tmp_path / "s.yaml")
    assert calibration.format == "scene" and calibration.scene.pixel_sigma == 0.3


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "a: 1\n",
            "{p}: not a camera calibration this program reads (expected the hvo-graph "
            "camera/scene YAML, an OpenCV FileStorage YAML/XML (camera_matrix, "
            "distortion_coefficients), a ROS camera_info YAML, a Kalibr camchain YAML or a "
            "EuRoC sensor.yaml)",
        ),
        (
            KALIBR_CAMCHAIN.replace("camera_model: pinhole", "camera_model: omni", 1),
            "{p}: cam0.camera_model: unsupported projection 'omni' (expected pinhole)",
        ),
        (
            EUROC_SENSOR.replace("radial-tangential", "fov"),
            "{p}: distortion_model: unsupported distortion model 'fov' (expected none, radtan, "
            "radial-tangential, plumb_bob, rational_polynomial, pinhole, equidistant, fisheye, "
            "equi)",
        ),
        (
            EUROC_SENSOR.replace("resolution: [752, 480]", "resolution: [752]"),
            "{p}: resolution: expected 2 finite numbers, got 1",
        ),
        (
            ROS_CAMERA_INFO.replace("image_height: 480\n", ""),
            "{p}: missing required key 'image_height'",
        ),
        (
            KALIBR_CAMCHAIN.replace(
                "distortion_model: equidistant", "distortion_model: radtan"
            ).replace("0.020727425669427896, ", ""),
            "{p}: cam0.distortion_coeffs: expected 0 or 4 or 5 or 8 or 12 or 14 finite numbers, "
            "got 3",
        ),
    ],
)
def test_bad_calibration_files(tmp_path, text, message):
    path = tmp_path / "calib.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_calibration(path)
    assert str(info.value) == message.format(p=path)


# -- on the command line -----------------------------------------------------------------------


def test_estimate_with_a_kalibr_fisheye_and_the_plane_flags(tmp_path):
    """Rendered through an equidistant lens, estimated from the camchain: poses match."""
    lens = np.array([0.02, -0.01, 0.004, -0.001])
    camera = CameraModel(CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, 320, 240, lens, "equidistant")
    frames = render_plane_images(camera, PLANE, POSES, noise_sigma=1.0, seed=3)
    folder = tmp_path / "seq"
    folder.mkdir()
    for k, image in enumerate(frames):
        assert cv2.imwrite(str(folder / f"{k}.png"), image)
    chain = tmp_path / "camchain.yaml"
    chain.write_text(
        "cam0:\n  camera_model: pinhole\n  distortion_model: equidistant\n"
        f"  distortion_coeffs: {lens.tolist()}\n"
        f"  intrinsics: {[CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy]}\n"
        "  resolution: [320, 240]\n"
    )
    normal = ",".join(repr(float(x)) for x in PLANE.normal)
    out = tmp_path / "out"
    args = ["estimate", "--camera", str(chain), "--images", str(folder), "--fps", "20"]
    args += ["--plane-distance", "2", "--plane-normal", normal, "--method", "measurements"]
    assert main([*args, "--out", str(out)]) == 0
    estimate = read_tum(out / "trajectory.txt")
    assert list(estimate.t) == [k / 20.0 for k in range(NUM_FRAMES)]
    truth = np.array([p.translation() for p in POSES])
    assert np.abs(np.asarray(estimate.positions) - truth).max() < 0.005


def test_plane_flags_where_they_do_not_apply_or_are_missing(tmp_path, capsys):
    scene = tmp_path / "scene.yaml"
    save_scene(scene, SceneConfig(CAMERA, PLANE))
    sensor = tmp_path / "sensor.yaml"
    sensor.write_text(EUROC_SENSOR)
    tracks = tmp_path / "tracks.csv"
    tracks.write_text("frame,t,id,u,v\n")
    folder = tmp_path / "seq"
    folder.mkdir()
    cv2.imwrite(str(folder / "0.png"), np.zeros((240, 320), np.uint8))

    def error(*args: str) -> str:
        capsys.readouterr()
        assert main(["estimate", *args, "--out", str(tmp_path / "o")]) == 2
        return capsys.readouterr().err.strip()

    assert error("--camera", str(scene), "--tracks", str(tracks), "--plane-distance", "1") == (
        f"hvo-graph: error: --plane-distance: {scene} already gives the plane "
        "(plane.distance); leave the plane flags out or edit the file"
    )
    assert error("--camera", str(sensor), "--tracks", str(tracks)) == (
        f"hvo-graph: error: --plane-distance: required with {sensor} (a calibration file), "
        "which gives no plane: d*, metres from the first frame's optical centre to the plane"
    )
    assert error("--images", str(folder), "--fps", "20", "--plane-distance", "1") == (
        "hvo-graph: error: --camera: required (camera/scene YAML or calibration file); "
        f"{folder} carries no calibration"
    )
    assert error("--camera", str(scene), "--tracks", str(tracks), "--topic", "/cam") == (
        "hvo-graph: error: --topic: only for --images input"
    )
    message = error("--camera", str(sensor), "--tracks", str(tracks), "--plane-normal", "1,0")
    assert message.endswith("argument --plane-normal: expected three numbers NX,NY,NZ, got '1,0'")


def test_a_bad_distortion_model_in_the_scene_yaml_names_its_line(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(
        "camera:\n  fx: 1\n  fy: 1\n  cx: 0\n  cy: 0\n  width: 4\n  height: 4\n"
        "  distortion_model: fisheye\nplane:\n  distance: 1\n"
    )
    with pytest.raises(InputError) as info:
        load_scene(path)
    assert str(info.value) == (
        f"{path}:8: camera.distortion_model: expected one of radtan, equidistant, got 'fisheye'"
    )
