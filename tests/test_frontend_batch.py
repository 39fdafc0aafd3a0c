"""The front end over a known sequence (``process_all``: plain stretches measured at once)
gives the records of ``process`` frame by frame, and the same state afterwards.

The per-frame path is the independent reference here: it runs the same mathematics one
frame at a time, through the geometry functions that tests/test_geometry_fit.py and
tests/test_frontend.py check against OpenCV and ground truth. The sequences mix in what
sends frames back to the per-frame path (dropped points, outliers RANSAC and the gate
reject, a drifting off-plane track that gets excluded, a gap below ``min_points``, keyframe
switches), so both paths and their hand-over are exercised.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hvo_graph.frontend import FrontEndConfig, MeasurementFrontEnd, measure_sequence
from hvo_graph.sim import paper_scenario, simulate
from hvo_graph.types import FrameObservations

#: Relative agreement: the stacked numpy calls round differently from the per-frame ones
#: (last bits); the pose covariances inherit that through the information matrix's
#: condition number (~1e5).
RTOL = 1e-8


def _compare(a: object, b: object, path: str) -> None:
    if a is None or b is None:
        assert a is None and b is None, path
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), path
        for f in dataclasses.fields(a):
            _compare(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape, path
        if a.dtype.kind in "iub":
            assert np.array_equal(a, b), path
        else:
            scale = max(float(np.abs(a).max(initial=0.0)), 1e-300)
            assert float(np.abs(a - b).max(initial=0.0)) <= RTOL * scale, path
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=RTOL, abs=1e-300), path
    else:
        assert a == b, path


def _perturbed(
    observations: list[FrameObservations], seed: int, renamed: bool = False
) -> list[FrameObservations]:
    rng = np.random.default_rng(seed)
    out = []
    for o in observations:
        ids, uv = np.asarray(o.ids), np.asarray(o.uv, dtype=float).copy()
        if renamed:  # tracks lost and found again under new ids: keyframes
            ids = ids + 100 * (((ids < 10) & (o.index >= 150)) | ((ids < 18) & (o.index >= 200)))
            order = np.argsort(ids)
            ids, uv = ids[order], uv[order]
        if rng.random() < 0.03:  # a few points drop out for a frame
            keep = rng.random(len(ids)) > 0.25
            ids, uv = ids[keep], uv[keep]
        if rng.random() < 0.04 and len(ids):  # an outlier
            uv[rng.integers(len(ids))] += rng.normal(0.0, 8.0, 2)
        if len(ids) > 6 and ids[3] == 3:  # track 3 drifts off the plane
            uv[3] += 0.05 * o.index * np.array([1.0, -0.5])
        if 100 <= o.index < 103:  # too few points for a pose
            ids, uv = ids[:3], uv[:3]
        out.append(FrameObservations(o.index, o.t, ids, uv))
    return out


@pytest.mark.parametrize(
    ("points", "options", "renamed"),
    [
        (4, {}, False),
        (20, {}, False),
        (20, {"ransac": False}, False),
        (20, {"keyframe_min_points": 12}, True),
        (12, {"outlier_chi2": None}, False),
    ],
)
def test_process_all_matches_process(points: int, options: dict, renamed: bool) -> None:
    scenario = simulate(paper_scenario(noisy=True, seed=3, duration=10.0, num_points=points))
    observations = _perturbed(list(scenario.observations), points, renamed)
    config = FrontEndConfig(pixel_sigma=scenario.pixel_sigma, **options)
    one = MeasurementFrontEnd(scenario.camera, scenario.plane, config)
    expected = [one.process(o) for o in observations]
    every = MeasurementFrontEnd(scenario.camera, scenario.plane, config)
    got = every.process_all(observations)
    assert len(got) == len(expected)
    for e, g in zip(expected, got, strict=True):
        _compare(e, g, f"frame {e.index}")
    assert every.excluded_tracks == one.excluded_tracks
    _compare(one._previous, every._previous, "previous frame")
    # The stream continues from the same state.
    more = FrameObservations(len(observations), observations[-1].t + 1 / 30, *_last(scenario))
    _compare(one.process(more), every.process(more), "next frame")


def _last(scenario) -> tuple[np.ndarray, np.ndarray]:
    o = scenario.observations[-1]
    return np.asarray(o.ids), np.asarray(o.uv, dtype=float)


def test_plain_sequence_is_measured_in_stretches_with_the_same_results() -> None:
    """Without perturbations nearly every frame goes through the stacked path (checked by
    counting the per-frame calls), and measure_sequence gives the per-frame records."""
    scenario = simulate(paper_scenario(noisy=True, seed=1, duration=5.0))
    front = MeasurementFrontEnd(scenario.camera, scenario.plane)
    calls = []
    process = front.process
    front.process = lambda obs: calls.append(obs.index) or process(obs)  # type: ignore[method-assign]
    got = front.process_all(scenario.observations)
    assert len(calls) < 5  # the first frames only
    again = measure_sequence(scenario.observations, scenario.camera, scenario.plane)
    single = MeasurementFrontEnd(scenario.camera, scenario.plane)
    for o, g, a in zip(scenario.observations, got, again, strict=True):
        e = single.process(o)
        _compare(e, g, f"frame {o.index}")
        _compare(e, a, f"frame {o.index}")


def test_time_error_is_raised_as_frame_by_frame() -> None:
    scenario = simulate(paper_scenario(noisy=True, seed=2, duration=2.0))
    obs = list(scenario.observations)
    obs[40] = FrameObservations(40, obs[39].t, obs[40].ids, obs[40].uv)
    front = MeasurementFrontEnd(scenario.camera, scenario.plane)
    with pytest.raises(Exception) as per_frame:
        for o in obs:
            front.process(o)
    with pytest.raises(type(per_frame.value), match="frame 40: time") as together:
        MeasurementFrontEnd(scenario.camera, scenario.plane).process_all(obs)
    assert str(together.value) == str(per_frame.value)
