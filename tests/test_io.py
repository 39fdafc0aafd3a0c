"""Round trips and error messages of the contract's file formats."""

from __future__ import annotations

import os
from pathlib import Path

import gtsam
import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.config import SceneConfig, load_scene, save_scene
from hvo_graph.io.tracks import read_tracks, write_tracks
from hvo_graph.io.trajectory import (
    COVARIANCE_HEADER,
    read_covariance,
    read_estimate_dir,
    read_groundtruth_dir,
    read_tum,
    read_velocity,
    write_covariance,
    write_estimate_dir,
    write_groundtruth_dir,
    write_tum,
    write_velocity,
)
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import FrameObservations, Plane, Trajectory

CONTRACT_YAML = """\
camera:
  fx: 800.0          # pixels
  fy: 800.0
  cx: 320.0
  cy: 240.0
  width: 640         # pixels
  height: 480
  distortion: [0.0, 0.0, 0.0, 0.0, 0.0]   # optional; OpenCV order k1 k2 p1 p2 k3
plane:
  distance: 2.0
  normal: [0.0, 0.0, 1.0]
noise:
  pixel_sigma: 0.2236
"""


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def scenario():
    return simulate(paper_scenario(duration=2.0, num_points=6, seed=2))


def random_trajectory(k: int = 20, seed: int = 0, twists: bool = True) -> Trajectory:
    rng = np.random.default_rng(seed)
    R = np.array([gtsam.Rot3.Expmap(rng.normal(size=3)).matrix() for _ in range(k)])
    return Trajectory(
        t=np.cumsum(rng.uniform(0.01, 0.1, size=k)),
        rotations=R,
        positions=rng.normal(size=(k, 3)),
        twists=rng.normal(size=(k, 6)) if twists else None,
    )


# ---------------------------------------------------------------- YAML


def test_contract_yaml_example_loads(tmp_path):
    scene = load_scene(write(tmp_path / "camera.yaml", CONTRACT_YAML))
    assert (scene.camera.fx, scene.camera.fy, scene.camera.cx, scene.camera.cy) == (
        800.0,
        800.0,
        320.0,
        240.0,
    )
    assert (scene.camera.width, scene.camera.height) == (640, 480)
    np.testing.assert_array_equal(scene.plane.normal, [0, 0, 1])
    assert scene.plane.distance == 2.0
    assert scene.pixel_sigma == 0.2236


def test_yaml_optional_keys_may_be_absent(tmp_path):
    text = "camera: {fx: 500, fy: 501, cx: 1.5e2, cy: 1e2, width: 300, height: 200}\n"
    text += "plane:\n  distance: 1e-1\n"
    scene = load_scene(write(tmp_path / "c.yaml", text))
    assert scene.plane.normal is None and scene.pixel_sigma is None
    assert scene.camera.cy == 100.0 and scene.plane.distance == 0.1  # YAML 1.1 '1e2' is a string
    np.testing.assert_array_equal(scene.camera.distortion, np.zeros(5))


