"""The measured-R Kalman filter's twist covariance calibrated after the run."""

from __future__ import annotations

import numpy as np
import pytest

from hvo_graph.estimators import kalman_calibration
from hvo_graph.estimators.kalman import KalmanBaseline
from hvo_graph.estimators.kalman_calibration import (
    CALIBRATION_FLOOR,
    calibrated,
    calibration_matrix,
    resolves_acceleration,
    smoothed_states,
)
from hvo_graph.estimators.kalman_model import process_covariance, transition_matrix
from hvo_graph.eval.consistency import trajectory_nees
from hvo_graph.montecarlo import FamilySeed, make_method, run_family_seed
from hvo_graph.pipeline import measure
from hvo_graph.sim.families import draw


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return A @ A.T + n * np.eye(n)


@pytest.mark.parametrize("block", [4096, 7])
def test_smoothed_states_are_the_batch_least_squares_optimum(block, monkeypatch):
    """RTS means = the minimiser of the whole sequence's quadratic (prior, dynamics with
    the same F_k and Q_k, measurements): solved here densely, as one linear system (the
    backward pass in one block and in blocks of 7 frames)."""
    monkeypatch.setattr(kalman_calibration, "_BLOCK", block)
    rng = np.random.default_rng(3)
    K, dt = 40, 0.05
    s = np.array([0.3, 0.2, 0.1, 0.05, 0.04, 0.03])
    Q = process_covariance(dt, s)
    R = np.diag(rng.uniform(1e-4, 1e-3, 12))
    P0 = np.eye(12) * 1e-2
    x, P = np.zeros(12), P0.copy()
    xs, Ps, Fs, zs = [], [], [], []
    for k in range(K):
        if k:
            F = transition_matrix(float(x[5]), float(x[3]), dt)
            x, P = F @ x, F @ P @ F.T + Q
            Fs.append(F)
        z = 0.01 * rng.standard_normal(12)  # angles stay small: no wrapping
        G = P @ np.linalg.inv(P + R)
        x, P = x + G @ (z - x), (np.eye(12) - G) @ P
        xs.append(x.copy())
        Ps.append(P.copy())
        zs.append(z)
    smoothed = smoothed_states(
        dt * np.arange(K), np.array(xs), np.array(Ps), lambda step: process_covariance(step, s)
    )
    # Dense normal equations: prior N(0, P0) on x_0, x_k - F_k x_{k-1} ~ N(0, Q),
    # z_k - x_k ~ N(0, R).
    n = 12 * K
    A, b = np.zeros((n, n)), np.zeros(n)
    Ri, Qi = np.linalg.inv(R), np.linalg.inv(Q)
    A[:12, :12] += np.linalg.inv(P0)
    for k in range(K):
        i = slice(12 * k, 12 * k + 12)
        A[i, i] += Ri
        b[i] += Ri @ zs[k]
        if k:
            M = np.hstack((-Fs[k - 1], np.eye(12)))  # rows of [x_{k-1}, x_k]
            block = slice(12 * k - 12, 12 * k + 12)
            A[block, block] += M.T @ Qi @ M
    batch = np.linalg.solve(A, b).reshape(K, 12)
    np.testing.assert_allclose(smoothed, batch, atol=1e-9)
    np.testing.assert_allclose(smoothed[-1], xs[-1])


def test_calibration_matrix_recovers_the_errors_second_moment_in_the_filters_metric():
    rng = np.random.default_rng(0)
    K = 20_000
    C = np.array([_random_spd(rng, 6) * 10.0 ** rng.uniform(-4, -2) for _ in range(K)])
    M = np.diag([0.5, 0.8, 1.0, 1.5, 3.0, 6.0])
    U = np.linalg.qr(rng.standard_normal((6, 6)))[0]
    M = U @ M @ U.T
    w, v = np.linalg.eigh(C)
    C_root = (v * np.sqrt(w)[:, None, :]) @ np.swapaxes(v, 1, 2)
    z = rng.standard_normal((K, 6)) @ np.linalg.cholesky(M).T
    b = np.einsum("kij,kj->ki", C_root, z)
    S = calibration_matrix(b, C, floor=0.0)
    assert S is not None
    np.testing.assert_allclose(S, M, atol=0.15)
    floored = calibration_matrix(b, C, floor=2.0)
    assert np.linalg.eigvalsh(floored).min() >= 2.0 - 1e-9
    assert calibration_matrix(b[:10], C[:10]) is None  # too few frames


