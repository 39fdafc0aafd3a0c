"""The back ends of the tightly coupled smoother (:mod:`hvo_graph.estimators.tight`).

Beside the homography graph's back ends (:mod:`hvo_graph.estimators.solvers`), with
what plane landmarks L(j) (``Point3``, symbol ``l``) need: a relinearization
threshold of their own, timestamps in the fixed-lag window, and a window rebuilt
from its own factors for the default solver, whose final solve, like the default
homography smoother's, is the batch optimum of a compact store of every factor,
solved in chunks (:mod:`hvo_graph.estimators.factor_store`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, V, X

from hvo_graph.estimators.factor_store import (
    CHUNK_FRAMES,
    CHUNK_OVERLAP,
    FactorStore,
    final_states,
    stored_optimum,
)
from hvo_graph.estimators.least_squares import levenberg_marquardt
from hvo_graph.estimators.plane_tracks import graph_statistic
from hvo_graph.estimators.solvers import Backend, BatchBackend, FixedLagBackend, FrameValues

__all__ = [
    "TRACK_WINDOW_MARGIN",
    "LandmarkFixedLagBackend",
    "WindowIsam2Backend",
    "confirm_off_plane",
    "copy_value",
    "drop_landmarks",
    "tight_isam2_params",
]

#: Frames either side of a track in the graph of :func:`confirm_off_plane` (the frames
#: beyond are held): the pose uncertainty near the track is that of its neighbourhood.
TRACK_WINDOW_MARGIN: int = CHUNK_OVERLAP

_LANDMARK = ord("l")


def tight_isam2_params(threshold: float, skip: int, factorization: str = "QR") -> gtsam.ISAM2Params:
    """ISAM2 parameters: poses and landmarks relinearize (every factor is affine in V);
    ``factorization`` "QR" or "CHOLESKY" (:class:`WindowIsam2Backend`)."""
    params = gtsam.ISAM2Params()
    thresholds = gtsam.ISAM2ThresholdMap()
    thresholds.insert(("x", np.full(6, threshold)))
    thresholds.insert(("v", np.full(6, np.inf)))
    thresholds.insert(("l", np.full(3, threshold)))
    params.setRelinearizeThreshold(thresholds)
    params.relinearizeSkip = skip
    params.enablePartialRelinearizationCheck = True
    params.findUnusedFactorSlots = True
    # QR by default: the world prior and the plane rows are far stiffer than the rest.
    params.setFactorization(factorization)
    return params


class LandmarkFixedLagBackend(FixedLagBackend):
    """The fixed-lag back end, with every landmark a factor touches stamped with the frame
    (a landmark stays in the window while it is observed)."""

    def _stamps(
        self, graph: gtsam.NonlinearFactorGraph, index: int, stamp: float
    ) -> dict[int, float]:
        stamps = super()._stamps(graph, index, stamp)
        for i in range(graph.size()):
            for key in graph.at(i).keys():
                if gtsam.Symbol(key).chr() == _LANDMARK:
                    stamps[key] = stamp
        return stamps


class WindowIsam2Backend(Backend):
    """ISAM2 over a window of recent frames for the online estimates, the batch
    optimum of the whole graph for the final ones.

    Every landmark in view for the whole sequence is touched by every frame, so in one
    ISAM2 over the whole sequence each update scans all of its factors (cost growing
    with the sequence), and GTSAM's fixed-lag smoother hangs one more dense marginal
    factor on it per marginalization (the same growth). Here, once the ISAM2 holds
    ``2 window`` frames, it is rebuilt from the last ``window`` frames' factors plus
    one prior: the older factors linearized at the current estimate, their own
    variables eliminated (the Gaussian marginal on what they share with the kept
    frames: the oldest kept X, V and the landmarks still observed). The cost per frame
    is bounded, the rebuild amortized over ``window`` frames. Landmarks only the older
    frames saw leave the online problem (:attr:`live`).

    The first ISAM2 (the world prior, 1e14 times stiffer than the first twist's, with
    perhaps no pixels yet between them) uses ``params`` (QR); the rebuilt ones may use
    ``rebuilt`` (Cholesky: half QR's time per update with 20 landmarks, the same
    estimates to rounding). Should an update find the system indeterminate, the updates
    since that ISAM2 was built are replayed on one with ``params``, kept from then on.

    Final (:meth:`final`): every factor, kept as numbers in :attr:`store` (filled by
    the smoother), solved from each variable's estimate as it left the window (a
    landmark's carries all its observations) in chunks of ``chunk`` frames sharing
    ``overlap`` (:func:`~hvo_graph.estimators.factor_store.solve_in_chunks`): the
    batch optimum, in memory bounded by one chunk's solve.
    """

    solver = "isam2"

    def __init__(
        self,
        params: gtsam.ISAM2Params,
        *,
        window: int = 30,
        max_iterations: int,
        compute_covariance: bool,
        pixel_noise: Callable[[float], gtsam.noiseModel.Base],
        chunk: int = CHUNK_FRAMES,
        overlap: int = CHUNK_OVERLAP,
        rebuilt: gtsam.ISAM2Params | None = None,
    ) -> None:
        super().__init__(compute_covariance=compute_covariance)
        self.max_iterations = max_iterations
        self.chunk, self.overlap = int(chunk), int(overlap)
        #: Every factor of the sequence, for the final solve (the smoother adds them).
        self.store = FactorStore(None, pixel_noise)
        #: Each variable's value as it left the window (the final solve's initial values).
        self.initial = gtsam.Values()
        self._result: gtsam.Values | None = None
        #: The largest move of each sweep of the last final solve (solve_in_chunks).
        self.moves: list[float] = []
        self.params = params
        self.rebuilt = params if rebuilt is None else rebuilt
        self._current = params  # those of the ISAM2 now
        #: The updates since the ISAM2 was (re)built: replayed on a failure.
        self._updates: list[tuple[gtsam.NonlinearFactorGraph, gtsam.Values]] = []
        self.window = int(window)
        self.isam = gtsam.ISAM2(params)
        # Held so the custom factors' callbacks are not handed copies (solvers docstring).
        self.theta = self.isam.getLinearizationPoint()
        #: Keys of the online problem (the landmarks a new observation may still use).
        self.live: set[int] = set()
        self._frames: list[tuple[int, gtsam.NonlinearFactorGraph]] = []
        self._prior = gtsam.NonlinearFactorGraph()

    def current_pose(self, index: int) -> gtsam.Pose3:
        if X(index) in self.live:
            return self.isam.calculateEstimatePose3(X(index))
        return self.initial.atPose3(X(index))

    def add(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> FrameValues:
        self.initial.insert(values)
        self._result = None
        self._update(graph, values)
        self.live.update(values.keys())
        self._frames.append((index, graph))
        pose = self.isam.calculateEstimatePose3(X(index))
        twist = self.isam.calculateEstimateVector(V(index))
        covariance = None
        if self.compute_covariance:
            joint = self.isam.jointMarginalCovariance([X(index), V(index)]).fullMatrix()
            covariance = 0.5 * (joint + joint.T)
        if len(self._frames) >= 2 * self.window:
            self._rebuild()
        return pose, twist, covariance

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """``isam.update``; should a rebuilt ISAM2 find the system indeterminate (Cholesky on a
        well-posed but badly scaled one), the updates since it was built are replayed on a
        new one with ``params``, kept from then on."""
        self._updates.append((graph, values))
        try:
            self.isam.update(graph, values)
        except RuntimeError:
            if self._current is self.params:
                raise
            self.rebuilt = self._current = self.params
            self.isam = gtsam.ISAM2(self.params)
            self.theta = self.isam.getLinearizationPoint()
            for update in self._updates:
                self.isam.update(*update)

    def online_graph(self) -> gtsam.NonlinearFactorGraph:
        """The online problem's factors: the prior of the older frames and the recent
        frames' own factors (what the current ISAM2 holds)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self._prior)
        for _, frame_graph in self._frames:
            graph.push_back(frame_graph)
        return graph

    def _rebuild(self) -> None:
        """A fresh ISAM2 on the last ``window`` frames and the marginal of the older ones."""
        estimate = self.isam.calculateBestEstimate()
        old, kept = self._frames[: -self.window], self._frames[-self.window :]
        dropped = {k for i, _ in old for k in (X(i), V(i))}
        older = gtsam.NonlinearFactorGraph()
        newer = gtsam.NonlinearFactorGraph()
        carried = gtsam.NonlinearFactorGraph()  # older frames' factors on kept keys only
        kept_graphs = []  # each kept frame's own factors on kept keys only
        # One pass over the factors, in order: each goes to the marginal (touching a
        # dropped key) or stays (newer; and carried, e.g. a landmark's plane factor, or
        # back into its kept frame's graph).
        for j, graph in enumerate([self._prior, *(g for _, g in old), *(g for _, g in kept)]):
            own = carried if j <= len(old) else gtsam.NonlinearFactorGraph()
            if j > len(old) and dropped.isdisjoint(graph.keyVector()):  # a kept frame's own
                newer.push_back(graph)
                kept_graphs.append(graph)
                continue
            for n in range(graph.size()):
                factor = graph.at(n)
                if dropped.intersection(factor.keys()):
                    older.add(factor)
                else:
                    newer.add(factor)
                    own.add(factor)
            if j > len(old):
                kept_graphs.append(own)
        kept_keys = set(newer.keyVector())
        # Frames in time order, then the landmarks no kept frame sees: the chain is
        # eliminated with fill-in only on the landmarks (key order interleaves badly).
        gone = [k for k in older.keyVector() if k not in kept_keys and k not in dropped]
        eliminate = [k for i, _ in old for k in (X(i), V(i))] + gone
        # QR, as ISAM2 here: the world and plane priors are far stiffer than the pixels,
        # and Cholesky's marginal of that system was not positive definite.
        _, marginal = older.linearize(estimate).eliminatePartialMultifrontal(
            gtsam.Ordering(eliminate), gtsam.EliminateQR
        )
        summary = gtsam.NonlinearFactorGraph()
        for n in range(marginal.size()):
            linear = marginal.at(n)
            point = gtsam.Values()
            for key in linear.keys():
                copy_value(estimate, point, key)
            summary.add(gtsam.LinearContainerFactor(linear, point))
        self._prior = carried
        self._prior.push_back(summary)
        for key in self.live - kept_keys:  # leaving: their estimate starts the final solve
            self.initial.update(key, _value(estimate, key))
        self.live = kept_keys
        values = gtsam.Values()
        for key in kept_keys:
            copy_value(estimate, values, key)
        self._current = self.rebuilt
        self.isam = gtsam.ISAM2(self._current)
        self.theta = self.isam.getLinearizationPoint()
        start = gtsam.NonlinearFactorGraph()
        start.push_back(summary)
        start.push_back(newer)  # holds the carried factors too
        self._updates = []
        self._update(start, values)
        # The frames' own factors are kept only for the next rebuild's split.
        self._frames = [(i, g) for (i, _), g in zip(kept, kept_graphs, strict=True)]

    def drop_landmarks(self, keys: set[int]) -> None:
        """Leave the landmarks ``keys`` (rejected tracks) and all their factors out of the
        final solve."""
        keys = keys - self.store.dropped
        if not keys:
            return
        self.store.drop_landmarks(keys)
        for key in keys:
            self.live.discard(key)  # not handed over by the online solver either
            if self.initial.exists(key):
                self.initial.erase(key)
        self._result = None

    def values(self) -> gtsam.Values:
        """The optimum of the graph so far (solved once, then kept until the next frame)."""
        if self._result is None:
            self._result, self.moves = stored_optimum(
                self.store,
                self.initial,
                self.isam,
                self.live,
                chunk=self.chunk,
                overlap=self.overlap,
                max_iterations=self.max_iterations,
            )
        return self._result

    def final(self, indices: Sequence[int], *, marginals: bool = True) -> Iterator[FrameValues]:
        values = self.values()
        yield from final_states(
            self.store, values, indices, marginals=self.compute_covariance and marginals
        )


