"""Levenberg-Marquardt on a landmark graph in bounded memory: each linear system solved
chunk by chunk.

The tightly coupled smoother's graph is a chain of frames (X(k), V(k): motion
factors between neighbours) plus landmarks L(j) that frames far apart observe
(a point in view for the whole sequence: every frame). Block Gauss-Seidel over
chunks of frames (:func:`~hvo_graph.estimators.factor_store.solve_in_chunks`)
does not fit it: moving every landmark and every frame together costs almost
nothing (only the first frame is anchored), and alternating between them
converges very slowly. Here each Levenberg-Marquardt iteration is the one of
:func:`~hvo_graph.estimators.least_squares.levenberg_marquardt` on the whole
graph (the same damping, acceptance and stopping rule, so the same optimum; a
step may also be extrapolated, :func:`chunked_levenberg_marquardt`), with its
linear system solved in two passes over chunks of frames:

- forward: a chunk's factors (those whose newest frame is in it) linearized at
  the current values, added to the factor carried from the previous chunk, and
  its frames (all but the last, which the next motion factor touches) and the
  landmarks no later frame observes eliminated in time order (GTSAM's
  default ``EliminatePreferCholesky``, as the whole-graph solve: QR's conditionals keep
  every row of the factors eliminated, ~20 times the memory with 20 points per
  frame); the remaining Gaussian factor,
  on that last frame and the landmarks still observed, is carried on (and kept:
  (3 L + 12)^2 numbers for L such landmarks);
- backward: the last chunk is solved outright; then each earlier chunk is
  linearized and eliminated again from its kept incoming factor, and
  back-substituted given the solution of what it was conditioned on.

Memory: one chunk's linearized factors and conditionals, the carried factors,
and the step (12 numbers per frame); the cost is about two linear solves of
the whole graph per iteration.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

if TYPE_CHECKING:
    from hvo_graph.estimators.factor_store import FactorStore

__all__ = ["chunked_levenberg_marquardt"]

_POSE, _LANDMARK = ord("x"), ord("l")

#: Factors a solve keeps (with their linearization and conditionals within a step)
#: instead of rebuilding them at every pass: those of the first chunks of a long
#: sequence, all of a short one (two per frame and one per observation; 10,000
#: frames of 4 points, ~0.1 GB).
CACHED_FACTORS: int = 60000

#: Two consecutive steps this aligned (cosine) make the next one tried extrapolated.
EXTRAPOLATE_COSINE: float = 0.95

#: The extrapolation is tried only for steps shrinking at least this fast (1 / (1 - rho)
#: up to 20).
MAX_RATIO: float = 0.95


class _Chunks:
    """The chunks of a store's graph and their linear systems at some values."""

    def __init__(self, store: FactorStore, chunk: int) -> None:
        self.store = store
        self.indices = store.indices()
        total = len(self.indices)
        self.ranges = [(first, min(first + chunk, total)) for first in range(0, total, chunk)]
        # The factors (and their linearization, within a step) of the first chunks, kept:
        # rebuilt only beyond CACHED_FACTORS (memory bounded; short sequences: no rebuild).
        self.cached, kept = 0, 0
        for first, stop in self.ranges:
            kept += 2 * (stop - first) + store.observations(first, stop)
            if kept > CACHED_FACTORS:
                break
            self.cached += 1
        self.graphs: dict[int, gtsam.NonlinearFactorGraph] = {}
        self.linearized: dict[int, gtsam.GaussianFactorGraph] = {}
        last = store.last_observed()  # landmark -> position of its last observation
        self.leaving: list[list[int]] = [[] for _ in self.ranges]
        for key in store.landmarks:
            self.leaving[min(last.get(key, 0) // chunk, len(self.ranges) - 1)].append(key)
        self.dims = {key: 3 for key in store.landmarks}
        # The cached chunks' values at the current iterate, and moved by the last step
        # (per multiple tried): an accepted step's are the next iterate's, so the values
        # are not picked out again key by key at every step.
        self.subsets: dict[int, gtsam.Values] = {}
        self.moved: dict[int, dict[float, gtsam.Values]] = {}

    def accept(self, scale: float) -> None:
        """The last step was taken, times ``scale``: its moved values are the new iterate's."""
        self.subsets = {c: moved[scale] for c, moved in self.moved.items()}

    def _error(
        self,
        c: int,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        delta: gtsam.VectorValues,
        scales: tuple[float, ...],
    ) -> np.ndarray:
        """Chunk ``c``'s error after the step ``delta`` times each of ``scales``."""
        subset = self.subsets.get(c)
        if subset is None:
            subset = _subset(values, graph)
        errors, moved = _graph_error(graph, subset, delta, scales)
        if c < self.cached:
            self.moved[c] = dict(zip(scales, moved, strict=True))
        return errors

    def error(self, values: gtsam.Values) -> float:
        """The whole graph's error at ``values``, one chunk's factors at a time."""
        return sum(self.graph(c).error(values) for c in range(len(self.ranges)))

    def graph(self, c: int) -> gtsam.NonlinearFactorGraph:
        """Chunk ``c``'s factors (those whose newest frame is in it; in the first chunk,
        the landmarks' own factors too). The last chunk's are kept too: every step builds
        them (their solve ends the forward pass), so keeping them adds one chunk's factors."""
        graph = self.graphs.get(c)
        if graph is None:
            first, stop = self.ranges[c]
            graph = self.store.graph(first, stop, newest=True)[0]
            if c == 0:
                graph.push_back(self.store.landmark_graph())
            if c < self.cached or c == len(self.ranges) - 1:
                self.graphs[c] = graph
        return graph

    def linear(
        self, c: int, values: gtsam.Values, root: float
    ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.GaussianFactorGraph]:
        """Chunk ``c``'s factors, and them linearized at ``values`` with the damping
        sqrt(lambda) I on its frames (in the first chunk: with the landmarks' own factors
        and damping too)."""
        first, stop = self.ranges[c]
        graph = self.graph(c)
        linear = self.linearized.pop(c, None)  # kept from the forward pass
        if linear is None:
            linear = graph.linearize(values)
            if c < self.cached:
                self.linearized[c] = linear
        damped = gtsam.GaussianFactorGraph()  # the kept linearization stays undamped
        damped.push_back(linear)
        linear = damped
        damping, zeros, unit = root * np.eye(6), np.zeros(6), gtsam.noiseModel.Unit.Create(6)
        for k in self.indices[first:stop].tolist():
            linear.add(X(k), damping, zeros, unit)
            linear.add(V(k), damping, zeros, unit)
        if c == 0:
            damping, zeros, unit = root * np.eye(3), np.zeros(3), gtsam.noiseModel.Unit.Create(3)
            for key in self.store.landmarks:
                linear.add(key, damping, zeros, unit)
        return graph, linear

    def ordering(self, c: int, *, keep_last: bool) -> gtsam.Ordering:
        """Chunk ``c``'s frames in time order (from the previous chunk's last), then the
        landmarks it is the last to observe."""
        first, stop = self.ranges[c]
        ordering = gtsam.Ordering()
        for k in self.indices[max(first - 1, 0) : stop - 1 if keep_last else stop].tolist():
            ordering.push_back(X(k))
            ordering.push_back(V(k))
        for key in self.leaving[c]:
            ordering.push_back(key)
        return ordering

    def step(self, values: gtsam.Values, lam: float, scale: float = 1.0) -> _Step:
        """The damped Gauss-Newton step at ``values`` (forward, then backward pass), and the
        graph's error after it and, for ``scale`` != 1, after it times ``scale``."""
        root = float(np.sqrt(lam))
        self.linearized.clear()
        self.moved = {}
        incoming = []
        nets: dict[int, gtsam.GaussianBayesNet] = {}
        parents: dict[int, list[int]] = {}
        carried = gtsam.GaussianFactorGraph()
        last = len(self.ranges) - 1
        for c in range(last):
            incoming.append(carried)
            graph = gtsam.GaussianFactorGraph()
            graph.push_back(carried)
            graph.push_back(self.linear(c, values, root)[1])
            ordering = self.ordering(c, keep_last=True)
            if c < self.cached:  # its conditionals kept: the backward pass only substitutes
                nets[c], carried = graph.eliminatePartialSequential(ordering)
                parents[c] = list(carried.keyVector())
            else:
                _, carried = graph.eliminatePartialMultifrontal(ordering)
        nonlinear, linear = self.linear(last, values, root)
        linear.push_back(carried)
        delta = linear.optimize(self.ordering(last, keep_last=False))
        scales = (1.0,) if scale == 1.0 else (1.0, scale)
        errors = self._error(last, nonlinear, values, delta, scales)
        for c in range(last - 1, -1, -1):
            ordering = self.ordering(c, keep_last=True)
            eliminated = [ordering.at(n) for n in range(ordering.size())]
            if c in nets:
                given = gtsam.VectorValues()
                for key in parents[c]:  # all solved: they are eliminated after the chunk
                    given.insert(key, delta.at(key))
                solved = nets.pop(c).optimize(given)
                nonlinear = self.graph(c)
            else:
                nonlinear, linear = self.linear(c, values, root)
                linear.push_back(incoming[c])
                net, remaining = linear.eliminatePartialSequential(ordering)
                given = gtsam.VectorValues()
                for key in remaining.keyVector():  # solved: eliminated after the chunk
                    given.insert(key, delta.at(key))
                solved = net.optimize(given)
            for key in eliminated:
                delta.insert(key, solved.at(key))
            # Every variable of the chunk's factors is solved now: their error after the
            # step, while they are at hand (chunk 0's include the landmarks' own).
            errors += self._error(c, nonlinear, values, delta, scales)
        return _Step(delta, *errors)


class _Step:
    """A step ``delta``, the graph's error after it and after it extrapolated (its
    multiple, :func:`chunked_levenberg_marquardt`; None: not tried)."""

    def __init__(
        self, delta: gtsam.VectorValues, error: float, extrapolated: float | None = None
    ) -> None:
        self.delta, self.error, self.extrapolated = delta, float(error), extrapolated

    def vector(self) -> np.ndarray:
        """The step as one vector (keys in order)."""
        return self.delta.vector()


def _graph_error(
    graph: gtsam.NonlinearFactorGraph,
    subset: gtsam.Values,
    delta: gtsam.VectorValues,
    scales: tuple[float, ...],
) -> tuple[np.ndarray, list[gtsam.Values]]:
    """The error of ``graph`` at ``subset`` (the values of its keys) moved by ``delta`` times
    each of ``scales``, and the moved values."""
    errors, moved = [], []
    for scale in scales:
        step = delta
        if scale != 1.0:
            step = gtsam.VectorValues()
            for key in graph.keyVector():
                step.insert(key, scale * delta.at(key))
        moved.append(subset.retract(step))
        errors.append(graph.error(moved[-1]))
    return np.array(errors), moved


def _subset(values: gtsam.Values, graph: gtsam.NonlinearFactorGraph) -> gtsam.Values:
    """``values`` of the keys of ``graph``."""
    subset = gtsam.Values()
    for key in graph.keyVector():
        kind = gtsam.Symbol(key).chr()
        if kind == _POSE:
            subset.insert(key, values.atPose3(key))
        elif kind == _LANDMARK:
            subset.insert(key, values.atPoint3(key))
        else:
            subset.insert(key, values.atVector(key))
    return subset


def chunked_levenberg_marquardt(
    store: FactorStore,
    values: gtsam.Values,
    *,
    chunk: int,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-10,
    absolute_tolerance: float = 1e-12,
    initial_lambda: float = 1e-5,
) -> tuple[int, float]:
    """Move ``values`` (every frame's X, V and landmark's L) to the optimum of the store's
    graph by Levenberg-Marquardt, each linear system solved ``chunk`` frames at a time.

    The scheme, tolerances and defaults are those of
    :func:`~hvo_graph.estimators.least_squares.levenberg_marquardt` (module docstring),
    with one addition: when two consecutive steps point the same way (cosine above
    :data:`EXTRAPOLATE_COSINE`), the second shorter by a ratio rho < 1, the next step is
    also tried extrapolated, times 1 / (1 - rho) (the sum of the steps to come if they
    kept shrinking so), and taken so when its error is the lower. Why: the Huber loss of
    the projection factors is linearized by reweighting (iteratively reweighted least
    squares converges linearly), and on long runs the iterates creep along one global
    direction (30,000 frames of the paper's scenario: each step 0.63 times the previous).
    After an extrapolated step that loses to the plain one, none is tried again. A step
    is still taken only when it lowers the whole graph's error and the stopping rule is
    unchanged, so the optimum is the same.
    Returns (iterations used, the largest coordinate of any step taken).
    """
    chunks = _Chunks(store, chunk)
    largest = 0.0
    error = chunks.error(values)
    lam = initial_lambda
    current = values
    iterations = 0
    previous: np.ndarray | None = None  # the last step, when it was taken as computed
    scale, extrapolate = 1.0, True
    while iterations < max_iterations:
        iterations += 1
        while True:
            step = chunks.step(current, lam, scale)
            best = min(step.error, np.inf if step.extrapolated is None else step.extrapolated)
            if best <= error:
                lam = max(lam / 10.0, 1e-15)
                break
            lam *= 10.0
            if lam > 1e10:  # no descent direction left: converged as far as it goes
                step = None
                break
        if step is None:
            break
        vector = step.vector()
        if step.extrapolated is not None and step.extrapolated < step.error:
            taken, candidate_error, previous = scale, step.extrapolated, None
        else:
            # An extrapolation that lost: the creep is not along a line here (curved, as
            # from the window's estimates at 100,000 frames): no more tries (each costs
            # one more evaluation of the graph's error).
            extrapolate = extrapolate and step.extrapolated is None
            taken, candidate_error = 1.0, step.error
            scale = _extrapolation(previous, vector) if extrapolate else 1.0
            previous = vector
        if taken != 1.0:
            scale = 1.0
        chunks.accept(taken)
        current = current.retract(step.delta if taken == 1.0 else step.delta.scale(taken))
        largest = max(largest, taken * float(np.abs(vector).max()))
        decrease = error - candidate_error
        error = candidate_error
        if decrease <= relative_tolerance * error + absolute_tolerance:
            break
    values.update(current)
    return iterations, largest


def _extrapolation(previous: np.ndarray | None, vector: np.ndarray) -> float:
    """The multiple 1 / (1 - rho) for the next step when ``vector`` is ``previous`` shrunk
    by rho < 1 in about the same direction (1: no extrapolation)."""
    if previous is None:
        return 1.0
    # einsum, not BLAS (np.linalg.norm, @): OpenBLAS splits a dot this long (12 numbers
    # per frame) over threads, whose start-up took milliseconds per call on a loaded machine.
    inner, before, after = (
        float(np.einsum("i,i->", a, b))
        for a, b in ((previous, vector), (previous, previous), (vector, vector))
    )
    norms = math.sqrt(before) * math.sqrt(after)
    if norms == 0.0 or inner < EXTRAPOLATE_COSINE * norms:
        return 1.0
    ratio = math.sqrt(after) / math.sqrt(before)
    return 1.0 / (1.0 - ratio) if ratio < MAX_RATIO else 1.0
