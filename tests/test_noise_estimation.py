"""hvo_graph.estimators.noise_estimation: the motion model's noise from the pose measurements."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from hvo_graph.estimators import noise_estimation
from hvo_graph.estimators.noise_estimation import (
    MIN_SPECTRAL_DENSITY,
    OUTLIER_GATE,
    estimate_process_noise,
    filter_process_noise,
    jerk_log_likelihood,
    log_likelihood,
    unrolled_poses,
)
from hvo_graph.measurement_table import MeasurementTable
from hvo_graph.types import FrameMeasurement, PoseMeasurement


def wna_sequence(q_w: float, q_v: float, r: float, n: int = 600, dt: float = 1 / 30, seed=0):
    """Poses of a white-noise-acceleration motion (exact discretisation), measured with
    isotropic noise of variance r on the tangent: what the estimator's model assumes."""
    rng = np.random.default_rng(seed)
    q = np.array([q_w] * 3 + [q_v] * 3)
    Qd = np.block(
        [[np.eye(6) * dt**3 / 3, np.eye(6) * dt**2 / 2], [np.eye(6) * dt**2 / 2, np.eye(6) * dt]]
    )
    Qd = Qd * np.concatenate((q, q))[None, :] ** 0.5 * np.concatenate((q, q))[:, None] ** 0.5
    L = np.linalg.cholesky(Qd) if np.any(q) else np.zeros((12, 12))
    pose, twist = gtsam.Pose3(), np.zeros(6)
    frames = []
    for k in range(n):
        if k:
            w = L @ rng.standard_normal(12)
            pose = pose.compose(gtsam.Pose3.Expmap(dt * twist + w[:6] - 0.0))
            twist = twist + w[6:]
        noisy = pose.retract(np.sqrt(r) * rng.standard_normal(6))
        cov = r * np.eye(6)
        frames.append(
            FrameMeasurement(
                k,
                k * dt,
                PoseMeasurement(noisy.rotation().matrix(), noisy.translation(), cov),
                None,
            )
        )
    return frames


@pytest.mark.parametrize(("q_w", "q_v"), [(1e-2, 1e-3), (1e-1, 1.0)])
def test_recovers_the_spectral_densities_of_a_wna_motion(q_w, q_v):
    frames = wna_sequence(q_w, q_v, r=1e-6)
    est = estimate_process_noise(frames, default=(1.0, 1.0))
    s_w, s_v = est.acceleration_sigma
    assert est.poses == len(frames)
    # 600 frames: the ML estimate is within a factor 1.6 of the truth
    assert q_w / 1.6 < s_w**2 < q_w * 1.6
    assert q_v / 1.6 < s_v**2 < q_v * 1.6


def test_static_camera_stays_at_the_floor_and_short_sequences_keep_the_default():
    frames = wna_sequence(0.0, 0.0, r=1e-6, n=200)
    s_w, s_v = estimate_process_noise(frames, default=(1.0, 1.0)).acceleration_sigma
    assert s_w**2 == pytest.approx(MIN_SPECTRAL_DENSITY)
    assert s_v**2 == pytest.approx(MIN_SPECTRAL_DENSITY)
    short = estimate_process_noise(frames[:5], default=(0.3, 0.4))
    assert short.acceleration_sigma == (0.3, 0.4) and short.poses == 0


def test_likelihood_of_one_step_is_the_gaussian_density():
    """Two poses: s_1 - s_0 ~ N(0, C_0 + C_1 + Q dt^3/3 + 1e4 dt^2 I) (broad twist prior)."""
    rng = np.random.default_rng(1)
    s = np.vstack((np.zeros(6), rng.normal(scale=0.01, size=6)))
    C = np.stack([np.eye(6) * 1e-4, np.eye(6) * 2e-4])
    t = np.array([0.0, 0.1])
    q_w, q_v = 0.5, 2.0
    S = C[0] + C[1] + np.diag([q_w] * 3 + [q_v] * 3) * 0.1**3 / 3 + 1e4 * 0.01 * np.eye(6)
    _, logdet = np.linalg.slogdet(S)
    expected = -0.5 * (s[1] @ np.linalg.solve(S, s[1]) + logdet + 6 * np.log(2 * np.pi))
    got = log_likelihood(t, s, C, np.array([q_w]), np.array([q_v]))
    np.testing.assert_allclose(got, [expected], rtol=1e-10)