def drop_landmarks(backend: Backend, keys: set[int]) -> None:
    """Leave the landmarks ``keys`` (rejected tracks) and every factor on them out of the
    final solve of ``backend`` (nothing for the fixed-lag one: its frames are final)."""
    if isinstance(backend, WindowIsam2Backend):
        backend.drop_landmarks(keys)
    if not isinstance(backend, BatchBackend):
        return
    kept = gtsam.NonlinearFactorGraph()
    for i in range(backend.graph.size()):
        factor = backend.graph.at(i)
        if factor is not None and not keys.intersection(factor.keys()):
            kept.add(factor)
    for key in keys:
        if backend.initial.exists(key):
            backend.initial.erase(key)
    backend.graph = kept
    backend._result = None


def _value(source: gtsam.Values, key: int) -> object:
    kind = gtsam.Symbol(key).chr()
    if kind == ord("x"):
        return source.atPose3(key)
    if kind == _LANDMARK:
        return source.atPoint3(key)
    return source.atVector(key)


def copy_value(source: gtsam.Values, target: gtsam.Values, key: int) -> None:
    """Insert ``source``'s value of ``key`` (X pose, L landmark or V twist) into ``target``."""
    target.insert(key, _value(source, key))


def _window(backend: Backend, frames: np.ndarray) -> tuple[int, int] | None:
    """Positions [first, stop) of the frames around a track's frames (indices) in a window
    back end's store ((0, 0) for the batch back end: its whole graph); None when that is
    more than one chunk of the final solve (too costly: :func:`confirm_off_plane`)."""
    if isinstance(backend, BatchBackend):
        return 0, 0
    if not isinstance(backend, WindowIsam2Backend):
        return None
    places = np.searchsorted(backend.store.indices(), frames)
    first = max(0, int(places.min()) - TRACK_WINDOW_MARGIN)
    stop = min(len(backend.store), int(places.max()) + 1 + TRACK_WINDOW_MARGIN)
    return (first, stop) if stop - first <= backend.chunk else None