@pytest.mark.parametrize("with_optional", [True, False])
def test_yaml_round_trip(tmp_path, with_optional):
    camera = CameraModel(
        fx=812.25,
        fy=799.1 / 3,
        cx=321.7,
        cy=239.3,
        width=1280,
        height=720,
        distortion=np.array([-0.1, 0.01, 1e-4, -2e-4, 0.003]) if with_optional else np.zeros(5),
    )
    plane = Plane(2.5, np.array([0.1, -0.2, 1.0]) if with_optional else None)
    scene = SceneConfig(camera, plane, np.sqrt(0.05) if with_optional else None)
    save_scene(tmp_path / "s.yaml", scene)
    back = load_scene(tmp_path / "s.yaml")
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        assert getattr(back.camera, key) == getattr(camera, key)
    np.testing.assert_array_equal(back.camera.distortion, camera.distortion)
    assert back.plane.distance == plane.distance
    if with_optional:
        # Plane re-normalises n*: equal to the last bit or so
        np.testing.assert_allclose(back.plane.normal, plane.normal, rtol=0, atol=3e-16)
    else:
        assert back.plane.normal is None
    assert back.pixel_sigma == scene.pixel_sigma


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("  fx: 800.0", "  fz: 800.0", "c.yaml:2: unknown key 'camera.fz'"),
        ("noise:", "nois:", "c.yaml:12: unknown key 'nois'"),
        ("  fy: 800.0\n", "", "c.yaml:1: missing required key 'camera.fy'"),
        ("  distance: 2.0\n", "", "c.yaml:9: missing required key 'plane.distance'"),
        ("  distance: 2.0", "  distance: -2.0", "c.yaml:10: plane.distance: expected a finite"),
        ("  fx: 800.0", "  fx: abc", "c.yaml:2: camera.fx: expected a number, got 'abc'"),
        ("  fx: 800.0", "  fx: .nan", "c.yaml:2: camera.fx: expected a finite number"),
        ("  width: 640", "  width: 640.5", "c.yaml:6: camera.width: expected an integer"),
        ("  height: 480", "  height: true", "c.yaml:7: camera.height: expected a number"),
        ("  fy: 800.0", "  fx: 1.0", "c.yaml:3: duplicate key 'camera.fx'"),
        ("  normal: [0.0, 0.0, 1.0]", "  normal: [0.0, 1.0]", "c.yaml:11: plane.normal: expected"),
        ("  normal: [0.0, 0.0, 1.0]", "  normal: 1.0", "c.yaml:11: plane.normal: expected a list"),
        ("  pixel_sigma: 0.2236", "  pixel_sigma: -1", "c.yaml:13: noise.pixel_sigma: expected"),
        ("  cx: 320.0", "  cx: [1", "c.yaml:5: not valid YAML"),
        (
            "  distortion: [0.0, 0.0, 0.0, 0.0, 0.0]",
            "  distortion: [0.1, 0.2]",
            "c.yaml:8: camera.distortion",
        ),
    ],
)
def test_yaml_errors_name_file_line_and_key(tmp_path, old, new, message):
    assert old in CONTRACT_YAML
    path = write(tmp_path / "c.yaml", CONTRACT_YAML.replace(old, new))
    with pytest.raises(InputError) as info:
        load_scene(path)
    assert str(info.value).startswith(str(tmp_path / message)), str(info.value)


def test_yaml_missing_section_and_empty_file(tmp_path):
    text = CONTRACT_YAML.split("plane:")[0]
    with pytest.raises(InputError, match=r"c\.yaml:1: missing required key 'plane'"):
        load_scene(write(tmp_path / "c.yaml", text))
    with pytest.raises(InputError, match=r"e\.yaml:1: expected a mapping"):
        load_scene(write(tmp_path / "e.yaml", "# nothing\n"))
    with pytest.raises(InputError, match=r"l\.yaml:1: expected a YAML file of a mapping"):
        load_scene(write(tmp_path / "l.yaml", "- 1\n- 2\n"))
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "missing.yaml")


# ---------------------------------------------------------------- tracks

TRACKS = """\
frame,t,id,u,v
0,0.0,0,100.0,200.0
0,0.0,1,110.5,201.25
1,0.1,0,101.0,199.0
1,0.1,1,111.5,200.25
1,0.1,7,50.0,60.0
"""


def test_tracks_read_hand_written_file(tmp_path):
    frames = read_tracks(write(tmp_path / "t.csv", TRACKS))
    assert [f.index for f in frames] == [0, 1]
    assert [f.t for f in frames] == [0.0, 0.1]
    np.testing.assert_array_equal(frames[1].ids, [0, 1, 7])
    np.testing.assert_array_equal(frames[1].uv, [[101.0, 199.0], [111.5, 200.25], [50.0, 60.0]])
    assert frames[0].ids.dtype == np.int64