def test_unrolled_poses_use_the_own_pixel_covariance_and_compose_keyframes():
    A = gtsam.Pose3(gtsam.Rot3.Rz(0.1), np.array([0.1, 0.0, 0.0]))
    B = gtsam.Pose3(gtsam.Rot3.Rx(0.05), np.array([0.0, 0.2, 0.0]))
    total, shared = 3e-4 * np.eye(6), 1e-4 * np.eye(6)
    frames = [
        FrameMeasurement(
            0,
            0.0,
            PoseMeasurement(np.eye(3), np.zeros(3), total, reference_covariance=shared),
            None,
        ),
        FrameMeasurement(
            1, 0.1, PoseMeasurement(A.rotation().matrix(), A.translation(), total), None
        ),
        FrameMeasurement(
            2,
            0.2,
            PoseMeasurement(
                B.rotation().matrix(),
                B.translation(),
                total,
                reference=1,
                reference_rotation=A.rotation().matrix(),
                reference_position=A.translation(),
                plane_jacobian=np.eye(6),
            ),
            None,
        ),
    ]
    t, s, C = unrolled_poses(frames)
    np.testing.assert_allclose(t, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(C[0], total - shared)
    np.testing.assert_allclose(s[1], gtsam.Pose3.Logmap(A))
    np.testing.assert_allclose(s[2] - s[1], gtsam.Pose3.Logmap(B), atol=1e-12)


def textbook_log_likelihood(t, s, C, q_w, q_v, gate, order):
    """One pair, the Kalman filter as written in the textbooks (full matrices, numpy's
    solve and slogdet): the reference for the lockstep filter of the module."""
    n = 6 * order
    x, P = np.zeros(n), np.zeros((n, n))
    x[:6], P[:6, :6], P[6:, 6:] = s[0], C[0], 1e4 * np.eye(n - 6)
    H = np.hstack((np.eye(6), np.zeros((6, n - 6))))
    q = np.diag([q_w] * 3 + [q_v] * 3)
    total = 0.0
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        # F = exp(A dt), Q_k = int_0^dt exp(A u) e e^T exp(A u)^T du (A: the shift matrix)
        f = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])[:order, :order]
        powers = 2 * order - 1 - np.add.outer(np.arange(order), np.arange(order))
        scale = np.array([math.factorial(order - 1 - i) for i in range(order)])
        u = dt**powers / (powers * np.outer(scale, scale))
        F = np.kron(f, np.eye(6))
        x, P = F @ x, F @ P @ F.T + np.kron(u, q)
        y, S = s[k] - H @ x, H @ P @ H.T + C[k]
        d2 = y @ np.linalg.solve(S, y)
        total -= 0.5 * (min(d2, gate) + np.linalg.slogdet(S)[1] + 6 * np.log(2 * np.pi))
        if d2 <= gate:
            gain = P @ H.T @ np.linalg.inv(S)
            x, P = x + gain @ y, P - gain @ H @ P
    return total


@pytest.mark.parametrize(("likelihood", "order"), [(log_likelihood, 2), (jerk_log_likelihood, 3)])
def test_the_lockstep_filter_equals_the_textbook_one_pair_by_pair(likelihood, order):
    """Irregular frame times, correlated pose noise and one gated outlier pose: every
    pair's likelihood as the textbook filter's, and alone as among the others."""
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.choice([1 / 30, 2 / 30], size=40))
    s = np.cumsum(rng.normal(scale=0.01, size=(40, 6)), axis=0)
    s[25] += 0.5  # an outlier: beyond the gate for every pair below
    A = rng.normal(size=(40, 6, 6))
    C = 1e-6 * (A @ A.transpose(0, 2, 1) + np.eye(6))
    q_w, q_v = np.array([1e-3, 0.5, 20.0]), np.array([2.0, 1e-2, 0.3])
    got = likelihood(t, s, C, q_w, q_v, OUTLIER_GATE)
    expected = [
        textbook_log_likelihood(t, s, C, a, b, OUTLIER_GATE, order)
        for a, b in zip(q_w, q_v, strict=True)
    ]
    np.testing.assert_allclose(got, expected, rtol=1e-9)
    alone = [likelihood(t, s, C, q_w[i : i + 1], q_v[i : i + 1], OUTLIER_GATE)[0] for i in range(3)]
    np.testing.assert_allclose(alone, got, rtol=1e-14)
    ungated = likelihood(t, s, C, q_w, q_v)
    assert np.all(ungated < got - 100.0)  # the outlier's density, no longer capped at the gate


