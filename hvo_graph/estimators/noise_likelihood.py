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
    """The S x M filters' start (stretch-major): per-axis densities q (S M, 6) = [q_w x3,
    q_v x3], the state x (S M, n) at each stretch's first pose s[:, 0] (S, 6), and P
    (S M, n, n): C[:, 0] on the pose, a broad 1e4 on the rest (twist, twist rate)."""
    stretches, m = len(s), len(q_w)
    q = np.concatenate((np.repeat(q_w[:, None], 3, 1), np.repeat(q_v[:, None], 3, 1)), axis=1)
    x = np.zeros((stretches * m, n))
    x[:, :6] = np.repeat(s[:, 0], m, axis=0)
    P = np.zeros((stretches * m, n, n))
    P[:, :6, :6] = np.repeat(C[:, 0], m, axis=0)
    P[:, 6:, 6:] = 1e4 * np.eye(n - 6)
    return np.tile(q, (stretches, 1)), x, P


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
        t: (K,) times; s: (K, 6) unrolled poses; C: (K, 6, 6) their covariances. Or S
            stretches of K poses each, filtered side by side: (S, K), (S, K, 6) and
            (S, K, 6, 6).
        q_w, q_v: (M,) spectral densities to evaluate.
        gate: an innovation whose squared Mahalanobis norm exceeds this is an
            outlier: it costs the gate (a bounded, Huber-like penalty) and does
            not update the state, so one bad pose cannot drive Q up.
    Returns:
        (M,) log-likelihoods of s_1..K given s_0 ((S, M) for stretches: each given its
        own first pose); each pair's filter runs alone (its value does not depend on
        the other pairs or stretches).
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
    starts with a broad prior too (100 rad/s^2, m/s^2). Stretches as :func:`log_likelihood`.
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
    numpy calls per step, not arithmetic. Hence the layout: the S stretches' pairs are
    the last (contiguous) axis of every array (stretch-major: S M filters in lockstep,
    each step's dt and pose per stretch), X = [P | x] (n, n + 1, S M) holds covariance
    and state together, and each step is ~40 calls over all of them:

    - predict: F [P | x] (block rows), then (F P) F^T (block columns), then Q_k
      onto the diagonals of P's 6x6 blocks (Q_k = unit(dt) (x) diag(q));
    - update (H = [I 0]): G = [S | E] with S = P_ss + C_k and E = [P_s. | x_s - z_k]
      (6, n + 7, S M); six pivots of Cholesky elimination on G's rows give L (S = L
      L^T) on the diagonal and W = L^-1 E in E's place, then [P | x] -= W_P^T W
      (one stacked matmul: the gain update P - P_s.^T S^-1 P_s. and x + K y at
      once), d^2 = |L^-1 y|^2 and log det S = 2 sum log diag L.
    """
    single = t.ndim == 1
    if single:
        t, s, C = t[None], s[None], C[None]
    stretches, pairs = len(t), len(q_w)
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
    pivot_rows = np.empty((5, n + 6, m))  # the elimination's outer products
    W = np.empty((m, 6, n + 1))  # L^-1 E, pairs first for the stacked matmul
    update = np.empty((m, n, n + 1))
    # Per stretch (the last axes S, 1 broadcast over its pairs in the views X_s, G_s).
    X_s, G_s = X.reshape(n, n + 1, stretches, pairs), G.reshape(6, n + 7, stretches, pairs)
    covariances = np.ascontiguousarray(C.transpose(1, 2, 3, 0))[..., None]  # (K, 6, 6, S, 1)
    measured = np.ascontiguousarray(s.transpose(1, 2, 0))[..., None]  # (K, 6, S, 1)
    steps = np.diff(t, axis=1).T  # (K - 1, S)
    uniform = (steps == steps[:, :1]).all(axis=1)  # every stretch steps by the same dt
    noise_steps: dict[object, np.ndarray] = {}
    ll = np.zeros(m)
    block_L = np.empty((_BLOCK, 6, m))
    block_d2 = np.empty((_BLOCK, m))
    for k in range(1, t.shape[1]):
        # One dt for every filter, else each stretch's own, broadcast over its pairs.
        dt = float(steps[k - 1, 0]) if uniform[k - 1] else np.repeat(steps[k - 1], pairs)
        key = dt if uniform[k - 1] else steps[k - 1].tobytes()
        Q = noise_steps.get(key)
        if Q is None:
            if len(noise_steps) > 64:  # irregular frame times: keep the cache small
                noise_steps.clear()
            unit = _unit_noise(dt, order)  # (order, order[, M])
            unit = unit[:, :, None, None] if unit.ndim == 2 else unit[:, :, None]
            Q = noise_steps[key] = unit * q.T[None, None]
        _predict(X, dt, order)
        diagonals += Q
        np.add(X_s[:6, :6], covariances[k], out=G_s[:, :6])
        G[:, 6:] = X[:6]
        G_s[:, -1] -= measured[k]
        i = (k - 1) % _BLOCK
        L = block_L[i]
        with np.errstate(invalid="ignore"):  # S indefinite by rounding: that pair's NaN
            for j in range(6):
                np.sqrt(G[j, j], out=L[j])
                G[j, j:] /= L[j]
                if j < 5:  # (into a kept buffer: a fresh one per pivot cost twice as much)
                    outer = pivot_rows[: 5 - j, : n + 6 - j]
                    np.multiply(G[j, j + 1 : 6, None], G[j, None, j + 1 :], out=outer)
                    G[j + 1 :, j + 1 :] -= outer
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
        if i == _BLOCK - 1 or k == t.shape[1] - 1:
            ll += _log_densities(block_L[: i + 1], block_d2[: i + 1], gate)
    return ll if single else ll.reshape(stretches, pairs)


def _predict(X: np.ndarray, dt: float | np.ndarray, order: int) -> None:
    """[P | x] <- F [P | x], then P <- P F^T, in place (F: the model's transition; dt a
    number, or (M,) one per filter)."""
    n = 6 * order
    if order == 2:
        X[:6] += dt * X[6:]
        X[:, :6] += dt * X[:, 6:12]
        return
    X[:6] += dt * X[6:12] + (0.5 * dt * dt) * X[12:]
    X[6:12] += dt * X[12:]
    X[:, :6] += dt * X[:, 6:12] + (0.5 * dt * dt) * X[:, 12:n]
    X[:, 6:12] += dt * X[:, 12:n]


def _unit_noise(dt: float | np.ndarray, order: int) -> np.ndarray:
    """The (order, order) discrete noise of unit spectral density over dt ((order, order,
    M) for M steps dt: the per-filter axis of Q)."""
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