def test_tracks_frame_gaps_keep_their_numbers(tmp_path):
    text = "frame,t,id,u,v\n0,0,0,1,2\n1,0.5,0,1,2\n3,1.5,0,1,2\n\n"
    frames = read_tracks(write(tmp_path / "t.csv", text))
    assert [f.index for f in frames] == [0, 1, 3]
    assert [f.t for f in frames] == [0.0, 0.5, 1.5]


def test_tracks_round_trip_is_exact(tmp_path, scenario):
    write_tracks(tmp_path / "t.csv", scenario.observations)
    back = read_tracks(tmp_path / "t.csv")
    assert len(back) == len(scenario.observations)
    for a, b in zip(scenario.observations, back, strict=True):
        assert (a.index, a.t) == (b.index, b.t)
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.uv, b.uv)


def test_tracks_large_file_and_error_on_its_last_line(tmp_path):
    rng = np.random.default_rng(0)
    n_frames, n_points = 3000, 100
    obs = [
        FrameObservations(k, k / 30.0, np.arange(n_points), rng.uniform(0, 640, (n_points, 2)))
        for k in range(n_frames)
    ]
    path = tmp_path / "big.csv"
    write_tracks(path, obs)
    back = read_tracks(path)
    assert len(back) == n_frames
    np.testing.assert_array_equal(back[-1].uv, obs[-1].uv)
    # a bad value on the very last line is found and named
    lines = path.read_text().splitlines()
    lines[-1] = lines[-1].rsplit(",", 1)[0] + ",x1"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as info:
        read_tracks(path)
    assert str(info.value) == f"{path}:{len(lines)}: column 'v': expected a number, got 'x1'"


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("frame,t,id,u,v", "frame,t,id,u", ":1: expected the header line 'frame,t,id,u,v', got"),
        ("frame,t,id,u,v", "frame t id u v", ":1: expected the header line 'frame,t,id,u,v'"),
        ("0,0.0,1,110.5,201.25", "0,0.0,1,110.5", ":3: expected 5 comma-separated values"),
        (
            "1,0.1,0,101.0,199.0",
            "1,0.1,0,abc,199.0",
            ":4: column 'u': expected a number, got 'abc'",
        ),
        ("1,0.1,0,101.0,199.0", "1,0.1,0,,199.0", ":4: column 'u': expected a number, got ''"),
        ("1,0.1,0,101.0,199.0", "1,0.1,0,nan,199.0", ":4: column 'u': expected a finite number"),
        ("1,0.1,0,101.0,199.0", "1,0.1,0,101.0,inf", ":4: column 'v': expected a finite number"),
        ("1,0.1,7,50.0,60.0", "0,0.1,7,50.0,60.0", ":6: column 'frame': frame numbers must not"),
        (
            "1,0.1,0,101.0,199.0",
            "-1,0.1,0,101.0,199.0",
            ":4: column 'frame': expected an integer >= 0",
        ),
        ("1,0.1,0,101.0,199.0", "1.5,0.1,0,101.0,199.0", ":4: column 'frame': expected an integer"),
        ("1,0.1,7,50.0,60.0", "1,0.1,7.2,50.0,60.0", ":6: column 'id': expected an integer"),
        (  # beyond 2^53 a float64 no longer holds every integer: ids would merge
            "1,0.1,7,50.0,60.0",
            "1,0.1,9007199254740993,50.0,60.0",
            ":6: column 'id': expected an integer below 2^53",
        ),
        ("1,0.1,7,50.0,60.0", "1,0.2,7,50.0,60.0", ":6: column 't': expected the same time"),
        ("0.1", "0.0", ":4: column 't': time must increase strictly"),
        (
            "1,0.1,7,50.0,60.0",
            "1,0.1,1,50.0,60.0",
            ":6: column 'id': id 1 appears twice in frame 1",
        ),
        ("0,0.0,1,110.5,201.25\n", "0,0.0,1,110.5,201.25\n\n", ":4: expected a row"),
    ],
)
def test_tracks_errors_name_file_and_line(tmp_path, old, new, message):
    assert old in TRACKS
    path = write(tmp_path / "tracks.csv", TRACKS.replace(old, new))
    with pytest.raises(InputError) as info:
        read_tracks(path)
    assert str(info.value).startswith(f"{path}{message}"), str(info.value)


