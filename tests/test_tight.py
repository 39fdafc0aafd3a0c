"""The tightly coupled plane-landmark smoother (hvo_graph.estimators.tight).

Independent references: ground truth from the simulation (poses, twists and the
plane points themselves), the homography smoother on the same measurements, the
batch optimum of the same graph, and chi^2 statistics of the errors against the
reported covariances.
"""

from __future__ import annotations

import dataclasses
import json

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X
from off_plane import with_off_plane_track

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.estimators.landmarks import farthest_points
from hvo_graph.estimators.least_squares import levenberg_marquardt
from hvo_graph.estimators.registry import build_estimator
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.estimators.tight import TightSmoother, back_project
from hvo_graph.estimators.tight_solvers import WindowIsam2Backend, tight_isam2_params
from hvo_graph.eval.consistency import trajectory_nees
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.frontend import FrontEndConfig, measure_sequence
from hvo_graph.pipeline import run_estimate
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import PointObservations

SEEDS = (0, 1, 2, 3)


def frames_of(scenario, **config):
    config = FrontEndConfig(pixel_sigma=scenario.pixel_sigma, **config)
    return measure_sequence(scenario.observations, scenario.camera, scenario.plane, config)


@pytest.fixture(scope="module")
def runs():
    """Tight (with covariances) and the homography smoother on short noisy paper runs."""
    out = []
    for seed in SEEDS:
        scenario = simulate(paper_scenario(seed=seed, duration=4.0, num_points=8))
        frames = frames_of(scenario)
        tight = TightSmoother(compute_covariance=True)
        out.append((scenario, tight, tight.run(frames), FactorGraphSmoother().run(frames)))
    return out


def test_back_project_returns_the_plane_point_seen():
    scenario = simulate(paper_scenario(duration=1.0, noise_var=0.0))
    truth = scenario.groundtruth
    k = 20
    pose = gtsam.Pose3(gtsam.Rot3(truth.rotations[k]), truth.positions[k])
    for point in scenario.points_world:
        c = truth.rotations[k].T @ (point - truth.positions[k])
        found = back_project(pose, c[:2] / c[2], scenario.plane.normal, scenario.plane.distance)
        np.testing.assert_allclose(found, point, atol=1e-12)
    # A ray pointing away from the plane meets it behind the camera: none.
    away = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.zeros(3))
    assert back_project(away, np.zeros(2), scenario.plane.normal, 2.0) is None


def test_farthest_points_maximises_the_nearest_distance_at_every_pick():
    """Each pick against an exhaustive search: the candidate whose nearest point in use
    (used points and earlier picks) is farthest."""
    rng = np.random.default_rng(3)
    candidates, used = rng.uniform(0, 1, (40, 2)), rng.uniform(0, 1, (3, 2))
    picks = farthest_points(candidates, used, 6)
    taken = list(used)
    for pick in picks:
        nearest = [min(np.linalg.norm(c - u) for u in taken) for c in candidates]
        for i in picks[: picks.index(pick)]:
            nearest[i] = -1.0
        assert pick == int(np.argmax(nearest))
        taken.append(candidates[pick])
    # Nothing in use: the first candidate, then the one farthest from it.
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [9.0, 0.0], [3.0, 0.0]])
    assert farthest_points(line, np.zeros((0, 2)), 3) == [0, 3, 4]
    assert farthest_points(line, np.zeros((0, 2)), 9) == [0, 3, 4, 1, 2]  # 1, 2: a tie
    assert farthest_points(line, line, 0) == []


def test_landmarks_are_capped_per_frame_and_kept_while_tracked():
    """20 points, at most 8 landmarks per frame: no frame observes more, a landmark
    stays observed while its track lasts, and the pose still recovers the truth."""
    scenario = simulate(paper_scenario(seed=1, duration=2.0, num_points=20))
    tight = TightSmoother(max_landmarks=8, acceleration_sigma=0.1)
    trajectory = tight.run(frames_of(scenario))
    per_frame = [keys for _, keys, _, _ in tight._observations]
    assert max(len(keys) for keys in per_frame) == 8
    assert tight.counts["landmarks"] == 8  # every point stays in view: the first 8 stay
    assert all(set(keys) == set(per_frame[0]) for keys in per_frame)
    errors = summarize(error_series(trajectory, scenario.groundtruth))
    assert errors.position_rmse < 0.02 and errors.orientation_rmse < 0.5
    with pytest.raises(InputError, match="max_landmarks"):
        TightSmoother(max_landmarks=3)


