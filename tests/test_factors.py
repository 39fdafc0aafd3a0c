"""Custom factors of the smoother (hvo_graph.estimators.factors).

Independent references: GTSAM's own numerical derivative
(gtsam.utils.numerical_derivative, central differences through retract on the
manifold) for every analytic Jacobian, as GTSAM's test_custom_factor does;
GTSAM's SE(3) exponential for the zero residual of constant-twist motion;
dense numerical quadrature (numpy.interp on a fine grid) for the interval
weights.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import V, X
from gtsam.utils.numerical_derivative import (
    numericalDerivative11,
    numericalDerivative41,
    numericalDerivative42,
    numericalDerivative43,
    numericalDerivative44,
)

from hvo_graph.errors import InputError
from hvo_graph.estimators.factors import (
    interval_weights,
    mean_velocity_factor,
    mean_velocity_residual,
    motion_factor,
    motion_residual,
)
from hvo_graph.estimators.motion_model import wna_factor
from hvo_graph.estimators.process_noise import twist_spectral_density


def random_case(seed: int, rotation_scale: float, relative_scale: float):
    """Two poses (the second near the first), two twists and a dt."""
    rng = np.random.default_rng(seed)
    first = gtsam.Pose3.Expmap(
        np.concatenate((rotation_scale * rng.normal(size=3), rng.normal(size=3)))
    )
    second = first.compose(gtsam.Pose3.Expmap(relative_scale * rng.normal(size=6)))
    dt = float(rng.uniform(0.01, 0.5))
    return first, second, rng.normal(size=6), rng.normal(size=6), dt


# (seed, rotation scale of the absolute poses, scale of the relative motion):
# large absolute rotations, large relative motion (|phi| ~ 1.5 rad), tiny relative
# motion (phi -> 0, where J_r^-1 -> I), and a realistic frame step.
CASES = [(0, 1.0, 0.8), (1, 2.0, 0.8), (2, 0.5, 1e-7), (3, 1.0, 0.02), (4, 3.0, 0.3)]


@pytest.mark.parametrize(("seed", "rotation_scale", "relative_scale"), CASES)
def test_motion_residual_jacobians_match_gtsam_numerical_derivative(
    seed, rotation_scale, relative_scale
):
    T1, T2, v1, v2, dt = random_case(seed, rotation_scale, relative_scale)
    e, J = motion_residual(T1, T2, v1, v2, dt, jacobians=True)
    np.testing.assert_allclose(e, motion_residual(T1, T2, v1, v2, dt), atol=1e-12)

    def f(a, b, c, d):
        return motion_residual(a, b, c, d, dt)

    derivatives = (
        numericalDerivative41,
        numericalDerivative42,
        numericalDerivative43,
        numericalDerivative44,
    )
    for i, numerical in enumerate(derivatives):
        np.testing.assert_allclose(
            J[i], numerical(f, T1, T2, v1, v2), atol=1e-7, err_msg=f"block {i}"
        )


def test_motion_residual_is_zero_for_constant_twist_motion():
    # Under a constant twist xi, T_k = T_{k-1} Exp(dt xi) exactly, so the trapezoid is exact.
    rng = np.random.default_rng(5)
    for _ in range(5):
        xi = rng.normal(size=6)
        dt = float(rng.uniform(0.01, 0.3))
        T1 = gtsam.Pose3.Expmap(rng.normal(size=6))
        T2 = T1.compose(gtsam.Pose3.Expmap(dt * xi))
        np.testing.assert_allclose(motion_residual(T1, T2, xi, xi, dt), np.zeros(6), atol=1e-12)


def test_motion_residual_is_log_of_relative_pose_minus_mean_twist():
    T1, T2, v1, v2, dt = random_case(6, 1.0, 0.5)
    relative = np.linalg.inv(T1.matrix()) @ T2.matrix()
    expected = gtsam.Pose3.Logmap(gtsam.Pose3(relative)) - dt * (v1 + v2) / 2
    np.testing.assert_allclose(motion_residual(T1, T2, v1, v2, dt), expected, atol=1e-12)


def factor_numerical_jacobian(factor, values: gtsam.Values, key: int, is_pose: bool) -> np.ndarray:
    """d(unwhitened error)/d(value of key), by GTSAM's central differences through retract."""

    def error_at(value):
        perturbed = gtsam.Values(values)
        perturbed.erase(key)
        perturbed.insert(key, value)
        return factor.unwhitenedError(perturbed)

    value = values.atPose3(key) if is_pose else values.atVector(key)
    return numericalDerivative11(error_at, value)