def test_tracks_header_only_and_empty(tmp_path):
    with pytest.raises(InputError, match=r"h\.csv:2: expected at least one observation row"):
        read_tracks(write(tmp_path / "h.csv", "frame,t,id,u,v\n"))
    with pytest.raises(InputError, match=r"e\.csv:1: expected the header line"):
        read_tracks(write(tmp_path / "e.csv", ""))
    with pytest.raises(InputError, match=r"b\.csv: expected a UTF-8 text file"):
        (tmp_path / "b.csv").write_bytes(b"\xff\xfe\x00frame")
        read_tracks(tmp_path / "b.csv")


def test_write_tracks_rejects_bad_frames(tmp_path):
    ok = FrameObservations(0, 0.0, np.array([0, 1]), np.zeros((2, 2)))
    with pytest.raises(InputError, match=r"observations\[1\] \(frame 0\): frame index and time"):
        write_tracks(tmp_path / "t.csv", [ok, ok])
    dup = FrameObservations(0, 0.0, np.array([3, 3]), np.zeros((2, 2)))
    with pytest.raises(InputError, match="ids must be unique integers"):
        write_tracks(tmp_path / "t.csv", [dup])
    assert not (tmp_path / "t.csv").exists()


# ---------------------------------------------------------------- TUM


def test_tum_reads_a_textbook_quaternion(tmp_path):
    """qx qy qz qw = (0, 0, sin 45, cos 45): 90 deg about z, R = [[0,-1,0],[1,0,0],[0,0,1]]."""
    s = float(np.sqrt(0.5))
    text = f"# comment\n\n1.5 1 2 3 0 0 {s!r} {s!r}\n  # another\n2.5 0 0 0 0 0 0 1\n"
    traj = read_tum(write(tmp_path / "a.txt", text))
    np.testing.assert_array_equal(traj.t, [1.5, 2.5])
    np.testing.assert_allclose(traj.rotations[0], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_array_equal(traj.positions[0], [1, 2, 3])
    assert traj.twists is None


def test_tum_writes_a_textbook_quaternion(tmp_path):
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    write_tum(tmp_path / "a.txt", Trajectory(np.array([3.0]), R[None], np.array([[1.0, 2.0, 3.0]])))
    lines = (tmp_path / "a.txt").read_text().splitlines()
    assert lines[0].startswith("#")
    values = np.array(lines[1].split(), dtype=float)
    np.testing.assert_allclose(values, [3, 1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


def test_tum_round_trip(tmp_path):
    traj = random_trajectory(50)
    write_tum(tmp_path / "x.txt", traj)
    back = read_tum(tmp_path / "x.txt")
    np.testing.assert_array_equal(back.t, traj.t)
    np.testing.assert_array_equal(back.positions, traj.positions)
    np.testing.assert_allclose(back.rotations, traj.rotations, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("2.0 0 0 0 0 0 1", ":3: expected 8 space-separated values"),
        ("2.0 0 0 zero 0 0 0 1", ":3: column 'tz': expected a number, got 'zero'"),
        ("2.0 0 0 0 0 0 0 0.9", ":3: expected a unit quaternion"),
        ("0.5 0 0 0 0 0 0 1", ":3: timestamp must be strictly increasing"),
        ("2.0 0 0 nan 0 0 0 1", ":3: column 'tz': expected a finite number"),
    ],
)
def test_tum_errors_name_file_and_line(tmp_path, line, message):
    path = write(tmp_path / "tr.txt", f"# header\n1.0 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(InputError) as info:
        read_tum(path)
    assert str(info.value).startswith(f"{path}{message}"), str(info.value)


def test_tum_writer_rejects_non_rotations(tmp_path):
    traj = random_trajectory(3)
    traj.rotations[1] *= 1.01
    with pytest.raises(InputError, match=r"trajectory\.rotations\[1\]: not a rotation matrix"):
        write_tum(tmp_path / "x.txt", traj)


# ---------------------------------------------------------------- velocity, covariance


def test_velocity_file_puts_v_before_w(tmp_path):
    twist = np.array([[0.1, 0.2, 0.3, 1.0, 2.0, 3.0]])  # [w; v]
    write_velocity(tmp_path / "v.csv", np.array([0.5]), twist)
    assert (tmp_path / "v.csv").read_text() == "t,vx,vy,vz,wx,wy,wz\n0.5,1.0,2.0,3.0,0.1,0.2,0.3\n"
    _, back = read_velocity(tmp_path / "v.csv")
    np.testing.assert_array_equal(back, twist)


def test_velocity_round_trip_with_unknown_rows(tmp_path):
    traj = random_trajectory(30)
    traj.twists[4] = np.nan
    write_velocity(tmp_path / "v.csv", traj.t, traj.twists)
    t, twists = read_velocity(tmp_path / "v.csv")
    np.testing.assert_array_equal(t, traj.t)
    np.testing.assert_array_equal(twists, traj.twists)  # NaN == NaN for assert_array_equal


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "t,wx,wy,wz,vx,vy,vz\n0,1,2,3,4,5,6\n",
            ":1: expected the header line 't,vx,vy,vz,wx,wy,wz'",
        ),
        ("t,vx,vy,vz,wx,wy,wz\n0,1,2,3,4,5\n", ":2: expected 7 comma-separated values"),
        ("t,vx,vy,vz,wx,wy,wz\n0,1,2,3,4,5,6\n0,1,2,3,4,5,6\n", ":3: t must be strictly"),
        ("t,vx,vy,vz,wx,wy,wz\n0,1,nan,3,4,5,6\n", ":2: expected finite velocities"),
        ("t,vx,vy,vz,wx,wy,wz\n", ":2: expected at least one row"),
    ],
)
def test_velocity_errors(tmp_path, text, message):
    path = write(tmp_path / "velocity.csv", text)
    with pytest.raises(InputError) as info:
        read_velocity(path)
    assert str(info.value).startswith(f"{path}{message}"), str(info.value)