@pytest.mark.parametrize("likelihood", [log_likelihood, jerk_log_likelihood])
def test_stretches_filtered_side_by_side_give_each_stretch_its_own_likelihood(likelihood):
    """Three stretches of equal length, their steps the same at some frames and not at
    others (one dt for all, or each its own): every stretch's likelihoods as when filtered
    alone, to the last bit, and the textbook filter's."""
    rng = np.random.default_rng(7)
    K = 30
    t = np.cumsum(rng.choice([1 / 30, 2 / 30], size=(3, K)), axis=1)
    t[:, :10] = np.arange(10) / 30  # the first steps the same in every stretch
    s = np.cumsum(rng.normal(scale=0.01, size=(3, K, 6)), axis=1)
    s[1, 12] += 0.5  # one gated outlier in one stretch
    A = rng.normal(size=(3, K, 6, 6))
    C = 1e-6 * (A @ A.transpose(0, 1, 3, 2) + np.eye(6))
    q_w, q_v = np.array([1e-3, 0.5, 20.0]), np.array([2.0, 1e-2, 0.3])
    together = likelihood(t, s, C, q_w, q_v, OUTLIER_GATE)
    assert together.shape == (3, 3)
    for i in range(3):
        alone = likelihood(t[i], s[i], C[i], q_w, q_v, OUTLIER_GATE)
        assert np.array_equal(together[i], alone)
    order = 2 if likelihood is log_likelihood else 3
    expected = textbook_log_likelihood(t[1], s[1], C[1], 0.5, 1e-2, OUTLIER_GATE, order)
    np.testing.assert_allclose(together[1, 1], expected, rtol=1e-9)


def test_a_filter_fits_below_the_bound_only_where_the_data_put_it():
    """A rotation 100x gentler than the bound: the smoother's fit stops at the bound, the
    filter's goes on down to the density of the motion; a density above the bound is
    the smoother's fit unchanged (a motion without rotation: the world frame's is the
    same)."""
    frames = wna_sequence(1e-6, 1e-3, r=1e-8)
    smoother = estimate_process_noise(frames, default=(1.0, 1.0)).acceleration_sigma
    s_w, s_v = filter_process_noise(frames, default=(1.0, 1.0))
    assert smoother[0] ** 2 == pytest.approx(MIN_SPECTRAL_DENSITY)
    assert 1e-6 / 2.0 < s_w**2 < 1e-6 * 2.0
    assert s_v**2 == pytest.approx(smoother[1] ** 2, rel=0.3)


def test_a_turning_constant_body_twist_accelerates_in_the_world_frame():
    """v = 1 m/s turning at 0.5 rad/s: in the body frame the twist is constant (the fit
    stays at the bound); in the world frame v turns at |w x v| = 0.5 m/s^2, and the
    filter's density holds it."""
    dt, twist = 1 / 30, np.array([0.0, 0.0, 0.5, 1.0, 0.0, 0.0])
    frames = [
        FrameMeasurement(
            k,
            k * dt,
            PoseMeasurement(
                (pose := gtsam.Pose3.Expmap(twist * k * dt)).rotation().matrix(),
                pose.translation(),
                1e-8 * np.eye(6),
            ),
            None,
        )
        for k in range(300)
    ]
    body = estimate_process_noise(frames, default=(1.0, 1.0)).acceleration_sigma
    world = estimate_process_noise(frames, default=(1.0, 1.0), translation="world")
    assert body[1] ** 2 == pytest.approx(MIN_SPECTRAL_DENSITY)
    assert world.acceleration_sigma[1] ** 2 > 10 * MIN_SPECTRAL_DENSITY
    assert filter_process_noise(frames, default=(1.0, 1.0))[1] == world.acceleration_sigma[1]


def test_unrolled_world_translation_is_the_position_with_its_covariance_rotated():
    R = gtsam.Rot3.Yaw(np.pi / 2)
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    frames = [
        FrameMeasurement(
            k, k * 0.1, PoseMeasurement(R.matrix(), np.array([k, 2.0, 3.0]), cov), None
        )
        for k in range(3)
    ]
    _, s, C = unrolled_poses(frames, translation="world")
    np.testing.assert_allclose(s[:, 3:], [[0, 2, 3], [1, 2, 3], [2, 2, 3]], atol=1e-12)
    np.testing.assert_allclose(np.diag(C[1])[3:], [5.0, 4.0, 6.0], atol=1e-12)  # x <-> y
    with pytest.raises(Exception, match="translation: expected 'body' or 'world'"):
        unrolled_poses(frames, translation="camera")


