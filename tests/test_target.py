"""The plane n*, d* from a target in the first image (``hvo-graph plane``, ``--plane auto``).

Boards are rendered at a known pose: the board image (a chessboard drawn here, or
OpenCV's own ChArUco / ArUco board images) is warped into the camera by the
homography of that pose, at 4x resolution and averaged down (anti-aliased). The
true plane is n* = R e_z (flipped to point away from the camera), d* = n*^T t; the
board's origin and in-plane axes do not matter (the plane does not depend on them).
"""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.frontend.target import (
    TargetSpec,
    chessboard_points,
    parse_target,
    plane_from_height,
    plane_from_target,
    target_board,
)
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.config import load_scene

CAMERA = CameraModel(600.0, 600.0, 319.5, 239.5, 640, 480)
SUPERSAMPLE = 4


def rotation(rx_deg: float, ry_deg: float) -> np.ndarray:
    return cv2.Rodrigues(np.deg2rad([rx_deg, ry_deg, 0.0]))[0]


def true_plane(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    n = R[:, 2]
    d = float(n @ t)
    return (n, d) if d > 0 else (-n, -d)


def render_board(pattern: np.ndarray, metres_per_px: float, R, t, camera=CAMERA) -> np.ndarray:
    """The board image ``pattern`` (pixel (u, v) centred at ((u + .5) s, (v + .5) s, 0) on
    the board, s = metres_per_px) seen by ``camera`` at board pose (R, t), gray uint8."""
    s = SUPERSAMPLE
    K = camera.K.copy()
    K[:2] *= s
    K[:2, 2] += (s - 1) / 2  # pixel centres of the fine grid
    m = metres_per_px
    to_board = np.array([[m, 0, m / 2], [0, m, m / 2], [0, 0, 1]])
    H = K @ np.column_stack((R[:, 0], R[:, 1], t)) @ to_board
    size = (camera.width * s, camera.height * s)
    fine = cv2.warpPerspective(pattern, H, size, flags=cv2.INTER_LINEAR, borderValue=128)
    return cv2.resize(fine, (camera.width, camera.height), interpolation=cv2.INTER_AREA)


def chessboard_image(columns: int, rows: int, px: int = 40) -> np.ndarray:
    """Inner corners columns x rows, one white square of margin, ``px`` pixels a square."""
    squares = np.indices((rows + 1, columns + 1)).sum(axis=0) % 2
    board = np.kron(1 - squares, np.ones((px, px))) * 255
    return np.pad(board, px, constant_values=255).astype(np.uint8)


POSES = [
    (rotation(20.0, -15.0), np.array([-0.15, -0.1, 0.45])),
    (rotation(-35.0, 10.0), np.array([-0.17, -0.12, 0.6])),
]


@pytest.mark.parametrize(("R", "t"), POSES)
def test_chessboard_plane_within_half_a_degree_and_one_percent(R, t):
    square = 0.03
    image = render_board(chessboard_image(9, 6), square / 40, R, t)
    found = plane_from_target(image, CAMERA, parse_target("chessboard:9x6:0.03"))
    n, d = true_plane(R, t)
    assert np.degrees(np.arccos(np.clip(found.plane.normal @ n, -1, 1))) < 0.5
    assert abs(found.plane.distance - d) < 0.01 * d
    assert found.plane.normal[2] > 0 and found.rms_px < 0.3
    assert len(found.image_points) == 54


@pytest.mark.parametrize(
    "spec", ["charuco:7x5:0.04:0.03:DICT_5X5_100", "aruco:4x3:0.04:0.01:DICT_4X4_50"]
)
def test_aruco_boards_give_the_plane(spec):
    target = parse_target(spec)
    board = target_board(target)
    width_m = (
        target.columns * target.square
        if target.kind == "charuco"
        else target.columns * target.marker + (target.columns - 1) * target.gap
    )
    height_m = width_m * (target.rows / target.columns) if target.kind == "charuco" else (
        target.rows * target.marker + (target.rows - 1) * target.gap
    )  # fmt: skip
    px_per_m = 4000
    pattern = board.generateImage((round(width_m * px_per_m), round(height_m * px_per_m)), 0, 0)
    pattern = np.pad(pattern, 80, constant_values=255)
    R, t = POSES[0]
    image = render_board(pattern, 1.0 / px_per_m, R, t - R @ [0.02, 0.02, 0])
    found = plane_from_target(image, CAMERA, target)
    n, d = true_plane(R, t)
    assert np.degrees(np.arccos(np.clip(found.plane.normal @ n, -1, 1))) < 0.5
    assert abs(found.plane.distance - d) < 0.01 * d


def test_plane_from_height_and_tilt():
    # A floor point straight below a level camera is at (0, h, 0); looking straight
    # down, the floor is z = h.
    assert np.allclose(plane_from_height(1.5, 0.0).normal, [0, 1, 0])
    down = plane_from_height(2.0, 90.0)
    assert np.allclose(down.normal, [0, 0, 1]) and down.distance == 2.0
    tilted = plane_from_height(1.2, 30.0)
    # The optical axis hits the floor at range h / sin(tilt).
    hit = np.array([0, 0, 1.2 / np.sin(np.deg2rad(30.0))])
    assert np.isclose(tilted.normal @ hit, tilted.distance)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("board:9x6:0.02", "expected one of chessboard:COLSxROWS:SQUARE"),
        ("chessboard:9x6", "expected chessboard:COLSxROWS:SQUARE"),
        ("chessboard:9by6:0.02", "expected chessboard:COLSxROWS:SQUARE"),
        ("chessboard:1x6:0.02", "at least 2x2"),
        ("chessboard:9x6:0", "SQUARE: expected a finite number > 0"),
        ("charuco:5x7:0.04:0.05:DICT_4X4_50", "MARKER must be smaller than SQUARE"),
        ("aruco:5x7:0.04:-0.01:DICT_4X4_50", "GAP: expected a finite number > 0"),
        ("charuco:5x7:0.04:nan:DICT_4X4_50", "MARKER: expected a finite number > 0"),
        ("charuco:5x7:0.04:0.03:DICT_NOPE", "unknown ArUco dictionary 'DICT_NOPE'"),
    ],
)
def test_bad_target_specs_are_named(spec, message):
    with pytest.raises(InputError, match=message):
        parse_target(spec)