def test_covariance_round_trip_and_layout(tmp_path):
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 12, 12))
    cov = A @ A.transpose(0, 2, 1)
    t = np.array([0.0, 0.1, 0.2, 0.3])
    write_covariance(tmp_path / "c.csv", t, cov)
    lines = (tmp_path / "c.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert lines[0] == COVARIANCE_HEADER
    assert len(header) == 79 and header[:3] == ["t", "c_0_0", "c_0_1"] and header[-1] == "c_11_11"
    row = [float(x) for x in lines[2].split(",")]
    assert row[header.index("c_0_11")] == cov[1, 0, 11]
    assert row[header.index("c_3_7")] == cov[1, 3, 7]
    t_back, cov_back = read_covariance(tmp_path / "c.csv")
    np.testing.assert_array_equal(t_back, t)
    np.testing.assert_array_equal(cov_back, cov)


# ---------------------------------------------------------------- folders


def test_estimate_dir_round_trip_with_covariance(tmp_path):
    traj = random_trajectory(10)
    traj.covariances = np.broadcast_to(np.eye(12) * 0.01, (10, 12, 12)).copy()
    write_estimate_dir(tmp_path / "est" / "sub", traj)
    names = sorted(os.listdir(tmp_path / "est" / "sub"))
    assert names == ["covariance.csv", "trajectory.txt", "velocity.csv"]
    back = read_estimate_dir(tmp_path / "est" / "sub")
    np.testing.assert_array_equal(back.positions, traj.positions)
    np.testing.assert_array_equal(back.twists, traj.twists)
    np.testing.assert_array_equal(back.covariances, traj.covariances)


def test_estimate_dir_without_twists_replaces_stale_files(tmp_path):
    old = random_trajectory(6)
    old.covariances = np.broadcast_to(np.eye(12), (6, 12, 12)).copy()
    write_estimate_dir(tmp_path, old)
    write_estimate_dir(tmp_path, random_trajectory(5, twists=False))
    assert sorted(os.listdir(tmp_path)) == ["trajectory.txt"]
    back = read_estimate_dir(tmp_path)
    assert back.twists is None and back.covariances is None


def test_groundtruth_dir_round_trip(tmp_path, scenario):
    write_groundtruth_dir(tmp_path, scenario.groundtruth)
    assert sorted(os.listdir(tmp_path)) == ["groundtruth.txt", "groundtruth_velocity.csv"]
    back = read_groundtruth_dir(tmp_path)
    gt = scenario.groundtruth
    np.testing.assert_array_equal(back.t, gt.t)
    np.testing.assert_array_equal(back.positions, gt.positions)
    np.testing.assert_array_equal(back.twists, gt.twists)
    np.testing.assert_allclose(back.rotations, gt.rotations, rtol=0, atol=2e-16 * 8)


def test_dir_with_mismatched_velocity_times_is_an_error(tmp_path):
    traj = random_trajectory(5)
    write_estimate_dir(tmp_path, traj)
    write_velocity(tmp_path / "velocity.csv", traj.t[:4], traj.twists[:4])
    with pytest.raises(InputError, match=r"velocity\.csv: expected the same timestamps as"):
        read_estimate_dir(tmp_path)
    with pytest.raises(InputError, match="expected a directory"):
        read_estimate_dir(tmp_path / "nope")
    (tmp_path / "trajectory.txt").unlink()
    with pytest.raises(FileNotFoundError):
        read_estimate_dir(tmp_path)


# ---------------------------------------------------------------- atomic writes


def test_failed_write_leaves_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "trajectory.txt"
    write_tum(path, random_trajectory(3))
    before = path.read_text()

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="No space left"):
        write_tum(path, random_trajectory(4, seed=1))
    assert path.read_text() == before
    assert os.listdir(tmp_path) == ["trajectory.txt"]


