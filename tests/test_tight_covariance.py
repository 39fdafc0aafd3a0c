"""The tight graph's covariances: the pose's marginal, the twist's error covariance.

References: the ground truth of simulated sequences (NEES), and the error covariance
P M P of the whole linearized graph computed densely (the textbook sandwich
Cov(x^ - x) = P A^T W Cov(eta) W A P with Cov(eta) = I on the whitened pixels).
"""

from __future__ import annotations

import numpy as np
import pytest

from hvo_graph.estimators.error_covariance import error_covariances, marginal_covariances
from hvo_graph.estimators.tight_covariance import (
    combine_pose_and_twist,
    landmark_roots,
    tight_chain,
)
from hvo_graph.eval.consistency import trajectory_nees
from hvo_graph.pipeline import run_estimate
from hvo_graph.sim.families import draw
from hvo_graph.sim.scenario import paper_scenario, simulate


def dense_sandwich(graph, values, indices):
    """(K, 12, 12) blocks of P M P over every variable of the graph, densely."""
    import gtsam
    from gtsam.symbol_shorthand import V, X

    columns, size = {}, 0
    for key in values.keys():
        columns[key] = size
        size += 3 if gtsam.Symbol(key).chr() == ord("l") else 6
    Lam, M = np.zeros((size, size)), np.zeros((size, size))
    linear = graph.linearize(values)
    for i in range(graph.size()):
        factor = linear.at(i)
        A, _ = factor.jacobian()
        rows = np.concatenate(
            [
                np.arange(columns[k], columns[k] + (3 if gtsam.Symbol(k).chr() == ord("l") else 6))
                for k in factor.keys()
            ]
        )
        Lam[np.ix_(rows, rows)] += A.T @ A
        if isinstance(graph.at(i), gtsam.GenericProjectionFactorCal3_S2):
            M[np.ix_(rows, rows)] += A.T @ A
    P = np.linalg.inv(Lam)
    C = P @ M @ P
    out = []
    for k in indices:
        rows = np.r_[columns[X(k)] : columns[X(k)] + 6, columns[V(k)] : columns[V(k)] + 6]
        out.append(C[np.ix_(rows, rows)])
    return np.array(out)


def batch_optimum(scenario):
    """``tight-batch`` on a scenario: (graph, optimum, frame indices, (K,) times, an ISAM2
    of the graph at the optimum)."""
    import gtsam

    run = run_estimate(scenario.observations, scenario, "tight-batch")
    backend = run.estimator.backend
    graph, values = backend.graph, backend.values()
    isam = gtsam.ISAM2()
    isam.update(graph, values)
    return graph, values, run.estimator._indices, run.trajectory.t, isam


def test_the_chain_matches_the_whole_graphs_error_covariance():
    """The chain leaves out that the landmarks' errors come from the frames' own pixels:
    past the first second the twist variance is within a few percent of the whole graph's
    P M P, and on the first frames (whose pixels place the map) 0.85-1.6x."""
    graph, values, indices, times, isam = batch_optimum(
        simulate(paper_scenario(seed=3, duration=6.0))
    )
    chain = tight_chain(graph, values, indices, times, landmark_roots(isam, values))
    ours = error_covariances(chain, bias_scale=None)
    dense = dense_sandwich(graph, values, indices)
    ratio = np.trace(ours[:, 6:, 6:], axis1=1, axis2=2) / np.trace(
        dense[:, 6:, 6:], axis1=1, axis2=2
    )
    later = times >= 1.0
    assert 0.95 < ratio[later].min() and ratio[later].max() < 1.1
    assert 0.85 < ratio.min() and ratio.max() < 1.6
    # landmarks taken apart (groups of one): their shared errors are double counted
    apart = tight_chain(graph, values, indices, times, landmark_roots(isam, values, group=1))
    first = np.trace(error_covariances(apart, bias_scale=None)[0, 6:, 6:])
    assert first > 2.5 * np.trace(dense[0, 6:, 6:])


def test_the_chains_marginal_is_gtsams():
    """Frames given the landmarks, plus the landmarks' joint marginal through the frames'
    sensitivity to them (the law of total covariance), is the whole graph's marginal."""
    from gtsam.symbol_shorthand import V, X

    graph, values, indices, times, isam = batch_optimum(draw("many-points", 1).scenario)
    chain = tight_chain(graph, values, indices, times, landmark_roots(isam, values))
    ours = marginal_covariances(chain)
    for n in (0, 1, len(indices) // 2, len(indices) - 1):
        k = indices[n]
        reference = isam.jointMarginalCovariance([X(k), V(k)]).fullMatrix()
        scale = np.sqrt(np.outer(np.diag(reference), np.diag(reference)))
        assert np.abs((ours[n] - reference) / scale).max() < 1e-8


def test_combining_keeps_the_blocks_and_stays_positive_semidefinite():
    rng = np.random.default_rng(0)
    roots = rng.normal(size=(50, 12, 12))
    errors = roots @ np.swapaxes(roots, 1, 2)
    marginals = errors.copy()
    marginals[:, :6, :6] *= 0.1  # a pose block far below the error's: a naive mix fails
    naive = errors.copy()
    naive[:, :6, :6] = marginals[:, :6, :6]
    assert np.linalg.eigvalsh(naive)[:, 0].min() < 0
    combined = combine_pose_and_twist(marginals, errors)
    np.testing.assert_array_equal(combined[:, :6, :6], marginals[:, :6, :6])
    np.testing.assert_array_equal(combined[:, 6:, 6:], errors[:, 6:, 6:])
    np.testing.assert_allclose(combined, np.swapaxes(combined, 1, 2))
    scale = np.linalg.eigvalsh(combined)[:, -1]
    assert (np.linalg.eigvalsh(combined)[:, 0] >= -1e-10 * scale).all()
    # equal pose blocks: the error covariance itself
    np.testing.assert_allclose(combine_pose_and_twist(errors, errors), errors, atol=1e-8)


@pytest.mark.parametrize("method", ["tight", "tight-batch"])
def test_the_twist_covariance_matches_its_errors(method):
    """The marginal made the twist 3-8x too uncertain (NEES per dof 0.13-0.54 on every
    family): over paper and family draws the twist NEES is now near 1, and the pose's
    stays the marginal's."""
    scenarios = [simulate(paper_scenario(seed=s)) for s in (0, 1, 2)]
    scenarios += [draw(family, 0).scenario for family in ("agile", "precise", "hover")]
    pose, twist = [], []
    for scenario in scenarios:
        trajectory = run_estimate(
            scenario.observations, scenario, method, covariance=True
        ).trajectory
        p, t = trajectory_nees(trajectory, scenario.groundtruth, t_start=1.0)
        pose.append(p)
        twist.append(t)
    assert 0.7 <= np.mean(twist) <= 1.3 and min(twist) > 0.6, twist
    assert 0.4 <= np.mean(pose) <= 1.5, pose