def test_a_missing_target_is_an_error():
    blank = np.full((CAMERA.height, CAMERA.width), 128, np.uint8)
    with pytest.raises(InputError, match="no chessboard 9x6 found in the image"):
        plane_from_target(blank, CAMERA, TargetSpec("chessboard", 9, 6, 0.03))


def test_chessboard_points_follow_opencv_order():
    points = chessboard_points(3, 2, 0.5)
    assert points[:, :2].tolist() == [[0, 0], [0.5, 0], [1, 0], [0, 0.5], [0.5, 0.5], [1, 0.5]]
    assert not points[:, 2].any()


CAMERA_YAML = """camera:
  fx: 600.0
  fy: 600.0
  cx: 319.5
  cy: 239.5
  width: 640
  height: 480
noise:
  pixel_sigma: 0.3
"""


def test_plane_command_writes_a_complete_camera_file(tmp_path, capsys):
    R, t = POSES[1]
    cv2.imwrite(str(tmp_path / "first.png"), render_board(chessboard_image(9, 6), 0.03 / 40, R, t))
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    out = tmp_path / "scene.yaml"
    args = ["plane", "--camera", str(tmp_path / "camera.yaml"), "--out", str(out)]
    assert (
        main([*args, "--target", "chessboard:9x6:0.03", "--image", str(tmp_path / "first.png")])
        == 0
    )
    assert "chessboard 9x6: 54 corners" in capsys.readouterr().out
    scene = load_scene(out)
    n, d = true_plane(R, t)
    assert abs(scene.plane.distance - d) < 0.01 * d
    assert np.degrees(np.arccos(scene.plane.normal @ n)) < 0.5
    assert scene.camera.fx == 600.0 and scene.pixel_sigma == 0.3
    assert main([*args, "--height", "1.5", "--tilt", "90"]) == 0
    assert np.allclose(load_scene(out).plane.normal, [0, 0, 1])


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "give either --target and --image, or --height and --tilt"),
        (["--height", "1", "--target", "chessboard:9x6:0.03"], "give either"),
        (["--height", "1"], "--tilt: required with --height"),
        (["--target", "chessboard:9x6:0.03"], "--image: required with --target"),
        (["--height", "1", "--tilt", "95"], r"tilt: expected degrees in \(-90, 90\]"),
    ],
)
def test_plane_command_usage_errors(tmp_path, capsys, extra, message):
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    args = ["plane", "--camera", str(tmp_path / "camera.yaml"), "--out", str(tmp_path / "o.yaml")]
    assert main([*args, *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hvo-graph: error:") and len(err.strip().splitlines()) == 1
    assert __import__("re").search(message, err), err
    assert not (tmp_path / "o.yaml").exists()


def test_estimate_plane_auto_takes_the_plane_from_the_first_image(tmp_path):
    """A board the camera moves over: --plane auto finds d*, n* in frame 0 and estimates."""
    R0, t0 = POSES[0]
    pattern = chessboard_image(9, 6)
    folder = tmp_path / "images"
    folder.mkdir()
    for k in range(8):  # the camera slides 2 mm per frame along its x axis
        t = t0 - np.array([0.002 * k, 0.0, 0.0])
        cv2.imwrite(str(folder / f"{k:03d}.png"), render_board(pattern, 0.03 / 40, R0, t))
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    out = tmp_path / "est"
    result = subprocess.run(
        [sys.executable, "-m", "hvo_graph", "estimate", "--camera", str(tmp_path / "camera.yaml"),
         "--images", str(folder), "--fps", "10", "--plane", "auto",
         "--target", "chessboard:9x6:0.03", "--method", "measurements", "--out", str(out)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    record = json.loads((out / "run.json").read_text())
    _, d = true_plane(R0, t0)
    assert abs(record["plane"]["distance"] - d) < 0.01 * d
    assert record["inputs"]["target"] == "chessboard:9x6:0.03"
    last = np.loadtxt(out / "trajectory.txt")[-1]
    assert np.allclose(last[1:4], [0.014, 0, 0], atol=0.01 * d)  # 7 steps of 2 mm along x


def test_estimate_plane_auto_needs_images_and_a_target(tmp_path, capsys):
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    base = ["estimate", "--camera", str(tmp_path / "camera.yaml"), "--out", str(tmp_path / "e")]
    assert main([*base, "--images", str(tmp_path), "--plane", "auto"]) == 2
    assert "--plane auto: needs --target" in capsys.readouterr().err
    assert (
        main([*base, "--tracks", "x.csv", "--plane", "auto", "--target", "chessboard:9x6:1"]) == 2
    )
    assert "--plane auto: needs --images" in capsys.readouterr().err


def board_over_a_static_background(pattern, metres_per_px, R, t) -> np.ndarray:
    """The board at pose (R, t) in front of a static textured wall (anti-aliased edges)."""
    from hvo_graph.sim.render import make_texture

    wall = cv2.resize(make_texture(512, seed=7), (CAMERA.width, CAMERA.height))
    wall = cv2.normalize(wall, None, 30, 225, cv2.NORM_MINMAX).astype(np.float64)
    board = render_board(pattern, metres_per_px, R, t).astype(np.float64)
    cover = render_board(np.full_like(pattern, 255), metres_per_px, R, t).astype(np.float64)
    alpha = np.clip((cover - 128.0) / 127.0, 0.0, 1.0)
    return np.rint(alpha * board + (1 - alpha) * wall).astype(np.uint8)


def board_homography(R_a, t_a, R_b, t_b, camera=CAMERA) -> np.ndarray:
    """Pixels of board points in view a -> view b: K [r1 r2 t]_b (K [r1 r2 t]_a)^-1."""
    G_a = camera.K @ np.column_stack((R_a[:, 0], R_a[:, 1], t_a))
    G_b = camera.K @ np.column_stack((R_b[:, 0], R_b[:, 1], t_b))
    return G_b @ np.linalg.inv(G_a)


@pytest.mark.parametrize("spec", ["chessboard:9x6:0.03", "charuco:7x5:0.04:0.03:DICT_5X5_100"])
def test_the_tracker_told_the_target_follows_the_board_across_a_wide_baseline(spec):
    """Two views of a board that moved 35+ degrees before a static camera and a static
    textured wall: told the target, the tracker keeps to the board (its corners aligned
    under the homography of the board's corners) and lands on the board points' true
    projections; not told, it follows the wall, the larger plane, which did not move."""
    from hvo_graph.frontend.tracking import track_images

    target = parse_target(spec)
    if target.kind == "chessboard":
        pattern, metres_per_px = chessboard_image(9, 6), target.square / 40
    else:
        px_per_m = 4000
        size = (round(target.columns * target.square * px_per_m),
                round(target.rows * target.square * px_per_m))  # fmt: skip
        pattern = np.pad(target_board(target).generateImage(size, 0, 0), 80, constant_values=255)
        metres_per_px = 1.0 / px_per_m
    (R_a, t_a), (R_b, t_b) = POSES
    views = [board_over_a_static_background(pattern, metres_per_px, R, t) for R, t in POSES]
    H = board_homography(R_a, t_a, R_b, t_b)

    first, second = track_images(views, [0.0, 1.0], CAMERA, target=target)
    _, ia, ib = np.intersect1d(first.ids, second.ids, return_indices=True)
    moved = cv2.perspectiveTransform(first.uv[ia].reshape(-1, 1, 2), H).reshape(-1, 2)
    errors = np.linalg.norm(moved - second.uv[ib], axis=1)
    assert len(errors) >= 30
    assert np.median(errors) < 0.1 and errors.max() < 0.5, (np.median(errors), errors.max())

    first, second = track_images(views, [0.0, 1.0], CAMERA)
    _, ia, ib = np.intersect1d(first.ids, second.ids, return_indices=True)
    still = np.linalg.norm(first.uv[ia] - second.uv[ib], axis=1)
    assert len(still) >= 30 and np.median(still) < 0.1