def _track_graph(
    backend: Backend, window: tuple[int, int], dropped: set[int]
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
    """The graph of the frames at positions ``window`` (:func:`_window`) without the
    landmarks ``dropped``, its optimum and the keys held (the frames beyond)."""
    if isinstance(backend, BatchBackend):
        graph, values, held = backend.graph, backend.values(), []
    else:
        store = backend.store  # type: ignore[attr-defined]
        indices = store.indices()
        first, stop = window
        graph, touched = store.graph(first, stop)
        outside = [*indices[touched.start : first].tolist(), *indices[stop : touched.stop].tolist()]
        held = [s(k) for k in outside for s in ((X, V, A) if store.rates else (X, V))]
        for key in set(graph.keyVector()).intersection(store.landmarks):
            for factor in store.landmarks[key]:
                graph.add(factor)
        values = backend.values()
    kept = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if factor is not None and not dropped.intersection(factor.keys()):
            kept.add(factor)
    window_values = gtsam.Values()
    for key in kept.keyVector():
        copy_value(values, window_values, key)
    if dropped.intersection(graph.keyVector()):  # no longer at its optimum
        window_values, _ = levenberg_marquardt(kept, window_values, fixed=held)
    return kept, window_values, held


def confirm_off_plane(
    backend: Backend,
    candidates: Sequence[int],
    observations: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    plane_noise: gtsam.noiseModel.Base,
    threshold: float,
) -> list[int]:
    """The landmarks of ``candidates`` (failing the test at fixed poses) that also fail it
    with the poses uncertain (:func:`~hvo_graph.estimators.plane_tracks.graph_statistic`
    above ``threshold``), each in the graph of its frames and ``TRACK_WINDOW_MARGIN``
    frames either side at the final optimum. One at a time, the largest statistic first:
    a track found off the plane leaves the graph (re-solved) before the tracks whose
    graph it was in are tested again, so its pull on the poses does not count against
    them. A track spanning more frames than a chunk of the final solve, or whose window's
    system GTSAM finds indeterminate, keeps the fixed-pose verdict.

    Args:
        backend: the batch or "isam2" back end, its graph complete.
        candidates: landmark keys.
        observations: (frame index (N,), landmark key (N,), m (N, 2), sigma (N,)) of
            every observation.
        plane_noise: the noise model of the plane prior; threshold: chi^2 (1 dof).
    Returns:
        The landmarks off the plane, in the order found.
    """
    frames, keys, m, sigma = observations
    rows = {key: np.flatnonzero(keys == key) for key in candidates}
    windows = {key: _window(backend, frames[rows[key]]) for key in candidates}
    failed = [key for key in candidates if windows[key] is None]
    remaining = [key for key in candidates if windows[key] is not None]
    statistics: dict[int, float] = {}  # kept until a track found off the plane is in its graph
    seen: dict[int, set[int]] = {}  # the keys of each candidate's graph
    while remaining:
        for key in remaining:
            if key in statistics:
                continue
            try:
                graph, values, held = _track_graph(backend, windows[key], set(failed))  # type: ignore[arg-type]
                seen[key] = set(graph.keyVector())
                start = np.asarray(values.atPoint3(key), dtype=float)
                r = rows[key]
                statistics[key] = graph_statistic(
                    graph, values, frames[r], m[r], sigma[r], plane_noise, start, held=held
                )
            except RuntimeError:  # GTSAM: the window's system is indeterminate (a landmark
                seen[key] = set()  # seen only from held frames): the fixed-pose verdict
                statistics[key] = np.inf
        worst = max(remaining, key=statistics.__getitem__)
        if statistics[worst] <= threshold:
            break
        failed.append(worst)
        remaining.remove(worst)
        for key in remaining:
            if worst in seen[key]:
                statistics.pop(key)
    return failed
