"""The white-noise-jerk motion model (hvo_graph.estimators.jerk, motion_model, noise_estimation).

Independent references: GTSAM's numerical derivative for the pose factor's
Jacobians; the textbook discretisation of a white-noise-jerk (constant-
acceleration) model, Q = q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2],
[dt^3/6, dt^2/2, dt]] (Bar-Shalom, Li & Kirubarajan, section 6.2.3), written out
here, for the two factors' joint information and the likelihood; exact
constant-acceleration and random-walk-twist trajectories for the smoother and
the model choice.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import A, V, X
from gtsam.utils.numerical_derivative import (
    numericalDerivative61,
    numericalDerivative62,
    numericalDerivative63,
    numericalDerivative64,
    numericalDerivative65,
    numericalDerivative66,
)

from hvo_graph.errors import InputError
from hvo_graph.estimators.jerk import (
    POSE_FLOOR,
    JerkNoise,
    jerk_motion_factor,
    jerk_motion_residual,
    twist_rate_factor,
)
from hvo_graph.estimators.noise_estimation import estimate_process_noise, jerk_log_likelihood
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.pipeline import make_estimator
from hvo_graph.types import FrameMeasurement, PoseMeasurement


def textbook(q: float, dt: float) -> np.ndarray:
    """Covariance of (position, velocity, acceleration) increments of one WNJ axis."""
    return q * np.array(
        [
            [dt**5 / 20, dt**4 / 8, dt**3 / 6],
            [dt**4 / 8, dt**3 / 3, dt**2 / 2],
            [dt**3 / 6, dt**2 / 2, dt],
        ]
    )


@pytest.mark.parametrize(("seed", "scale"), [(0, 1.0), (1, 0.05), (2, 1e-4)])
def test_pose_factor_jacobians_match_gtsam_numerical_derivative(seed, scale):
    rng = np.random.default_rng(seed)
    T1 = gtsam.Pose3.Expmap(rng.normal(size=6))
    T2 = T1.compose(gtsam.Pose3.Expmap(scale * rng.normal(size=6)))
    v1, v2, a1, a2 = (rng.normal(size=6) for _ in range(4))
    dt = 0.04
    e, J = jerk_motion_residual(T1, T2, v1, v2, a1, a2, dt, jacobians=True)
    np.testing.assert_allclose(e, jerk_motion_residual(T1, T2, v1, v2, a1, a2, dt), atol=1e-12)

    def f(*args):
        return jerk_motion_residual(*args, dt)

    derivatives = (
        numericalDerivative61,
        numericalDerivative62,
        numericalDerivative63,
        numericalDerivative64,
        numericalDerivative65,
        numericalDerivative66,
    )
    for derivative, analytic in zip(derivatives, J, strict=True):
        numeric = derivative(f, T1, T2, v1, v2, a1, a2, 1e-5)
        np.testing.assert_allclose(analytic, numeric, atol=1e-7)


def test_the_two_factors_are_the_textbook_wnj_prior():
    """On one translation axis, near zero motion (where Log is the identity), the pose
    factor and the twist-rate factor together carry the information of the textbook
    increment covariance: J^T Q^-1 J with (e_p, e_v, e_a) = J [x0 v0 a0 x1 v1 a1]."""
    dt, q = 0.5, 2.0  # Q dt^5 / 720 >> the floor: the exact model is tested
    assert q * dt**5 / 720 > 1e4 * POSE_FLOOR**2
    sigma = (np.sqrt(q), np.sqrt(q))
    noise = JerkNoise(sigma)
    keys = (X(0), X(1), V(0), V(1), A(0), A(1))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(jerk_motion_factor(keys, dt, noise(dt)))
    graph.add(twist_rate_factor((V(0), A(0), V(1), A(1)), dt, noise.q))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3())
    values.insert(X(1), gtsam.Pose3())
    for key in keys[2:]:
        values.insert(key, np.zeros(6))
    H = graph.linearize(values).hessian(gtsam.Ordering(list(keys)))[0]
    axis = 3  # x translation of every variable, in the order x0 x1 v0 v1 a0 a1
    picked = [6 * i + axis for i in range(6)]
    got = H[np.ix_(picked, picked)]
    # e_p = x1 - x0 - dt v0 - dt^2/2 a0; e_v = v1 - v0 - dt a0; e_a = a1 - a0
    J = np.array(
        [
            [-1, 1, -dt, 0, -(dt**2) / 2, 0],
            [0, 0, -1, 1, -dt, 0],
            [0, 0, 0, 0, -1, 1],
        ]
    )
    expected = J.T @ np.linalg.solve(textbook(q, dt), J)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-6 * np.abs(expected).max())


def test_twist_rate_factor_error_is_the_gaussian_exponent():
    rng = np.random.default_rng(3)
    dt, q = 1 / 30, rng.uniform(0.1, 2.0, 6)
    factor = twist_rate_factor((V(0), A(0), V(1), A(1)), dt, q)
    x = {key: rng.normal(size=6) for key in (V(0), A(0), V(1), A(1))}
    values = gtsam.Values()
    for key, value in x.items():
        values.insert(key, value)
    expected = 0.0
    for i in range(6):
        r = np.array([x[V(1)][i] - x[V(0)][i] - dt * x[A(0)][i], x[A(1)][i] - x[A(0)][i]])
        expected += 0.5 * r @ np.linalg.solve(textbook(q[i], dt)[1:, 1:], r)
    assert factor.error(values) == pytest.approx(expected, rel=1e-9)


def test_one_step_jerk_likelihood_is_the_gaussian_density():
    """Two poses: s_1 - s_0 ~ N(0, C_0 + C_1 + Q dt^5/20 + prior), the broad priors on
    twist and rate (1e4) moving the position by dt and dt^2 / 2."""
    rng = np.random.default_rng(1)
    s = np.vstack((np.zeros(6), rng.normal(scale=0.01, size=6)))
    C = np.stack([np.eye(6) * 1e-4, np.eye(6) * 2e-4])
    t, dt = np.array([0.0, 0.1]), 0.1
    q_w, q_v = 0.5, 2.0
    q = np.diag([q_w] * 3 + [q_v] * 3)
    S = C[0] + C[1] + q * dt**5 / 20 + 1e4 * (dt**2 + dt**4 / 4) * np.eye(6)
    _, logdet = np.linalg.slogdet(S)
    expected = -0.5 * (s[1] @ np.linalg.solve(S, s[1]) + logdet + 6 * np.log(2 * np.pi))
    got = jerk_log_likelihood(t, s, C, np.array([q_w]), np.array([q_v]))
    np.testing.assert_allclose(got, [expected], rtol=1e-10)


def frames_of(poses: list[gtsam.Pose3], dt: float, r: float, rng=None) -> list[FrameMeasurement]:
    out = []
    for k, pose in enumerate(poses):
        if rng is not None:
            pose = pose.retract(np.sqrt(r) * rng.standard_normal(6))
        measured = PoseMeasurement(pose.rotation().matrix(), pose.translation(), r * np.eye(6))
        out.append(FrameMeasurement(k, k * dt, measured, None))
    return out


@pytest.mark.parametrize("solver", ["isam2", "batch", "fixed-lag"])
def test_wnj_recovers_a_constant_acceleration_motion(solver):
    """Exact poses of p(t) = v0 t + a t^2 / 2 (no rotation): no jerk, so the WNJ
    smoother's twists are the truth v0 + a t at every frame, the ends included."""
    dt, n = 1 / 30, 90
    v0, a = np.array([0.2, -0.1, 0.05]), np.array([0.6, 0.3, -0.4])
    t = np.arange(n) * dt
    poses = [gtsam.Pose3(gtsam.Rot3(), v0 * tk + 0.5 * a * tk**2) for tk in t]
    smoother = FactorGraphSmoother(solver=solver, motion_model="wnj", acceleration_sigma=0.1)
    estimate = smoother.run(frames_of(poses, dt, r=1e-10))
    truth = v0[None] + t[:, None] * a[None]
    np.testing.assert_allclose(estimate.twists[:, 3:], truth, atol=1e-4)
    np.testing.assert_allclose(estimate.twists[:, :3], 0.0, atol=1e-4)
    np.testing.assert_allclose(estimate.positions, [p.translation() for p in poses], atol=1e-6)


