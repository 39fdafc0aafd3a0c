"""The smoother's error covariance: block recursions against dense linear algebra, and
against the spread of a simulated linear smoother's errors."""

from __future__ import annotations

import numpy as np
import pytest

from hvo_graph.estimators.error_covariance import (
    STATE,
    ChainSystem,
    dense_error_covariances,
    error_covariances,
)


def random_chain(K: int, m: int, seed: int) -> ChainSystem:
    """A random chain: motion factors between neighbours, measurements per frame."""
    rng = np.random.default_rng(seed)
    n = STATE
    motion_diagonal = np.zeros((K, n, n))
    motion_upper = np.zeros((K - 1, n, n))
    for k in range(K - 1):
        J = rng.normal(size=(n, 2 * n))  # a factor on [x_k; x_k+1]
        H = J.T @ J
        motion_diagonal[k] += H[:n, :n]
        motion_diagonal[k + 1] += H[n:, n:]
        motion_upper[k] = H[:n, n:]
    measurement = np.zeros((K, n, n))
    for k in range(K):
        a = rng.normal(size=(6, n))
        measurement[k] = a.T @ a
    fixed = np.zeros((K, n, n))
    fixed[0] = np.eye(n)
    return ChainSystem(
        motion_diagonal=motion_diagonal,
        motion_upper=motion_upper,
        fixed=fixed,
        measurement=measurement,
        measurement_upper=np.zeros((K - 1, n, n)),
        shared=rng.normal(size=(K, n, m)),
        gradient=rng.normal(size=(K, n)),
        times=np.arange(K) / 30.0,
    )


@pytest.mark.parametrize("anchored", [False, True])
@pytest.mark.parametrize("gap", [False, True])
def test_block_recursions_equal_the_dense_sandwich(anchored: bool, gap: bool) -> None:
    system = random_chain(K=9, m=4, seed=3)
    if gap:  # frames 3-5 without measurements: the model's spread bridges them
        system.measurement[3:6] = 0.0
    adjoint = None
    if anchored:
        adjoint = np.random.default_rng(5).normal(size=(9, 6, 6))
    fast = error_covariances(system, anchor_adjoint=adjoint, bias_scale=None)
    dense = dense_error_covariances(system, anchor_adjoint=adjoint)
    np.testing.assert_allclose(fast, dense, rtol=1e-8, atol=1e-10 * np.abs(dense).max())


def test_the_covariance_matches_the_spread_of_simulated_errors() -> None:
    """A linear smoother x^ = P A^T W z with independent and shared measurement noise:
    the empirical covariance of its errors over many draws is what the formula says."""
    system = random_chain(K=6, m=3, seed=11)
    K, n = 6, STATE
    rng = np.random.default_rng(2)
    # measurement model: z_k = x_k-part + own noise (info M_k) + shared rho response
    diagonal, upper = system.information()
    Lam = np.zeros((K * n, K * n))
    for k in range(K):
        Lam[k * n : (k + 1) * n, k * n : (k + 1) * n] = diagonal[k]
        if k + 1 < K:
            Lam[k * n : (k + 1) * n, (k + 1) * n : (k + 2) * n] = upper[k]
            Lam[(k + 1) * n : (k + 2) * n, k * n : (k + 1) * n] = upper[k].T
    P = np.linalg.inv(Lam)
    roots = [np.linalg.cholesky(system.measurement[k] + 1e-12 * np.eye(n)) for k in range(K)]
    draws = 20000
    errors = np.empty((draws, K * n))
    for i in range(draws):
        # A^T W eta: own part ~ N(0, M_k) per frame, shared part Y rho
        g = np.concatenate([roots[k] @ rng.normal(size=n) for k in range(K)])
        g += system.shared.reshape(K * n, -1) @ rng.normal(size=system.shared.shape[2])
        errors[i] = P @ g
    empirical = np.cov(errors.T)
    predicted = error_covariances(system, bias_scale=None)
    for k in range(K):
        block = empirical[k * n : (k + 1) * n, k * n : (k + 1) * n]
        np.testing.assert_allclose(np.diag(block), np.diag(predicted[k]), rtol=0.05)


