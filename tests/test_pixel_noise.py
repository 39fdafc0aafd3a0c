"""The pixel noise read from the tracks when the camera file does not give it.

References: the simulator's own pixel noise (the sigma it drew the tracks with),
and, for what the estimate is for, the ground-truth trajectory.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from hvo_graph.cli import main
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.frontend.pixel_noise import estimate_pixel_sigma
from hvo_graph.io.config import load_scene
from hvo_graph.io.tracks import read_track_table, read_tracks
from hvo_graph.pipeline import DEFAULT_PIXEL_SIGMA, run_estimate
from hvo_graph.sim.families import draw
from hvo_graph.sim.scenario import paper_scenario, simulate, write_scenario
from hvo_graph.types import FrameObservations


@pytest.mark.parametrize(
    "scenario",
    [
        simulate(paper_scenario(seed=2)),  # 4 points, 0.22 px
        simulate(paper_scenario(seed=3, noise_var=1.0, duration=20.0)),  # 1 px
        draw("10fps", 0).scenario,  # fast motion between frames
        draw("precise", 1).scenario,  # 20 points, 0.1 px
        draw("outliers-dropouts", 0).scenario,  # off-plane tracks, dropped frames
    ],
    ids=["paper", "1px", "10fps", "precise", "outliers-dropouts"],
)
def test_the_estimate_recovers_the_simulated_noise(scenario):
    noise = estimate_pixel_sigma(scenario.observations)
    assert noise is not None and noise.differences >= 1000
    assert noise.sigma == pytest.approx(scenario.pixel_sigma, rel=0.08)


def test_jumps_and_uneven_frames_do_not_count():
    scenario = simulate(paper_scenario(seed=4, noise_var=0.25))
    rng = np.random.default_rng(0)
    jumped = []
    for obs in scenario.observations:  # 1 % of the points off by 20 px (tracker slips)
        uv = obs.uv + 20.0 * (rng.random((len(obs.ids), 1)) < 0.01)
        jumped.append(dataclasses.replace(obs, uv=uv))
    noise = estimate_pixel_sigma(jumped)
    assert noise is not None and noise.sigma == pytest.approx(0.5, rel=0.12)
    # every other interval twice as long: no window of evenly spaced frames is left
    t = np.cumsum([0.0] + [1 / 30 if k % 2 else 2 / 30 for k in range(len(jumped) - 1)])
    uneven = [dataclasses.replace(obs, t=float(t[k])) for k, obs in enumerate(jumped)]
    assert estimate_pixel_sigma(uneven) is None
    assert estimate_pixel_sigma(scenario.observations[:5]) is None  # one window per point
    empty = [
        FrameObservations(k, k / 30, np.empty(0, np.int64), np.empty((0, 2))) for k in range(9)
    ]
    assert estimate_pixel_sigma(empty) is None


@pytest.mark.parametrize(("every", "readable"), [(10, True), (20, False), (60, False)])
def test_motion_between_frames_is_not_taken_for_noise(every, readable):
    """The paper's motion seen at 3, 1.5 and 0.5 frames/s: at 1.5 the fifth differences
    still hold motion (the estimates of orders 4 and 6 disagree, 3x the noise); at 0.5
    the orders agree, but on 22 px, more than a tracker's noise: no estimate."""
    scenario = simulate(paper_scenario(seed=7, duration=300.0, num_points=8))
    frames = [
        dataclasses.replace(obs, index=k) for k, obs in enumerate(scenario.observations[::every])
    ]
    noise = estimate_pixel_sigma(frames)
    if readable:
        assert noise is not None and noise.sigma == pytest.approx(scenario.pixel_sigma, rel=0.08)
    else:
        assert noise is None


def test_a_tracks_file_gives_the_same_estimate_as_its_frames(tmp_path):
    scenario = simulate(paper_scenario(seed=5, duration=5.0))
    write_scenario(tmp_path, scenario)
    listed = estimate_pixel_sigma(read_tracks(tmp_path / "tracks.csv"))
    table = estimate_pixel_sigma(read_track_table(tmp_path / "tracks.csv"))
    assert listed == table and listed is not None


