"""The tight smoother's hold on the scale of its map (hvo_graph.estimators.plane_gauge).

Independent references: a similarity applied exactly (Rodrigues rotation) and GTSAM's
Pose3 logarithm; a Monte Carlo of the first frame's pixel noise; the simulation's ground
truth (the landmarks' true spread); GTSAM's marginals of the graph whose scale is left
free (where the graph itself carries the scale's uncertainty).
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L
from off_plane import with_off_plane_track

from hvo_graph.errors import InputError
from hvo_graph.estimators import plane_gauge
from hvo_graph.estimators.plane_gauge import FirstFrameGauge
from hvo_graph.estimators.tight import TightSmoother
from hvo_graph.pipeline import measure, run_estimate
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import PointObservations

NORMAL = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
DISTANCE = 1.5
SIGMA = 1e-3


def plane_points(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) points of the plane n^T X = d in front of the camera at the origin."""
    rng = np.random.default_rng(seed)
    axes = plane_gauge.plane_axes(NORMAL)
    return DISTANCE * NORMAL + rng.uniform(-0.6, 0.6, (count, 2)) @ axes.T


def seen(points: np.ndarray) -> np.ndarray:
    return points[:, :2] / points[:, 2:]


def similarity(points, center, t, theta, s):
    """c + (1 + s) Rot(n, theta)(X - c) + E t, exactly."""
    R = gtsam.Rot3.Rodrigues(theta * NORMAL).matrix()
    return (
        center + (1 + s) * (np.asarray(points) - center) @ R.T + plane_gauge.plane_axes(NORMAL) @ t
    )


def test_axes_are_orthonormal_in_the_plane_and_right_handed():
    E = plane_gauge.plane_axes(NORMAL)
    np.testing.assert_allclose(E.T @ E, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(E.T @ NORMAL, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(NORMAL, E[:, 0]), E[:, 1], atol=1e-12)


def test_a_known_similarity_of_the_map_is_read_back():
    truth = plane_points(6)
    gauge = FirstFrameGauge([L(i) for i in range(6)], seen(truth), SIGMA, NORMAL, DISTANCE)
    np.testing.assert_allclose(gauge.points, truth, atol=1e-12)  # the back-projection
    t, theta, s = np.array([2e-4, -1e-4]), 3e-4, -2e-4
    # the map is the first frame's points moved by the inverse: g maps it back onto them
    moved = similarity(truth, gauge.center, -t, -theta, -s)
    np.testing.assert_allclose(gauge.similarity(moved), [*t, theta, s], atol=1e-7)


def test_the_first_frame_covariance_is_that_of_its_pixel_noise():
    truth = plane_points(8, seed=1)
    keys = [L(i) for i in range(8)]
    clean = FirstFrameGauge(keys, seen(truth), SIGMA, NORMAL, DISTANCE)
    rng = np.random.default_rng(3)
    draws = [
        FirstFrameGauge(
            keys, seen(truth) + SIGMA * rng.standard_normal((8, 2)), SIGMA, NORMAL, DISTANCE
        ).similarity(truth)
        for _ in range(3000)
    ]
    sample = np.cov(np.array(draws).T)
    scale = np.sqrt(np.diag(clean.covariance))
    np.testing.assert_allclose(
        sample / np.outer(scale, scale), clean.covariance / np.outer(scale, scale), atol=0.08
    )


def test_bad_first_frames_are_refused():
    points = plane_points(4)
    keys = [L(i) for i in range(4)]
    with pytest.raises(InputError, match="at least 3 points"):
        FirstFrameGauge(keys[:2], seen(points[:2]), SIGMA, NORMAL, DISTANCE)
    with pytest.raises(InputError, match="in front"):
        FirstFrameGauge(keys, seen(points), SIGMA, NORMAL, -DISTANCE)
    with pytest.raises(InputError, match="do not fix a similarity"):
        FirstFrameGauge(keys[:3], seen(points[[0, 0, 0]]), SIGMA, NORMAL, DISTANCE)
    # in the smoother such a first frame holds nothing (the graph keeps its own scale)
    observations = PointObservations(
        ids=np.arange(3), m=seen(points[[0, 0, 0]]), sigma=SIGMA, normal=NORMAL, distance=DISTANCE
    )
    added = [(i, key, m) for i, (key, m) in enumerate(zip(keys, observations.m, strict=False))]
    assert plane_gauge.first_frame_gauge(0, added, observations) is None
    assert plane_gauge.first_frame_gauge(0, added[:2], observations) is None


def spread_ratio(tight: TightSmoother, scenario) -> float:
    """RMS distance of the estimated landmarks from their centroid over the true one."""
    values = tight.backend.values()
    keys = [key for key in tight._key_track if values.exists(key)]
    estimated = np.array([values.atPoint3(key) for key in keys])
    true = scenario.points_world[[tight._key_track[key] for key in keys]]

    def spread(points):
        return np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())

    return float(spread(estimated) / spread(true))


