"""How far the smoothed states are from the truth: the covariance of the errors.

A Bayesian marginal (the inverse information) is the error covariance only
when the motion really is the model's white-noise acceleration. Real motions
(and the simulated ones) are smooth: the marginal then counts a random twist
wander the motion never makes, and was 2-5x too large for the twist. Instead,
at the estimate x^ the Gauss-Newton step is linear in the measurement errors
eta, x^ - x = P A^T W eta with P = Lambda^-1, so over the measurement noise

    Cov(x^ - x) = P A^T W Cov(eta) W A P
                = P M P                       (each frame's own pixels, independent)
                + (P Y)(P Y)^T                (the reference frame's pixels, shared)

with M the information of the measurement factors and Y = A^T W d eta / d rho
the response to the reference pixel noise rho (unit variance). What the
motion model leaves out (a smoothed twist lags a fast change; along a weakly
measured pose direction, such as the tilt-shift ambiguity of a plane seen
head-on, the pose follows the model more than the data) is added from the
data: the step d = Lambda_hi^-1 A^T W r (1 - 1/c) towards a c-times weaker
motion model, whose square, averaged over a short window, estimates the
squared bias of pose and twist where it exceeds (a margin times) the noise the
step carries, direction by direction in that noise's own metric.
The anchor (below) is an extrapolation of the motion model to the first
frame: its error gets the model's own spread, P - P M P, as well.

The smoother's graph is a chain: per frame the 12-vector [pose tangent; twist],
motion factors between consecutive frames, measurement factors on one frame
(or two consecutive ones). Lambda is block tridiagonal and every quantity
comes from O(K) block recursions (Rybicki-Hummer / Thomas), never the dense
inverse; :func:`dense_error_covariances` is the same computation with dense
matrices, for tests.

With the smoother's anchor (the first pose is estimated, and every pose is
reported relative to it: X_k = Y_0^-1 Y_k), the reported error is
r_k = dY_k - Ad(Y_k^-1 Y_0) dY_0, and its covariance needs the cross terms
with frame 0 (also recursions).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

#: Per frame: pose tangent (6) and twist (6).
STATE = 12

#: The motion model the bias is measured against is this many times weaker.
BIAS_MODEL_SCALE: float = 100.0


#: A bias counts only beyond this many times the probe's own noise (in the noise's
#: metric): the squared probe averaged over a window still scatters, and keeping every
#: positive excess made the covariance 20-35 % too large where the model has no bias.
#: At 1.5 the scatter still counted: over the ten scenario families (10 seeds, ISAM2)
#: the twist NEES per dof averaged 0.87 with the white-noise-acceleration model and 0.78
#: with motion_model "auto" (0.62-0.67 on three families, 0.8-1.3 there without the bias
#: term); at 2.0 it is 1.02 and 0.90, every family within 0.73-1.37, pose NEES +0.03.
BIAS_NOISE_MARGIN: float = 2.0

#: Half-width of the window the squared bias is averaged over, seconds.
BIAS_WINDOW_SECONDS: float = 0.5

#: The shared noise sources are solved for a slice at a time, each (K, n, width) array
#: about this many bytes (at least :data:`SHARED_CHUNK_MIN` sources): with one source
#: pair per keyframe point, all at once took 2.6 GB for a 2-minute traverse.
SHARED_CHUNK_BYTES: int = 32 * 2**20
SHARED_CHUNK_MIN: int = 32


@dataclass(frozen=True)
class SharedResponse:
    """Y = A^T W d eta / d rho stored by frame: a keyframe's points reach only the frames
    measured against it, so the dense (K, n, m) array is mostly zeros.

    Attributes:
        frames, size, sources: K, n and m of the dense array.
        entries: (frame, row offset, source columns (c,), block (rows, c)) each.
    """

    frames: int
    size: int
    sources: int
    entries: list[tuple[int, int, np.ndarray, np.ndarray]]

    def dense(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(K, n, stop - start): the sources ``start:stop`` of the dense array."""
        stop = self.sources if stop is None else stop
        out = np.zeros((self.frames, self.size, max(stop - start, 0)))
        for n, offset, columns, block in self.entries:
            inside = (columns >= start) & (columns < stop)
            if inside.any():
                rows = out[n, offset : offset + block.shape[0]]
                rows[:, columns[inside] - start] += block[:, inside]
        return out

    def chunks(self, width: int) -> Iterator[np.ndarray]:
        """The dense array, ``width`` sources at a time."""
        if not self.entries:
            return
        low = np.array([c.min() for _, _, c, _ in self.entries])
        high = np.array([c.max() for _, _, c, _ in self.entries])
        for start in range(0, self.sources, width):
            stop = min(start + width, self.sources)
            reach = np.flatnonzero((low < stop) & (high >= start))
            part = SharedResponse(
                self.frames, self.size, self.sources, [self.entries[i] for i in reach]
            )
            yield part.dense(start, stop)


