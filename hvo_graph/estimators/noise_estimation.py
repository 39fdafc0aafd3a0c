"""The motion model's noise from the data: maximum likelihood on the pose measurements.

The smoother's motion model is white-noise acceleration (WNA): the body twist
V is a random walk, dV = sqrt(Q) dW, Q = diag(q_w I_3, q_v I_3), with q_w
(rad^2 s^-3) and q_v (m^2 s^-3) the spectral densities of the angular and
linear acceleration; ``acceleration_sigma`` = (sqrt(q_w), sqrt(q_v)).

A fixed Q only suits motions like the one it was tuned on. Here Q is chosen
per sequence to maximise the marginal likelihood p(z_1..K | Q) of the H_d pose
measurements, computed by a Kalman filter on the unrolled pose sequence:

    s_k = s_{k-1} + Log(Z_{k-1}^-1 Z_k),   s_k = s(t_k) + e_k,

where Z_k is the measured world pose (keyframe-relative poses composed with
their keyframe's measured pose) and e_k has the covariance of frame k's *own*
pixels (``covariance - reference_covariance``: the reference frame's noise is
one offset shared by all poses and does not inform Q). Over short intervals
the unrolled s(t) moves like the integral of the twist, so (s, V) is a 12-state
linear WNA model, and the likelihood is the product of the innovation
densities. A grid over (log q_w, log q_v), refined twice around its maximum,
finds the optimum in ~0.2 s for 300 frames (vectorised over the grid).

The densities are bounded below by :data:`MIN_SPECTRAL_DENSITY`: a sequence
with (nearly) no acceleration has its likelihood maximal at q -> 0, where
the smoother would trust the motion model without limit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.process_noise import DEFAULT_JERK_SIGMA, acceleration_sigma
from hvo_graph.types import FrameMeasurement

#: Lower bound of q_w and q_v (rad^2 s^-3, m^2 s^-3): a random-walk twist change of
#: 1 cm/s (10 mrad/s) per second. Below it the likelihood of a near-static sequence
#: is flat, the smoother would trust the motion model without limit, and ISAM2's
#: Cholesky factorization of the near-singular system fails.
MIN_SPECTRAL_DENSITY: float = 1e-4

#: Upper bound of the search (an acceleration of ~100 m/s^2 per frame interval).
MAX_SPECTRAL_DENSITY: float = 1e4

#: Innovation gate of the likelihood: the 99.9 % quantile of chi^2 with 6 dof.
OUTLIER_GATE: float = 22.457744484825323

#: The densities chosen are the upper ends of their 95 % likelihood intervals (a drop
#: of chi^2_1(0.95) / 2 = 1.92 in log-likelihood from the maximum), not the maximum
#: itself: where the poses hardly tell q (rotation absorbs slow translation, and
#: near-static sequences), the likelihood is flat at small q and its maximum can sit
#: far below the motion; a twist covariance from such a q was overconfident by 40x.
INTERVAL_DROP: float = 1.920729410347062

#: Step of the search for the interval's upper end, log10 units.
INTERVAL_STEP: float = 0.1

#: Fewest pose measurements for an estimate; shorter sequences keep the default.
MIN_POSES: int = 10

#: Most poses the likelihood is evaluated on (the latest ones); beyond, the estimate
#: changes little and the cost would grow with the sequence.
MAX_POSES: int = 3000


@dataclass(frozen=True)
class ProcessNoiseEstimate:
    """The maximum-likelihood white-noise-acceleration strengths of a sequence.

    Attributes:
        acceleration_sigma: (s_w, s_v) = (sqrt(q_w), sqrt(q_v)), rad s^-3/2 and m s^-3/2.
        log_likelihood: log p(z | Q) at the optimum (nats).
        poses: number of pose measurements used.
        model: the motion model fitted, "wna" or "wnj" (then the sigmas are the
            jerk's, rad s^-5/2 and m s^-5/2).
    """

    acceleration_sigma: tuple[float, float]
    log_likelihood: float
    poses: int
    model: str = "wna"


def unrolled_poses(
    frames: Sequence[FrameMeasurement],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measured pose sequence as times, unrolled tangent positions and noise.

    Returns:
        t: (K,) times of the frames with a pose measurement.
        s: (K, 6) s_k = sum_j Log(Z_{j-1}^-1 Z_j), tangent order [rot; trans].
        C: (K, 6, 6) covariance of frame k's own pixel noise.
    """
    world: dict[int, gtsam.Pose3] = {}
    times, unrolled, covariances = [], [], []
    s = np.zeros(6)
    previous: gtsam.Pose3 | None = None
    for frame in frames:
        pose = frame.pose
        if pose is None:
            continue
        Z = gtsam.Pose3(gtsam.Rot3(pose.rotation), np.asarray(pose.position, dtype=float))
        if pose.reference != 0:
            if pose.reference_rotation is not None and pose.reference_position is not None:
                base = gtsam.Pose3(gtsam.Rot3(pose.reference_rotation), pose.reference_position)
            elif pose.reference in world:
                base = world[pose.reference]
            else:
                continue
            Z = base.compose(Z)
        world[frame.index] = Z
        covariance = np.asarray(pose.covariance, dtype=float)
        if pose.reference_covariance is not None:
            covariance = covariance - np.asarray(pose.reference_covariance, dtype=float)
        if previous is not None:
            s = s + gtsam.Pose3.Logmap(previous.between(Z))
        previous = Z
        times.append(frame.t)
        unrolled.append(s.copy())
        covariances.append(covariance)
    if not times:
        return np.empty(0), np.empty((0, 6)), np.empty((0, 6, 6))
    return np.array(times), np.array(unrolled), np.array(covariances)


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
        (M,) log-likelihoods of s_1..K given s_0.
    """
    q, x, P = _initial_state(s, C, q_w, q_v, 12)
    Q = q[:, :, None] * np.eye(6)[None]
    ll = np.zeros(len(q_w))
    Pss, Psv, Pvs, Pvv = P[:, :6, :6], P[:, :6, 6:], P[:, 6:, :6], P[:, 6:, 6:]
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        # predict (F = [[I, dt I], [0, I]]), block by block in place (P stays symmetric)
        x[:, :6] += dt * x[:, 6:]
        Pss += dt * (Psv + Pvs) + dt * dt * Pvv + Q * (dt**3 / 3)
        Psv += dt * Pvv + Q * (dt**2 / 2)
        Pvs[...] = Psv.transpose(0, 2, 1)
        Pvv += Q * dt
        ll += _pose_update(x, P, s[k], C[k], gate)
    return ll


def _pose_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, gate: float
) -> np.ndarray:
    """Kalman update of M states (M, n) and covariances (M, n, n), in place, with the pose
    z (6,) of covariance R (6, 6) measuring the first six components (H = [I 0]); returns
    the (M,) log densities of the innovation (gated: beyond ``gate`` it costs the gate
    and does not update)."""
    # one Cholesky factor L of S; L^-1 by substitution
    S = P[:, :6, :6] + R[None]
    y = z[None] - x[:, :6]
    L = np.linalg.cholesky(S)
    L_inv = _lower_inverse(L)
    w = np.einsum("mij,mj->mi", L_inv, y)
    d2 = np.sum(w * w, axis=1)
    log_density = -0.5 * (
        np.minimum(d2, gate)
        + 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)
        + 6.0 * np.log(2.0 * np.pi)
    )
    # gain P H^T S^-1, S^-1 = L^-T L^-1 (M, n, 6)
    gain = (P[:, :, :6] @ np.transpose(L_inv, (0, 2, 1))) @ L_inv
    gain[d2 > gate] = 0.0  # an outlier pose neither updates the state nor inflates Q
    x += np.einsum("mij,mj->mi", gain, y)
    P -= gain @ P[:, :6, :]
    P += P.transpose(0, 2, 1).copy()
    P *= 0.5
    return log_density


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
    q, x, P = _initial_state(s, C, q_w, q_v, 18)
    ll = np.zeros(len(q_w))
    eye = np.eye(6)
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        F = np.kron(np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]]), eye)
        unit = np.array(
            [
                [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
                [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
                [dt**3 / 6.0, dt**2 / 2.0, dt],
            ]
        )
        x = x @ F.T
        P = F @ P @ F.T
        P += np.kron(unit, eye)[None] * np.tile(q, 3)[:, None, :]  # Q_k = unit (x) diag(q)
        ll += _pose_update(x, P, s[k], C[k], gate)
    return ll


def _lower_inverse(L: np.ndarray) -> np.ndarray:
    """(M, n, n) inverses of lower-triangular L (M, n, n) by forward substitution: n
    vectorised steps instead of M calls of LAPACK (M small systems per time step)."""
    n = L.shape[1]
    inv = np.zeros_like(L)
    diagonal = 1.0 / np.diagonal(L, axis1=1, axis2=2)  # (M, n)
    for i in range(n):
        row = -np.einsum("mj,mjk->mk", L[:, i, :i], inv[:, :i, :])  # zeros for i = 0
        row[:, i] = 1.0
        inv[:, i, :] = row * diagonal[:, i : i + 1]
    return inv


def estimate_process_noise(
    frames: Sequence[FrameMeasurement],
    *,
    default: tuple[float, float],
    grid: int = 10,
    refinements: int = 2,
    model: str = "wna",
) -> ProcessNoiseEstimate:
    """(s_w, s_v) of the motion model from the pose measurements: the maximum of the
    likelihood, then the upper end of each density's 95 % interval (:data:`INTERVAL_DROP`).

    Args:
        frames: the sequence's measurements (only the poses are used).
        default: (s_w, s_v) returned when fewer than :data:`MIN_POSES` poses exist.
        grid: points per axis of the first (log-spaced) grid.
        refinements: times the grid is refined (x3 finer) around the optimum.
        model: "wna" (:func:`log_likelihood`), "wnj" (:func:`jerk_log_likelihood`), or
            "auto": both, and the one with the larger maximised likelihood (both have
            two parameters, so the likelihoods compare directly).
    Returns:
        The estimate; ``poses`` = 0 and the default when there was too little data
        (``model`` then "wnj" for "auto").
    """
    t, s, C = unrolled_poses(frames)
    if len(t) < MIN_POSES:
        return ProcessNoiseEstimate(default, float("nan"), 0, "wnj" if model == "auto" else model)
    t, s, C = t[-MAX_POSES:], s[-MAX_POSES:], C[-MAX_POSES:]
    fits = [
        _fit(t, s, C, name, grid, refinements)
        for name in (("wna", "wnj") if model == "auto" else (model,))
    ]
    return max(fits, key=lambda fit: fit.log_likelihood)


_LIKELIHOODS = {"wna": "log_likelihood", "wnj": "jerk_log_likelihood"}


def _fit(
    t: np.ndarray, s: np.ndarray, C: np.ndarray, model: str, grid: int, refinements: int
) -> ProcessNoiseEstimate:
    likelihood = globals()[_LIKELIHOODS[model]]
    lo, hi = np.log10(MIN_SPECTRAL_DENSITY), np.log10(MAX_SPECTRAL_DENSITY)
    axis_w = axis_v = np.linspace(lo, hi, grid)
    step = axis_w[1] - axis_w[0]
    for _ in range(refinements + 1):
        A, B = np.meshgrid(axis_w, axis_v, indexing="ij")
        ll = likelihood(t, s, C, 10.0 ** A.ravel(), 10.0 ** B.ravel(), OUTLIER_GATE)
        i = int(np.argmax(ll))
        best, best_ll = (float(A.ravel()[i]), float(B.ravel()[i])), float(ll[i])
        step /= 3.0
        axis_w = np.clip(best[0] + step * np.arange(-3, 4), lo, hi)
        axis_v = np.clip(best[1] + step * np.arange(-3, 4), lo, hi)
    upper = _upper_interval_ends(likelihood, t, s, C, best, best_ll, hi)
    sigma = (float(10.0 ** (upper[0] / 2)), float(10.0 ** (upper[1] / 2)))
    return ProcessNoiseEstimate(sigma, best_ll, len(t), model)


def _upper_interval_ends(
    likelihood: Callable[..., np.ndarray],
    t: np.ndarray,
    s: np.ndarray,
    C: np.ndarray,
    best: tuple[float, float],
    best_ll: float,
    hi: float,
) -> tuple[float, float]:
    """log10 of the largest q_w and q_v whose likelihood, the other density at its
    optimum, is within :data:`INTERVAL_DROP` of the maximum."""
    ends = []
    steps = np.arange(0.0, hi - min(best) + INTERVAL_STEP, INTERVAL_STEP)
    trials = [np.clip(best[axis] + steps, None, hi) for axis in (0, 1)]
    others = [np.full(len(steps), best[1 - axis]) for axis in (0, 1)]
    q_w, q_v = [trials[0], others[1]], [others[0], trials[1]]
    if likelihood is log_likelihood:
        # Both axes in one pass over the poses: the WNA filter computes each pair's row
        # alone (the same numbers for any number of pairs); the WNJ's stacked products not.
        q = (10.0 ** np.concatenate(q_w), 10.0 ** np.concatenate(q_v))
        both = likelihood(t, s, C, *q, OUTLIER_GATE)
        lls = np.split(both, 2)
    else:
        lls = [likelihood(t, s, C, 10.0 ** q_w[a], 10.0 ** q_v[a], OUTLIER_GATE) for a in (0, 1)]
    for axis, ll in enumerate(lls):
        inside = np.flatnonzero(ll >= best_ll - INTERVAL_DROP)
        ends.append(float(trials[axis][inside.max()]) if inside.size else best[axis])
    return ends[0], ends[1]


#: Streaming "auto" process noise: the first refit after this many frames, then at
#: every doubling (the cost stays O(frames) overall).
FIRST_REFIT: int = 30


class ProcessNoiseSchedule:
    """The motion model and (s_w, s_v) a streaming estimator uses: fixed, or fitted ("auto").

    With "auto", :meth:`fit_all` fits them on a whole sequence known in advance;
    otherwise :meth:`observe` refits on the frames seen so far after
    :data:`FIRST_REFIT`, 60, 120, ... frames.

    Args:
        value: "auto", or one or two numbers (angular, linear; see
            :func:`~hvo_graph.estimators.process_noise.acceleration_sigma`).
        default: (s_w, s_v) of the WNA model until the first fit (and when a fit has
            too few poses).
        model: "wna", "wnj" or "auto". "auto" with fitted values: the model of the
            larger maximised likelihood, chosen by :meth:`fit_all`; streamed frames
            (no whole sequence to choose on) keep "wnj". "auto" with fixed values:
            "wna" (the values are then acceleration strengths, as they always were).
    """

    def __init__(
        self,
        value: float | Sequence[float] | str,
        default: tuple[float, float],
        model: str = "wna",
    ):
        self.auto = isinstance(value, str)
        if self.auto and value != "auto":
            raise InputError(
                "acceleration_sigma: expected 'auto' or one or two finite numbers > 0 "
                f"(angular, linear), got {value!r}"
            )
        self._choose = model == "auto" and self.auto
        #: The motion model in force, "wna" or "wnj".
        self.model = ("wnj" if self.auto else "wna") if model == "auto" else model
        self.default = DEFAULT_JERK_SIGMA if self.model == "wnj" else default
        self._wna_default = default
        #: (s_w, s_v) in force.
        self.sigma = self.default if self.auto else acceleration_sigma(value)  # type: ignore[arg-type]
        #: The latest maximum-likelihood fit (None with fixed values or before a fit).
        self.fit: ProcessNoiseEstimate | None = None
        self._seen: list[FrameMeasurement] = []
        self._next: int | None = FIRST_REFIT if self.auto else None

    def fit_all(self, frames: Sequence[FrameMeasurement]) -> None:
        """Fit on the whole sequence (no refits afterwards); nothing with fixed values."""
        if self.auto:
            self._fit(frames, "auto" if self._choose else self.model)
            self._next = None

    def observe(self, frame: FrameMeasurement) -> bool:
        """Record one streamed frame; True when the values changed (a refit)."""
        if self._next is None:
            return False
        self._seen.append(frame)
        if len(self._seen) < self._next:
            return False
        self._next *= 2
        return self._fit(self._seen, self.model)

    def _fit(self, frames: Sequence[FrameMeasurement], model: str) -> bool:
        fit = estimate_process_noise(frames, default=self.default, model=model)
        if not fit.poses:
            return False
        self.fit, self.sigma, self.model = fit, fit.acceleration_sigma, fit.model
        self.default = DEFAULT_JERK_SIGMA if self.model == "wnj" else self._wna_default
        return True
