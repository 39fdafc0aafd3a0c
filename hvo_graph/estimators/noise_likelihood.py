"""The marginal likelihood of the unrolled pose sequence under a motion model.

p(s_1..K | q) for the white-noise acceleration (order 2) and white-noise jerk (order 3)
models, computed by a Kalman filter over s_k = s(t_k) + e_k (e_k: frame k's own pixel
noise) for many density pairs q at once; :mod:`.noise_estimation` maximises it.
"""

from __future__ import annotations

import numpy as np


def _initial_state(
    s: np.ndarray, C: np.ndarray, q_w: np.ndarray, q_v: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The M filters' start: per-axis densities q (M, 6) = [q_w x3, q_v x3], the state
    x (M, n) at the first pose s_0, and P (M, n, n): C_0 on the pose, a broad 1e4 on
    the rest (twist, twist rate)."""
    m = len(q_w)
    q = np.concatenate((np.repeat(q_w[:, None], 3, 1), np.repeat(q_v[:, None], 3, 1)), axis=1)
    x = np.zeros((m, n))
    x[:, :6] = s[0]
    P = np.zeros((m, n, n))
    P[:, :6, :6] = C[0]
    P[:, 6:, 6:] = 1e4 * np.eye(n - 6)
    return q, x, P


def log_likelihood(
    t: np.ndarray,
    s: np.ndarray,
    C: np.ndarray,
    q_w: np.ndarray,
    q_v: np.ndarray,
    gate: float = np.inf,
) -> np.ndarray:
    """log p(s_1..K | q_w, q_v) of the 12-state WNA model, for M pairs at once.

    State [s (6); V (6)]: s' = s + dt V, V' = V + w, with the exact WNA
    discretisation Q_k = Q [[dt^3/3, dt^2/2], [dt^2/2, dt]]. The first pose
    initialises s (covariance C_0) and a broad prior (100 rad/s, m/s) the twist.

    Args:
        t: (K,) times; s: (K, 6) unrolled poses; C: (K, 6, 6) their covariances.
        q_w, q_v: (M,) spectral densities to evaluate.
        gate: an innovation whose squared Mahalanobis norm exceeds this is an
            outlier: it costs the gate (a bounded, Huber-like penalty) and does
            not update the state, so one bad pose cannot drive Q up.
    Returns:
        (M,) log-likelihoods of s_1..K given s_0; each pair's filter runs alone
        (the other pairs change its value by rounding at most).
    """
    return _kalman_log_likelihood(t, s, C, q_w, q_v, gate, order=2)


def jerk_log_likelihood(
    t: np.ndarray,
    s: np.ndarray,
    C: np.ndarray,
    q_w: np.ndarray,
    q_v: np.ndarray,
    gate: float = np.inf,
) -> np.ndarray:
    """log p(s_1..K | q_w, q_v) of the 18-state white-noise-jerk model, M pairs at once.

    State [s (6); V (6); A (6)]: s' = s + dt V + dt^2/2 A, V' = V + dt A, A' = A + w,
    with the exact discretisation Q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3,
    dt^2/2], [dt^3/6, dt^2/2, dt]] (q_w, q_v now jerk densities, rad^2 s^-5 and
    m^2 s^-5). Priors, gate and return as :func:`log_likelihood`; the twist rate
    starts with a broad prior too (100 rad/s^2, m/s^2).
    """
    return _kalman_log_likelihood(t, s, C, q_w, q_v, gate, order=3)


#: Steps whose innovation terms are summed at once (bounds the filter's buffers).
_BLOCK: int = 256


def _kalman_log_likelihood(
    t: np.ndarray,
    s: np.ndarray,
    C: np.ndarray,
    q_w: np.ndarray,
    q_v: np.ndarray,
    gate: float,
    order: int,
) -> np.ndarray:
    """The Kalman filter of :func:`log_likelihood` (order 2) and
    :func:`jerk_log_likelihood` (order 3), n = 6 order states, M pairs in lockstep.

    M is small (~50-150) and the filter runs K steps, so the cost is the number of
    numpy calls per step, not arithmetic. Hence the layout: the pairs are the last
    (contiguous) axis of every array, X = [P | x] (n, n + 1, M) holds covariance
    and state together, and each step is ~40 calls over all pairs:

    - predict: F [P | x] (block rows), then (F P) F^T (block columns), then Q_k
      onto the diagonals of P's 6x6 blocks (Q_k = unit(dt) (x) diag(q));
    - update (H = [I 0]): G = [S | E] with S = P_ss + C_k and E = [P_s. | x_s - z_k]
      (6, n + 7, M); six pivots of Cholesky elimination on G's rows give L (S = L
      L^T) on the diagonal and W = L^-1 E in E's place, then [P | x] -= W_P^T W
      (one stacked matmul: the gain update P - P_s.^T S^-1 P_s. and x + K y at
      once), d^2 = |L^-1 y|^2 and log det S = 2 sum log diag L.
    """
    q, x, P = _initial_state(s, C, q_w, q_v, 6 * order)
    n, m = 6 * order, len(q)
    X = np.empty((n, n + 1, m))
    X[:, :n] = P.transpose(1, 2, 0)
    X[:, n] = x.T
    step = X.strides
    # Flat views of the rows of X (i, j) -> i (n + 1) + j: P's upper and lower triangles.
    flat = X.reshape(n * (n + 1), m)
    rows, cols = np.triu_indices(n, 1)  # (i, j) with i < j
    upper, lower = rows * (n + 1) + cols, cols * (n + 1) + rows
    # The diagonals of P's (order x order) 6x6 blocks, where Q_k goes: (order, order, 6, M).
    diagonals = np.lib.stride_tricks.as_strided(
        X,
        shape=(order, order, 6, m),
        strides=(6 * step[0], 6 * step[1], step[0] + step[1], step[2]),
    )
    G = np.empty((6, n + 7, m))
    W = np.empty((m, 6, n + 1))  # L^-1 E, pairs first for the stacked matmul
    update = np.empty((m, n, n + 1))
    covariances = np.ascontiguousarray(C)[:, :, :, None]
    measured = s[:, :, None]
    noise_steps: dict[float, np.ndarray] = {}
    ll = np.zeros(m)
    block_L = np.empty((_BLOCK, 6, m))
    block_d2 = np.empty((_BLOCK, m))
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        Q = noise_steps.get(dt)
        if Q is None:
            if len(noise_steps) > 64:  # irregular frame times: keep the cache small
                noise_steps.clear()
            Q = noise_steps[dt] = _unit_noise(dt, order)[:, :, None, None] * q.T[None, None]
        _predict(X, dt, order)
        diagonals += Q
        np.add(X[:6, :6], covariances[k], out=G[:, :6])
        G[:, 6:] = X[:6]
        G[:, -1] -= measured[k]
        i = (k - 1) % _BLOCK
        L = block_L[i]
        with np.errstate(invalid="ignore"):  # S indefinite by rounding: that pair's NaN
            for j in range(6):
                np.sqrt(G[j, j], out=L[j])
                G[j, j:] /= L[j]
                if j < 5:
                    G[j + 1 :, j + 1 :] -= G[j, j + 1 : 6, None] * G[j, None, j + 1 :]
        W.transpose(1, 2, 0)[...] = G[:, 6:]
        d2 = np.einsum("mi,mi->m", W[:, :, n], W[:, :, n], out=block_d2[i])
        outliers = d2 > gate  # (a pair gone NaN is not one: the others are unaffected)
        if outliers.any():
            W[outliers] = 0.0  # an outlier pose neither updates the state nor inflates Q
        np.matmul(W[:, :, :n].transpose(0, 2, 1), W, out=update)
        X -= update.transpose(1, 2, 0)
        # kept symmetric: the predict's rounding leaves P asymmetric, and in the 18-state
        # model that asymmetry grows. The lower triangle takes the upper's values (one
        # gather and scatter; averaging the overlapping transpose cost 6x as much)
        flat[lower] = flat[upper]
        if i == _BLOCK - 1 or k == len(t) - 1:
            ll += _log_densities(block_L[: i + 1], block_d2[: i + 1], gate)
    return ll


def _predict(X: np.ndarray, dt: float, order: int) -> None:
    """[P | x] <- F [P | x], then P <- P F^T, in place (F: the model's transition)."""
    n = 6 * order
    if order == 2:
        X[:6] += dt * X[6:]
        X[:, :6] += dt * X[:, 6:12]
        return
    X[:6] += dt * X[6:12] + (0.5 * dt * dt) * X[12:]
    X[6:12] += dt * X[12:]
    X[:, :6] += dt * X[:, 6:12] + (0.5 * dt * dt) * X[:, 12:n]
    X[:, 6:12] += dt * X[:, 12:n]


def _unit_noise(dt: float, order: int) -> np.ndarray:
    """The (order, order) discrete noise of unit spectral density over dt."""
    if order == 2:
        return np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    return np.array(
        [
            [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
            [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
            [dt**3 / 6.0, dt**2 / 2.0, dt],
        ]
    )


def _log_densities(L: np.ndarray, d2: np.ndarray, gate: float) -> np.ndarray:
    """(M,) sum over steps of the innovations' log densities, from the diagonals of their
    Cholesky factors L (B, 6, M) and squared Mahalanobis norms d2 (B, M) (gated: beyond
    ``gate`` an innovation costs the gate)."""
    terms = np.minimum(d2, gate) + 2.0 * np.log(L).sum(axis=1) + 6.0 * np.log(2.0 * np.pi)
    return -0.5 * terms.sum(axis=0)