def test_written_files_have_ordinary_permissions(tmp_path):
    write_velocity(tmp_path / "v.csv", np.array([0.0]), np.zeros((1, 6)))
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "v.csv").stat().st_mode & 0o777 == 0o666 & ~umask


def test_tum_quaternions_are_gtsams_digit_for_digit(tmp_path: Path) -> None:
    """write_tum converts all rotations at once; every line equals the one gtsam's own
    Rot3.toQuaternion gives (SVD projection first, qw >= 0), including rotations by pi,
    the identity and slightly non-orthonormal input."""
    rng = np.random.default_rng(4)
    rotations = [gtsam.Rot3.Expmap(rng.normal(size=3) * s).matrix() for s in (0.01, 1, 3) * 400]
    rotations += [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    rotations += [
        gtsam.Rot3.Expmap(np.array(a) * (np.pi - 1e-9)).matrix()
        for a in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0.0])
    ]
    R = np.array(rotations)
    R[:50] += rng.normal(size=(50, 3, 3)) * 1e-9
    t = np.arange(len(R)) / 30.0
    p = rng.normal(size=(len(R), 3))
    write_tum(tmp_path / "t.txt", Trajectory(t=t, rotations=R, positions=p))
    lines = [s for s in (tmp_path / "t.txt").read_text().splitlines() if not s.startswith("#")]
    for tk, Rk, pk, line in zip(t, R, p, lines, strict=True):
        U, _, Vt = np.linalg.svd(Rk)
        exact = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        q = gtsam.Rot3(exact).toQuaternion()
        qv = np.array([q.x(), q.y(), q.z(), q.w()])
        qv = -qv if qv[3] < 0 else qv
        assert line == " ".join(repr(float(x) + 0.0) for x in (tk, *pk, *qv))