@pytest.mark.parametrize(("seed", "rotation_scale", "relative_scale"), CASES)
def test_motion_factor_linearization_matches_numerical_derivative(
    seed, rotation_scale, relative_scale
):
    T1, T2, v1, v2, dt = random_case(seed, rotation_scale, relative_scale)
    values = gtsam.Values()
    values.insert(X(3), T1)
    values.insert(X(4), T2)
    values.insert(V(3), v1)
    values.insert(V(4), v2)
    # A full (non-diagonal) covariance: the whitening must not hide a wrong block.
    L = np.tril(np.random.default_rng(seed).normal(size=(6, 6))) + 3 * np.eye(6)
    noise = gtsam.noiseModel.Gaussian.Covariance(L @ L.T)
    factor = motion_factor(X(3), X(4), V(3), V(4), dt, noise)
    assert list(factor.keys()) == [X(3), X(4), V(3), V(4)]
    np.testing.assert_allclose(
        factor.unwhitenedError(values), motion_residual(T1, T2, v1, v2, dt), atol=1e-12
    )
    # The linearized factor is whitened by the square-root information R (R^T R = Sigma^-1).
    A, b = factor.linearize(values).jacobian()
    R = noise.R()
    np.testing.assert_allclose(b, -R @ motion_residual(T1, T2, v1, v2, dt), atol=1e-10)
    for i, (key, is_pose) in enumerate(((X(3), True), (X(4), True), (V(3), False), (V(4), False))):
        numerical = factor_numerical_jacobian(factor, values, key, is_pose)
        np.testing.assert_allclose(
            A[:, 6 * i : 6 * i + 6], R @ numerical, atol=1e-7, err_msg=f"key {i}"
        )


def wna_values(T1, T2, v1, v2) -> gtsam.Values:
    values = gtsam.Values()
    for key, value in ((X(3), T1), (X(4), T2)):
        values.insert(key, value)
    for key, value in ((V(3), v1), (V(4), v2)):
        values.insert(key, value)
    return values


@pytest.mark.parametrize(("seed", "rotation_scale", "relative_scale"), CASES)
def test_wna_factor_is_the_gaussian_process_prior(seed, rotation_scale, relative_scale):
    # Anderson and Barfoot's SE(3) white-noise-on-acceleration prior, written out here:
    # e = [xi - dt v1; J_r^-1(xi) v2 - v1], Cov = Q (x) [[dt^3/3, dt^2/2], [dt^2/2, dt]].
    T1, T2, v1, v2, dt = random_case(seed, rotation_scale, relative_scale)
    q = twist_spectral_density((0.3, 0.7))
    factor = wna_factor(3, 4, dt, q)
    assert set(factor.keys()) == {X(3), X(4), V(3), V(4)}
    J_inv = np.empty((6, 6), order="F")
    xi = gtsam.Pose3.Logmap(T1.between(T2), J_inv)
    expected = np.concatenate((xi - dt * v1, J_inv @ v2 - v1))
    values = wna_values(T1, T2, v1, v2)
    np.testing.assert_allclose(factor.unwhitenedError(values), expected, atol=1e-9)
    Q = np.diag(q)
    covariance = np.block([[Q * dt**3 / 3, Q * dt**2 / 2], [Q * dt**2 / 2, Q * dt]])
    R = factor.noiseModel().R()
    np.testing.assert_allclose(np.linalg.inv(R.T @ R), covariance, rtol=1e-9)


def test_wna_factor_is_the_trapezoid_and_random_walk_when_nothing_turns():
    # Without rotation J_r^-1(xi) leaves the twist as it is, and the trapezoid e1 - dt/2 e2
    # (variance Q dt^3/12) with the random walk e2 (Q dt) is a linear transform of the same
    # Gaussian (the Brownian bridge): the costs are equal (docs/smoother.md).
    rng = np.random.default_rng(7)
    dt, sigma = 0.04, (0.2, 0.5)
    T1 = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.3, -0.2, 0.5), rng.normal(size=3))
    T2 = T1.compose(gtsam.Pose3(gtsam.Rot3(), 0.05 * rng.normal(size=3)))
    v1 = np.concatenate((np.zeros(3), rng.normal(size=3)))
    v2 = np.concatenate((np.zeros(3), rng.normal(size=3)))
    q = twist_spectral_density(sigma)
    values = wna_values(T1, T2, v1, v2)
    bridge = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(q * dt**3 / 12))
    walk = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(q * dt))
    pair = motion_factor(X(3), X(4), V(3), V(4), dt, bridge).error(values)
    pair += gtsam.BetweenFactorVector(V(3), V(4), np.zeros(6), walk).error(values)
    np.testing.assert_allclose(wna_factor(3, 4, dt, q).error(values), pair, rtol=1e-9)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_mean_velocity_factor_error_and_jacobians(n):
    rng = np.random.default_rng(n)
    weights = rng.uniform(0.1, 1.0, size=n)
    weights /= weights.sum()
    twists = [rng.normal(size=6) for _ in range(n)]
    z = rng.normal(size=6)
    values = gtsam.Values()
    for i, xi in enumerate(twists):
        values.insert(V(10 + i), xi)
    noise = gtsam.noiseModel.Gaussian.Covariance(np.diag(rng.uniform(0.1, 2.0, size=6)))
    factor = mean_velocity_factor([V(10 + i) for i in range(n)], weights, z, noise)
    expected = sum(w * xi for w, xi in zip(weights, twists, strict=True)) - z
    np.testing.assert_allclose(factor.unwhitenedError(values), expected, atol=1e-12)
    np.testing.assert_allclose(mean_velocity_residual(twists, weights, z), expected, atol=1e-12)
    A, _ = factor.linearize(values).jacobian()  # whitened by R, R^T R = Sigma^-1
    for i in range(n):
        numerical = factor_numerical_jacobian(factor, values, V(10 + i), is_pose=False)
        np.testing.assert_allclose(A[:, 6 * i : 6 * i + 6], noise.R() @ numerical, atol=1e-8)


