"""The default smoother's whole graph in compact arrays, and its final solve in chunks.

The final trajectory of the default smoother is the batch optimum of every
factor of the sequence. Kept as GTSAM objects, those factors cost ~2.2 kB per
frame (each with its own noise model), and one Levenberg-Marquardt solve of the
whole graph held another ~9 kB per frame at its peak (linearized system,
elimination tree, iterates): over 1 GiB at 100,000 frames. Here

- the two factors of every frame that depend only on numbers (the motion factor
  on X(k-1), V(k-1), X(k), V(k) with its dt and (s_w, s_v); an H_d pose against
  the world, with its pose and 6x6 covariance) are rows of growing numpy
  arrays, 56 floats per frame, rebuilt as GTSAM factors when solved; any other
  factor (anchor and first-frame priors, keyframe between factors, H_c twist
  factors) is kept as it is, with the span of frames it touches;
- :func:`solve_in_chunks` solves the graph chunk by chunk: the factors
  touching a chunk of consecutive frames, with the frames just outside it held
  at their current values (block Gauss-Seidel, overlapping chunks). A sweep
  over every chunk is repeated until no value moves by more than the
  tolerance: then every frame's gradient is zero, the stationary point of the
  whole problem, i.e. the batch optimum (to that tolerance). The graph is a
  chain, so a change at a chunk's edge fades within a few tens of frames and
  a second sweep only confirms the first. Peak memory: one chunk's solve.

The tightly coupled smoother's graph adds plane landmarks L(j) (``Point3``) that
frames far apart observe: its projection factors are rows of 6 numbers (frame,
landmark, image point m, sigma, robust or not), and it is solved by Levenberg-Marquardt
with each linear system solved chunk by chunk (:mod:`~hvo_graph.estimators.chunked_lm`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, V, X

from hvo_graph.estimators.chunked_lm import chunked_levenberg_marquardt
from hvo_graph.estimators.least_squares import levenberg_marquardt
from hvo_graph.estimators.motion_model import STORED_FORMS, MotionFactors
from hvo_graph.estimators.state_log import GrowingRows

__all__ = [
    "CHUNK_FRAMES",
    "CHUNK_OVERLAP",
    "FactorStore",
    "batch_marginals",
    "copy_value",
    "final_states",
    "solve_in_chunks",
    "stored_optimum",
]

#: Frames solved together by :func:`solve_in_chunks` (a sequence this long or shorter
#: is one batch solve).
CHUNK_FRAMES: int = 2000

#: Frames shared by consecutive chunks: a chunk's values near its far edge, held
#: at the values before the sweep, are solved again by the next chunk.
CHUNK_OVERLAP: int = 200

#: A sweep that moves no value (rad, m, rad/s, m/s) by more than this ends the solve.
CHUNK_TOLERANCE: float = 1e-9

#: Most sweeps before the whole graph is solved at once (the second sweep usually
#: moves nothing beyond the tolerance).
MAX_SWEEPS: int = 6

#: The camera of the projection factors: unit focal length, no offset (normalized
#: coordinates m = (x/z, y/z), undistorted by the front end).
UNIT_CALIBRATION = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


class FactorStore:
    """Every factor of a smoother run, motion and world-pose factors as array rows.

    Frames are numbered by position (0, 1, ... in the order added); a frame's
    variables are X(index), V(index).

    Args:
        noise: the noise model of an H_d pose factor from its (6, 6) covariance (the
            smoother's, robust loss included), called again when the factor is rebuilt.
            None: a store that keeps nothing (for back ends that keep their own graph).
        pixel_noise: the noise model of a projection factor from its sigma (normalized
            image units; robust loss included), for a store with landmarks.
    """

    def __init__(
        self,
        noise: Callable[[np.ndarray], gtsam.noiseModel.Base] | None,
        pixel_noise: Callable[[float], gtsam.noiseModel.Base] | None = None,
    ) -> None:
        self.noise = noise
        self.pixel_noise = pixel_noise
        self.keeps = noise is not None or pixel_noise is not None
        self._index = GrowingRows(1, np.int64)  # frame index by position
        self._motion = GrowingRows(5)  # position of the later frame, dt, s_w, s_v, model
        self._prior = GrowingRows(1 + 12 + 36)  # position, R (row-major) and t, covariance
        self._span = GrowingRows(2, np.int64)  # oldest and newest position of each other factor
        self._other: list[gtsam.NonlinearFactor] = []
        self._motion_factors = MotionFactors()
        #: Whether any frame has a twist rate A(k) (the white-noise-jerk model).
        self.rates = False
        self._observation = GrowingRows(5)  # position of the frame, m (2), sigma, robust (1/0)
        self._observed = GrowingRows(1, np.int64)  # landmark key of each observation
        #: Landmark key -> its own factors (the plane prior), for the landmarks kept.
        self.landmarks: dict[int, list[gtsam.NonlinearFactor]] = {}
        #: Keys of the landmarks left out (:meth:`drop_landmarks`).
        self.dropped: set[int] = set()

    def __len__(self) -> int:
        return self._index.size

    def add_frame(self, index: int) -> None:
        """A new frame (its index larger than every earlier one); the factors added next
        are on it."""
        if not self.keeps:
            return
        self._index.append([index])

    def add_motion(self, dt: float, sigma: tuple[float, float], model: str = "wna") -> None:
        """The motion factors of ``model`` (:mod:`.motion_model`) between the previous
        frame and the newest one, over ``dt`` with strengths sigma (s_w, s_v)."""
        if not self.keeps:
            return
        self.rates = self.rates or model == "wnj"
        self._motion.append([len(self) - 1, dt, *sigma, STORED_FORMS.index(model)])

    def add_pose_prior(self, pose: gtsam.Pose3, covariance: np.ndarray) -> None:
        """An H_d pose factor against the world on the newest frame."""
        if not self.keeps:
            return
        row = np.empty(49)
        row[0] = len(self) - 1
        row[1:10] = pose.rotation().matrix().ravel()
        row[10:13] = pose.translation()
        row[13:] = np.asarray(covariance, dtype=float).ravel()
        self._prior.append(row)

    def add_world_frames(
        self,
        indices: np.ndarray,
        dts: np.ndarray,
        sigma: tuple[float, float],
        model: str,
        poses: np.ndarray,
    ) -> None:
        """n new frames, each with its motion factor from the frame before (over ``dts``)
        and a world pose prior (``poses`` (n, 48): R row-major, t, covariance): what
        :meth:`add_frame`, :meth:`add_motion`, :meth:`add_pose_prior` add, at once."""
        if not self.keeps:
            return
        n, first = len(indices), len(self)
        self._index.extend(np.asarray(indices, dtype=np.int64)[:, None])
        self.rates = self.rates or model == "wnj"
        places = np.arange(first, first + n, dtype=float)[:, None]
        form = np.full((n, 1), STORED_FORMS.index(model), dtype=float)
        self._motion.extend(np.hstack((places, dts[:, None], np.tile(sigma, (n, 1)), form)))
        self._prior.extend(np.hstack((places, poses)))

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        """Any other factor, on frames added already."""
        if not self.keeps:
            return
        indices = self._index.view()[:, 0]
        frames = [gtsam.Symbol(key).index() for key in factor.keys()]
        places = np.searchsorted(indices, frames)
        self._span.append([places.min(), places.max()])
        self._other.append(factor)

    def add_landmark(self, key: int, factor: gtsam.NonlinearFactor) -> None:
        """A new landmark ``key`` (a ``Point3``) with a factor on it alone (its plane prior)."""
        if self.keeps:
            self.landmarks.setdefault(key, []).append(factor)

    def add_observations(
        self, keys: Sequence[int], m: np.ndarray, sigma: float, *, robust: bool = True
    ) -> None:
        """Projection factors of the landmarks ``keys`` in the newest frame: normalized image
        points m (N, 2), isotropic noise ``sigma`` (``pixel_noise(sigma)``; Gaussian if not
        ``robust``)."""
        if not self.keeps or not len(keys):
            return
        rows = np.empty((len(keys), 5))
        rows[:, 0], rows[:, 1:3], rows[:, 3], rows[:, 4] = len(self) - 1, m, sigma, robust
        self._observation.extend(rows)
        self._observed.extend(np.asarray(keys, dtype=np.int64)[:, None])

    def drop_landmarks(self, keys: set[int]) -> None:
        """Leave out every factor of the landmarks ``keys`` (rejected tracks) from now on."""
        self.dropped.update(keys)
        for key in keys:
            self.landmarks.pop(key, None)

    def landmark_graph(self) -> gtsam.NonlinearFactorGraph:
        """The factors on the landmarks alone (their plane priors)."""
        graph = gtsam.NonlinearFactorGraph()
        for factors in self.landmarks.values():
            for factor in factors:
                graph.add(factor)
        return graph

    def _observations(self, first: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """The observation rows of the frames at positions [first, stop) and their
        landmark keys, those of dropped landmarks left out."""
        rows = self._observation.view()
        lo, hi = np.searchsorted(rows[:, 0], [first, stop])  # rows are in frame order
        rows, keys = rows[lo:hi], self._observed.view()[lo:hi, 0]
        if self.dropped and len(keys):
            kept = ~np.isin(keys, np.fromiter(self.dropped, np.int64))
            rows, keys = rows[kept], keys[kept]
        return rows, keys

    def last_observed(self) -> dict[int, int]:
        """Landmark key -> the position of the last frame observing it."""
        rows, keys = self._observations(0, len(self))
        if not len(keys):
            return {}
        unique, last = np.unique(keys[::-1], return_index=True)
        positions = rows[len(keys) - 1 - last, 0].astype(int)
        return dict(zip(unique.tolist(), positions.tolist(), strict=True))

    def observations(self, first: int, stop: int) -> int:
        """How many observations the frames at positions [first, stop) hold."""
        return len(self._observations(first, stop)[1])

    def observed(self, first: int, stop: int) -> np.ndarray:
        """The keys of the landmarks the frames at positions [first, stop) observe."""
        return np.unique(self._observations(first, stop)[1])

    def longest_span(self) -> int:
        """The most positions apart two frames of one factor are (1: a chain)."""
        span = self._span.view()
        return max(1, int((span[:, 1] - span[:, 0]).max())) if len(span) else 1

    def indices(self) -> np.ndarray:
        """(K,) frame index of every position."""
        return self._index.view()[:, 0]

    def graph(
        self, first: int, stop: int, *, newest: bool = False
    ) -> tuple[gtsam.NonlinearFactorGraph, range]:
        """Every factor touching a frame at a position in [first, stop) (``newest``: every
        factor whose newest frame is there), and the range of positions they touch. The
        landmarks' own factors are not included (:meth:`landmark_graph`)."""
        indices = self.indices()
        graph = gtsam.NonlinearFactorGraph()
        lo, hi = first, stop
        motion = self._motion.view()
        late = stop if newest else stop + 1
        motion = motion[(motion[:, 0] >= first) & (motion[:, 0] < late)]
        places = motion[:, 0].astype(np.int64)  # lists: numpy scalars are slow one by one
        pairs = zip(indices[places - 1].tolist(), indices[places].tolist(), strict=True)
        for (previous, k), (_, dt, s_w, s_v, model) in zip(pairs, motion.tolist(), strict=True):
            for factor in self._motion_factors(
                STORED_FORMS[int(model)], previous, k, dt, (s_w, s_v)
            ):
                graph.add(factor)
        if len(places):
            lo, hi = min(lo, int(places.min()) - 1), max(hi, int(places.max()) + 1)
        prior = self._prior.view()
        for row in prior[(prior[:, 0] >= first) & (prior[:, 0] < stop)]:
            pose = gtsam.Pose3(gtsam.Rot3(row[1:10].reshape(3, 3)), row[10:13])
            key = X(int(indices[int(row[0])]))
            noise = self.noise(row[13:].reshape(6, 6))  # type: ignore[misc]
            graph.add(gtsam.PriorFactorPose3(key, pose, noise))
        span = self._span.view()
        reach = (span[:, 1] >= first) & ((span[:, 1] < stop) if newest else (span[:, 0] < stop))
        for i in np.flatnonzero(reach):
            graph.add(self._other[i])
            lo, hi = min(lo, int(span[i, 0])), max(hi, int(span[i, 1]) + 1)
        rows, keys = self._observations(first, stop)
        poses = (np.uint64(X(0)) + indices[rows[:, 0].astype(np.int64)].astype(np.uint64)).tolist()
        kinds = list(zip(rows[:, 3].tolist(), rows[:, 4].tolist(), strict=True))
        plain = gtsam.noiseModel.Isotropic.Sigma
        noise = {(s, r): self.pixel_noise(s) if r else plain(2, s) for s, r in set(kinds)}  # type: ignore[misc]
        for m, kind, pose, key in zip(rows[:, 1:3], kinds, poses, keys.tolist(), strict=True):
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(m, noise[kind], pose, key, UNIT_CALIBRATION)
            )
        return graph, range(lo, hi)

    def whole_graph(self) -> gtsam.NonlinearFactorGraph:
        """Every factor (as GTSAM objects: for small problems and tests)."""
        graph = self.graph(0, len(self))[0]
        graph.push_back(self.landmark_graph())
        return graph


