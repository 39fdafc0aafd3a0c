"""The back ends of the factor-graph smoother: ISAM2, batch Levenberg-Marquardt, fixed-lag.

:class:`~hvo_graph.estimators.smoother.FactorGraphSmoother` builds each frame's
factors and initial values and hands them to one back end (:class:`Backend`),
which owns the solver's state:

- :class:`Isam2Backend` (``"isam2"``, ``--method smoother``): one ISAM2 update
  per frame over a sliding window (older frames marginalized); the online
  estimate of frame k is the value right after its update, the final values
  the batch Levenberg-Marquardt optimum of the whole graph;
- :class:`BatchBackend` (``"batch"``): collects the graph and solves it with
  :func:`levenberg_marquardt` when the trajectory is asked for; its online
  estimates are the initial values (unfused);
- :class:`FixedLagBackend` (``"fixed-lag"``): GTSAM's
  ``IncrementalFixedLagSmoother`` with a window of ``lag`` seconds; a frame's
  final value is its value as it left the window (or its current value).

Speed note: pybind11 copies a C++ ``Values`` into every Python factor callback
unless a Python object already wraps it (O(frames) per call). The ISAM2 back ends
keep a reference to ISAM2's linearization point, and the batch back end runs its
own Levenberg-Marquardt loop on Python-owned ``Values`` (GTSAM's would be O(N^2)).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterator, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from hvo_graph.estimators.factor_store import (
    FactorStore,
    batch_marginals,
    copy_value,
    final_states,
    stored_optimum,
)
from hvo_graph.estimators.least_squares import levenberg_marquardt

#: The fixed-lag smoother marginalizes in blocks of lag / MARGINALIZATION_BLOCKS
#: seconds (timestamps rounded down to the block): a window of lag to 1.1 lag seconds.
#: Marginalizing at every frame made GTSAM's update about three times as costly.
MARGINALIZATION_BLOCKS: int = 10

#: Frames the default smoother ("isam2") keeps in its online window before
#: marginalizing them (2 s at 30 fps). Longer than any usual keyframe use or
#: twist interval, so the online estimates match one ISAM2 over the whole sequence.
ONLINE_WINDOW: int = 60

#: A frame's values: (pose, twist, 12x12 covariance of [pose tangent; twist] or None).
FrameValues = tuple[gtsam.Pose3, np.ndarray, "np.ndarray | None"]


def isam2_params(
    relinearize_threshold: float, relinearize_skip: int, *, find_unused_factor_slots: bool
) -> gtsam.ISAM2Params:
    """ISAM2's parameters: only the poses relinearize, checked in the touched cliques."""
    params = gtsam.ISAM2Params()
    # Only the poses trigger relinearizing: every factor is affine in V for given poses (the
    # motion prior's pose Jacobian moves with V only through J_r^-1(xi) V(k): second order).
    thresholds = gtsam.ISAM2ThresholdMap()
    thresholds.insert(("x", np.full(6, relinearize_threshold)))
    thresholds.insert(("v", np.full(6, np.inf)))
    thresholds.insert(("a", np.full(6, np.inf)))  # twist rates (white-noise jerk): linear too
    params.setRelinearizeThreshold(thresholds)
    params.relinearizeSkip = relinearize_skip
    # Check only the cliques touched by the update, not every variable (O(1) per frame).
    params.enablePartialRelinearizationCheck = True
    params.findUnusedFactorSlots = find_unused_factor_slots
    # QR, not Cholesky: the world prior (1e-6) and the broad first-twist prior (10) differ
    # by 1e14 in information; after frames without any measurement at the start, Cholesky
    # declared that well-posed system indeterminate. QR solves it (same results otherwise).
    params.setFactorization("QR")
    return params


def _symmetric(c: np.ndarray) -> np.ndarray:
    return 0.5 * (c + c.T)