def test_noise_free_pixels_give_the_ground_truth():
    scenario = simulate(paper_scenario(noisy=False, duration=2.0))
    trajectory = TightSmoother().run(frames_of(scenario))
    errors = error_series(trajectory, scenario.groundtruth)
    assert np.max(errors.position) < 1e-4  # metres (pixel sigma floored at 1e-3 px)
    assert np.max(errors.orientation) < 1e-2  # degrees


def test_tight_beats_the_homography_smoother(runs):
    tight = [summarize(error_series(t, s.groundtruth)) for s, _, t, _ in runs]
    smoother = [summarize(error_series(h, s.groundtruth)) for s, _, _, h in runs]

    def rms(summaries, field):
        return np.sqrt(np.mean([getattr(x, field) ** 2 for x in summaries]))

    for field in ("position_rmse", "orientation_rmse"):
        assert rms(tight, field) < 0.9 * rms(smoother, field), field


def test_pose_nees_is_near_one(runs):
    """Smoothed and online pose errors against the marginals: chi^2 / dof near 1."""
    smoothed = [trajectory_nees(t, s.groundtruth)[0] for s, _, t, _ in runs]
    online = [trajectory_nees(e.online_trajectory(), s.groundtruth)[0] for s, e, _, _ in runs]
    assert 0.6 <= np.mean(smoothed) <= 1.5
    assert 0.6 <= np.mean(online) <= 1.5


def test_variants_share_the_optimum(runs):
    scenario, _, smoothed, _ = runs[0]
    frames = frames_of(scenario)
    batch = TightSmoother(solver="batch").run(frames)
    np.testing.assert_allclose(batch.positions, smoothed.positions, atol=2e-5)
    lagged = build_estimator("tight-fixed-lag")
    assert lagged.name == "tight-fixed-lag"
    fixed_lag = lagged.run(frames)
    # Each frame as it left a 1 s window: close to the optimum, not equal.
    assert np.sqrt(np.mean((fixed_lag.positions - smoothed.positions) ** 2)) < 5e-3


def test_online_window_keeps_the_information_of_older_frames():
    """After several rebuilds of the online ISAM2, its problem (the older frames' marginal
    plus the recent frames) has the optimum of the whole graph on the recent frames."""
    scenario = simulate(paper_scenario(duration=5.0, num_points=6))
    tight = TightSmoother(acceleration_sigma=0.1)
    for frame in frames_of(scenario):
        tight.update(frame)
    backend = tight.backend
    assert len(tight._indices) > 4 * backend.window  # rebuilt more than twice
    online = backend.online_graph()
    start = backend.isam.calculateBestEstimate()
    reduced, _ = levenberg_marquardt(online, start)
    whole = tight.trajectory()  # the batch optimum of every factor
    for k in sorted(i for i in tight._indices if backend.isam.valueExists(X(i))):
        pose = reduced.atPose3(X(k))
        # The prior is linearized at the online estimates of its time (mm from the final
        # optimum): agreement to second order, far inside the pose error (~6 mm).
        np.testing.assert_allclose(pose.translation(), whole.positions[k], atol=2e-4)


def test_an_update_cholesky_finds_indeterminate_is_replayed_with_qr():
    """The first 14 frames without points: the first rebuilt ISAM2's Cholesky finds the
    marginal of the world prior (1e-6) and the first twist's (10), with only the motion
    model between them, indeterminate. Its updates are replayed with QR: the estimates of
    a back end on QR throughout, to the bit."""
    scenario = simulate(paper_scenario(duration=2.0, num_points=6))
    frames = [
        dataclasses.replace(f, points=None) if f.index < 14 else f for f in frames_of(scenario)
    ]
    tight = TightSmoother()
    smoothed = tight.run(frames)
    assert tight.backend.rebuilt.getFactorization() == "QR"  # switched from Cholesky
    reference = TightSmoother()
    reference.backend = WindowIsam2Backend(
        tight_isam2_params(0.05, 10),
        max_iterations=100,
        compute_covariance=False,
        pixel_noise=reference._pixel_noise_model,
    )
    np.testing.assert_array_equal(smoothed.positions, reference.run(frames).positions)
    online = tight.online_trajectory()
    np.testing.assert_array_equal(online.positions, reference.online_trajectory().positions)
    np.testing.assert_array_equal(online.rotations, reference.online_trajectory().rotations)