def test_mean_velocity_factor_rejects_bad_input():
    noise = gtsam.noiseModel.Unit.Create(6)
    with pytest.raises(InputError, match="weights: expected finite weights summing to 1"):
        mean_velocity_factor([V(0), V(1)], [0.5, 0.6], np.zeros(6), noise)
    with pytest.raises(InputError, match="expected the same number"):
        mean_velocity_factor([V(0), V(0)], [0.5, 0.5], np.zeros(6), noise)
    with pytest.raises(InputError, match="expected the same number"):
        mean_velocity_factor([V(0), V(1)], [1.0], np.zeros(6), noise)
    with pytest.raises(InputError, match=r"measured: expected a finite \(6,\) twist"):
        mean_velocity_factor([V(0)], [1.0], np.zeros(5), noise)
    with pytest.raises(InputError, match="noise: expected a 6-dimensional noise model"):
        mean_velocity_factor([V(0)], [1.0], np.zeros(6), gtsam.noiseModel.Unit.Create(3))


def test_motion_factor_rejects_bad_dt_and_noise():
    noise = gtsam.noiseModel.Unit.Create(6)
    with pytest.raises(InputError, match="dt: expected a finite number > 0"):
        motion_factor(X(0), X(1), V(0), V(1), 0.0, noise)
    with pytest.raises(InputError, match="noise: expected a 6-dimensional noise model"):
        motion_factor(X(0), X(1), V(0), V(1), 0.1, gtsam.noiseModel.Unit.Create(3))


def quadrature_average(node_times, node_values, start, end):
    """Mean of the piecewise-linear interpolant (constant outside) over [start, end]."""
    grid = np.linspace(start, end, 200001)
    samples = np.interp(grid, node_times, node_values)
    return np.trapezoid(samples, grid) / (end - start)


@pytest.mark.parametrize(
    ("start", "end"),
    [(1.0, 2.0), (1.5, 3.0), (0.2, 0.7), (-1.0, 0.5), (2.5, 4.0), (-2.0, 5.0), (1.1, 1.2)],
)
def test_interval_weights_average_a_piecewise_linear_twist(start, end):
    times = np.array([0.0, 1.0, 2.0, 3.0])
    weights = interval_weights(times, start, end)
    assert abs(sum(w for _, w in weights) - 1.0) < 1e-12
    rng = np.random.default_rng(0)
    for _ in range(3):  # the weights are linear in the node values: check several
        node_values = rng.normal(size=4)
        from_weights = sum(w * node_values[i] for i, w in weights)
        assert from_weights == pytest.approx(
            quadrature_average(times, node_values, start, end), abs=1e-8
        )


def test_interval_weights_of_the_usual_interval_are_one_half():
    times = [0.0, 1 / 30, 2 / 30, 3 / 30]
    # The front end's interval [t_{k-1}, t_k] as mid-time +- dt/2 (with round-off).
    mid, dt = (times[1] + times[2]) / 2, times[2] - times[1]
    assert interval_weights(times, mid - dt / 2, mid + dt / 2) == [
        (1, pytest.approx(0.5)),
        (2, pytest.approx(0.5)),
    ]


def test_interval_weights_for_an_instant_interpolate():
    times = [0.0, 1.0, 2.0]
    assert interval_weights(times, 1.25, 1.25) == [
        (1, pytest.approx(0.75)),
        (2, pytest.approx(0.25)),
    ]
    assert interval_weights(times, -1.0, -1.0) == [(0, 1.0)]
    assert interval_weights(times, 9.0, 9.0) == [(2, 1.0)]


def test_interval_weights_reject_reversed_interval():
    with pytest.raises(InputError, match=r"interval: expected start <= end, got \[2, 1\]"):
        interval_weights([0.0, 1.0], 2, 1)
