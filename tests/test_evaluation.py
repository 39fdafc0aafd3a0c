"""Trajectory error statistics against hand-computed values and independent references."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.eval.metrics import (
    ErrorSummary,
    error_series,
    format_table,
    rotation_angle,
    summarize,
)
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import Trajectory


def rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


@pytest.fixture
def tiny() -> tuple[Trajectory, Trajectory]:
    t = np.array([0.0, 0.1, 0.2])
    gt = Trajectory(
        t=t,
        rotations=np.array([np.eye(3), rz(30.0), rz(-20.0)]),
        positions=np.array([[0.0, 0, 0], [1, 1, 1], [2, 0, 0]]),
        twists=np.zeros((3, 6)),
    )
    est = Trajectory(
        t=t.copy(),
        rotations=np.array([np.eye(3), rz(40.0), rz(-20.0) @ rz(3.0)]),  # errors 0, 10, 3 deg
        positions=gt.positions + np.array([[0, 0, 0], [3, 4, 0], [0, 0, 1]]),  # errors 0, 5, 1 m
        twists=np.array(
            [
                [0, 0, 0, 0, 0, 0],
                [0, 2, 0, 0, 0, 0],  # w error 2
                [0, 0, 0, 0, 6, 8],  # v error 10
            ],
            dtype=float,
        ),
    )
    return est, gt


def test_hand_computed_rmse_and_max(tiny):
    est, gt = tiny
    s = summarize(error_series(est, gt))
    assert s.frames == 3
    assert s.position_rmse == pytest.approx(np.sqrt((0 + 25 + 1) / 3))
    assert s.position_max == pytest.approx(5.0)
    assert s.orientation_rmse == pytest.approx(np.sqrt((0 + 100 + 9) / 3))
    assert s.orientation_max == pytest.approx(10.0)
    assert s.linear_velocity_rmse == pytest.approx(np.sqrt(100 / 3))
    assert s.linear_velocity_max == pytest.approx(10.0)
    assert s.angular_velocity_rmse == pytest.approx(np.sqrt(4 / 3))
    assert s.angular_velocity_max == pytest.approx(2.0)


def test_t_start_keeps_later_frames(tiny):
    est, gt = tiny
    s = summarize(error_series(est, gt), t_start=0.1)
    assert s.frames == 2
    assert s.position_rmse == pytest.approx(np.sqrt(26 / 2))
    with pytest.raises(InputError, match=r"t_start: no matched frame at t >= 5 s"):
        summarize(error_series(est, gt), t_start=5.0)


def test_groundtruth_against_itself_is_zero():
    gt = simulate(paper_scenario(duration=3.0)).groundtruth
    d = summarize(error_series(gt, gt)).as_dict()
    assert d["frames"] == 91
    for key in ("position_m", "orientation_deg", "linear_velocity_mps", "angular_velocity_radps"):
        assert d[key] == {"rmse": 0.0, "max": 0.0}


def test_matching_by_timestamp_subset_and_jitter(tiny):
    est, gt = tiny
    sub = Trajectory(
        t=est.t[1:] + 5e-7,  # within the default tolerance
        rotations=est.rotations[1:],
        positions=est.positions[1:],
        twists=est.twists[1:],
    )
    series = error_series(sub, gt)
    np.testing.assert_array_equal(series.t, gt.t[1:])
    np.testing.assert_allclose(series.position, [5.0, 1.0])


def test_no_match_is_an_error(tiny):
    est, gt = tiny
    est.t = est.t + 0.05
    with pytest.raises(InputError, match=r"estimate: only 0 of its 3 timestamps match"):
        error_series(est, gt)


def test_orientation_angle_matches_gtsam_logmap():
    rng = np.random.default_rng(0)
    rots = [gtsam.Rot3.Expmap(rng.normal(size=3) * s) for s in (1e-9, 1e-4, 0.5, 2.0, 3.1)]
    rots.append(gtsam.Rot3.Expmap(np.array([0.0, np.pi - 1e-7, 0.0])))
    angles = rotation_angle(np.array([r.matrix() for r in rots]))
    expected = [np.linalg.norm(gtsam.Rot3.Logmap(r)) for r in rots]
    np.testing.assert_allclose(angles, expected, rtol=1e-6, atol=1e-15)


def test_missing_or_unknown_velocities(tiny):
    est, gt = tiny
    est.twists[1] = np.nan
    s = summarize(error_series(est, gt))
    assert s.linear_velocity_max == pytest.approx(10.0)
    assert s.angular_velocity_max == pytest.approx(0.0)
    est.twists = None
    s = summarize(error_series(est, gt))
    assert s.linear_velocity_rmse is None and s.angular_velocity_max is None
    assert s.as_dict()["linear_velocity_mps"] is None


def test_format_table_is_aligned_and_marks_missing_velocity(tiny):
    est, gt = tiny
    full = summarize(error_series(est, gt))
    est.twists = None
    no_vel = summarize(error_series(est, gt))
    text = format_table({"smoother": full, "kalman-long-name": no_vel})
    lines = text.splitlines()
    assert len(lines) == 3
    header = lines[0]
    for label in (
        "pos RMSE [m]",
        "pos max [m]",
        "orient RMSE [deg]",
        "orient max [deg]",
        "lin vel RMSE [m/s]",
        "lin vel max [m/s]",
        "ang vel RMSE [rad/s]",
        "ang vel max [rad/s]",
    ):
        assert label in header
    # columns are right-aligned: every line ends at the same place
    assert len({len(line) for line in lines}) == 1
    assert lines[1].startswith("smoother ") and lines[2].startswith("kalman-long-name ")
    assert lines[2].split()[-5:] == ["-", "-", "-", "-", "3"]
    assert "5" in lines[1].split()  # position max, 5 m


def test_summary_dict_layout():
    s = ErrorSummary(1.0, 2.0, 3.0, 4.0, None, None, 5.0, 6.0, frames=7)
    assert s.as_dict() == {
        "position_m": {"rmse": 1.0, "max": 2.0},
        "orientation_deg": {"rmse": 3.0, "max": 4.0},
        "linear_velocity_mps": None,
        "angular_velocity_radps": {"rmse": 5.0, "max": 6.0},
        "frames": 7,
    }
