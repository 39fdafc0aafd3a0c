"""The hvo-graph command line, in process (main) and as an installed command (subprocess)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hvo_graph.pipeline
from hvo_graph import cli
from hvo_graph.cli import main
from hvo_graph.io.config import load_scene
from hvo_graph.io.tracks import read_tracks
from hvo_graph.sim.scenario import paper_scenario, simulate

COMMAND = Path(sys.executable).parent / "hvo-graph"


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(COMMAND), *args], capture_output=True, text=True, timeout=120, check=False
    )


def as_estimate(sim_dir: Path, out: Path) -> Path:
    """An estimate folder holding the ground truth itself."""
    out.mkdir()
    shutil.copy(sim_dir / "groundtruth.txt", out / "trajectory.txt")
    shutil.copy(sim_dir / "groundtruth_velocity.csv", out / "velocity.csv")
    return out


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("hvo-graph: error: ")
    for fragment in fragments:
        assert fragment in lines[0]


def test_simulate_then_evaluate_groundtruth_against_itself(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim)]) == 0
    for name in ("camera.yaml", "tracks.csv", "groundtruth.txt", "groundtruth_velocity.csv"):
        assert (sim / name).is_file()
    scene = load_scene(sim / "camera.yaml")
    assert scene.pixel_sigma == pytest.approx(np.sqrt(0.05))
    assert len(read_tracks(sim / "tracks.csv")) == 301
    capsys.readouterr()

    est = as_estimate(sim, tmp_path / "est")
    assert main(["evaluate", "--estimate", str(est), "--groundtruth", str(sim), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["frames"] == 301
    for key in ("position_m", "orientation_deg", "linear_velocity_mps", "angular_velocity_radps"):
        assert result[key] == {"rmse": 0.0, "max": 0.0}

    assert main(["evaluate", "--estimate", str(est), "--groundtruth", str(sim), "--skip", "1"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("method") and "pos RMSE [m]" in table[0]
    assert table[1].split()[0] == "est" and table[1].split()[-1] == "271"


def test_simulate_options_match_the_library(tmp_path):
    args = ["--noise-var", "0", "--duration", "2", "--fps", "10", "--num-points", "6"]
    assert main(["simulate", "--out", str(tmp_path), "--seed", "3", *args]) == 0
    expected = simulate(paper_scenario(noise_var=0.0, duration=2.0, fps=10.0, num_points=6, seed=3))
    frames = read_tracks(tmp_path / "tracks.csv")
    assert len(frames) == 21
    for got, want in zip(frames, expected.clean_observations, strict=True):
        assert got.t == want.t
        np.testing.assert_array_equal(got.uv, want.uv)
    assert load_scene(tmp_path / "camera.yaml").pixel_sigma == 0.0


def test_installed_command_end_to_end(tmp_path):
    sim = tmp_path / "sim"
    result = run("simulate", "--out", str(sim), "--duration", "2")
    assert result.returncode == 0 and result.stderr == ""  # no progress when not a TTY
    est = as_estimate(sim, tmp_path / "est")
    result = run("evaluate", "--estimate", str(est), "--groundtruth", str(sim), "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["position_m"] == {"rmse": 0.0, "max": 0.0}
    module = subprocess.run(
        [sys.executable, "-m", "hvo_graph", "--help"], capture_output=True, text=True, check=False
    )
    assert module.returncode == 0 and "simulate" in module.stdout and "evaluate" in module.stdout


def test_estimate_measurements_end_to_end(tmp_path):
    """simulate (noise-free) -> estimate --method measurements -> evaluate."""
    sim, est = tmp_path / "sim", tmp_path / "est"
    assert run("simulate", "--out", str(sim), "--noise-var", "0", "--duration", "3").returncode == 0
    camera, tracks = str(sim / "camera.yaml"), str(sim / "tracks.csv")
    result = run("estimate", "--camera", camera, "--tracks", tracks, "--method", "measurements",
                 "--out", str(est))  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert (est / "trajectory.txt").is_file() and (est / "velocity.csv").is_file()
    result = run("evaluate", "--estimate", str(est), "--groundtruth", str(sim), "--json")
    errors = json.loads(result.stdout)
    assert errors["frames"] == 91
    # noise-free homographies give the pose to round-off; finite-difference flow
    # gives the velocity to a small discretisation error (a sign error would be ~0.3).
    assert errors["position_m"]["max"] < 1e-8
    assert errors["orientation_deg"]["max"] < 1e-6
    assert errors["linear_velocity_mps"]["rmse"] < 0.01
    assert errors["angular_velocity_radps"]["rmse"] < 0.01


def test_estimate_is_a_thin_layer_over_the_pipeline(tmp_path, monkeypatch):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "1"]) == 0
    calls = []
    real = hvo_graph.pipeline.run_estimate

    def spy(observations, scene, method="smoother", **options):
        calls.append((len(observations), scene.plane.distance, method, dict(options)))
        return real(observations, scene, method, **options)

    monkeypatch.setattr(hvo_graph.pipeline, "run_estimate", spy)
    base = ["estimate", "--camera", str(sim / "camera.yaml"), "--tracks", str(sim / "tracks.csv")]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    assert calls[-1] == (31, 2.0, "smoother", {})
    extra = ["--method", "fixed-lag", "--lag", "2", "--robust", "none", "--online"]
    extra += ["--covariance", "--acceleration-sigma", "0.1,0.2", "--no-ransac", "--gate-chi2", "9"]
    assert main([*base, "--out", str(tmp_path / "b"), *extra, "--pixel-sigma", "0.5"]) == 0
    assert calls[-1][2:] == (
        "fixed-lag",
        {
            "online": True,
            "covariance": True,
            "lag": 2.0,
            "robust": None,
            "acceleration_sigma": (0.1, 0.2),
            "pixel_sigma": 0.5,
            "outlier_chi2": 9.0,
            "ransac": False,
        },
    )
    assert (tmp_path / "b" / "trajectory.txt").is_file()
    kalman = ["--method", "kalman", "--seed", "4", "--kalman-r", "measured"]
    assert main([*base, "--out", str(tmp_path / "c"), *kalman, "--kalman-world-velocity"]) == 0
    assert calls[-1][3] == {"seed": 4, "kalman_r": "measured", "kalman_world_velocity": True}


def test_cli_methods_are_the_pipeline_methods():
    assert cli.METHODS == hvo_graph.pipeline.METHODS


def test_bad_inputs_exit_2_with_one_line(tmp_path):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "1"]) == 0

    missing = tmp_path / "nothing"
    assert_one_line_error(
        run("evaluate", "--estimate", str(missing), "--groundtruth", str(sim)),
        f"{missing}: expected a directory",
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_one_line_error(
        run("evaluate", "--estimate", str(empty), "--groundtruth", str(sim)),
        f"{empty / 'trajectory.txt'}: No such file or directory",
    )
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text((sim / "camera.yaml").read_text().replace("  fx:", "  fz:"))
    tracks = str(sim / "tracks.csv")
    assert_one_line_error(
        run(
            "estimate", "--camera", str(bad_yaml), "--tracks", tracks, "--out", str(tmp_path / "o")
        ),
        f"{bad_yaml}:3: unknown key 'camera.fz'",
    )
    assert_one_line_error(
        run("estimate", "--camera", tracks, "--tracks", tracks, "--out", str(tmp_path / "o")),
        f"{tracks}: not a camera calibration this program reads (expected the hvo-graph "
        "camera/scene YAML, an OpenCV FileStorage YAML/XML",
    )
    bad_tracks = tmp_path / "bad.csv"
    lines = (sim / "tracks.csv").read_text().splitlines()
    lines[5] = lines[5].replace(",", ";")
    bad_tracks.write_text("\n".join(lines))
    camera = str(sim / "camera.yaml")
    assert_one_line_error(
        run("estimate", "--camera", camera, "--tracks", str(bad_tracks), "--out", str(tmp_path)),
        f"{bad_tracks}:6: expected 5 comma-separated values",
    )
    assert_one_line_error(
        run("estimate", "--camera", camera, "--tracks", str(tmp_path / "no.csv"), "--out", "x"),
        f"{tmp_path / 'no.csv'}: No such file or directory",
    )
    empty_images = tmp_path / "no_images"
    empty_images.mkdir()
    assert_one_line_error(
        run("estimate", "--camera", camera, "--images", str(empty_images), "--out", "x"),
        f"{empty_images}: no images and no known layout in the folder (expected an image folder",
    )
    assert_one_line_error(
        run("estimate", "--camera", camera, "--tracks", tracks, "--fps", "30", "--out", "x"),
        "--fps: only for --images input",
    )
    assert_one_line_error(
        run("estimate", "--camera", camera, "--tracks", tracks, "--compensate-exposure",
            "--out", "x"),
        "--compensate-exposure: only for --images input",
    )  # fmt: skip


@pytest.mark.parametrize("method", ["smoother", "ippe"])
def test_a_flipped_plane_normal_is_named_and_writes_nothing(tmp_path, method):
    # n* points from the camera towards the plane; flipped, every point of frame 0 is
    # behind it (n*^T m <= 0). IPPE used to run on and write a mirrored trajectory.
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "1"]) == 0
    text = (sim / "camera.yaml").read_text()
    n = re.search(r"normal: \[([^\]]*)\]", text)
    assert n is not None
    normal = [float(c) for c in n.group(1).split(",")]
    flipped_text = ", ".join(repr(-c) for c in normal)
    camera = tmp_path / "flipped.yaml"
    camera.write_text(text.replace(n.group(0), f"normal: [{flipped_text}]"))
    out = tmp_path / "out"
    result = run(
        "estimate", "--camera", str(camera), "--tracks", str(sim / "tracks.csv"),
        "--method", method, "--out", str(out),
    )  # fmt: skip
    original = ", ".join(f"{c:g}" for c in normal)
    assert_one_line_error(
        result,
        f"{camera}: plane.normal: 4 of the 4 points of frame 0 are behind the plane as given "
        "(n*^T m <= 0); n* points from the camera towards the plane (the flipped normal "
        f"would be [{original}])",
    )
    assert not out.exists()


def test_a_camera_that_does_not_translate_is_warned_about_the_fitted_normal(tmp_path):
    from hvo_graph.io.config import SceneConfig, save_scene
    from hvo_graph.io.tracks import write_tracks
    from hvo_graph.types import Plane

    s = simulate(
        paper_scenario(duration=3.0, num_points=6, linear_amplitude=(0, 0, 0),
                       angular_amplitude=(0.0, -0.05, 0.1))
    )  # fmt: skip
    camera, tracks = tmp_path / "camera.yaml", tmp_path / "tracks.csv"
    save_scene(camera, SceneConfig(s.camera, Plane(s.plane.distance, None), s.pixel_sigma))
    write_tracks(tracks, s.observations)
    result = run(
        "estimate", "--camera", str(camera), "--tracks", str(tracks), "--out", str(tmp_path / "o")
    )
    assert result.returncode == 0, result.stderr
    assert "standard deviation 90.00 deg" in result.stderr
    assert (
        "hvo-graph estimate: warning: no frame translates measurably against the first "
        "(the camera turns or stands still): these tracks cannot tell n*"
    ) in result.stderr
    record = json.loads((tmp_path / "o" / "run.json").read_text())
    assert record["plane_normal_fit"]["translation_chi2"] < 27.34


def test_ippe_without_a_plane_normal_names_the_camera_file_key(tmp_path):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "1"]) == 0
    camera = tmp_path / "no_normal.yaml"
    lines = (sim / "camera.yaml").read_text().splitlines()
    camera.write_text("\n".join(line for line in lines if "normal:" not in line) + "\n")
    result = run(
        "estimate", "--camera", str(camera), "--tracks", str(sim / "tracks.csv"),
        "--method", "ippe", "--out", str(tmp_path / "out"),
    )  # fmt: skip
    assert_one_line_error(
        result,
        f"{camera}: plane.normal: required by method 'ippe' (IPPE does not estimate n*; "
        "the homography methods do)",
    )


@pytest.mark.parametrize(
    "args",
    [
        ["simulate"],
        ["simulate", "--out", "x", "--num-points", "3"],
        ["simulate", "--out", "x", "--fps", "0"],
        ["simulate", "--out", "x", "--scenario", "other"],
        ["estimate", "--camera", "c.yaml", "--out", "x"],
        ["estimate", "--camera", "c", "--tracks", "t", "--images", "i", "--out", "x"],
        ["estimate", "--camera", "c", "--tracks", "t", "--out", "x", "--method", "magic"],
        ["evaluate", "--estimate", "e"],
        ["frobnicate"],
        [],
    ],
)
def test_usage_errors_exit_2(args, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error:" in err


def test_usage_error_via_subprocess_has_no_traceback():
    result = run("simulate", "--out", "x", "--noise-var", "-1")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "--noise-var: expected a finite number >= 0" in result.stderr


def test_estimate_from_images_end_to_end(tmp_path):
    """Rendered images of the paper's plane -> KLT tracks -> poses that match the truth."""
    import cv2

    from hvo_graph.io.trajectory import write_groundtruth_dir
    from hvo_graph.sim.render import render_plane_images
    from hvo_graph.sim.scenario import paper_scenario, simulate

    scenario = simulate(paper_scenario(noisy=False, duration=1.0, fps=15.0))
    truth = scenario.groundtruth
    images = render_plane_images(
        scenario.camera, scenario.plane, list(zip(truth.rotations, truth.positions, strict=True))
    )
    folder = tmp_path / "images"
    folder.mkdir()
    for k, image in enumerate(images):
        cv2.imwrite(str(folder / f"frame{k:04d}.png"), image)
    (folder / "times.txt").write_text("".join(f"{t:.17g}\n" for t in truth.t))
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "1", "--fps", "15"]) == 0
    write_groundtruth_dir(sim, truth)
    out = tmp_path / "est"
    tracks = tmp_path / "tracks.csv"
    args = ["estimate", "--camera", str(sim / "camera.yaml"), "--images", str(folder)]
    args += ["--method", "measurements", "--out", str(out), "--save-tracks", str(tracks)]
    assert main(args) == 0
    assert tracks.read_text().startswith("frame,t,id,u,v\n")
    result = run("evaluate", "--estimate", str(out), "--groundtruth", str(sim), "--json")
    errors = json.loads(result.stdout)
    assert errors["frames"] == len(truth)
    assert errors["position_m"]["max"] < 0.01
    assert errors["orientation_deg"]["max"] < 0.2
