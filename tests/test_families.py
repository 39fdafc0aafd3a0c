"""hvo_graph.sim.families: randomised scenario families span what the docs promise."""

from __future__ import annotations

import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.sim.families import FAMILIES, OUTLIER_ID_START, draw


def test_draws_are_reproducible_and_differ_between_seeds():
    a, b, c = (
        draw("agile", 3, duration=1.0),
        draw("agile", 3, duration=1.0),
        draw("agile", 4, duration=1.0),
    )
    np.testing.assert_array_equal(a.scenario.observations[5].uv, b.scenario.observations[5].uv)
    assert a.scenario.config.base_frequency != c.scenario.config.base_frequency


def test_families_span_tilt_points_rate_noise_and_motion():
    configs = [draw(f, s, duration=0.5).scenario.config for f in FAMILIES for s in range(2)]
    tilts = [np.degrees(np.arccos(abs(c.plane.normal[2]))) for c in configs]
    assert min(tilts) < 10 and max(tilts) > 35
    assert min(c.num_points for c in configs) == 4 and max(c.num_points for c in configs) >= 30
    assert {10.0, 30.0, 60.0, 120.0} <= {c.fps for c in configs}
    assert min(c.noise_var for c in configs) == 0.01 and max(c.noise_var for c in configs) >= 1.0
    top = max(max(h) * c.base_frequency for c in configs for h in (c.linear_harmonics,))
    assert top > 1.0  # Hz: agile motion
    assert min(max(map(abs, c.linear_amplitude)) for c in configs) < 0.01  # near-hover


def test_outliers_are_off_plane_tracks_and_frames_are_dropped():
    d = draw("outliers-dropouts", 0)
    ids = np.concatenate([o.ids for o in d.scenario.observations])
    assert d.outliers == 2 and np.any(ids >= OUTLIER_ID_START)
    n = len(d.scenario.groundtruth.t)
    assert 0.03 * n < len(d.dropped) < 0.2 * n
    kept = {o.index for o in d.scenario.observations}
    assert kept.isdisjoint(d.dropped) and len(kept) + len(d.dropped) == n


def test_unknown_family_is_named():
    with pytest.raises(
        InputError, match=r"^family: expected one of paper-like, agile, .*got 'fast'$"
    ):
        draw("fast", 0)


def test_a_traverse_sees_points_leave_and_enter_and_takes_keyframes():
    from hvo_graph.pipeline import measure

    scenario = draw("traverse", 0).scenario
    first = scenario.observations[0].ids
    shared = [len(np.intersect1d(first, o.ids)) for o in scenario.observations]
    assert min(shared) == 0  # the view moved past every point the first frame saw
    assert min(len(o.ids) for o in scenario.observations) >= 20
    # the clean pixels are the points' projections by the ground truth, inside the image
    truth, camera = scenario.groundtruth, scenario.camera
    for k in (0, len(truth.t) // 2, len(truth.t) - 1):
        obs = scenario.clean_observations[k]
        X = (scenario.points_world[obs.ids] - truth.positions[k]) @ truth.rotations[k]
        np.testing.assert_allclose(camera.project(X), obs.uv, atol=1e-9)
        assert camera.in_view(obs.uv).all()
    frames = measure(scenario.observations, scenario)
    references = {f.pose.reference for f in frames if f.pose is not None}
    assert len(references) >= 3 and all(f.pose is not None for f in frames)