def _frame_values(
    source: gtsam.Values, indices: np.ndarray, rates: bool, landmarks: np.ndarray
) -> gtsam.Values:
    values = gtsam.Values()
    for k in indices.tolist():
        values.insert(X(k), source.atPose3(X(k)))
        for key in (V(k), A(k)) if rates else (V(k),):
            values.insert(key, source.atVector(key))
    for key in landmarks.tolist():
        values.insert(key, source.atPoint3(key))
    return values


def solve_in_chunks(
    store: FactorStore,
    values: gtsam.Values,
    *,
    chunk: int = CHUNK_FRAMES,
    overlap: int = CHUNK_OVERLAP,
    tolerance: float = CHUNK_TOLERANCE,
    max_iterations: int = 100,
) -> list[float]:
    """Move ``values`` (every frame's X and V, every landmark's L) to the optimum of the
    store's graph.

    At most ``chunk`` frames are solved at once by :func:`levenberg_marquardt`, the
    frames just outside held (module docstring). A sequence of at most ``chunk``
    frames is one plain batch solve. Longer ones: a sweep over chunks of ``chunk``
    frames, consecutive ones sharing ``overlap``; then, when every factor is local
    (its frames at most ``overlap`` / 2 apart: a chain), the seams between chunks
    (``overlap`` / 4 frames, and at least the longest factor's span, either side of
    each chunk's start: only there did a frame's neighbours move after it was
    solved) are solved again until none moves by more than ``tolerance``, with a
    full sweep between two seam sweeps that do move;
    otherwise (a keyframe factor reaching far back: its frames moved anywhere) full
    sweeps until one moves nothing by more than ``tolerance``. Should
    :data:`MAX_SWEEPS` sweeps not settle, or full sweeps shrink their move by less
    than half (a keyframe used for thousands of frames couples every chunk), the
    whole graph is solved at once: the batch optimum always, in bounded memory
    where the graph is a chain.

    With landmarks (longer than ``chunk`` frames): Levenberg-Marquardt on the whole
    graph, its linear systems solved ``chunk`` frames at a time
    (:func:`~hvo_graph.estimators.chunked_lm.chunked_levenberg_marquardt`).
    Returns the largest move of each sweep (with landmarks: the largest step of the solve).
    """
    total = len(store)
    indices = store.indices()
    whole = (store, values, indices, 0, total, max_iterations, tolerance)
    if total <= chunk:
        return [_solve_range(*whole, landmarks=True)]
    if store.landmarks:
        kept = chunked_levenberg_marquardt(
            store, values, chunk=chunk, max_iterations=max_iterations
        )
        return [kept[1]]
    starts = [0]
    while starts[-1] + chunk < total:
        starts.append(starts[-1] + max(1, chunk - overlap))
    chunks = [(first, min(first + chunk, total)) for first in starts]
    span = store.longest_span()
    half = max(overlap // 4, span)
    seams = [(first - half, min(first + half, total)) for first in starts[1:]]
    if span > overlap // 2:
        seams = chunks
    moves: list[float] = []
    if _sweeps(store, values, indices, chunks, seams, tolerance, max_iterations, moves):
        return moves
    moves.append(_solve_range(*whole))
    return moves


def _sweeps(
    store: FactorStore,
    values: gtsam.Values,
    indices: np.ndarray,
    chunks: list[tuple[int, int]],
    seams: list[tuple[int, int]],
    tolerance: float,
    max_iterations: int,
    moves: list[float],
) -> bool:
    """Sweeps over the chunks and seams (:func:`solve_in_chunks`), landmarks held, their
    largest moves appended to ``moves``; whether they settled."""

    def sweep(ranges: list[tuple[int, int]]) -> float:
        return max(
            _solve_range(store, values, indices, *r, max_iterations, tolerance) for r in ranges
        )

    count = 1
    moves.append(sweep(chunks))
    while count < MAX_SWEEPS:
        moves.append(sweep(seams))
        count += 1
        if moves[-1] <= tolerance:
            return True
        if seams is chunks and moves[-1] > 0.5 * moves[-2]:
            return False  # sweeps converge slowly here: solve it at once
        if seams is not chunks:
            moves.append(sweep(chunks))
            count += 1
    return False


def _solve_range(
    store: FactorStore,
    values: gtsam.Values,
    indices: np.ndarray,
    first: int,
    stop: int,
    max_iterations: int,
    tolerance: float,
    *,
    landmarks: bool = False,
) -> float:
    """Solve the frames at positions [first, stop) with every other frame held (and the
    landmarks, unless ``landmarks``: then they are solved too, with their own factors),
    to within ``tolerance`` of their optimum (:func:`levenberg_marquardt`'s step test);
    update ``values``; return the largest move (any tangent coordinate)."""
    graph, touched = store.graph(first, stop)
    observed = store.observed(touched.start, touched.stop)
    if landmarks:
        graph.push_back(store.landmark_graph())
        observed = np.union1d(observed, np.fromiter(store.landmarks, np.int64))
    frames = indices[touched.start : touched.stop]
    chunk_values = _frame_values(values, frames, store.rates, observed)
    outside = np.concatenate([indices[touched.start : first], indices[stop : touched.stop]])
    symbols = (X, V, A) if store.rates else (X, V)
    held = [symbol(k) for k in outside.tolist() for symbol in symbols]
    if not landmarks:
        held.extend(observed.tolist())
    solved, _ = levenberg_marquardt(
        graph, chunk_values, max_iterations=max_iterations, fixed=held, step_tolerance=tolerance
    )
    own = [symbol(k) for k in indices[first:stop].tolist() for symbol in symbols]
    if landmarks:
        own.extend(observed.tolist())
    # Whole Values at once: one call each, not three per variable.
    values.update(solved.extract(own))
    return float(np.abs(chunk_values.localCoordinates(solved).vector(own)).max())


def stored_optimum(
    store: FactorStore,
    initial: gtsam.Values,
    isam: gtsam.ISAM2,
    live: Iterable[int],
    *,
    chunk: int = CHUNK_FRAMES,
    overlap: int = CHUNK_OVERLAP,
    max_iterations: int = 100,
) -> tuple[gtsam.Values, list[float]]:
    """The optimum of the store's graph (:func:`solve_in_chunks`) started from
    ``initial`` (each variable's value as it left an online window), with ISAM2's
    current estimate for the keys ``live`` (still in the window); and the moves."""
    result = gtsam.Values(initial)
    live = [key for key in live if result.exists(key)]
    if live:
        estimate = isam.calculateBestEstimate()
        for key in live:
            copy_value(estimate, result, key)
    moves = solve_in_chunks(
        store, result, chunk=chunk, overlap=overlap, max_iterations=max_iterations
    )
    return result, moves


def final_states(
    store: FactorStore, values: gtsam.Values, indices: Sequence[int], *, marginals: bool
) -> Iterator[tuple[gtsam.Pose3, np.ndarray, np.ndarray | None]]:
    """Each frame's (pose, twist, 12x12 marginal or None) at the optimum ``values`` of the
    store's graph; ``marginals``: from :func:`batch_marginals` of the whole graph."""
    if marginals:
        yield from batch_marginals(store.whole_graph(), values, indices)
        return
    for index in indices:
        yield values.atPose3(X(index)), values.atVector(V(index)), None


def batch_marginals(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, indices: Sequence[int]
) -> Iterator[tuple[gtsam.Pose3, np.ndarray, np.ndarray]]:
    """Each frame's values and Bayesian marginal at the optimum ``values``."""
    # One ISAM2 elimination at the optimum gives the joint marginals quickly
    # (gtsam.Marginals took O(N) per query here); its linearization point is
    # held so the custom factors are not handed copies.
    isam = gtsam.ISAM2()
    theta = isam.getLinearizationPoint()
    isam.update(graph, values)
    for index in indices:
        c = isam.jointMarginalCovariance([X(index), V(index)]).fullMatrix()
        yield values.atPose3(X(index)), values.atVector(V(index)), 0.5 * (c + c.T)
    del theta


def copy_value(source: gtsam.Values, target: gtsam.Values, key: int) -> None:
    """Set ``target``'s value of ``key`` (an X pose, a V twist or an L landmark) to ``source``'s."""
    kind = gtsam.Symbol(key).chr()
    if kind == ord("x"):
        value = source.atPose3(key)
    elif kind == ord("l"):  # the tightly coupled smoother's plane landmarks (Point3)
        value = source.atPoint3(key)
    else:
        value = source.atVector(key)
    if target.exists(key):
        target.update(key, value)
    else:
        target.insert(key, value)