def random_walk_poses(rng: np.random.Generator, n: int, dt: float, q: float):
    """A twist random walk (white-noise acceleration, exact discretisation)."""
    poses, twist = [gtsam.Pose3()], np.zeros(6)
    for _ in range(n - 1):
        w = np.sqrt(q * dt) * rng.standard_normal(6)
        poses.append(poses[-1].compose(gtsam.Pose3.Expmap(dt * (twist + 0.5 * w))))
        twist = twist + w
    return poses


def test_the_likelihood_picks_wnj_on_smooth_motion_and_wna_on_a_random_walk():
    rng = np.random.default_rng(5)
    dt, n = 1 / 30, 300
    t = np.arange(n) * dt
    smooth = [
        gtsam.Pose3(
            gtsam.Rot3.Rz(0.2 * np.sin(0.6 * tk)),
            np.array([0.3 * np.sin(0.8 * tk), 0.2 * np.cos(0.5 * tk), 0.1 * tk]),
        )
        for tk in t
    ]
    rough = random_walk_poses(rng, n, dt, q=1.0)
    picked = estimate_process_noise(frames_of(smooth, dt, 1e-6, rng), default=(1, 1), model="auto")
    assert picked.model == "wnj"
    picked = estimate_process_noise(frames_of(rough, dt, 1e-6, rng), default=(1, 1), model="auto")
    assert picked.model == "wna"


def test_auto_resolves_per_sequence_and_fixed_values_and_the_default_are_wna():
    rng = np.random.default_rng(6)
    dt = 1 / 30
    rough = frames_of(random_walk_poses(rng, 200, dt, q=1.0), dt, 1e-6, rng)
    smoother = FactorGraphSmoother(motion_model="auto")
    smoother.run(rough)
    assert smoother.motion_model == "wna"
    assert FactorGraphSmoother(motion_model="auto", acceleration_sigma=0.1).motion_model == "wna"
    assert FactorGraphSmoother().motion_model == "wna"  # the default
    assert make_estimator("batch", motion_model="wnj").motion_model == "wnj"


def test_bad_motion_model_is_an_input_error():
    with pytest.raises(InputError, match=r"motion_model: expected one of auto, wna, wnj, got 'cv'"):
        FactorGraphSmoother(motion_model="cv")
    with pytest.raises(InputError, match="motion_model"):
        make_estimator("kalman", motion_model="wnj")  # not an option of the filter
