"""The Kalman filter's offline run converts every frame's measurement at once; the
result is the filter's frame-by-frame one, number for number."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.estimators.kalman import KalmanBaseline
from hvo_graph.estimators.kalman_model import _prepared_measurements, _state_measurement
from hvo_graph.frontend import measure_sequence
from hvo_graph.geometry.rotation import euler_to_rotation
from hvo_graph.sim import paper_scenario, simulate


@pytest.fixture(scope="module")
def frames() -> list:
    scenario = simulate(paper_scenario(noisy=True, seed=5, duration=6.0))
    return measure_sequence(scenario.observations, scenario.camera, scenario.plane)


def test_prepared_measurements_equal_the_per_frame_conversion(frames: list) -> None:
    odd = list(frames)
    odd[5] = dataclasses.replace(odd[5], velocity=None)  # pose only: not prepared
    odd[6] = dataclasses.replace(odd[6], pose=None)  # velocity only: not prepared
    bad = np.array(odd[7].pose.rotation)
    bad[0, 0] = np.nan
    odd[7] = dataclasses.replace(odd[7], pose=dataclasses.replace(odd[7].pose, rotation=bad))
    near_lock = euler_to_rotation(0.1, np.deg2rad(89.5), 0.2)  # pitch beyond the filter's bound
    odd[8] = dataclasses.replace(odd[8], pose=dataclasses.replace(odd[8].pose, rotation=near_lock))
    prepared = _prepared_measurements(odd)
    for k, frame in enumerate(odd):
        got = prepared.get(id(frame))
        if k in (5, 6, 7, 8) or frame.pose is None or frame.velocity is None:
            assert got is None  # measured frame by frame (frame 0 has no velocity)
            continue
        want = _state_measurement(frame, False, None, variances=False)
        assert np.array_equal(got.rows, want.rows)
        assert np.array_equal(got.z, want.z)  # bit for bit
        assert got.variance.size == 0
    with pytest.raises(InputError, match=r"frame 7: pose\.rotation: contains NaN or inf"):
        KalmanBaseline(seed=1).run(odd)


def test_run_equals_updates_frame_by_frame(frames: list) -> None:
    run = KalmanBaseline(seed=3).run(frames)
    one = KalmanBaseline(seed=3)
    states = [one.update(f) for f in frames]
    assert np.array_equal(run.positions, np.array([s.position for s in states]))
    assert np.array_equal(run.rotations, np.array([s.rotation for s in states]))
    assert np.array_equal(run.twists, np.array([s.twist for s in states]))
    assert np.array_equal(run.covariances, np.array([s.covariance for s in states]))
