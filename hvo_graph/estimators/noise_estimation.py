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
finds the optimum in ~0.15 s for 300 frames and ~1.4 s for 3,000 (one filter
runs all the grid's pairs in lockstep: :mod:`.noise_likelihood`).

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
from hvo_graph.estimators.noise_likelihood import jerk_log_likelihood, log_likelihood
from hvo_graph.estimators.process_noise import DEFAULT_JERK_SIGMA, acceleration_sigma
from hvo_graph.types import FrameMeasurement

#: Lower bound of q_w and q_v (rad^2 s^-3, m^2 s^-3): a random-walk twist change of
#: 1 cm/s (10 mrad/s) per second. Below it the likelihood of a near-static sequence
#: is flat, the smoother would trust the motion model without limit, and ISAM2's
#: Cholesky factorization of the near-singular system fails.
MIN_SPECTRAL_DENSITY: float = 1e-4

#: The lower bound for a Kalman filter's fit where the data put a density at or near
#: :data:`MIN_SPECTRAL_DENSITY` (:func:`filter_process_noise`): a filter has no
#: factorization to fail. At 1e-8 a near-hover draw fitted 1e-7 and its filter's twist
#: covariance was 15x too small; at 1e-5 the hover family's was still 1.5x too large.
FILTER_MIN_SPECTRAL_DENSITY: float = 1e-6

#: A density fitted within this factor of :data:`MIN_SPECTRAL_DENSITY` is at the bound for
#: :func:`filter_process_noise` (5 s of hover: 1.2-1.6x).
NEAR_BOUND: float = 2.0

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

#: Steps of that search taken first (one decade). Over four draws of every family of
#: docs/generalization.md the end lay within 0.6 decades of the optimum; an axis still
#: within the drop at the last of them is searched on to the upper bound.
INTERVAL_FIRST_STEPS: int = 11

#: Fewest pose measurements for an estimate; shorter sequences keep the default.
MIN_POSES: int = 10

#: Most poses the likelihood is evaluated on; beyond, the estimate changes little and
#: the cost would grow with the sequence.
MAX_POSES: int = 3000

#: A sequence with more than :data:`MAX_POSES` poses is represented by this many
#: stretches of MAX_POSES / STRETCHES consecutive poses, spread evenly from its start to
#: its end (its latest poses alone would fit a long sequence on how it ends).
STRETCHES: int = 6


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
    frames: Sequence[FrameMeasurement], *, translation: str = "body"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measured pose sequence as times, unrolled tangent positions and noise.

    Args:
        frames: the measurements (only the poses are read).
        translation: "body": s's translation is unrolled like its rotation (the smoother's
            body-frame twist); "world": it is the world position p_wc (a Kalman filter's
            world-frame velocity: a constant body twist that turns is no acceleration for
            the first, and is one for the second).
    Returns:
        t: (K,) times of the frames with a pose measurement.
        s: (K, 6) s_k = sum_j Log(Z_{j-1}^-1 Z_j), tangent order [rot; trans].
        C: (K, 6, 6) covariance of frame k's own pixel noise.
    """
    if translation not in ("body", "world"):
        raise InputError(f"translation: expected 'body' or 'world', got {translation!r}")
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
            # The keyframe as its own measurement put it: the front end's placement of it
            # may have been corrected since (keyframe tilt), a jump no motion made.
            if pose.reference in world:
                base = world[pose.reference]
            elif pose.reference_rotation is not None and pose.reference_position is not None:
                base = gtsam.Pose3(gtsam.Rot3(pose.reference_rotation), pose.reference_position)
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
        if translation == "world":
            s[3:] = Z.translation()
            M = np.eye(6)
            M[3:, 3:] = Z.rotation().matrix()  # right-perturbation translation is body-frame
            covariance = M @ covariance @ M.T
        unrolled.append(s.copy())
        covariances.append(covariance)
    if not times:
        return np.empty(0), np.empty((0, 6)), np.empty((0, 6, 6))
    return np.array(times), np.array(unrolled), np.array(covariances)


def estimate_process_noise(
    frames: Sequence[FrameMeasurement],
    *,
    default: tuple[float, float],
    grid: int = 10,
    refinements: int = 2,
    model: str = "wna",
    floor: float = MIN_SPECTRAL_DENSITY,
    translation: str = "body",
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
        floor: the smallest density searched (:data:`MIN_SPECTRAL_DENSITY`; a filter:
            :data:`FILTER_MIN_SPECTRAL_DENSITY`); the first grid keeps its spacing, so a
            lower floor adds points.
        translation: the frame of the linear velocity's random walk (:func:`unrolled_poses`).
    Returns:
        The estimate; ``poses`` = 0 and the default when there was too little data
        (``model`` then "wnj" for "auto").
    """
    data = [
        tuple(a[-count:] for a in unrolled_poses(stretch, translation=translation))
        for stretch, count in _sampled_stretches(frames, MAX_POSES, STRETCHES)
    ]
    data = [d for d in data if len(d[0]) > 1]  # a stretch of one pose has no step
    poses = sum(len(t) for t, _, _ in data)
    if poses < MIN_POSES:
        return ProcessNoiseEstimate(default, float("nan"), 0, "wnj" if model == "auto" else model)
    decades = np.log10(MAX_SPECTRAL_DENSITY / floor) / np.log10(
        MAX_SPECTRAL_DENSITY / MIN_SPECTRAL_DENSITY
    )
    grid = max(grid, int(np.ceil((grid - 1) * decades)) + 1)
    fits = [
        _fit(data, poses, name, grid, refinements, floor)
        for name in (("wna", "wnj") if model == "auto" else (model,))
    ]
    return max(fits, key=lambda fit: fit.log_likelihood)


