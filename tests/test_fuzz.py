"""Property-based fuzzing (hypothesis) of every reader and of the geometry: whatever the
bytes or numbers, only the documented error types escape (InputError for bad content;
the command line turns it into one line and exit 2). A crash of any other type is a bug."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.continuous import (
    decompose_continuous_homography,
    estimate_continuous_homography,
    velocity_known_normal,
)
from hvo_graph.geometry.decomposition import (
    decompose_homography,
    motion_from_homography_known_normal,
)
from hvo_graph.geometry.discrete import estimate_homography, euclidean_homography
from hvo_graph.io.config import load_scene
from hvo_graph.io.images import read_times
from hvo_graph.io.tracks import read_tracks
from hvo_graph.io.trajectory import (
    read_covariance,
    read_estimate_dir,
    read_tum,
    read_velocity,
)
from hvo_graph.types import Plane

# Huge finite inputs (1e308) overflow inside numpy on their way to an InputError: expected.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

FUZZ = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)

CAMERA = """\
camera:
  fx: 800.0
  fy: 800.0
  cx: 320.0
  cy: 240.0
  width: 640
  height: 480
  distortion: [0.0, 0.0, 0.0, 0.0, 0.0]
plane:
  distance: 2.0
  normal: [0.0, -0.196, 0.981]
noise:
  pixel_sigma: 0.2236