def _shared_chunks(shared: np.ndarray | SharedResponse) -> Iterator[np.ndarray]:
    """(K, n, width) slices of the shared response, within :data:`SHARED_CHUNK_BYTES`."""
    K, n = shared.shape[:2] if isinstance(shared, np.ndarray) else (shared.frames, shared.size)
    width = max(SHARED_CHUNK_MIN, SHARED_CHUNK_BYTES // (8 * max(K * n, 1)))
    if isinstance(shared, SharedResponse):
        yield from shared.chunks(width)
        return
    for start in range(0, shared.shape[2], width):
        yield shared[:, :, start : start + width]


def _dense_shared(shared: np.ndarray | SharedResponse) -> np.ndarray:
    return shared if isinstance(shared, np.ndarray) else shared.dense()


@dataclass(frozen=True)
class ChainSystem:
    """The smoother's linearized system at its estimate, split by where it comes from.

    K frames, each state [pose tangent (6); twist (6)], right perturbation.

    Attributes:
        motion_diagonal: (K, 12, 12) information of the motion factors on each frame.
        motion_upper: (K-1, 12, 12) their block between frames k and k+1.
        fixed: (K, 12, 12) information of priors whose error is not random (the
            world anchor, the weak first-twist prior).
        measurement: (K, 12, 12) information of the measurement factors (each
            frame's own noise) on each frame.
        measurement_upper: (K-1, 12, 12) their blocks between frames k and k+1 (twist
            factors across a frame interval; in Lambda, left out of the noise: the
            few such factors are treated as if their frames' noise were separate).
        shared: (K, 12, m) A^T W d eta / d rho: how the measurement factors pull
            each frame's state per unit of the m shared noise sources rho (an array,
            or the same stored by frame, :class:`SharedResponse`).
        gradient: (K, 12) A^T W r of the measurement factors at the estimate.
        times: (K,) frame times (seconds).
    """

    motion_diagonal: np.ndarray
    motion_upper: np.ndarray
    fixed: np.ndarray
    measurement: np.ndarray
    measurement_upper: np.ndarray
    shared: np.ndarray | SharedResponse
    gradient: np.ndarray
    times: np.ndarray

    def information(self, motion_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(diagonal, upper) blocks of Lambda, the motion model's information scaled."""
        diagonal = self.fixed + self.measurement + motion_scale * self.motion_diagonal
        return diagonal, self.measurement_upper + motion_scale * self.motion_upper


def _symmetric(c: np.ndarray) -> np.ndarray:
    return 0.5 * (c + np.swapaxes(c, -1, -2))


@dataclass(frozen=True)
class _Chain:
    """Recursions of a block-tridiagonal Lambda: P_kk, and P_kj = A_k P_k+1,j (j > k),
    P_kj = B_k P_k-1,j (j < k)."""

    P: np.ndarray  # (K, n, n) diagonal blocks of Lambda^-1
    A: np.ndarray  # (K-1, n, n)
    B: np.ndarray  # (K, n, n); B[0] unused
    forward: np.ndarray  # (K, n, n) forward Schur complements


def _chain(diagonal: np.ndarray, upper: np.ndarray) -> _Chain:
    K, n = len(diagonal), diagonal.shape[1]
    forward = np.empty_like(diagonal)
    backward = np.empty_like(diagonal)
    forward[0] = diagonal[0]
    for k in range(1, K):
        forward[k] = diagonal[k] - upper[k - 1].T @ np.linalg.solve(forward[k - 1], upper[k - 1])
    backward[K - 1] = diagonal[K - 1]
    for k in range(K - 2, -1, -1):
        backward[k] = diagonal[k] - upper[k] @ np.linalg.solve(backward[k + 1], upper[k].T)
    P = _symmetric(np.linalg.inv(forward + backward - diagonal))
    A = -np.linalg.solve(forward[:-1], upper) if K > 1 else np.empty((0, n, n))
    B = np.zeros_like(diagonal)
    if K > 1:
        B[1:] = -np.linalg.solve(backward[1:], np.swapaxes(upper, 1, 2))
    return _Chain(P, A, B, forward)


def _solve(chain: _Chain, upper: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Lambda^-1 rhs for rhs (K, n, m) (block Thomas with the forward complements)."""
    K = len(rhs)
    y = np.empty_like(rhs)
    y[0] = rhs[0]
    for k in range(1, K):
        y[k] = rhs[k] - upper[k - 1].T @ np.linalg.solve(chain.forward[k - 1], y[k - 1])
    x = np.empty_like(rhs)
    x[K - 1] = np.linalg.solve(chain.forward[K - 1], y[K - 1])
    for k in range(K - 2, -1, -1):
        x[k] = np.linalg.solve(chain.forward[k], y[k] - upper[k] @ x[k + 1])
    return x


def _noise_induced(chain: _Chain, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks N_kk of P M P (M block diagonal) and the cross blocks N_0k."""
    N, N0 = _cross_noise(chain, chain, M)
    return _symmetric(N), N0


def _cross_noise(a: _Chain, b: _Chain, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks and first-row blocks (0, k) of P_a M P_b (two chains with the
    same sparsity, M block diagonal)."""
    K = len(M)
    Q = a.P @ M @ b.P
    after = np.empty_like(Q)  # sum over j >= k of (P_a)_kj M_j (P_b)_jk
    after[K - 1] = Q[K - 1]
    for k in range(K - 2, -1, -1):
        after[k] = Q[k] + a.A[k] @ after[k + 1] @ b.A[k].T
    before = np.empty_like(Q)  # sum over j <= k
    before[0] = Q[0]
    for k in range(1, K):
        before[k] = Q[k] + a.B[k] @ before[k - 1] @ b.B[k].T
    # (P_a M P_b)_0k = sum_j (P_a)_0j M_j (P_b)_jk with (P_a)_0j = G_j (P_a)_jj,
    # G_j = A^a_0 ... A^a_j-1.
    G = np.empty_like(Q)
    G[0] = np.eye(Q.shape[1])
    for k in range(1, K):
        G[k] = G[k - 1] @ a.A[k - 1]
    PM = a.P @ M
    reach = np.empty_like(Q)  # sum over j <= k of G_j (P_a)_jj M_j A^b_j ... A^b_k-1
    reach[0] = PM[0]
    for k in range(1, K):
        reach[k] = reach[k - 1] @ b.A[k - 1] + G[k] @ PM[k]
    beyond = np.zeros_like(Q)  # sum over j > k of G_j Q_j (A^b_k ... A^b_j-1)^T
    for k in range(K - 2, -1, -1):
        beyond[k] = (G[k + 1] @ Q[k + 1] + beyond[k + 1]) @ b.A[k].T
    return after + before - Q, reach @ b.P + beyond


def _outer(s: np.ndarray) -> np.ndarray:
    """(K, n, n): s_k s_k^T of (K, n, m)."""
    return s @ np.swapaxes(s, 1, 2)


def _anchored(s: np.ndarray, adjoint: np.ndarray | None) -> np.ndarray:
    """Responses (K, n, m) of the poses relative to frame 0's: s_k - Ad_k s_0 (pose rows)."""
    if adjoint is None:
        return s
    out = s.copy()
    out[:, :6] -= adjoint @ s[0, :6]
    return out


def _relative(N: np.ndarray, N0: np.ndarray, adjoint: np.ndarray | None) -> np.ndarray:
    """Covariance of [dY_k - Ad_k dY_0 (pose); dV_k] from Cov(d_k), Cov(d_0, d_k)."""
    if adjoint is None:
        return N
    T = np.zeros_like(N)  # d_rel = d_k - T_k d_0
    T[:, :6, :6] = adjoint
    cross = T @ N0  # Cov(T d_0, d_k)
    out = N - cross - np.swapaxes(cross, 1, 2) + T @ N[0] @ np.swapaxes(T, 1, 2)
    return _symmetric(out)


def _bridged(spread: np.ndarray, system: ChainSystem) -> np.ndarray:
    """The model's extra spread on frames without a pose measurement (a gap the motion
    model bridges): P - P M P there beyond its value at the nearest measured frames.

    Where poses come every frame, a smooth motion does not realise the model's spread
    (the bias probe measures what it does); across a gap the estimate is the model's
    interpolation, and its error is the model's."""
    measured = np.trace(system.measurement[:, :6, :6], axis1=1, axis2=2) > 0
    extra = np.zeros_like(spread)
    if measured.all() or not measured.any():
        return extra
    t, where = system.times, np.flatnonzero(measured)
    for k in np.flatnonzero(~measured):
        i = np.searchsorted(t[where], t[k])
        near = [where[j] for j in (i - 1, i) if 0 <= j < len(where)]
        reference = np.mean([spread[j] for j in near], axis=0)
        extra[k] = _psd_part((spread[k] - reference)[None])[0]
    return extra


def _window_mean(values: np.ndarray, times: np.ndarray, half_width: float) -> np.ndarray:
    """Mean of values (K, ...) over the frames within +-half_width seconds of each frame."""
    flat = values.reshape(len(values), -1)
    cumulative = np.vstack((np.zeros((1, flat.shape[1])), np.cumsum(flat, axis=0)))
    lo = np.searchsorted(times, times - half_width, side="left")
    hi = np.searchsorted(times, times + half_width, side="right")
    mean = (cumulative[hi] - cumulative[lo]) / (hi - lo)[:, None]
    return mean.reshape(values.shape)


def _excess(square: np.ndarray, noise: np.ndarray, margin: float) -> np.ndarray:
    """L (S - margin I)_+ L^T with noise = L L^T, S = L^-1 square L^-T: the part of
    ``square`` beyond ``margin`` times ``noise``, direction by direction in the noise's
    own metric (units of rotation and translation do not mix)."""
    n = noise.shape[-1]
    diagonal = np.diagonal(noise, axis1=1, axis2=2)
    # A floor relative to each frame's largest variance: a direction with (numerically)
    # no noise, e.g. a reference pose's -1e-20, would otherwise scale its row by 1e150.
    floor = 1e-12 * diagonal.max(axis=1, keepdims=True) + 1e-300
    scale = np.sqrt(np.maximum(diagonal, floor))
    D = scale[:, :, None] * scale[:, None, :]
    w, v = np.linalg.eigh(_symmetric(noise / D) + 1e-9 * np.eye(n))
    root = v * np.sqrt(np.clip(w, 1e-12, None))[:, None, :] * scale[:, :, None]  # L = D^1/2 V W^1/2
    inv = np.linalg.pinv(root)
    S = _symmetric(inv @ square @ np.swapaxes(inv, 1, 2))
    e, u = np.linalg.eigh(S)
    excess = np.einsum("kij,kj,klj->kil", u, np.clip(e - margin, 0.0, None), u)
    return _symmetric(root @ excess @ np.swapaxes(root, 1, 2))


def _psd_part(c: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(_symmetric(c))
    return np.einsum("kij,kj,klj->kil", v, np.clip(w, 0.0, None), v)


def error_covariances(
    system: ChainSystem,
    *,
    anchor_adjoint: np.ndarray | None = None,
    bias_scale: float | None = BIAS_MODEL_SCALE,
    bias_window: float = BIAS_WINDOW_SECONDS,
    bias_states: int | None = None,
) -> np.ndarray:
    """(K, n, n) covariance of each frame's error [pose tangent; twist (; twist rate)]
    (module docstring).

    Args:
        system: the linearized chain.
        anchor_adjoint: (K, 6, 6) Ad(Y_k^-1 Y_0) when poses are reported relative to
            frame 0's (X_k = Y_0^-1 Y_k); None: as estimated.
        bias_scale: c, how much weaker the motion model of the bias probe is; None:
            no bias term (the noise-induced covariance alone).
        bias_window: half-width (s) of the window the squared bias is averaged over.
        bias_states: the leading entries of each frame's state the bias is measured on
            (None: all). A keyframe copy is its keyframe's pose: next to the frame's
            own pose it adds a direction of tiny noise (their well-measured relative
            pose), where rounding in the probe became a bias up to 3x the twist's
            variance.
    """
    diagonal, upper = system.information()
    chain = _chain(diagonal, upper)
    N, N0 = _noise_induced(chain, system.measurement)
    covariance = _relative(N, N0, anchor_adjoint).copy()  # N itself is used below
    if bias_scale is not None:
        diagonal_hi, upper_hi = system.information(1.0 / bias_scale)
        chain_hi = _chain(diagonal_hi, upper_hi)
    shared_step_noise = np.zeros_like(covariance)  # the shared pixels' share of the probe
    for Y in _shared_chunks(system.shared):
        raw = _solve(chain, upper, Y)  # (K, n, width)
        covariance += _outer(_anchored(raw, anchor_adjoint))
        if bias_scale is not None:
            step = _solve(chain_hi, upper_hi, Y) - raw
            shared_step_noise += _outer(_anchored(step, anchor_adjoint))
    if anchor_adjoint is not None:
        # The anchor Y_0 is where the motion model extrapolates the first poses to: its
        # error is also the model's, the prior-induced spread P - P M P of the marginal.
        spread = (chain.P[0] - N[0])[:6, :6]
        covariance[:, :6, :6] += anchor_adjoint @ spread @ np.swapaxes(anchor_adjoint, 1, 2)
    covariance += _bridged(chain.P - N, system)
    if bias_scale is None:
        return _symmetric(covariance)

    # The bias probe: the step d to a c-times weaker motion model, less its noise.
    # Own pixels: Cov = (P_hi - P) M (P_hi - P) = N_hi + N - X - X^T, X = P_hi M P;
    # shared pixels: (P_hi - P) Y. The pose counts too: along a weakly measured
    # direction the motion model's bias reaches the pose (it was 40-75 % of the
    # smoothed pose's mean squared error along the tilt-shift ambiguity of a
    # paper-like sequence, over 120 noise draws).
    step = _solve(chain_hi, upper_hi, (1.0 - 1.0 / bias_scale) * system.gradient[..., None])[..., 0]
    if anchor_adjoint is not None:
        step[:, :6] -= anchor_adjoint @ step[0, :6]
    N_hi, N0_hi = _noise_induced(chain_hi, system.measurement)
    X, X0 = _cross_noise(chain_hi, chain, system.measurement)
    _, X0_t = _cross_noise(chain, chain_hi, system.measurement)
    noise = (
        _relative(N_hi + N - X - np.swapaxes(X, 1, 2), N0_hi + N0 - X0 - X0_t, anchor_adjoint)
        + shared_step_noise
    )
    b = slice(0, bias_states)
    step, noise = step[:, b], noise[:, b, b]
    square = _window_mean(np.einsum("ki,kj->kij", step, step), system.times, bias_window)
    excess = _excess(square, noise, BIAS_NOISE_MARGIN)
    if anchor_adjoint is not None:
        # Frame 0's pose is its own reference: no error for a bias to add to, and its
        # noise there is zero up to rounding, which _excess would amplify into the
        # twist too (a 1e-11 change of the estimate moved its twist variance 1e10-fold).
        excess[0] = 0.0
        excess[0, 6:, 6:] = _excess(square[:1, 6:, 6:], noise[:1, 6:, 6:], BIAS_NOISE_MARGIN)[0]
    covariance[:, b, b] += excess
    return _symmetric(covariance)


def marginal_covariances(system: ChainSystem) -> np.ndarray:
    """(K, n, n) Bayesian marginal of each frame's state: P + (P Y)(P Y)^T, the chain's
    inverse information and the spread its shared noise sources add (the law of total
    covariance: exact when the sources are variables the chain was conditioned on, with
    their marginal covariance, as the tight graph's landmarks)."""
    diagonal, upper = system.information()
    chain = _chain(diagonal, upper)
    covariance = chain.P.copy()
    for Y in _shared_chunks(system.shared):
        covariance += _outer(_solve(chain, upper, Y))
    return _symmetric(covariance)


def dense_error_covariances(
    system: ChainSystem, *, anchor_adjoint: np.ndarray | None = None
) -> np.ndarray:
    """:func:`error_covariances` without the bias term, with dense matrices: O(K^3),
    a reference for tests."""
    K, size = system.fixed.shape[:2]
    n = K * size
    diagonal, upper = system.information()
    Lam = np.zeros((n, n))
    M = np.zeros((n, n))
    for k in range(K):
        s = slice(k * size, (k + 1) * size)
        Lam[s, s] = diagonal[k]
        M[s, s] = system.measurement[k]
        if k + 1 < K:
            t = slice((k + 1) * size, (k + 2) * size)
            Lam[s, t] = upper[k]
            Lam[t, s] = upper[k].T
    P = np.linalg.inv(Lam)
    Y = _dense_shared(system.shared).reshape(n, -1)
    T = np.eye(n)
    if anchor_adjoint is not None:
        for k in range(K):
            T[k * size : k * size + 6, :6] -= anchor_adjoint[k]
    TP = T @ P
    C = TP @ M @ TP.T + (TP @ Y) @ (TP @ Y).T
    out = np.array([C[k * size : (k + 1) * size, k * size : (k + 1) * size] for k in range(K)])
    model = P - P @ M @ P
    if anchor_adjoint is not None:
        spread = model[:6, :6]
        out[:, :6, :6] += anchor_adjoint @ spread @ np.swapaxes(anchor_adjoint, 1, 2)
    blocks = np.array(
        [model[k * size : (k + 1) * size, k * size : (k + 1) * size] for k in range(K)]
    )
    return out + _bridged(blocks, system)