def test_off_plane_track_is_rejected():
    scenario = simulate(paper_scenario(duration=4.0, num_points=8))
    observations = with_off_plane_track(scenario)
    # Front end gates off, so the tight graph must find the track by itself.
    run = run_estimate(
        observations, scenario, "tight", outlier_chi2=None, reject_after=None, ransac=False
    )
    assert run.estimator.rejected_tracks == {99}
    assert run.summary()["counts"]["off_plane_tracks"] == [99]
    clean = run_estimate(scenario.observations, scenario, "tight")
    got = summarize(error_series(run.trajectory, scenario.groundtruth)).position_rmse
    want = summarize(error_series(clean.trajectory, scenario.groundtruth)).position_rmse
    assert got < 1.5 * want + 1e-3


def test_frames_without_points_are_predicted_and_bad_points_refused():
    scenario = simulate(paper_scenario(duration=1.0))
    frames = frames_of(scenario)
    estimator = TightSmoother(acceleration_sigma=0.1)
    bare = [dataclasses.replace(f, points=None) if 10 <= f.index < 13 else f for f in frames]
    trajectory = estimator.run(bare)
    assert len(trajectory) == len(frames)
    assert np.max(error_series(trajectory, scenario.groundtruth).position) < 0.05
    bad = dataclasses.replace(
        frames[1],
        points=PointObservations(np.arange(3), np.zeros((3, 3)), 1e-3, np.array([0, 0, 1.0]), 2.0),
    )
    fresh = TightSmoother(acceleration_sigma=0.1)
    fresh.update(frames[0])
    with pytest.raises(InputError, match=r"frame 1: points.m must be \(N, 2\)"):
        fresh.update(bad)
    with pytest.raises(InputError, match="solver: expected one of isam2, batch, fixed-lag"):
        TightSmoother(solver="lm")


def test_cli_writes_the_contract_outputs(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "2", "--num-points", "6"]) == 0
    out = tmp_path / "est"
    args = ["estimate", "--camera", str(sim / "camera.yaml"), "--tracks", str(sim / "tracks.csv")]
    assert main([*args, "--method", "tight", "--covariance", "--out", str(out)]) == 0
    for name in ("trajectory.txt", "velocity.csv", "covariance.csv", "run.json"):
        assert (out / name).is_file()
    record = json.loads((out / "run.json").read_text())
    assert record["method"] == "tight"
    assert record["counts"]["landmarks"] == 6
    assert record["counts"]["pixel_observations"] == 6 * 61
    capsys.readouterr()
    assert main(["evaluate", "--estimate", str(out), "--groundtruth", str(sim), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["position_m"]["rmse"] < 0.02


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--method", "tight", "--lag", "1"], "--lag: does not apply to method 'tight'"),
        (["--method", "tight", "--robust", "huber"], "--robust: does not apply to method 'tight'"),
        (["--method", "tight-batch", "--relinearize-skip", "2"], "--relinearize-skip: does not"),
        (["--method", "tight", "--independent-poses"], "--independent-poses: does not apply"),
    ],
)
def test_flags_that_do_not_apply_are_errors(tmp_path, capsys, flags, message):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "0.5"]) == 0
    capsys.readouterr()
    args = ["estimate", "--camera", str(sim / "camera.yaml"), "--tracks", str(sim / "tracks.csv")]
    assert main([*args, *flags, "--out", str(tmp_path / "est")]) == 2
    err = capsys.readouterr().err
    assert "hvo-graph: error: " + message in err
    assert not (tmp_path / "est").exists()