def test_calibrated_covariance_maps_the_twist_block_and_keeps_the_pose():
    rng = np.random.default_rng(1)
    cov = np.array([_random_spd(rng, 12) for _ in range(5)])
    S = _random_spd(rng, 6) / 6
    out = calibrated(cov, S)
    np.testing.assert_array_equal(out[:, :6, :6], cov[:, :6, :6])
    for k in range(5):
        w, v = np.linalg.eigh(cov[k, 6:, 6:])
        root = v @ np.diag(np.sqrt(w)) @ v.T
        np.testing.assert_allclose(out[k, 6:, 6:], root @ S @ root, rtol=1e-9)
        assert np.linalg.eigvalsh(out[k]).min() > 0  # a congruence keeps it definite


def test_resolves_acceleration_reads_the_fits_lower_bound():
    assert not resolves_acceleration(np.full(6, 1e-5))
    assert resolves_acceleration(np.array([1e-5, 1e-5, 1e-5, 1e-2, 1e-2, 1e-2]))


def test_measured_r_filter_twist_nees_is_honest_where_it_lagged():
    """many-points: a weakly measured tilt-shift direction where the filtered twist lags
    smooth motion by several standard deviations (twist NEES per dof 1.6 over 16 draws
    before the calibration)."""
    values = [
        run_family_seed(FamilySeed("many-points", seed), ["kalman-measured"]).nees[
            "kalman-measured"
        ][1]
        for seed in range(4)
    ]
    assert 0.7 < np.mean(values) < 1.3, values


def test_calibration_changes_only_the_reported_twist_covariance():
    scenario = draw("paper-like", 0, duration=6.0).scenario
    frames = measure(scenario.observations, scenario)
    kf = make_method("kalman-measured", 0, covariance=True)
    final = kf.run(frames)
    online = kf.online_trajectory()
    np.testing.assert_array_equal(final.positions, online.positions)
    np.testing.assert_array_equal(final.twists, online.twists)
    np.testing.assert_array_equal(final.covariances[:, :6, :6], online.covariances[:, :6, :6])
    assert not np.allclose(final.covariances[:, 6:, 6:], online.covariances[:, 6:, 6:])
    before = trajectory_nees(online, scenario.groundtruth, t_start=1.0)[1]
    after = trajectory_nees(final, scenario.groundtruth, t_start=1.0)[1]
    assert abs(np.log(after)) < abs(np.log(before)), (before, after)
    # Off: the filter's own covariance.
    plain = KalmanBaseline(
        r_preset="measured",
        process_noise="auto",
        velocity_updates="gaps",
        world_frame_velocity=True,
        calibrate_twist=False,
    ).run(frames)
    np.testing.assert_array_equal(plain.covariances, online.covariances)


def test_paper_presets_and_near_static_motion_are_not_calibrated():
    scenario = draw("paper-like", 1, duration=3.0).scenario
    frames = measure(scenario.observations, scenario)
    kf = KalmanBaseline()
    np.testing.assert_array_equal(kf.run(frames).covariances, kf.online_trajectory().covariances)
    hover = draw("hover", 0, duration=5.0).scenario
    kf = make_method("kalman-measured", 0, covariance=True)
    final = kf.run(measure(hover.observations, hover))
    assert not resolves_acceleration(kf.process_noise)
    np.testing.assert_array_equal(final.covariances, kf.online_trajectory().covariances)
    assert 0.0 < CALIBRATION_FLOOR < 1.0