def filter_process_noise(
    frames: Sequence[FrameMeasurement], *, default: tuple[float, float]
) -> tuple[float, float]:
    """(s_w, s_v) for a Kalman filter whose linear velocity lives in the world frame.

    Each density is the larger of two fits (:func:`estimate_process_noise`): the linear
    velocity's random walk in the body frame (the smoother's) and in the world frame
    (the filter's: a constant body twist that turns is an acceleration for it, and a
    body-frame fit near zero left the filter's pose covariance 2-3x too small on a
    turning traverse). Where both end within :data:`NEAR_BOUND` times
    :data:`MIN_SPECTRAL_DENSITY` (the fit stops at or near the bound), the search goes on
    down to :data:`FILTER_MIN_SPECTRAL_DENSITY`.

    At the bound a near-hover sequence's filter reported a twist covariance 2.7x its
    errors' (twist NEES per dof 0.40 over 16 draws; 1.04 now). Only there: a lower bound everywhere
    let the flat likelihood of a few noisy points (rotation absorbs slow translation)
    pick a density 500x below the motion's, and a twist covariance 180x too confident.
    """

    def fit(floor: float) -> np.ndarray:
        return np.maximum(
            *(
                estimate_process_noise(
                    frames, default=default, floor=floor, translation=frame
                ).acceleration_sigma
                for frame in ("body", "world")
            )
        )

    sigma = fit(MIN_SPECTRAL_DENSITY)
    at_bound = sigma**2 <= NEAR_BOUND * MIN_SPECTRAL_DENSITY
    if at_bound.any():
        sigma = np.where(at_bound, fit(FILTER_MIN_SPECTRAL_DENSITY), sigma)
    return float(sigma[0]), float(sigma[1])


_LIKELIHOODS = {"wna": log_likelihood, "wnj": jerk_log_likelihood}


#: The poses of a sequence a fit reads: (t (K,), s (K, 6), C (K, 6, 6)) per stretch.
_Stretch = tuple[np.ndarray, np.ndarray, np.ndarray]


def _sampled_stretches(
    frames: Sequence[FrameMeasurement], count: int, stretches: int
) -> list[tuple[Sequence[FrameMeasurement], int]]:
    """(frames, poses to keep) of the stretches a fit reads: every frame when there are
    at most ``count`` poses; else ``stretches`` runs of count // stretches consecutive
    poses, evenly spread from the first pose to the last, each with the pose before it
    (unrolling starts there; the caller keeps the run's own poses). Unrolling the whole
    sequence would grow with it."""
    has_pose = getattr(frames, "has_pose", None)  # a MeasurementTable's column: no records
    if has_pose is None:
        has_pose = np.fromiter((f.pose is not None for f in frames), bool, len(frames))
    posed = np.flatnonzero(has_pose)
    if len(posed) <= count:
        return [(frames, count)]
    run = count // stretches
    firsts = np.linspace(1, len(posed) - run, stretches).round().astype(int)
    return [(frames[int(posed[a - 1]) : int(posed[a + run - 1]) + 1], run) for a in firsts]


