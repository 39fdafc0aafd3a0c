"""The Kalman filter's offline run converts every frame's measurement at once, filters
in a loop of its own and converts the estimates after it; the result is the filter's
frame-by-frame one (``update``, which tests/test_kalman.py holds to a textbook step),
number for number, and so is the filter's state afterwards, also when a frame raises."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.estimators.kalman import KalmanBaseline
from hvo_graph.estimators.kalman_model import _prepared_measurements, _state_measurement
from hvo_graph.estimators.state_log import StateLog
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


def _same_state(a: KalmanBaseline, b: KalmanBaseline) -> None:
    """Bit for bit: the logged estimates and the filterpy attributes of the last step."""
    ta, tb = a.online_trajectory(), b.online_trajectory()
    for name in ("t", "rotations", "positions", "twists", "covariances"):
        assert np.array_equal(getattr(ta, name), getattr(tb, name)), name
    assert [s.index for s in a._online] == [s.index for s in b._online]
    for name in ("x", "P", "F", "Q", "H", "R", "y", "S", "K", "_t_prev", "_last_pose"):
        va, vb = getattr(a, name), getattr(b, name)
        if va is None or vb is None:
            assert va is None and vb is None, name
        else:
            assert np.array_equal(va, vb), name


def _one_by_one(kf: KalmanBaseline, frames: list) -> None:
    for f in frames:
        kf.update(f)


def test_run_equals_updates_frame_by_frame(frames: list) -> None:
    run = KalmanBaseline(seed=3).run(frames)
    one = KalmanBaseline(seed=3)
    states = [one.update(f) for f in frames]
    assert np.array_equal(run.positions, np.array([s.position for s in states]))
    assert np.array_equal(run.rotations, np.array([s.rotation for s in states]))
    assert np.array_equal(run.twists, np.array([s.twist for s in states]))
    assert np.array_equal(run.covariances, np.array([s.covariance for s in states]))


def _mixed(frames: list) -> list:
    """Frames of every kind: pose only, twist only, neither, a gap of 0.2 s (other F_k,
    Q_k), a yaw beyond +-pi (wrapped innovation)."""
    out = list(frames)
    out[3] = dataclasses.replace(out[3], velocity=None)
    out[4] = dataclasses.replace(out[4], pose=None)
    out[5] = dataclasses.replace(out[5], pose=None, velocity=None)
    out = out[:20] + out[26:]
    turned = euler_to_rotation(0.05, -0.1, np.pi - 1e-3)
    out[30] = dataclasses.replace(out[30], pose=dataclasses.replace(out[30].pose, rotation=turned))
    return out


@pytest.mark.parametrize("preset", ["paper-noisy", "paper-noise-free"])
def test_run_leaves_the_state_of_updates_frame_by_frame(frames: list, preset: str) -> None:
    mixed = _mixed(frames)
    run, one = KalmanBaseline(seed=2, r_preset=preset), KalmanBaseline(seed=2, r_preset=preset)
    run.run(mixed[:50])  # a run continues where the last one stopped
    run.run(mixed[50:])
    _one_by_one(one, mixed)
    _same_state(run, one)


def test_run_hands_keyframe_poses_to_update(frames: list) -> None:
    """A keyframe-relative pose needs the filter's estimate of its keyframe: the frames
    from it on are updated one by one, with the same result."""
    mixed = list(frames)
    keyframe = mixed[40]
    for k in (60, 61):  # T_rc against frame 40's measured pose
        pose = mixed[k].pose
        R_rc = keyframe.pose.rotation.T @ pose.rotation
        p_rc = keyframe.pose.rotation.T @ (pose.position - keyframe.pose.position)
        relative = dataclasses.replace(pose, rotation=R_rc, position=p_rc, reference=40)
        mixed[k] = dataclasses.replace(mixed[k], pose=relative)
    run, one = KalmanBaseline(seed=4), KalmanBaseline(seed=4)
    run.run(mixed)
    _one_by_one(one, mixed)
    _same_state(run, one)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("time", r"^frame 30 \(t=0\.9\) does not follow frame 29 \(t=0\.9666"),
        ("nan", r"^frame 30: t is not finite \(nan\)$"),
        ("twist", r"^frame 30: velocity\.twist: expected shape \(6,\)"),
        ("pitch", r"^frame 30: measured pose: pitch p = 89\.500 deg"),
    ],
)
def test_run_stops_at_a_bad_frame_as_updates_do(frames: list, change: str, message: str) -> None:
    """The same error, and the frames before it estimated and logged as ``update`` leaves
    them (the bad frame's predict included)."""
    bad = list(frames)
    frame = bad[30]
    if change == "time":
        frame = dataclasses.replace(frame, t=0.9)
    elif change == "nan":
        frame = dataclasses.replace(frame, t=float("nan"))
    elif change == "twist":
        twist = dataclasses.replace(frame.velocity, twist=np.zeros(5))
        frame = dataclasses.replace(frame, pose=None, velocity=twist)
    else:  # a pose the paper's Euler angles cannot represent
        near_lock = euler_to_rotation(0.1, np.deg2rad(89.5), 0.2)
        frame = dataclasses.replace(frame, pose=dataclasses.replace(frame.pose, rotation=near_lock))
    bad[30] = frame
    run, one = KalmanBaseline(seed=6), KalmanBaseline(seed=6)
    with pytest.raises(InputError, match=message):
        run.run(bad)
    with pytest.raises(InputError, match=message):
        _one_by_one(one, bad)
    assert len(run.online_trajectory()) == 30
    _same_state(run, one)


def test_state_log_extend_equals_appends(frames: list) -> None:
    """Appending states as arrays keeps what appending them one by one keeps."""
    kf = KalmanBaseline(seed=1)
    _one_by_one(kf, frames[:40])
    states = list(kf._online)
    one, many = StateLog(), StateLog()
    for s in states:
        one.append(s)
    many.append(states[0])  # then 39 at once: past the first capacity (16)
    rest = states[1:]
    many.extend(
        np.array([s.index for s in rest]),
        np.array([s.t for s in rest]),
        np.array([s.rotation for s in rest]),
        np.array([s.position for s in rest]),
        np.array([s.twist for s in rest]),
        np.array([s.covariance for s in rest]),
    )
    assert len(many) == len(one) == 40
    for a, b in zip(one, many, strict=True):
        assert a.index == b.index and a.t == b.t
        for name in ("rotation", "position", "twist", "covariance"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert many.find(states[25].index).t == states[25].t
