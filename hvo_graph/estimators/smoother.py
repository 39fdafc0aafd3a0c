"""The factor-graph smoother: H_d poses and H_c twists fused in GTSAM (ISAM2 by default).

Variables per frame k (keys from ``gtsam.symbol_shorthand``): X(k), the pose
T_wc (``gtsam.Pose3``), and V(k), the body twist [w; v] (6-vector, contract
sign: d/dt T_wc = T_wc [w; v]^). Factors (docs/smoother.md has the equations
and the reasons for every default):

- world prior: X(k0) = I at the first frame k0 (W = the first camera frame),
  standard deviation ``world_sigma``; a weak zero-mean prior on V(k0)
  (``initial_twist_sigma``) so the first update is well posed;
- pose measurement from the discrete homography H_d: with reference 0 (W) a
  ``PriorFactorPose3`` on X(k); with a keyframe reference r a
  ``BetweenFactorPose3`` X(r) -> X(k); noise ``Gaussian.Covariance`` of the
  front end's full 6x6 covariance (tangent [rot; trans], right perturbation);
- twist measurement from the continuous homography H_c over [t - dt/2,
  t + dt/2]: :func:`~hvo_graph.estimators.factors.mean_velocity_factor` on the
  time average of the piecewise-linear twist ((V(k-1) + V(k)) / 2 for the usual
  interval), full covariance;
- motion: :func:`~hvo_graph.estimators.factors.motion_factor`,
  Log(X(k-1)^-1 X(k)) = dt (V(k-1) + V(k)) / 2 with the Brownian-bridge
  covariance Q dt^3 / 12 of the white-noise-acceleration model;
- twist random walk: ``BetweenFactorVector`` V(k-1) -> V(k), zero mean,
  covariance Q dt; Q = diag(s_w^2 I_3, s_v^2 I_3) from ``acceleration_sigma``;
- optional robust loss (Huber or Cauchy) on the two measurement factors.

Solvers (one :class:`~hvo_graph.estimators.base.Estimator` interface):

- ``"isam2"`` (``--method smoother``): one ISAM2 update per frame; the online
  estimate of frame k is the value right after its update, :meth:`trajectory`
  the final (smoothed) values;
- ``"batch"``: Levenberg-Marquardt over the whole graph when
  :meth:`trajectory` is called; its online estimates are the initial values
  (the frame's own measurement, or the motion-model prediction), i.e. unfused;
- ``"fixed-lag"``: GTSAM's ``IncrementalFixedLagSmoother`` with a window of
  ``lag`` seconds; :meth:`trajectory` gives each frame's value as it left the
  window (or its current value).

Speed note: the two custom factors are Python callbacks that GTSAM hands the
solver's ``Values``. pybind11 copies a C++ ``Values`` into Python on every call
unless a Python object already wraps that instance, which would make every
frame O(number of frames). The ISAM2 solvers therefore keep a Python reference
to ISAM2's linearization point (``getLinearizationPoint()``), and the batch
solver runs its own Levenberg-Marquardt loop on Python-owned ``Values``
(GTSAM's optimizer would copy the whole ``Values`` per factor: O(N^2)).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from hvo_graph.errors import InputError, as_covariance, as_integer, as_number, as_rotation
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.factors import (
    _mean_velocity_factor,
    interval_weights,
    keyframe_between_factor,
    motion_factor,
    replace_keyframe_plane,
)
from hvo_graph.estimators.process_noise import (
    DEFAULT_ACCELERATION_SIGMA,
    bridge_variance,
    twist_spectral_density,
    velocity_variance,
)
from hvo_graph.estimators.process_noise import acceleration_sigma as check_acceleration_sigma
from hvo_graph.estimators.registry import ROBUST_LOSSES, SOLVERS
from hvo_graph.types import (
    FrameMeasurement,
    PoseMeasurement,
    StateEstimate,
    Trajectory,
    VelocityMeasurement,
)

__all__ = [
    "DEFAULT_ACCELERATION_SIGMA",
    "DEFAULT_INITIAL_TWIST_SIGMA",
    "DEFAULT_RELINEARIZE_SKIP",
    "DEFAULT_RELINEARIZE_THRESHOLD",
    "DEFAULT_ROBUST_THRESHOLD",
    "DEFAULT_WORLD_SIGMA",
    "ROBUST_LOSSES",
    "SOLVERS",
    "BatchSmoother",
    "FactorGraphSmoother",
    "FixedLagSmoother",
    "levenberg_marquardt",
]

#: Default robust threshold on the whitened residual norm (GTSAM applies the
#: M-estimator to sqrt(e^T Sigma^-1 e)): sqrt of the 95 % quantile of chi^2 with
#: 6 degrees of freedom, so an inlier 6-vector is down-weighted 5 % of the time.
DEFAULT_ROBUST_THRESHOLD: float = math.sqrt(12.591587243743977)

#: Standard deviation (rad, m) of the prior X(k0) = I that defines the world frame.
DEFAULT_WORLD_SIGMA: float = 1e-6

#: Standard deviation (rad/s, m/s) of the zero-mean prior on the first twist V(k0).
DEFAULT_INITIAL_TWIST_SIGMA: float = 10.0

#: ISAM2 relinearizes a pose whose accumulated delta exceeds this (rad, m). The
#: initial values are the measurements themselves, within noise (~2 cm, 0.5 deg)
#: of the optimum, so the linearization error O(delta^2) stays far below the
#: noise; on the paper scenario the final ISAM2 poses stay within 0.25 mm of the
#: batch Levenberg-Marquardt optimum (docs/smoother.md).
DEFAULT_RELINEARIZE_THRESHOLD: float = 0.05

#: ISAM2 checks for relinearization every this many updates (GTSAM's default).
DEFAULT_RELINEARIZE_SKIP: int = 10

#: The fixed-lag smoother marginalizes in blocks of lag / MARGINALIZATION_BLOCKS
#: seconds (frame timestamps are rounded down to the block), so its window holds
#: between lag and 1.1 lag seconds. Marginalizing at every frame made GTSAM's
#: update about three times as costly (IncrementalFixedLagSmoother re-orders and
#: re-eliminates the window at each marginalization).
MARGINALIZATION_BLOCKS: int = 10

_ZERO6 = np.zeros(6)


def _checked_covariance(matrix: object, name: str) -> np.ndarray:
    """A (6, 6) symmetric positive definite covariance, symmetrized, or InputError."""
    c = as_covariance(matrix, name, 6)
    return 0.5 * (c + c.T)


def _checked_pose(pose: PoseMeasurement, k: int) -> tuple[gtsam.Pose3, np.ndarray, int]:
    name = f"frame {k}: pose"
    R = as_rotation(pose.rotation, f"{name}.rotation")
    p = np.asarray(pose.position, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"{name}.position: expected a finite (3,) vector, got shape {p.shape}")
    cov = _checked_covariance(pose.covariance, f"{name}.covariance")
    ref = as_integer(pose.reference, f"{name}.reference", 0, what="a frame index")
    if ref != 0 and ref >= k:
        raise InputError(f"{name}.reference: expected an earlier frame than {k}, got {ref}")
    return gtsam.Pose3(gtsam.Rot3(R), p), cov, int(ref)


def _checked_velocity(velocity: VelocityMeasurement, k: int) -> tuple[np.ndarray, np.ndarray]:
    name = f"frame {k}: velocity"
    z = np.asarray(velocity.twist, dtype=float)
    if z.shape != (6,) or not np.all(np.isfinite(z)):
        raise InputError(f"{name}.twist: expected a finite (6,) vector, got shape {z.shape}")
    cov = _checked_covariance(velocity.covariance, f"{name}.covariance")
    if not math.isfinite(velocity.t):
        raise InputError(f"{name}.t: expected a finite time, got {velocity.t}")
    if not (math.isfinite(velocity.dt) and velocity.dt >= 0):
        raise InputError(f"{name}.dt: expected a finite interval >= 0, got {velocity.dt}")
    return z, cov


def _keyframe_model(pose: PoseMeasurement, k: int) -> tuple[gtsam.Pose3, np.ndarray] | None:
    """(assumed keyframe pose A, plane Jacobian J) of a keyframe-relative pose, or None."""
    fields = (pose.reference_rotation, pose.reference_position, pose.plane_jacobian)
    if all(f is None for f in fields):
        return None
    name = f"frame {k}: pose"
    if any(f is None for f in fields):
        raise InputError(
            f"{name}: reference_rotation, reference_position and plane_jacobian go together"
        )
    R = as_rotation(pose.reference_rotation, f"{name}.reference_rotation")
    p = np.asarray(pose.reference_position, dtype=float)
    J = np.asarray(pose.plane_jacobian, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"{name}.reference_position: expected a finite (3,) vector")
    if J.shape != (6, 6) or not np.all(np.isfinite(J)):
        raise InputError(f"{name}.plane_jacobian: expected a finite (6, 6) matrix")
    return gtsam.Pose3(gtsam.Rot3(R), p), J


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


class FactorGraphSmoother(Estimator):
    """Pose (H_d) and twist (H_c) measurements fused in a GTSAM factor graph.

    Args:
        solver: "isam2" (default; ``--method smoother``), "batch" or "fixed-lag".
        lag: window of the fixed-lag smoother, seconds (> 0; used by "fixed-lag").
        acceleration_sigma: (s_w, s_v), square roots of the white-noise
            acceleration spectral densities, angular (rad s^-3/2) and linear
            (m s^-3/2); a single number sets both. Default
            :data:`DEFAULT_ACCELERATION_SIGMA`.
        robust: None, "huber" or "cauchy": robust loss on the measurement factors.
        robust_threshold: M-estimator threshold on the whitened residual norm;
            default :data:`DEFAULT_ROBUST_THRESHOLD`.
        compute_covariance: also return the 12x12 marginal covariance of
            [pose tangent; twist] per frame (online: the latest frame after its
            update, from ISAM2's Bayes tree; smoothed: every frame at the end).
            Batch online estimates have none.
        initial_twist_sigma: standard deviation of the zero-mean prior on the first twist.
        world_sigma: standard deviation of the prior X(k0) = I.
        relinearize_threshold: ISAM2 relinearizes a variable whose delta exceeds this.
        relinearize_skip: ISAM2 checks for relinearization every this many updates.
        max_iterations: most Levenberg-Marquardt iterations ("batch").
    """

    name = "smoother"

    def __init__(
        self,
        *,
        solver: str = "isam2",
        lag: float = 1.0,
        acceleration_sigma: float | Sequence[float] = DEFAULT_ACCELERATION_SIGMA,
        robust: str | None = None,
        robust_threshold: float | None = None,
        compute_covariance: bool = False,
        initial_twist_sigma: float = DEFAULT_INITIAL_TWIST_SIGMA,
        world_sigma: float = DEFAULT_WORLD_SIGMA,
        relinearize_threshold: float = DEFAULT_RELINEARIZE_THRESHOLD,
        relinearize_skip: int = DEFAULT_RELINEARIZE_SKIP,
        max_iterations: int = 100,
    ) -> None:
        super().__init__()
        if solver not in SOLVERS:
            raise InputError(f"solver: expected one of {', '.join(SOLVERS)}, got {solver!r}")
        self.solver = solver
        self.name = SOLVERS[solver]
        self.lag = as_number(lag, "lag", above=0.0)
        self.acceleration_sigma = check_acceleration_sigma(acceleration_sigma)
        #: diag(Q): white-noise-acceleration spectral densities, [rot x3; trans x3].
        self._q = twist_spectral_density(self.acceleration_sigma)
        if robust is not None and robust not in ROBUST_LOSSES:
            raise InputError(
                f"robust: expected None or one of {', '.join(ROBUST_LOSSES)}, got {robust!r}"
            )
        self.robust = robust
        self.robust_threshold = (
            DEFAULT_ROBUST_THRESHOLD
            if robust_threshold is None
            else as_number(robust_threshold, "robust_threshold", above=0.0)
        )
        self.compute_covariance = bool(compute_covariance)
        self._world_noise = gtsam.noiseModel.Isotropic.Sigma(
            6, as_number(world_sigma, "world_sigma", above=0.0)
        )
        self._twist_prior_noise = gtsam.noiseModel.Isotropic.Sigma(
            6, as_number(initial_twist_sigma, "initial_twist_sigma", above=0.0)
        )
        self.max_iterations = as_integer(max_iterations, "max_iterations", 1)
        relinearize_skip = as_integer(relinearize_skip, "relinearize_skip", 1)

        # Frame bookkeeping: index and time of every frame, position by index.
        self._indices: list[int] = []
        self._times: list[float] = []
        self._position: dict[int, int] = {}
        self._pose = gtsam.Pose3()  # latest online estimate (for predictions)
        self._twist = _ZERO6
        self._noise_cache: dict[float, tuple[gtsam.noiseModel.Base, gtsam.noiseModel.Base]] = {}

        params = gtsam.ISAM2Params()
        # Only the poses need relinearizing: every factor is affine in the twists V with
        # constant Jacobians (motion: -dt/2 I; measured and random-walk twists: linear).
        thresholds = gtsam.ISAM2ThresholdMap()
        thresholds.insert(
            ("x", np.full(6, as_number(relinearize_threshold, "relinearize_threshold", above=0.0)))
        )
        thresholds.insert(("v", np.full(6, np.inf)))
        params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = relinearize_skip
        # Check only the cliques touched by the update, not every variable (O(1) per frame).
        params.enablePartialRelinearizationCheck = True
        params.findUnusedFactorSlots = solver == "fixed-lag"
        self._isam: gtsam.ISAM2 | None = None
        self._fixed_lag: gtsam.IncrementalFixedLagSmoother | None = None
        if solver == "isam2":
            self._isam = gtsam.ISAM2(params)
        elif solver == "fixed-lag":
            # Stamps are multiples of the block and the lag is MARGINALIZATION_BLOCKS blocks:
            # half a block more keeps GTSAM's test "stamp < latest - lag" away from ties.
            self._smoother_lag = self.lag * (1.0 + 0.5 / MARGINALIZATION_BLOCKS)
            self._fixed_lag = gtsam.IncrementalFixedLagSmoother(self._smoother_lag, params)
            self._isam = self._fixed_lag.getISAM2()  # a reference to the smoother's own ISAM2
        # The Python wrapper of ISAM2's linearization point: while it lives, the custom
        # factors' callbacks receive it instead of a fresh copy (see the module docstring).
        self._theta = None if self._isam is None else self._isam.getLinearizationPoint()
        # batch: the whole graph and its initial values; the optimum once computed.
        self._graph = gtsam.NonlinearFactorGraph()
        self._initial = gtsam.Values()
        self._batch_result: gtsam.Values | None = None
        #: Levenberg-Marquardt iterations of the last batch solve.
        self.iterations = 0
        # fixed-lag: smoother timestamps, frames still in the window (positions), and the
        # frozen ones.
        self._stamps: list[float] = []
        self._window: deque[int] = deque()
        self._frozen: dict[int, tuple[gtsam.Pose3, np.ndarray, np.ndarray | None]] = {}

    # -- noise models -----------------------------------------------------------------------

    def _process_noise(self, dt: float) -> tuple[gtsam.noiseModel.Base, gtsam.noiseModel.Base]:
        """(motion, random walk) noise over dt: Q dt^3 / 12 (Brownian bridge) and Q dt."""
        cached = self._noise_cache.get(dt)
        if cached is None:
            if len(self._noise_cache) > 64:  # irregular frame times: keep the cache small
                self._noise_cache.clear()
            cached = (
                gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(bridge_variance(self._q, dt))),
                gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(velocity_variance(self._q, dt))),
            )
            self._noise_cache[dt] = cached
        return cached

    def _measurement_noise(self, covariance: np.ndarray) -> gtsam.noiseModel.Base:
        gaussian = gtsam.noiseModel.Gaussian.Covariance(covariance)
        if self.robust is None:
            return gaussian
        if self.robust == "huber":
            loss = gtsam.noiseModel.mEstimator.Huber.Create(self.robust_threshold)
        else:
            loss = gtsam.noiseModel.mEstimator.Cauchy.Create(self.robust_threshold)
        return gtsam.noiseModel.Robust.Create(loss, gaussian)

    # -- per frame --------------------------------------------------------------------------

    def _in_graph(self, index: int) -> bool:
        """Whether X(index) is still a variable (always, except fixed-lag after it left)."""
        return self._fixed_lag is None or index not in self._frozen

    def _current_pose(self, index: int) -> gtsam.Pose3:
        if self.solver == "batch":
            return self._initial.atPose3(X(index))
        if index in self._frozen:
            return self._frozen[index][0]
        assert self._isam is not None
        return self._isam.calculateEstimatePose3(X(index))

    def _twist_nodes(
        self, k: int, t: float, meas: VelocityMeasurement
    ) -> tuple[list[int], list[float]]:
        """Frame indices and weights of the mean-twist factor of frame k (at time t).

        Called before frame k is added: the nodes are the earlier frames and (k, t).
        """
        start, end = meas.t - 0.5 * meas.dt, meas.t + 0.5 * meas.dt
        tol = 1e-9 * max(1.0, abs(t))
        if start > t + tol:
            raise InputError(
                f"frame {k}: velocity interval [{start:.6g}, {end:.6g}] s starts after the "
                f"frame time {t:.6g} s"
            )
        first_time = self._times[0] if self._times else t
        if end < first_time - tol:
            raise InputError(
                f"frame {k}: velocity interval [{start:.6g}, {end:.6g}] s ends before the "
                f"first frame ({first_time:.6g} s)"
            )
        if self._times and abs(start - self._times[-1]) <= tol and abs(end - t) <= tol:
            # the usual finite-difference interval [t_{k-1}, t_k]
            indices, weights = [self._indices[-1], k], [0.5, 0.5]
        else:
            # Only the nodes that can carry weight: from the last one at or before `start`.
            first = len(self._times)
            while first > 0 and (first == len(self._times) or self._times[first] > start):
                first -= 1
            times = [*self._times[first:], t]
            candidates = [*self._indices[first:], k]
            nodes = interval_weights(times, start, end)
            indices = [candidates[i] for i, _ in nodes]
            weights = [w for _, w in nodes]
        for index in indices:
            if index != k and not self._in_graph(index):
                raise InputError(
                    f"frame {k}: the velocity interval [{start:.6g}, {end:.6g}] s reaches frame "
                    f"{index}, which already left the fixed-lag window ({self.lag} s); "
                    "increase lag"
                )
        return indices, weights

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        k, t = as_integer(frame.index, "frame.index", 0), float(frame.t)
        if not math.isfinite(t):
            raise InputError(f"frame {k}: t is not finite ({frame.t})")
        pose_meas = None if frame.pose is None else _checked_pose(frame.pose, k)
        twist_meas = None if frame.velocity is None else _checked_velocity(frame.velocity, k)
        if pose_meas is not None and pose_meas[2] != 0 and pose_meas[2] not in self._position:
            raise InputError(
                f"frame {k}: pose.reference {pose_meas[2]} is not an earlier frame of this sequence"
            )
        twist_nodes = None
        if twist_meas is not None:
            assert frame.velocity is not None
            twist_nodes = self._twist_nodes(k, t, frame.velocity)
        # Everything is checked: from here on the state changes.

        graph = gtsam.NonlinearFactorGraph()
        first = not self._indices
        dt = 0.0 if first else t - self._times[-1]
        if first:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(), self._world_noise))
            graph.add(gtsam.PriorFactorVector(V(k), _ZERO6, self._twist_prior_noise))
        else:
            previous = self._indices[-1]
            motion_noise, walk_noise = self._process_noise(dt)
            graph.add(motion_factor(X(previous), X(k), V(previous), V(k), dt, motion_noise))
            graph.add(gtsam.BetweenFactorVector(V(previous), V(k), _ZERO6, walk_noise))
        self._position[k] = len(self._indices)
        self._indices.append(k)
        self._times.append(t)

        # Initial values: the frame's own measurements, else the motion-model prediction.
        # With a robust loss, always the prediction: a factor is linearized (and its
        # robust weight fixed) at the initial value until ISAM2 relinearizes it, and an
        # outlier measured at its own value would get full weight.
        use_measured = self.robust is None
        twist_guess = twist_meas[0] if twist_meas is not None and use_measured else self._twist
        pose_guess: gtsam.Pose3 | None = None
        if pose_meas is not None:
            measured, cov, ref = pose_meas
            noise = self._measurement_noise(cov)
            if ref == 0:
                graph.add(gtsam.PriorFactorPose3(X(k), measured, noise))
                pose_guess = measured
            else:
                keyframe_model = _keyframe_model(frame.pose, k)
                measured_here = (
                    measured
                    if keyframe_model is None
                    else replace_keyframe_plane(measured, *keyframe_model, self._current_pose(ref))
                )
                pose_guess = self._current_pose(ref).compose(measured_here)
                if self._in_graph(ref) and keyframe_model is not None:
                    graph.add(
                        keyframe_between_factor(
                            X(ref), X(k), measured, keyframe_model[0], keyframe_model[1], noise
                        )
                    )
                elif self._in_graph(ref):
                    graph.add(gtsam.BetweenFactorPose3(X(ref), X(k), measured, noise))
                else:
                    # fixed-lag, keyframe already out of the window: its frozen estimate
                    # becomes the reference (its own uncertainty is not propagated).
                    graph.add(gtsam.PriorFactorPose3(X(k), pose_guess, noise))
        if first:
            pose_guess = gtsam.Pose3()
        elif pose_guess is None or not use_measured:
            pose_guess = self._pose.compose(
                gtsam.Pose3.Expmap((0.5 * dt) * (self._twist + twist_guess))
            )
        if twist_meas is not None and twist_nodes is not None:
            indices, weights = twist_nodes
            noise = self._measurement_noise(twist_meas[1])
            graph.add(_mean_velocity_factor([V(i) for i in indices], weights, twist_meas[0], noise))

        values = gtsam.Values()
        values.insert(X(k), pose_guess)
        values.insert(V(k), twist_guess)

        covariance: np.ndarray | None = None
        if self.solver == "batch":
            self._graph.push_back(graph)
            self._initial.insert(values)
            self._batch_result = None
            pose, twist = pose_guess, np.array(twist_guess, dtype=float)
        else:
            assert self._isam is not None
            if self._fixed_lag is not None:
                stamp = self._stamp(t)
                self._stamps.append(stamp)
                self._freeze_leaving(stamp)
                self._fixed_lag.update(graph, values, {X(k): stamp, V(k): stamp})
                self._window.append(self._position[k])
                self._collect_frozen()
            else:
                self._isam.update(graph, values)
            pose = self._isam.calculateEstimatePose3(X(k))
            twist = self._isam.calculateEstimateVector(V(k))
            if self.compute_covariance:
                covariance = self._joint_covariance(k)
        self._pose, self._twist = pose, twist
        return StateEstimate(
            index=k,
            t=t,
            rotation=pose.rotation().matrix(),
            position=np.asarray(pose.translation(), dtype=float),
            twist=np.asarray(twist, dtype=float),
            covariance=covariance,
        )

    def _joint_covariance(self, index: int) -> np.ndarray:
        assert self._isam is not None
        c = self._isam.jointMarginalCovariance([X(index), V(index)]).fullMatrix()
        return 0.5 * (c + c.T)

    # -- fixed-lag window -------------------------------------------------------------------

    def _stamp(self, t: float) -> float:
        """The smoother timestamp of time t: relative to the first frame, rounded down to a
        multiple of the block length lag / MARGINALIZATION_BLOCKS."""
        block = self.lag / MARGINALIZATION_BLOCKS
        return math.floor((t - self._times[0]) / block + 1e-9) * block

    def _freeze_leaving(self, stamp: float) -> None:
        """Record the current estimate of every frame the coming update will marginalize.

        IncrementalFixedLagSmoother drops the variables with timestamp < (latest
        timestamp) - lag after adding the new factors. (Should a frame recorded
        here be kept after all, it is recorded again at the next update: see
        :meth:`_collect_frozen`.)
        """
        assert self._isam is not None
        horizon = stamp - self._smoother_lag
        values: gtsam.Values | None = None
        for pos in self._window:
            if self._stamps[pos] >= horizon:
                break
            if values is None:
                # A full back-substitution: the per-key estimates use ISAM2's wildfire-
                # limited delta, which can be stale far from the root, where these are.
                values = self._isam.calculateBestEstimate()
            index = self._indices[pos]
            cov = self._joint_covariance(index) if self.compute_covariance else None
            self._frozen[index] = (values.atPose3(X(index)), values.atVector(V(index)), cov)

    def _collect_frozen(self) -> None:
        """Drop the marginalized frames from the window; forget records of frames kept."""
        assert self._isam is not None
        while self._window:
            index = self._indices[self._window[0]]
            if self._isam.valueExists(X(index)):
                break
            self._window.popleft()
        for pos in self._window:
            if self._indices[pos] not in self._frozen:
                break
            del self._frozen[self._indices[pos]]

    # -- results ----------------------------------------------------------------------------

    def trajectory(self) -> Trajectory:
        """The smoothed estimate of every frame so far (see the class docstring per solver)."""
        n = len(self._indices)
        rotations = np.empty((n, 3, 3))
        positions = np.empty((n, 3))
        twists = np.empty((n, 6))
        covariances = np.empty((n, 12, 12)) if self.compute_covariance else None
        if n == 0:
            return Trajectory(np.empty(0), rotations, positions, twists, covariances)

        def put(i: int, pose: gtsam.Pose3, twist: np.ndarray) -> None:
            rotations[i] = pose.rotation().matrix()
            positions[i] = pose.translation()
            twists[i] = twist

        if self.solver == "batch":
            values = self._batch_values()
            # One ISAM2 elimination at the optimum gives the joint marginals quickly
            # (gtsam.Marginals took O(N) per query here); its linearization point is
            # held (second item) so the custom factors are not handed copies.
            marginals: tuple[gtsam.ISAM2, gtsam.Values] | None = None
            if self.compute_covariance:
                isam = gtsam.ISAM2()
                marginals = (isam, isam.getLinearizationPoint())
                isam.update(self._graph, values)
            for i, index in enumerate(self._indices):
                put(i, values.atPose3(X(index)), values.atVector(V(index)))
                if marginals is not None and covariances is not None:
                    c = marginals[0].jointMarginalCovariance([X(index), V(index)]).fullMatrix()
                    covariances[i] = 0.5 * (c + c.T)
        else:
            assert self._isam is not None
            values = self._isam.calculateBestEstimate()
            for i, index in enumerate(self._indices):
                if index in self._frozen:
                    pose, twist, cov = self._frozen[index]
                    put(i, pose, twist)
                    if covariances is not None:
                        assert cov is not None
                        covariances[i] = cov
                    continue
                put(i, values.atPose3(X(index)), values.atVector(V(index)))
                if covariances is not None:
                    covariances[i] = self._joint_covariance(index)
        return Trajectory(
            t=np.array(self._times),
            rotations=rotations,
            positions=positions,
            twists=twists,
            covariances=covariances,
        )

    def _batch_values(self) -> gtsam.Values:
        if self._batch_result is None:
            self._batch_result, self.iterations = levenberg_marquardt(
                self._graph, self._initial, max_iterations=self.max_iterations
            )
        return self._batch_result


class BatchSmoother(FactorGraphSmoother):
    """:class:`FactorGraphSmoother` with ``solver="batch"`` (``--method batch``)."""

    name = "batch"

    def __init__(self, **options: object) -> None:
        super().__init__(solver="batch", **options)  # type: ignore[arg-type]


class FixedLagSmoother(FactorGraphSmoother):
    """:class:`FactorGraphSmoother` with ``solver="fixed-lag"`` (``--method fixed-lag``)."""

    name = "fixed-lag"

    def __init__(self, **options: object) -> None:
        super().__init__(solver="fixed-lag", **options)  # type: ignore[arg-type]