@pytest.mark.parametrize(("n", "r"), [(12, 1e-2), (20, 1e-3), (600, 1e-6)])
def test_the_interval_search_ends_where_a_scan_of_the_whole_axis_ends(n, r, monkeypatch):
    frames = wna_sequence(1e-2, 1e-3, r=r, n=n)
    passes: list[int] = []
    evaluate = noise_estimation._evaluate

    def counted(*args):
        passes.append(len(args[2]))  # (likelihood, stretches, log_w, log_v)
        return evaluate(*args)

    monkeypatch.setattr(noise_estimation, "_evaluate", counted)
    staged = estimate_process_noise(frames, default=(1.0, 1.0))
    # Few poses: a flat likelihood, searched past the first decade; 600: within it.
    assert len(passes) == (5 if n < 100 else 4)
    monkeypatch.setattr(noise_estimation, "INTERVAL_FIRST_STEPS", 10**6)
    whole = estimate_process_noise(frames, default=(1.0, 1.0))
    assert staged.acceleration_sigma == whole.acceleration_sigma


def test_a_table_and_its_records_fit_on_the_same_sampled_poses(monkeypatch):
    frames = wna_sequence(1e-2, 1e-3, r=1e-6, n=60)
    # Every third frame without a pose: the stretches are counted in poses, not frames.
    frames = [
        f if k % 3 else FrameMeasurement(f.index, f.t, None, None) for k, f in enumerate(frames)
    ]
    monkeypatch.setattr(noise_estimation, "MAX_POSES", 25)
    from_records = estimate_process_noise(frames, default=(1.0, 1.0))
    from_table = estimate_process_noise(MeasurementTable(frames), default=(1.0, 1.0))
    # 40 poses > 25: six stretches of 25 // 6 = 4 poses.
    assert from_records.poses == from_table.poses == 24
    assert from_records.acceleration_sigma == from_table.acceleration_sigma


def two_regime_sequence(fast: float, slow: float, n: int, seed: int = 0) -> list:
    """n frames of WNA motion with linear density ``fast``, then n with ``slow`` (one
    continuous motion: the second half starts where the first ends)."""
    first = wna_sequence(1e-3, fast, r=1e-6, n=n, seed=seed)
    second = wna_sequence(1e-3, slow, r=1e-6, n=n + 1, seed=seed + 1)
    last = first[-1].pose
    end = gtsam.Pose3(gtsam.Rot3(last.rotation), last.position)
    start = gtsam.Pose3(gtsam.Rot3(second[0].pose.rotation), second[0].pose.position)
    frames = list(first)
    for f in second[1:]:
        p = end.compose(start.between(gtsam.Pose3(gtsam.Rot3(f.pose.rotation), f.pose.position)))
        pose = PoseMeasurement(p.rotation().matrix(), p.translation(), f.pose.covariance)
        frames.append(FrameMeasurement(n - 1 + f.index, (n - 1 + f.index) / 30, pose, None))
    return frames


def test_a_long_sequence_is_fitted_over_its_whole_length(monkeypatch):
    # A fast start and a slow end, each longer than MAX_POSES: the fit reads stretches
    # spread over both, so its density lies between the halves' own (the latest poses
    # alone gave the slow end's, and a smoother too confident on the fast start).
    monkeypatch.setattr(noise_estimation, "MAX_POSES", 300)
    frames = two_regime_sequence(fast=1.0, slow=1e-3, n=400)
    assert np.all(np.diff([f.t for f in frames]) > 0)
    whole = estimate_process_noise(frames, default=(1.0, 1.0))
    fast = estimate_process_noise(frames[:400], default=(1.0, 1.0))
    slow = estimate_process_noise(frames[400:], default=(1.0, 1.0))
    q_fast, q_slow, q_whole = (e.acceleration_sigma[1] ** 2 for e in (fast, slow, whole))
    assert q_fast > 100 * q_slow  # the halves are told apart
    assert whole.poses == 300
    assert 10 * q_slow < q_whole < q_fast
