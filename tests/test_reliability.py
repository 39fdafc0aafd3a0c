"""Input hygiene and atomic outputs: a bad file is a one-line error naming file, line and
field (exit 2); an error or Ctrl-C while writing leaves the output folder as it was."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import hvo_graph.io.trajectory
from hvo_graph.cli import main
from hvo_graph.io._common import staged_output
from hvo_graph.sim.scenario import paper_scenario, simulate, write_scenario

COMMAND = Path(sys.executable).parent / "hvo-graph"
CAMERA = """\
camera:
  fx: 800.0
  fy: 800.0
  cx: 320.0
  cy: 240.0
  width: 640
  height: 480
plane:
  distance: 2.0
  normal: [0.0, 0.0, 1.0]
"""
TRACKS = "frame,t,id,u,v\n" + "".join(
    f"{k},{k / 30},{i},{100 + 50 * i + k},{120 + 30 * (i % 2)}\n"
    for k in range(3)
    for i in range(4)
)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("seq")
    write_scenario(root, simulate(paper_scenario(duration=1.0)))
    return root


def one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("hvo-graph: error: ")
    return err.removeprefix("hvo-graph: error: ")


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("[0.0, 0.0, 1.0]", "[0.0, 0.0, 2.0]", "cam.yaml:10: plane.normal: expected a unit vector "
         "(length 1), got length 2; did you mean [0, 0, 1]?"),
        ("[0.0, 0.0, 1.0]", "[0.0, -0.2, 1.0]", "cam.yaml:10: plane.normal: expected a unit "
         "vector (length 1), got length 1.0198; did you mean [0, -0.1961, 0.9806]?"),
        ("[0.0, 0.0, 1.0]", "[0.0, 0.0, 0.0]", "cam.yaml:10: plane.normal: expected a unit vector "
         "(length 1), got length 0"),
        ("fx: 800.0", "fx: .inf", "cam.yaml:2: camera.fx: expected a finite number, got inf"),
        ("cy: 240.0", "cy: .nan", "cam.yaml:5: camera.cy: expected a finite number, got nan"),
        ("distance: 2.0", "distance: 0",
         "cam.yaml:9: plane.distance: expected a finite number > 0, got 0.0"),
    ],
)  # fmt: skip
def test_bad_camera_files_are_one_line_errors(tmp_path, capsys, old, new, message):
    camera = tmp_path / "cam.yaml"
    camera.write_text(CAMERA.replace(old, new))
    (tmp_path / "t.csv").write_text(TRACKS)
    argv = ["estimate", "--camera", str(camera), "--tracks", str(tmp_path / "t.csv")]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    assert one_line_error(capsys) == str(tmp_path / message)
    assert not (tmp_path / "out").exists()


def test_a_normal_written_to_three_decimals_is_accepted_and_normalized(tmp_path):
    from hvo_graph.io.config import load_scene

    camera = tmp_path / "cam.yaml"
    camera.write_text(CAMERA.replace("[0.0, 0.0, 1.0]", "[0.0, -0.196, 0.981]"))
    n = load_scene(camera).plane.normal
    assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-15)
    assert n == pytest.approx(np.array([0.0, -0.196, 0.981]) / np.hypot(0.196, 0.981))


def test_duplicate_frame_id_rows_name_the_later_line(tmp_path, capsys):
    (tmp_path / "cam.yaml").write_text(CAMERA)
    lines = TRACKS.splitlines()
    lines.insert(5, lines[3].replace(",200,", ",201,"))  # frame 0 id 2 again, on line 6
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    argv = ["estimate", "--camera", str(tmp_path / "cam.yaml"), "--tracks", str(tmp_path / "t.csv")]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    assert (
        one_line_error(capsys)
        == f"{tmp_path / 't.csv'}:6: column 'id': id 2 appears twice in frame 0"
    )


def test_an_image_of_another_size_mid_sequence_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "cam.yaml").write_text(CAMERA)
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        shape = (480, 640) if k != 2 else (240, 320)
        cv2.imwrite(str(images / f"f{k}.png"), rng.integers(0, 255, shape, dtype=np.uint8))
    argv = ["estimate", "--camera", str(tmp_path / "cam.yaml"), "--images", str(images)]
    assert main([*argv, "--fps", "30", "--out", str(tmp_path / "out")]) == 2
    err = one_line_error(capsys)
    assert err.startswith(f"{images / 'f2.png'}: ") and "320x240" in err and "640x480" in err
    assert not (tmp_path / "out").exists()


# -- atomic outputs ----------------------------------------------------------------------------


def snapshot(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def test_an_estimate_interrupted_while_writing_leaves_the_old_output(
    sequence, tmp_path, capsys, monkeypatch
):
    out = tmp_path / "out"
    argv = ["estimate", "--camera", str(sequence / "camera.yaml")]
    argv += ["--tracks", str(sequence / "tracks.csv"), "--out", str(out)]
    assert main([*argv, "--method", "measurements"]) == 0
    (out / "mine.txt").write_text("the user's own file\n")
    before = snapshot(out)
    written = []

    def interrupted(directory, record):
        written.extend(p.name for p in Path(directory).iterdir())
        raise KeyboardInterrupt  # Ctrl-C after the trajectory files, before run.json

    monkeypatch.setattr(hvo_graph.io.trajectory, "write_run_record", interrupted)
    assert main([*argv, "--method", "smoother", "--covariance"]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert sorted(written) == ["covariance.csv", "trajectory.txt", "velocity.csv"]
    assert snapshot(out) == before  # old files intact, no new one, no staging folder


def test_a_new_estimate_removes_stale_files_of_the_old_one(sequence, tmp_path):
    out = tmp_path / "out"
    argv = ["estimate", "--camera", str(sequence / "camera.yaml")]
    argv += ["--tracks", str(sequence / "tracks.csv"), "--out", str(out)]
    assert main([*argv, "--covariance"]) == 0
    assert (out / "covariance.csv").exists()
    assert main(argv) == 0  # no covariances this time: the old file must go
    assert sorted(p.name for p in out.iterdir()) == ["run.json", "trajectory.txt", "velocity.csv"]


def test_simulate_interrupted_writes_nothing(tmp_path, monkeypatch):
    import hvo_graph.sim.scenario

    def interrupted(directory, truth):
        raise KeyboardInterrupt

    monkeypatch.setattr(hvo_graph.sim.scenario, "write_groundtruth_dir", interrupted)
    assert main(["simulate", "--out", str(tmp_path / "sim"), "--duration", "0.5"]) == 130
    assert list((tmp_path / "sim").iterdir()) == []


def test_staged_output_commits_all_or_nothing(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    with pytest.raises(RuntimeError), staged_output(tmp_path, owned=("a.txt", "b.txt")) as stage:
        (stage / "a.txt").write_text("new a")
        raise RuntimeError
    assert snapshot(tmp_path) == {"a.txt": b"old a"}
    with staged_output(tmp_path, owned=("a.txt", "b.txt")) as stage:
        (stage / "b.txt").write_text("b")
        (stage / "run.json").write_text("{}")
    assert snapshot(tmp_path) == {"b.txt": b"b", "run.json": b"{}"}  # a.txt was stale


def test_ctrl_c_on_a_running_estimate_leaves_all_or_nothing(tmp_path):
    """A real SIGINT at an arbitrary moment: exit 130 (or 0 if it had finished) and the
    folder holds either nothing or every file with a complete run.json."""
    write_scenario(tmp_path / "seq", simulate(paper_scenario(duration=20.0)))
    out = tmp_path / "out"
    argv = [str(COMMAND), "estimate", "--camera", str(tmp_path / "seq" / "camera.yaml")]
    argv += ["--tracks", str(tmp_path / "seq" / "tracks.csv"), "--out", str(out), "--covariance"]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(2.5)  # imports done, somewhere in the front end or the smoother
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode in (0, 130), err
    assert "Traceback" not in err
    names = sorted(os.listdir(out)) if out.exists() else []
    complete = ["covariance.csv", "run.json", "trajectory.txt", "velocity.csv"]
    assert names in ([], complete), names
    if process.returncode == 130:
        assert err.strip() == "hvo-graph: interrupted"


# -- determinism -------------------------------------------------------------------------------


def test_simulate_twice_writes_the_same_bytes(tmp_path):
    for name in ("a", "b"):
        assert (
            main(["simulate", "--out", str(tmp_path / name), "--duration", "1", "--seed", "4"]) == 0
        )
    assert snapshot(tmp_path / "a") == snapshot(tmp_path / "b")


@pytest.mark.parametrize(
    "method", ["smoother", "batch", "fixed-lag", "kalman", "measurements", "ippe"]
)
def test_estimate_twice_writes_the_same_bytes(sequence, tmp_path, method):
    import json

    argv = ["estimate", "--camera", str(sequence / "camera.yaml")]
    argv += ["--tracks", str(sequence / "tracks.csv"), "--method", method]
    if method not in ("measurements", "ippe"):
        argv.append("--covariance")
    outputs = []
    for name in ("first", "second"):
        assert main([*argv, "--out", str(tmp_path / name)]) == 0
        files = snapshot(tmp_path / name)
        record = json.loads(files.pop("run.json"))
        record.pop("wall_time_s")  # the only field allowed to differ
        outputs.append((files, record))
    assert outputs[0] == outputs[1]
    assert "trajectory.txt" in outputs[0][0]