def test_a_camera_file_without_noise_takes_the_tracks_noise(tmp_path, capsys):
    """1 px tracks, a camera file without ``noise``: the paper's 0.22 px would make every
    covariance 20x too confident and the fitted process noise absorb the rest."""
    scenario = simulate(paper_scenario(seed=6, noise_var=1.0, duration=20.0))
    truth = scenario.groundtruth
    estimated = run_estimate(scenario.observations, dataclasses.replace(scenario, pixel_sigma=None))
    assert estimated.pixel_noise is not None
    assert estimated.front_end.pixel_sigma == estimated.pixel_noise.sigma
    assert estimated.pixel_noise.sigma == pytest.approx(1.0, rel=0.08)
    default = run_estimate(
        scenario.observations, scenario, pixel_sigma=DEFAULT_PIXEL_SIGMA
    ).trajectory
    ours = summarize(error_series(estimated.trajectory, truth), t_start=1.0)
    paper = summarize(error_series(default, truth), t_start=1.0)
    assert ours.linear_velocity_rmse < 0.5 * paper.linear_velocity_rmse
    assert ours.angular_velocity_rmse < 0.5 * paper.angular_velocity_rmse
    # given (camera file or option), it is never replaced
    given = run_estimate(scenario.observations, scenario)
    assert given.pixel_noise is None and given.front_end.pixel_sigma == scenario.pixel_sigma

    # the command line says so, and writes it to run.json
    write_scenario(tmp_path / "sim", scenario)
    camera = tmp_path / "camera.yaml"
    text = (tmp_path / "sim" / "camera.yaml").read_text()
    camera.write_text(text[: text.index("noise:")])
    assert load_scene(camera).pixel_sigma is None
    args = ["estimate", "--camera", str(camera), "--tracks", str(tmp_path / "sim" / "tracks.csv")]
    assert main([*args, "--out", str(tmp_path / "est")]) == 0
    err = capsys.readouterr().err
    assert "pixel noise sigma = " in err and "read from the tracks" in err
    record = json.loads((tmp_path / "est" / "run.json").read_text())
    sigma = record["pixel_noise_estimated"]["sigma"]
    assert sigma == pytest.approx(1.0, rel=0.08) and record["front_end"]["pixel_sigma"] == sigma
    assert record["pixel_noise_estimated"]["used"] is True


def test_tracks_more_precise_than_the_paper_keep_its_noise(tmp_path, capsys):
    """0.1 px tracks: read and reported, but the paper's 0.2236 px stays in force (the
    differences cannot see errors that neighbouring tracks share, the bulk of the pose
    error on image tracks), so the covariances are not made more confident."""
    scenario = draw("precise", 1).scenario
    unknown = dataclasses.replace(scenario, pixel_sigma=None)
    run = run_estimate(scenario.observations, unknown, "measurements")
    assert run.pixel_noise is not None and run.pixel_noise_used is False
    assert run.pixel_noise.sigma == pytest.approx(0.1, rel=0.08)
    assert run.front_end.pixel_sigma == DEFAULT_PIXEL_SIGMA
    write_scenario(tmp_path / "sim", scenario)
    camera = tmp_path / "camera.yaml"
    text = (tmp_path / "sim" / "camera.yaml").read_text()
    camera.write_text(text[: text.index("noise:")])
    args = ["estimate", "--camera", str(camera), "--tracks", str(tmp_path / "sim" / "tracks.csv")]
    assert main([*args, "--method", "measurements", "--out", str(tmp_path / "est")]) == 0
    record = json.loads((tmp_path / "est" / "run.json").read_text())
    noise = record["pixel_noise_estimated"]["sigma"]  # from the CSV's rounded pixels
    assert noise == pytest.approx(run.pixel_noise.sigma, rel=0.01)
    assert (
        f"hvo-graph estimate: the tracks' frame-to-frame noise is {noise:.3g} px; the pixel "
        "sigma stays 0.2236 px, since errors that neighbouring tracks share do not show in "
        "it (the camera file's noise.pixel_sigma or --pixel-sigma sets it)"
    ) in capsys.readouterr().err.splitlines()
    assert record["pixel_noise_estimated"]["used"] is False
    assert record["front_end"]["pixel_sigma"] == DEFAULT_PIXEL_SIGMA


def test_the_tight_graph_rejecting_every_track_is_an_error(tmp_path, capsys):
    # 1 px tracks said to be 0.1 px: every track fails the plane test; the trajectory
    # would be the motion model's start state (metres and 100 degrees off), written as if
    # it were an estimate.
    scenario = simulate(paper_scenario(seed=7, noise_var=1.0, duration=20.0))
    write_scenario(tmp_path / "sim", scenario)
    args = ["estimate", "--camera", str(tmp_path / "sim" / "camera.yaml")]
    args += ["--tracks", str(tmp_path / "sim" / "tracks.csv"), "--pixel-sigma", "0.1"]
    for method in ("tight", "tight-fixed-lag"):
        out = tmp_path / method
        assert main([*args, "--method", method, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1] == (
            "hvo-graph: error: tracks: the tight graph found every track (4) off the plane: "
            "are the pixels noisier than noise.pixel_sigma says?"
        )
        assert not out.exists()