def _fit(
    data: list[_Stretch],
    poses: int,
    model: str,
    grid: int,
    refinements: int,
    floor: float = MIN_SPECTRAL_DENSITY,
) -> ProcessNoiseEstimate:
    likelihood = _LIKELIHOODS[model]
    lo, hi = np.log10(floor), np.log10(MAX_SPECTRAL_DENSITY)
    axis_w = axis_v = np.linspace(lo, hi, grid)
    step = axis_w[1] - axis_w[0]
    for _ in range(refinements + 1):
        A, B = np.meshgrid(axis_w, axis_v, indexing="ij")
        ll = _evaluate(likelihood, data, A.ravel(), B.ravel())
        i = int(np.argmax(ll))
        best, best_ll = (float(A.ravel()[i]), float(B.ravel()[i])), float(ll[i])
        step /= 3.0
        axis_w = np.clip(best[0] + step * np.arange(-3, 4), lo, hi)
        axis_v = np.clip(best[1] + step * np.arange(-3, 4), lo, hi)
    upper = _upper_interval_ends(likelihood, data, best, best_ll, hi)
    sigma = (float(10.0 ** (upper[0] / 2)), float(10.0 ** (upper[1] / 2)))
    return ProcessNoiseEstimate(sigma, best_ll, poses, model)


def _evaluate(
    likelihood: Callable[..., np.ndarray],
    data: list[_Stretch],
    log_w: np.ndarray,
    log_v: np.ndarray,
) -> np.ndarray:
    """(M,) gated likelihoods of the pairs (10^log_w, 10^log_v), each distinct pair filtered
    once (grids clipped at a bound repeat pairs), summed over the stretches (each filtered
    from its own broad prior). At extreme densities (~1e4 jerk) the filter's covariance
    can lose definiteness by rounding (NaN): such a pair, far from the optimum, is ruled
    out (-inf)."""
    unique, index = np.unique(np.stack((log_w, log_v), axis=1), axis=0, return_inverse=True)
    q_w, q_v = 10.0 ** unique[:, 0], 10.0 ** unique[:, 1]
    # Stretches of one length are filtered side by side (far fewer numpy calls), then
    # summed in the order of the stretches.
    rows: list[np.ndarray | None] = [None] * len(data)
    for length in {len(t) for t, _, _ in data}:
        same = [i for i, (t, _, _) in enumerate(data) if len(t) == length]
        t, s, C = (np.stack([data[i][j] for i in same]) for j in range(3))
        for i, row in zip(same, likelihood(t, s, C, q_w, q_v, OUTLIER_GATE), strict=True):
            rows[i] = row
    ll = sum(rows)
    return np.where(np.isnan(ll), -np.inf, ll)[index.ravel()]


def _upper_interval_ends(
    likelihood: Callable[..., np.ndarray],
    data: list[_Stretch],
    best: tuple[float, float],
    best_ll: float,
    hi: float,
) -> tuple[float, float]:
    """log10 of the largest q_w and q_v whose likelihood, the other density at its
    optimum, is within :data:`INTERVAL_DROP` of the maximum, on steps of
    :data:`INTERVAL_STEP` up from the optimum: the first :data:`INTERVAL_FIRST_STEPS` of
    both axes in one pass over the poses, the rest of an axis only where its likelihood is
    still within the drop at the last of them."""
    steps = np.arange(0.0, hi - min(best) + INTERVAL_STEP, INTERVAL_STEP)
    trials = [np.clip(best[axis] + steps, None, hi) for axis in (0, 1)]
    inside = [np.zeros(len(steps), dtype=bool) for _ in (0, 1)]
    scans = {axis: slice(0, INTERVAL_FIRST_STEPS) for axis in (0, 1)}
    while scans:
        # Both axes in one pass (each pair's filter runs alone; the trials clipped at the
        # upper bound repeat, and step 0 of both axes is the optimum).
        pairs = []
        for axis, r in scans.items():
            trial, other = trials[axis][r], np.full(len(trials[axis][r]), best[1 - axis])
            pairs.append((trial, other) if axis == 0 else (other, trial))
        ll = _evaluate(likelihood, data, *(np.concatenate(q) for q in zip(*pairs, strict=True)))
        start = 0
        for axis, r in scans.items():
            count = len(trials[axis][r])
            inside[axis][r] = ll[start : start + count] >= best_ll - INTERVAL_DROP
            start += count
        scans = {
            axis: slice(r.stop, len(steps))
            for axis, r in scans.items()
            if r.stop < len(steps) and inside[axis][r.stop - 1]
        }
    ends = []
    for axis in (0, 1):
        found = np.flatnonzero(inside[axis])
        ends.append(float(trials[axis][found.max()]) if found.size else best[axis])
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

    @property
    def refits(self) -> bool:
        """Whether :meth:`observe` may still refit (streamed "auto" frames)."""
        return self._next is not None

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