def smooth_motion_chain(
    K: int, dt: float, q: float, pose_sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The smoother's chain for independent axes: trapezoidal motion factors
    (q dt^3 / 12) and twist random walks (q dt) between frames, a pose measurement
    of standard deviations ``pose_sigma`` (6,) on every frame."""
    n, eye, zero = STATE, np.eye(6), np.zeros((6, 6))
    trapezoid = np.hstack((-eye, -dt / 2 * eye, eye, -dt / 2 * eye)) / np.sqrt(q * dt**3 / 12)
    walk = np.hstack((zero, -eye, zero, eye)) / np.sqrt(q * dt)
    H = trapezoid.T @ trapezoid + walk.T @ walk
    motion_diagonal, motion_upper = np.zeros((K, n, n)), np.zeros((K - 1, n, n))
    for k in range(K - 1):
        motion_diagonal[k] += H[:n, :n]
        motion_diagonal[k + 1] += H[n:, n:]
        motion_upper[k] = H[:n, n:]
    measurement = np.zeros((K, n, n))
    measurement[:, :6, :6] = np.diag(pose_sigma**-2.0)
    return motion_diagonal, motion_upper, measurement


def test_the_motion_model_s_bias_on_a_weakly_measured_pose_axis_is_counted() -> None:
    """A sinusoid the white-noise-acceleration model is too stiff for, measured weakly
    along one pose axis (as a plane seen head-on measures its tilt-shift ambiguity):
    there the smoothed pose is biased well beyond its noise. The covariance counts
    the bias the data show; the noise-induced part alone is several times too small."""
    K, dt, q = 60, 1.0 / 30.0, 0.1
    pose_sigma = np.array([0.05, 0.002, 0.002, 0.002, 0.002, 0.002])
    motion_diagonal, motion_upper, measurement = smooth_motion_chain(K, dt, q, pose_sigma)
    Lam = np.zeros((K * STATE, K * STATE))
    for k in range(K):
        s = slice(k * STATE, (k + 1) * STATE)
        Lam[s, s] = motion_diagonal[k] + measurement[k]
        if k + 1 < K:
            t = slice((k + 1) * STATE, (k + 2) * STATE)
            Lam[s, t] = motion_upper[k]
            Lam[t, s] = motion_upper[k].T
    times = np.arange(K) * dt
    omega = 2.0 * np.pi * 0.7
    pose = 0.2 * np.sin(omega * times)[:, None] * np.ones(6)
    truth = np.hstack((pose, 0.2 * omega * np.cos(omega * times)[:, None] * np.ones(6)))
    rng = np.random.default_rng(4)
    nees: dict[bool, list[float]] = {True: [], False: []}
    for _ in range(8):
        z = pose + rng.normal(size=pose.shape) * pose_sigma
        pull = np.zeros((K, STATE))
        pull[:, :6] = z / pose_sigma**2
        estimate = np.linalg.solve(Lam, pull.ravel()).reshape(K, STATE)
        gradient = np.zeros((K, STATE))
        gradient[:, :6] = (z - estimate[:, :6]) / pose_sigma**2
        system = ChainSystem(
            motion_diagonal=motion_diagonal,
            motion_upper=motion_upper,
            fixed=np.zeros((K, STATE, STATE)),
            measurement=measurement,
            measurement_upper=np.zeros((K - 1, STATE, STATE)),
            shared=np.zeros((K, STATE, 0)),
            gradient=gradient,
            times=times,
        )
        error = estimate - truth
        for with_bias in (True, False):
            C = error_covariances(system, bias_scale=100.0 if with_bias else None)
            for k in range(10, K - 10):
                e = error[k, :6]
                nees[with_bias].append(e @ np.linalg.solve(C[k, :6, :6], e) / 6)
    assert np.mean(nees[False]) > 2.0
    assert 0.6 < np.mean(nees[True]) < 1.4


def test_a_near_static_sequence_with_a_numerically_noiseless_direction_gets_covariances() -> None:
    """A near-hover draw (4 s) once made the bias probe's noise metric divide by 1e-150
    (a -1e-20 variance at the reference pose) and numpy's eigh fail; the fixed-lag run
    must give finite, symmetric, positive semi-definite covariances that are not
    overconfident."""
    from hvo_graph.eval.consistency import trajectory_nees
    from hvo_graph.montecarlo import make_method
    from hvo_graph.pipeline import measure
    from hvo_graph.sim.families import draw

    scenario = draw("hover", 0, duration=4.0).scenario
    frames = measure(scenario.observations, scenario, method="smoother")
    trajectory = make_method("fixed-lag", 0, covariance=True).run(frames)
    C = np.asarray(trajectory.covariances)
    assert np.isfinite(C).all()
    np.testing.assert_allclose(C, np.swapaxes(C, 1, 2), atol=1e-12)
    assert np.linalg.eigvalsh(C).min() > -1e-12
    pose_nees, twist_nees = trajectory_nees(
        trajectory, scenario.groundtruth, t_start=float(scenario.groundtruth.t[0]) + 1.0
    )
    assert pose_nees < 3.0 and twist_nees < 3.0
