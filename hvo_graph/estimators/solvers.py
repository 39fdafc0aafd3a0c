"""The back ends of the factor-graph smoother: ISAM2, batch Levenberg-Marquardt, fixed-lag.

:class:`~hvo_graph.estimators.smoother.FactorGraphSmoother` builds each frame's
factors and initial values and hands them to one back end (:class:`Backend`),
which owns the solver's state:

- :class:`Isam2Backend` (``"isam2"``, ``--method smoother``): one ISAM2 update
  per frame; the online estimate of frame k is the value right after its
  update, the final values the smoothed ones;
- :class:`BatchBackend` (``"batch"``): collects the graph and solves it with
  :func:`levenberg_marquardt` when the trajectory is asked for; its online
  estimates are the initial values (unfused);
- :class:`FixedLagBackend` (``"fixed-lag"``): GTSAM's
  ``IncrementalFixedLagSmoother`` with a window of ``lag`` seconds; a frame's
  final value is its value as it left the window (or its current value).

Speed note: the custom factors are Python callbacks that GTSAM hands the
solver's ``Values``. pybind11 copies a C++ ``Values`` into Python on every call
unless a Python object already wraps that instance, which would make every
frame O(number of frames). The ISAM2 back ends therefore keep a Python reference
to ISAM2's linearization point (``getLinearizationPoint()``), and the batch back
end runs its own Levenberg-Marquardt loop on Python-owned ``Values`` (GTSAM's
optimizer would copy the whole ``Values`` per factor: O(N^2)).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterator, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

#: The fixed-lag smoother marginalizes in blocks of lag / MARGINALIZATION_BLOCKS
#: seconds (frame timestamps are rounded down to the block), so its window holds
#: between lag and 1.1 lag seconds. Marginalizing at every frame made GTSAM's
#: update about three times as costly (IncrementalFixedLagSmoother re-orders and
#: re-eliminates the window at each marginalization).
MARGINALIZATION_BLOCKS: int = 10

#: A frame's values: (pose, twist, 12x12 covariance of [pose tangent; twist] or None).
FrameValues = tuple[gtsam.Pose3, np.ndarray, "np.ndarray | None"]


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    *,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-10,
    absolute_tolerance: float = 1e-12,
    initial_lambda: float = 1e-5,
) -> tuple[gtsam.Values, int]:
    """Minimize the graph's error with Levenberg-Marquardt (GTSAM's scheme, Python loop).

    Each iteration linearizes the graph at the current values (Gauss-Newton
    system J delta = -e), adds sqrt(lambda) I damping priors on every variable
    (GTSAM's default, non-diagonal damping), solves with GTSAM's multifrontal
    elimination, and retracts; a step that does not lower the error is retried
    with lambda x 10, an accepted one divides lambda by 10. Stops when the
    error decrease is below ``relative_tolerance * error + absolute_tolerance``.

    Why not ``gtsam.LevenbergMarquardtOptimizer``: its iterates are C++
    ``Values``, which pybind11 copies in full for every Python ``CustomFactor``
    callback, making one iteration O(N^2) in the number of frames (34 s for
    3,000 frames against 1 s here, where the iterates are Python-owned).

    Args:
        graph: the nonlinear factor graph.
        initial: initial values of every variable.
        max_iterations: most linearizations.
        relative_tolerance, absolute_tolerance: convergence test on the error decrease.
        initial_lambda: starting damping.
    Returns:
        (optimized values, iterations used).
    """
    values = gtsam.Values(initial)
    error = graph.error(values)
    dims = [(key, values.zeroVectors().at(key).size) for key in values.keys()]
    units = {d: gtsam.noiseModel.Unit.Create(d) for _, d in dims}
    eyes = {d: np.eye(d) for _, d in dims}
    lam = initial_lambda
    for iteration in range(1, max_iterations + 1):
        linear = graph.linearize(values)
        while True:
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(linear)
            root = math.sqrt(lam)
            for key, d in dims:
                damped.add(key, root * eyes[d], np.zeros(d), units[d])
            candidate = values.retract(damped.optimize())
            candidate_error = graph.error(candidate)
            if candidate_error <= error:
                lam = max(lam / 10.0, 1e-15)
                break
            lam *= 10.0
            if lam > 1e10:  # no descent direction left: converged as far as it goes
                return values, iteration
        decrease = error - candidate_error
        values, error = candidate, candidate_error
        if decrease <= relative_tolerance * error + absolute_tolerance:
            return values, iteration
    return values, max_iterations


def isam2_params(
    relinearize_threshold: float, relinearize_skip: int, *, find_unused_factor_slots: bool
) -> gtsam.ISAM2Params:
    """ISAM2's parameters: only the poses relinearize, checked in the touched cliques."""
    params = gtsam.ISAM2Params()
    # Only the poses need relinearizing: every factor is affine in the twists V with
    # constant Jacobians (motion: -dt/2 I; measured and random-walk twists: linear).
    thresholds = gtsam.ISAM2ThresholdMap()
    thresholds.insert(("x", np.full(6, relinearize_threshold)))
    thresholds.insert(("v", np.full(6, np.inf)))
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
    def final(self, indices: Sequence[int]) -> Iterator[FrameValues]:
        """The final values of the frames ``indices`` (every frame so far), in order."""


class Isam2Backend(Backend):
    """One ISAM2 update per frame."""

    solver = "isam2"

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

    def final(self, indices: Sequence[int]) -> Iterator[FrameValues]:
        values = self.isam.calculateBestEstimate()
        for index in indices:
            if index in self.frozen:
                yield self.frozen[index]
                continue
            cov = self.joint_covariance(index) if self.compute_covariance else None
            yield values.atPose3(X(index)), values.atVector(V(index)), cov


class FixedLagBackend(Isam2Backend):
    """GTSAM's incremental fixed-lag smoother over a window of ``lag`` seconds."""

    solver = "fixed-lag"

    def __init__(self, params: gtsam.ISAM2Params, lag: float, *, compute_covariance: bool) -> None:
        self.lag = lag
        # Stamps are multiples of the block and the lag is MARGINALIZATION_BLOCKS blocks:
        # half a block more keeps GTSAM's test "stamp < latest - lag" away from ties.
        self.smoother_lag = lag * (1.0 + 0.5 / MARGINALIZATION_BLOCKS)
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
        return math.floor(stamp_time / block + 1e-9) * block

    def _update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        index: int,
        stamp_time: float,
    ) -> None:
        stamp = self.stamp(stamp_time)
        self._freeze_leaving(stamp)
        self.smoother.update(graph, values, {X(index): stamp, V(index): stamp})
        self.window.append((index, stamp))
        self._collect_frozen()

    def _freeze_leaving(self, stamp: float) -> None:
        """Record the current estimate of every frame the coming update will marginalize.

        IncrementalFixedLagSmoother drops the variables with timestamp < (latest
        timestamp) - lag after adding the new factors. (Should a frame recorded
        here be kept after all, it is recorded again at the next update: see
        :meth:`_collect_frozen`.)
        """
        horizon = stamp - self.smoother_lag
        values: gtsam.Values | None = None
        for index, frame_stamp in self.window:
            if frame_stamp >= horizon:
                break
            if values is None:
                # A full back-substitution: the per-key estimates use ISAM2's wildfire-
                # limited delta, which can be stale far from the root, where these are.
                values = self.isam.calculateBestEstimate()
            cov = self.joint_covariance(index) if self.compute_covariance else None
            self.frozen[index] = (values.atPose3(X(index)), values.atVector(V(index)), cov)

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
        return (
            values.atPose3(X(index)),
            np.array(values.atVector(V(index)), dtype=float),
            None,
        )

    def values(self) -> gtsam.Values:
        """The optimum of the graph so far (solved once, then kept)."""
        if self._result is None:
            self._result, self.iterations = levenberg_marquardt(
                self.graph, self.initial, max_iterations=self.max_iterations
            )
        return self._result

    def final(self, indices: Sequence[int]) -> Iterator[FrameValues]:
        values = self.values()
        # One ISAM2 elimination at the optimum gives the joint marginals quickly
        # (gtsam.Marginals took O(N) per query here); its linearization point is
        # held (second item) so the custom factors are not handed copies.
        marginals: tuple[gtsam.ISAM2, gtsam.Values] | None = None
        if self.compute_covariance:
            isam = gtsam.ISAM2()
            marginals = (isam, isam.getLinearizationPoint())
            isam.update(self.graph, values)
        for index in indices:
            cov = None
            if marginals is not None:
                c = marginals[0].jointMarginalCovariance([X(index), V(index)]).fullMatrix()
                cov = _symmetric(c)
            yield values.atPose3(X(index)), values.atVector(V(index)), cov


def make_backend(
    solver: str,
    *,
    lag: float,
    relinearize_threshold: float,
    relinearize_skip: int,
    max_iterations: int,
    compute_covariance: bool,
) -> Backend:
    """The back end called ``solver`` ("isam2", "batch" or "fixed-lag"), options checked."""
    if solver == BatchBackend.solver:
        return BatchBackend(max_iterations=max_iterations, compute_covariance=compute_covariance)
    params = isam2_params(
        relinearize_threshold,
        relinearize_skip,
        find_unused_factor_slots=solver == FixedLagBackend.solver,
    )
    if solver == FixedLagBackend.solver:
        return FixedLagBackend(params, lag, compute_covariance=compute_covariance)
    return Isam2Backend(params, compute_covariance=compute_covariance)