"""
TRACKS = "frame,t,id,u,v\n" + "".join(
    f"{k},{k / 30!r},{i},{200.0 + 100 * (i % 2) + k},{150.0 + 100 * (i // 2) - k}\n"
    for k in range(4)
    for i in range(4)
)
TUM = "# t tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.5 0.1 0 0 0 0 0.0998 0.995\n"
VELOCITY = "t,vx,vy,vz,wx,wy,wz\n0.0,0,0,0,0,0,0\n0.5,0.1,0,0,0,0,0.2\n"
COVARIANCE = "t," + ",".join(f"c{i}" for i in range(78)) + "\n"  # replaced by a real one below
TIMES = "0.0\n0.033\n0.067\n"

#: Tokens that provoke parsers: numbers of every kind, separators, YAML syntax.
TOKENS = st.sampled_from(
    ["nan", "inf", "-inf", "1e309", "-0", "0", "1", "-1", "1e-300", "0x10", "1_0", ",", " ",
     "\t", "\n", "#", ":", "[", "]", "{", "}", "- ", "~", "null", "true", "'", '"', "&a", "*a",
     "!!python", "\x00", "é", "\ufeff", "\r\n", "9" * 30, "frame,t,id,u,v", "---", "..."]
)  # fmt: skip


def mutations(valid: str) -> st.SearchStrategy[str]:
    """Texts near a valid file: a span replaced by provoking tokens, or random text."""

    @st.composite
    def mutate(draw: st.DrawFn) -> str:
        i = draw(st.integers(0, len(valid)))
        j = draw(st.integers(i, min(len(valid), i + 40)))
        insert = "".join(draw(st.lists(TOKENS | st.text(max_size=4), max_size=4)))
        return valid[:i] + insert + valid[j:]

    return mutate() | st.text(max_size=200)


def only_documented(call: Callable[[], object]) -> None:
    try:
        call()
    except InputError as exc:
        assert "\n" not in str(exc), f"a multi-line message: {exc!r}"


def written(data: str | bytes, name: str, folder: Path) -> Path:
    path = folder / name
    path.write_bytes(data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data)
    return path


def _covariance_text() -> str:
    from hvo_graph.io.trajectory import write_covariance

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "covariance.csv"
        write_covariance(path, np.array([0.0, 0.5]), np.stack([np.eye(12), 2 * np.eye(12)]))
        return path.read_text()


COVARIANCE = _covariance_text()

READERS: dict[str, tuple[str, Callable[[Path], object]]] = {
    "camera.yaml": (CAMERA, load_scene),
    "tracks.csv": (TRACKS, read_tracks),
    "trajectory.txt": (TUM, read_tum),
    "velocity.csv": (VELOCITY, read_velocity),
    "covariance.csv": (COVARIANCE, read_covariance),
    "times.txt": (TIMES, lambda p: read_times(p, 3)),
}


def test_the_valid_files_read(tmp_path: Path) -> None:
    for name, (text, reader) in READERS.items():
        reader(written(text, name, tmp_path))


@FUZZ
@given(st.sampled_from(sorted(READERS)), st.data())
def test_readers_raise_only_input_errors(name: str, data: st.DataObject) -> None:
    valid, reader = READERS[name]
    text = data.draw(mutations(valid) | st.binary(max_size=100).map(bytes), label="content")
    with tempfile.TemporaryDirectory() as folder:
        only_documented(lambda: reader(written(text, name, Path(folder))))


@FUZZ
@given(mutations(TUM), mutations(VELOCITY))
def test_estimate_folders_raise_only_input_errors(tum: str, velocity: str) -> None:
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        written(tum, "trajectory.txt", folder)
        written(velocity, "velocity.csv", folder)
        only_documented(lambda: read_estimate_dir(folder))


@settings(FUZZ, max_examples=40)
@given(mutations(CAMERA), mutations(TRACKS), st.sampled_from(["measurements", "smoother"]))
def test_the_command_line_exits_0_or_2_on_any_camera_and_tracks(camera, tracks, method) -> None:
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        argv = ["estimate", "--camera", str(written(camera, "camera.yaml", folder))]
        argv += ["--tracks", str(written(tracks, "tracks.csv", folder))]
        out = folder / "out"
        status = main([*argv, "--method", method, "--out", str(out)])
        assert status in (0, 2)
        if status == 2:  # nothing half-written
            assert not out.exists() or os.listdir(out) == []


# -- geometry --------------------------------------------------------------------------------

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64) | st.floats(-2.0, 2.0)


def arrays(rows: st.SearchStrategy[int], cols: st.SearchStrategy[int]):
    return st.tuples(rows, cols).flatmap(
        lambda shape: st.lists(
            FLOATS, min_size=shape[0] * shape[1], max_size=shape[0] * shape[1]
        ).map(lambda v: np.array(v, dtype=float).reshape(shape))
    )


POINTS = arrays(st.integers(0, 8), st.sampled_from([2, 3]))
MATRIX = arrays(st.just(3), st.just(3)) | arrays(st.integers(0, 4), st.integers(0, 4))
VECTOR = arrays(st.just(1), st.integers(2, 4)).map(lambda a: a[0])


@FUZZ
@given(POINTS, POINTS, st.none() | st.floats(-1.0, 1.0))
def test_homography_estimation_raises_only_input_errors(m_ref, m_cur, threshold) -> None:
    only_documented(lambda: estimate_homography(m_ref, m_cur, ransac_threshold=threshold))
    only_documented(lambda: estimate_continuous_homography(m_ref, m_cur))


@FUZZ
@given(MATRIX, POINTS, POINTS, VECTOR)
def test_homography_decompositions_raise_only_input_errors(H, m_ref, m_cur, normal) -> None:
    only_documented(lambda: euclidean_homography(H, m_ref, m_cur))
    only_documented(lambda: decompose_homography(H))
    only_documented(lambda: motion_from_homography_known_normal(H, normal))
    only_documented(lambda: decompose_continuous_homography(H))


@FUZZ
@given(POINTS, POINTS, VECTOR, FLOATS)
def test_velocity_from_flow_raises_only_input_errors(m, mdot, normal, distance) -> None:
    only_documented(lambda: velocity_known_normal(m, mdot, normal, distance))
    only_documented(lambda: Plane(distance, normal))


@FUZZ
@given(st.lists(FLOATS, min_size=4, max_size=4), st.lists(FLOATS, min_size=2, max_size=2), POINTS)
@example([1.0, 1.0, 0.0, 0.0], [np.inf, 0.0], np.zeros((0, 2)))  # int(inf): OverflowError once
@example([1.0, 1.0, 0.0, 0.0], [np.nan, 480.0], np.zeros((0, 2)))
def test_camera_model_raises_only_input_errors(focal_centre, size, uv) -> None:
    def run() -> None:
        fx, fy, cx, cy = focal_centre
        width, height = size
        camera = CameraModel(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
        m = camera.pixel_to_normalized(uv)
        camera.normalized_to_pixel(m)

    only_documented(run)