class Backend(ABC):
    """What the smoother asks of a solver.

    Args:
        compute_covariance: also give the 12x12 marginal covariances.
    """

    #: The ``solver`` name of the back end.
    solver: str = ""
    #: Where the smoother also keeps every factor, compactly (by default: nowhere).
    store: FactorStore = FactorStore(None)
    #: ISAM2: whether frames go through the online window (else they are only stored).
    windowed: bool = True

    def __init__(self, *, compute_covariance: bool) -> None:
        self.compute_covariance = compute_covariance

    def in_graph(self, index: int) -> bool:
        """Whether X(index) is still a variable (always, except fixed-lag after it left)."""
        return True

    @abstractmethod
    def current_pose(self, index: int) -> gtsam.Pose3:
        """The current estimate of X(index), an earlier frame (keyframe references)."""

    @abstractmethod
    def add(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> FrameValues:
        """Add frame ``index``'s factors and initial values; its online estimate.

        ``stamp_time`` is the frame time relative to the first frame (seconds).
        """

    @abstractmethod
    def final(self, indices: Sequence[int], *, marginals: bool = True) -> Iterator[FrameValues]:
        """The final values of the frames ``indices`` (every frame so far), in order; with
        ``marginals`` (and ``compute_covariance``) their Bayesian marginals too."""


class IncrementalBackend(Backend):
    """One ISAM2 update per frame (the base of :class:`FixedLagBackend`)."""

    solver = ""

    def __init__(self, params: gtsam.ISAM2Params, *, compute_covariance: bool) -> None:
        super().__init__(compute_covariance=compute_covariance)
        self.isam = self._make_isam(params)
        # The Python wrapper of ISAM2's linearization point: while it lives, the custom
        # factors' callbacks receive it instead of a fresh copy (see the module docstring).
        self.theta = self.isam.getLinearizationPoint()
        #: index -> values of the frames that left the graph (fixed-lag).
        self.frozen: dict[int, FrameValues] = {}

    def _make_isam(self, params: gtsam.ISAM2Params) -> gtsam.ISAM2:
        return gtsam.ISAM2(params)

    def _update(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, index: int, stamp: float
    ) -> None:
        self.isam.update(graph, values)

    def current_pose(self, index: int) -> gtsam.Pose3:
        if index in self.frozen:
            return self.frozen[index][0]
        return self.isam.calculateEstimatePose3(X(index))

    def joint_covariance(self, index: int) -> np.ndarray:
        """The 12x12 marginal covariance of [X(index) tangent; V(index)]."""
        return _symmetric(self.isam.jointMarginalCovariance([X(index), V(index)]).fullMatrix())

    def add(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> FrameValues:
        self._update(graph, values, index, stamp_time)
        pose = self.isam.calculateEstimatePose3(X(index))
        twist = self.isam.calculateEstimateVector(V(index))
        return pose, twist, self.joint_covariance(index) if self.compute_covariance else None

    def final(self, indices: Sequence[int], *, marginals: bool = True) -> Iterator[FrameValues]:
        values = self.isam.calculateBestEstimate()
        for index in indices:
            if index in self.frozen:  # its values (and marginal) as it left the window
                yield self.frozen[index]
                continue
            wanted = self.compute_covariance and marginals
            cov = self.joint_covariance(index) if wanted else None
            yield values.atPose3(X(index)), values.atVector(V(index)), cov


class FixedLagBackend(IncrementalBackend):
    """GTSAM's incremental fixed-lag smoother over a window of ``lag`` seconds."""

    solver = "fixed-lag"

    def __init__(self, params: gtsam.ISAM2Params, lag: float, *, compute_covariance: bool) -> None:
        self.lag = lag
        # Stamps are multiples of the block and the lag is MARGINALIZATION_BLOCKS blocks:
        # half a block more keeps GTSAM's test "stamp < latest - lag" away from ties.
        self.smoother_lag = lag * (1.0 + 0.5 / MARGINALIZATION_BLOCKS)
        # Wildfire threshold 0: an estimate read back-substitutes the whole window, so frames
        # leaving it are read exactly per key (0.001 left them stale far from the root).
        params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.smoother_lag, params)
        #: (index, stamp) of the frames still in the window, oldest first.
        self.window: deque[tuple[int, float]] = deque()
        super().__init__(params, compute_covariance=compute_covariance)

    def _make_isam(self, params: gtsam.ISAM2Params) -> gtsam.ISAM2:
        return self.smoother.getISAM2()  # a reference to the smoother's own ISAM2

    def in_graph(self, index: int) -> bool:
        return index not in self.frozen

    def stamp(self, stamp_time: float) -> float:
        """The smoother timestamp of a time relative to the first frame, rounded down to
        a multiple of the block length lag / MARGINALIZATION_BLOCKS."""
        block = self.lag / MARGINALIZATION_BLOCKS
        # A frame due on a block boundary stays on it: wall-clock times (~1e9 s) keep only
        # ~1e-7 s of resolution, so times relative to the first frame round off by that much.
        return math.floor(stamp_time / block + 1e-4) * block

    def _update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> None:
        stamp = self.stamp(stamp_time)
        self._freeze_leaving(stamp)
        stamps = self._stamps(graph, index, stamp)
        stamps.update(dict.fromkeys(values.keys(), stamp))  # the twist rate A too
        self.smoother.update(graph, values, stamps)
        self.window.append((index, stamp))
        self._collect_frozen()

    def _stamps(self, graph: gtsam.NonlinearFactorGraph, index: int, t: float) -> dict:
        """The keys the new factors keep in the window, with their timestamp."""
        return {X(index): t, V(index): t}

    def _freeze_leaving(self, stamp: float) -> None:
        """Record the current estimate of every frame the coming update will marginalize.

        IncrementalFixedLagSmoother drops the variables with timestamp < (latest
        timestamp) - lag after adding the new factors. (Should a frame recorded
        here be kept after all, it is recorded again at the next update: see
        :meth:`_collect_frozen`.)
        """
        horizon = stamp - self.smoother_lag
        for index, frame_stamp in self.window:
            if frame_stamp >= horizon:
                break
            pose = self.isam.calculateEstimatePose3(X(index))  # exact: see __init__
            twist = self.isam.calculateEstimateVector(V(index))
            cov = self.joint_covariance(index) if self.compute_covariance else None
            self.frozen[index] = (pose, twist, cov)

    def _collect_frozen(self) -> None:
        """Drop the marginalized frames from the window; forget records of frames kept."""
        while self.window:
            index = self.window[0][0]
            if self.isam.valueExists(X(index)):
                break
            self.window.popleft()
        for index, _ in self.window:
            if index not in self.frozen:
                break
            del self.frozen[index]


class BatchBackend(Backend):
    """The whole graph, solved by :func:`levenberg_marquardt` when asked for."""

    solver = "batch"

    def __init__(self, *, max_iterations: int, compute_covariance: bool) -> None:
        super().__init__(compute_covariance=compute_covariance)
        self.max_iterations = max_iterations
        self.graph = gtsam.NonlinearFactorGraph()
        self.initial = gtsam.Values()
        self._result: gtsam.Values | None = None
        #: Levenberg-Marquardt iterations of the last solve.
        self.iterations = 0

    def current_pose(self, index: int) -> gtsam.Pose3:
        return self.initial.atPose3(X(index))

    def add(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> FrameValues:
        self.graph.push_back(graph)
        self.initial.insert(values)
        self._result = None
        twist = np.array(values.atVector(V(index)), dtype=float)
        return values.atPose3(X(index)), twist, None

    def values(self) -> gtsam.Values:
        """The optimum of the graph so far (solved once, then kept)."""
        if self._result is None:
            self._result, self.iterations = levenberg_marquardt(
                self.graph, self.initial, max_iterations=self.max_iterations
            )
        return self._result

    def final(self, indices: Sequence[int], *, marginals: bool = True) -> Iterator[FrameValues]:
        values = self.values()
        if self.compute_covariance and marginals:
            yield from batch_marginals(self.graph, values, indices)
            return
        for index in indices:
            yield values.atPose3(X(index)), values.atVector(V(index)), None


class Isam2Backend(Backend):
    """ISAM2 over a sliding window for the online estimates, batch LM for the final ones.

    Online: GTSAM's ``IncrementalFixedLagSmoother`` keeps the last ``window``
    frames (plus any earlier variable a new factor still touches: a keyframe in
    use stays in the window); older frames are marginalized into a linear prior
    on the window, so the estimate of the newest frame is the causal (filtered)
    estimate of every measurement so far, and each update costs the same at
    frame 1,000 and at frame 100,000. (One ISAM2 holding the whole sequence
    costs O(number of frames) per update in GTSAM 4.3: each update destroys a
    temporary Bayes tree whose destructor visits every clique;
    docs/performance.md has a reproduction.)

    Final (:meth:`final`): the whole graph, the same factors as the
    ``"batch"`` solver's, kept in compact arrays (:attr:`store`, filled by the
    smoother) and solved from the window's estimates (each frame's value as it
    left the window) chunk by chunk until it is stationary
    (:func:`~hvo_graph.estimators.factor_store.solve_in_chunks`): the batch
    optimum, in memory bounded by one chunk's solve.

    A factor that touches a variable already marginalized (a keyframe first
    used after it left the window, a twist interval reaching that far back)
    enters the window conditioned on that variable's estimate (linearized
    there, its columns dropped); the final solve uses it unchanged.
    """

    solver = "isam2"

    def __init__(
        self,
        params: gtsam.ISAM2Params,
        *,
        window: int,
        max_iterations: int,
        compute_covariance: bool,
        pose_noise: Callable[[np.ndarray], gtsam.noiseModel.Base],
    ) -> None:
        super().__init__(compute_covariance=compute_covariance)
        self.max_iterations = max_iterations
        #: Every factor of the sequence, for the final solve (the smoother adds them).
        self.store = FactorStore(pose_noise)
        #: Each frame's value as it left the window (the final solve's initial values).
        self.initial = gtsam.Values()
        self._result: gtsam.Values | None = None
        #: The largest move of each sweep of the last final solve (solve_in_chunks).
        self.moves: list[float] = []
        #: Marginalization block (frames): stamps are frame counts rounded down to it.
        self.block = max(1, window // MARGINALIZATION_BLOCKS)
        # Half a block more than the window keeps "stamp < latest - lag" away from ties.
        self.smoother_lag = float(window) + 0.5 * self.block
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.smoother_lag, params)
        self.isam = self.smoother.getISAM2()
        # Held so the custom factors' callbacks are not handed copies (module docstring).
        self.theta = self.isam.getLinearizationPoint()
        #: key -> stamp of every variable in the window.
        self.live: dict[int, float] = {}
        self._count = 0

    def current_pose(self, index: int) -> gtsam.Pose3:
        if X(index) in self.live:
            return self.isam.calculateEstimatePose3(X(index))
        return self.initial.atPose3(X(index))  # its estimate as it left the window

    def add(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> FrameValues:
        self.initial.insert(values)
        self._result = None
        if not self.windowed:  # the initial values are the measurements (as batch's)
            return values.atPose3(X(index)), np.asarray(values.atVector(V(index))), None
        stamp = float(self._count // self.block * self.block)
        self._count += 1
        stamps = dict.fromkeys(values.keys(), stamp)  # the frame's X, V (and A)
        online = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            factor = graph.at(i)
            keys = list(factor.keys())
            gone = [key for key in keys if key not in self.live and not values.exists(key)]
            if gone:
                factor = self._conditioned(factor, keys, values)
            else:  # every variable it touches stays in the window with the newest frame
                stamps.update((key, stamp) for key in keys)
            if factor is not None:
                online.add(factor)
        leaving = self._record_leaving(stamp)
        self.smoother.update(online, values, stamps)
        self.live.update(stamps)
        for key in leaving:
            if not self.isam.valueExists(key):
                del self.live[key]
        pose = self.isam.calculateEstimatePose3(X(index))
        twist = self.isam.calculateEstimateVector(V(index))
        return pose, twist, self.joint_covariance(index) if self.compute_covariance else None

    def joint_covariance(self, index: int) -> np.ndarray:
        """The 12x12 marginal of [X(index) tangent; V(index)] in the window (with its prior)."""
        return _symmetric(self.isam.jointMarginalCovariance([X(index), V(index)]).fullMatrix())

    def _record_leaving(self, stamp: float) -> list[int]:
        """Keep the estimate of every variable the coming update may marginalize
        (as the final solve's initial value); return their keys."""
        horizon = stamp - self.smoother_lag
        leaving = [key for key, s in self.live.items() if s < horizon]
        if leaving:
            # A full back-substitution: the per-key estimates use ISAM2's wildfire-
            # limited delta, which can be stale far from the root, where these are.
            estimate = self.isam.calculateBestEstimate()
            for key in leaving:
                copy_value(estimate, self.initial, key)
        return leaving

    def _conditioned(
        self, factor: gtsam.NonlinearFactor, keys: list[int], values: gtsam.Values
    ) -> gtsam.NonlinearFactor | None:
        """The factor with its marginalized variables held at their estimates: linearized
        at the current estimates, their Jacobian columns dropped (all variables are 6-D)."""
        point = gtsam.Values()
        kept = gtsam.Values()
        for key in keys:
            if values.exists(key):
                source = values
            elif key in self.live:
                source = self.isam.calculateEstimate()
            else:
                source = self.initial
            copy_value(source, point, key)
            if key in self.live or values.exists(key):
                copy_value(source, kept, key)
        if kept.size() == 0:
            return None
        A, b = gtsam.JacobianFactor(factor.linearize(point)).jacobian()
        blocks = [(key, A[:, 6 * j : 6 * j + 6]) for j, key in enumerate(keys) if kept.exists(key)]
        unit = gtsam.noiseModel.Unit.Create(len(b))
        if len(blocks) == 1:
            linear = gtsam.JacobianFactor(*blocks[0], b, unit)
        else:
            (k1, A1), (k2, A2), *rest = blocks
            if rest:
                linear = gtsam.JacobianFactor(k1, A1, k2, A2, *rest[0], b, unit)
            else:
                linear = gtsam.JacobianFactor(k1, A1, k2, A2, b, unit)
        return gtsam.LinearContainerFactor(linear, kept)

    def values(self) -> gtsam.Values:
        """The optimum of the graph so far (solved once, then kept until the next frame)."""
        if self._result is None:
            self._result, self.moves = stored_optimum(
                self.store, self.initial, self.isam, self.live, max_iterations=self.max_iterations
            )
        return self._result

    def final(self, indices: Sequence[int], *, marginals: bool = True) -> Iterator[FrameValues]:
        values = self.values()
        yield from final_states(
            self.store, values, indices, marginals=self.compute_covariance and marginals
        )


def make_backend(
    solver: str,
    *,
    lag: float,
    relinearize_threshold: float,
    relinearize_skip: int,
    max_iterations: int,
    compute_covariance: bool,
    pose_noise: Callable[[np.ndarray], gtsam.noiseModel.Base],
) -> Backend:
    """The back end called ``solver`` ("isam2", "batch" or "fixed-lag"), options checked;
    ``pose_noise``: the noise model of an H_d pose factor from its covariance."""
    if solver == BatchBackend.solver:
        return BatchBackend(max_iterations=max_iterations, compute_covariance=compute_covariance)
    params = isam2_params(
        relinearize_threshold,
        relinearize_skip,
        find_unused_factor_slots=True,  # both keep a window: reuse the freed slots
    )
    if solver == FixedLagBackend.solver:
        return FixedLagBackend(params, lag, compute_covariance=compute_covariance)
    return Isam2Backend(
        params,
        window=ONLINE_WINDOW,
        max_iterations=max_iterations,
        compute_covariance=compute_covariance,
        pose_noise=pose_noise,
    )
