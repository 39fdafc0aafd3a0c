"""Levenberg-Marquardt on Python-owned Values, against GTSAM's own optimizer."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from hvo_graph.estimators.least_squares import levenberg_marquardt


def _noisy_chain(poses: int, seed: int = 0) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """A turning Pose3 chain: noisy odometry and a noisy absolute pose per frame (as the
    smoother's motion and H_d factors), started from the absolute poses."""
    rng = np.random.default_rng(seed)
    step = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.02, -0.01, 0.05), np.array([0.3, 0.05, 0.0]))
    odometry = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01] * 3 + [0.02] * 3))
    absolute = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05] * 3 + [0.1] * 3))
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    truth = gtsam.Pose3()
    for k in range(poses):
        if k:
            truth = truth.compose(step)
            measured = step.compose(gtsam.Pose3.Expmap(rng.normal(0.0, 0.01, 6)))
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), measured, odometry))
        seen = truth.compose(gtsam.Pose3.Expmap(rng.normal(0.0, 0.05, 6)))
        graph.add(gtsam.PriorFactorPose3(X(k), seen, absolute))
        initial.insert(X(k), seen)
    return graph, initial


def _largest_difference(a: gtsam.Values, b: gtsam.Values) -> float:
    """The largest tangent coordinate between two sets of poses."""
    return max(float(np.abs(a.atPose3(k).localCoordinates(b.atPose3(k))).max()) for k in a.keys())


def test_the_optimum_is_gtsams_levenberg_marquardt() -> None:
    graph, initial = _noisy_chain(300)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(100)
    reference = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    ours, iterations = levenberg_marquardt(graph, initial)
    assert 2 < iterations < 100
    # The default error test stops where a step would still move a pose by ~1e-8.
    assert _largest_difference(ours, reference) < 1e-7
    exact, _ = levenberg_marquardt(graph, initial, relative_tolerance=1e-16, absolute_tolerance=0)
    assert _largest_difference(exact, reference) < 1e-9  # GTSAM stops ~4e-10 short


def test_the_step_test_stops_sooner_within_its_tolerance_of_the_optimum() -> None:
    graph, initial = _noisy_chain(300, seed=1)
    # The error test as good as off: only rounding stops the strict solve.
    tests = {"relative_tolerance": 1e-16, "absolute_tolerance": 0.0}
    strict, strict_iterations = levenberg_marquardt(graph, initial, **tests)
    early, early_iterations = levenberg_marquardt(graph, initial, step_tolerance=1e-9, **tests)
    assert early_iterations < strict_iterations
    assert _largest_difference(early, strict) <= 1e-9
    # A tolerance no sequence of steps reaches leaves the error test alone to stop.
    same, same_iterations = levenberg_marquardt(graph, initial, step_tolerance=1e-300, **tests)
    assert same_iterations == strict_iterations
    assert _largest_difference(same, strict) <= 1e-15
