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