def test_the_scale_is_held_on_a_long_run(monkeypatch):
    """Noisy pixels (1 px^2), 4 points and a motion model stiffer than the fitted one:
    the pull of 600 frames is strong enough to show in 20 s. Held, the map's spread is
    the true one within 3 standard deviations of the held scale; left free (the joint
    optimum), it shrinks by more than that."""
    scenario = simulate(paper_scenario(seed=0, duration=20.0, num_points=4, noise_var=1.0))
    frames = measure(scenario.observations, scenario, method="tight")
    held = TightSmoother(acceleration_sigma=(0.02, 0.02))
    held.run(frames)
    tolerance = 3 * np.sqrt(held.gauge.variance)
    assert abs(spread_ratio(held, scenario) - 1) < tolerance
    monkeypatch.setattr(plane_gauge, "HOLD_AFTER", 10**9)
    free = TightSmoother(acceleration_sigma=(0.02, 0.02))
    free.run(frames)
    assert free.gauge is not None and free.gauge.scale is None
    assert spread_ratio(free, scenario) < 1 - tolerance


def similarity_derivative(gauge, pose, twist):
    """(12,) derivative of a pose and twist moved by the exact similarity with scale s about
    the gauge's center (no shift, no turn), by central differences through GTSAM's Logmap."""
    step = 1e-6
    moved = []
    for s in (-step, step):
        p = similarity(pose.translation()[None], gauge.center, np.zeros(2), 0.0, s)[0]
        moved.append(gtsam.Pose3.Logmap(pose.between(gtsam.Pose3(pose.rotation(), p))))
    return np.concatenate(((moved[1] - moved[0]) / (2 * step), np.zeros(3), twist[3:]))


def test_the_covariance_includes_the_held_scale(monkeypatch):
    """With the scale held the graph no longer carries its uncertainty: added back, each
    frame's covariance is the marginal of the graph whose scale is left free (6 s, where
    the pull is negligible), also next to the first frame, whose velocity the motion model
    ties to the scale; without the share the positions' would be measurably smaller. Far
    from the first frame, the optimum moves with the scale as the similarity moves it."""
    scenario = simulate(paper_scenario(seed=0, duration=6.0, num_points=4, noise_var=1.0))
    frames = measure(scenario.observations, scenario, method="tight")
    held = TightSmoother(acceleration_sigma=(0.05, 0.1), compute_covariance=True)
    with_scale = held.run(frames)
    gauge = held.gauge
    assert gauge.first == frames[0].index and gauge.variance > 0
    monkeypatch.setattr(plane_gauge, "HOLD_AFTER", 10**9)
    free = TightSmoother(acceleration_sigma=(0.05, 0.1), compute_covariance=True).run(frames)
    last = len(frames) - 1
    for k in (0, 1, 10, last // 2, last):
        # the twist blocks are error covariances (tight_covariance): the free graph carries
        # the scale there through its landmarks' marginals, the held one through the share
        for block, tolerance in zip(
            (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)),
            (0.02, 0.02, 0.06, 0.06),
            strict=True,
        ):
            reference = free.covariances[k][block, block]
            total = with_scale.covariances[k][block, block]
            atol = tolerance * np.trace(reference)
            np.testing.assert_allclose(total, reference, rtol=0, atol=atol)
    graph = held.backend.store.whole_graph()
    j = gauge.sensitivities(graph, held.backend.values(), [last])[0]
    share = gauge.variance * np.outer(j, j)
    assert np.trace(share[3:6, 3:6]) > 0.01 * np.trace(free.covariances[last][3:6, 3:6])
    pose = gtsam.Pose3(gtsam.Rot3(with_scale.rotations[last]), with_scale.positions[last])
    # s maps the map onto the first frame's back-projection: holding it larger shrinks the map
    np.testing.assert_allclose(
        -j,
        similarity_derivative(gauge, pose, with_scale.twists[last]),
        rtol=0,
        atol=0.05 * np.abs(j).max(),
    )


def test_an_off_plane_first_frame_track_releases_the_scale(monkeypatch):
    """The scale read after 30 frames was pulled by the off-plane point: once its track is
    rejected the hold leaves the final solve, which is then the free graph's optimum."""
    scenario = simulate(paper_scenario(duration=4.0, num_points=8))
    observations = with_off_plane_track(scenario)
    # Front end gates off, so the tight graph must find the track by itself.
    options = {"outlier_chi2": None, "reject_after": None, "ransac": False}
    run = run_estimate(observations, scenario, "tight", **options)
    assert run.estimator.rejected_tracks == {99}
    assert run.estimator.gauge is None
    monkeypatch.setattr(plane_gauge, "HOLD_AFTER", 10**9)
    free = run_estimate(observations, scenario, "tight", **options)
    assert free.estimator.gauge.scale is None
    np.testing.assert_allclose(run.trajectory.positions, free.trajectory.positions, atol=1e-6)
