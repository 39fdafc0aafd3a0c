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

Solvers (one :class:`~hvo_graph.estimators.base.Estimator` interface; the back
ends are in :mod:`hvo_graph.estimators.solvers`):

- ``"isam2"`` (``--method smoother``): one ISAM2 update per frame; the online
  estimate of frame k is the value right after its update, :meth:`trajectory`
  the final (smoothed) values;
- ``"batch"``: Levenberg-Marquardt over the whole graph when
  :meth:`trajectory` is called; its online estimates are the initial values
  (the frame's own measurement, or the motion-model prediction), i.e. unfused;
- ``"fixed-lag"``: GTSAM's ``IncrementalFixedLagSmoother`` with a window of
  ``lag`` seconds; :meth:`trajectory` gives each frame's value as it left the
  window (or its current value).
"""

from __future__ import annotations

import math
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
from hvo_graph.estimators.solvers import (
    MARGINALIZATION_BLOCKS,
    Backend,
    levenberg_marquardt,
    make_backend,
)
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
    "MARGINALIZATION_BLOCKS",
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

_ZERO6 = np.zeros(6)

#: A checked twist measurement: (z, covariance, node frame indices, node weights).
_TwistMeasurement = tuple[np.ndarray, np.ndarray, list[int], list[float]]


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
        max_iterations = as_integer(max_iterations, "max_iterations", 1)
        relinearize_skip = as_integer(relinearize_skip, "relinearize_skip", 1)
        threshold = as_number(relinearize_threshold, "relinearize_threshold", above=0.0)

        # Frame bookkeeping: index and time of every frame, position by index.
        self._indices: list[int] = []
        self._times: list[float] = []
        self._position: dict[int, int] = {}
        self._pose = gtsam.Pose3()  # latest online estimate (for predictions)
        self._twist = _ZERO6
        self._noise_cache: dict[float, tuple[gtsam.noiseModel.Base, gtsam.noiseModel.Base]] = {}

        #: The solver's back end (:mod:`hvo_graph.estimators.solvers`).
        self.backend: Backend = make_backend(
            solver,
            lag=self.lag,
            relinearize_threshold=threshold,
            relinearize_skip=relinearize_skip,
            max_iterations=max_iterations,
            compute_covariance=self.compute_covariance,
        )

    @property
    def iterations(self) -> int:
        """Levenberg-Marquardt iterations of the last batch solve (0 for the other solvers)."""
        return getattr(self.backend, "iterations", 0)

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
            if index != k and not self.backend.in_graph(index):
                raise InputError(
                    f"frame {k}: the velocity interval [{start:.6g}, {end:.6g}] s reaches frame "
                    f"{index}, which already left the fixed-lag window ({self.lag} s); "
                    "increase lag"
                )
        return indices, weights

    def _checked_frame(
        self, frame: FrameMeasurement
    ) -> tuple[int, float, tuple[gtsam.Pose3, np.ndarray, int] | None, _TwistMeasurement | None]:
        """(k, t, checked pose, checked twist with its nodes): every check before any change."""
        k, t = as_integer(frame.index, "frame.index", 0), float(frame.t)
        if not math.isfinite(t):
            raise InputError(f"frame {k}: t is not finite ({frame.t})")
        pose_meas = None if frame.pose is None else _checked_pose(frame.pose, k)
        velocity = None if frame.velocity is None else _checked_velocity(frame.velocity, k)
        if pose_meas is not None and pose_meas[2] != 0 and pose_meas[2] not in self._position:
            raise InputError(
                f"frame {k}: pose.reference {pose_meas[2]} is not an earlier frame of this sequence"
            )
        twist_meas = None
        if velocity is not None:
            assert frame.velocity is not None
            twist_meas = (*velocity, *self._twist_nodes(k, t, frame.velocity))
        return k, t, pose_meas, twist_meas

    def _add_pose_factor(
        self,
        graph: gtsam.NonlinearFactorGraph,
        k: int,
        pose: PoseMeasurement,
        pose_meas: tuple[gtsam.Pose3, np.ndarray, int],
    ) -> gtsam.Pose3:
        """The H_d factor of frame k (prior, between, or keyframe between); its pose value."""
        measured, cov, ref = pose_meas
        noise = self._measurement_noise(cov)
        if ref == 0:
            graph.add(gtsam.PriorFactorPose3(X(k), measured, noise))
            return measured
        keyframe_model = _keyframe_model(pose, k)
        reference = self.backend.current_pose(ref)
        measured_here = (
            measured
            if keyframe_model is None
            else replace_keyframe_plane(measured, *keyframe_model, reference)
        )
        pose_guess = reference.compose(measured_here)
        if self.backend.in_graph(ref) and keyframe_model is not None:
            graph.add(
                keyframe_between_factor(
                    X(ref), X(k), measured, keyframe_model[0], keyframe_model[1], noise
                )
            )
        elif self.backend.in_graph(ref):
            graph.add(gtsam.BetweenFactorPose3(X(ref), X(k), measured, noise))
        else:
            # fixed-lag, keyframe already out of the window: its frozen estimate
            # becomes the reference (its own uncertainty is not propagated).
            graph.add(gtsam.PriorFactorPose3(X(k), pose_guess, noise))
        return pose_guess

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        k, t, pose_meas, twist_meas = self._checked_frame(frame)
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
            assert frame.pose is not None
            pose_guess = self._add_pose_factor(graph, k, frame.pose, pose_meas)
        if first:
            pose_guess = gtsam.Pose3()
        elif pose_guess is None or not use_measured:
            pose_guess = self._pose.compose(
                gtsam.Pose3.Expmap((0.5 * dt) * (self._twist + twist_guess))
            )
        if twist_meas is not None:
            z, cov, indices, weights = twist_meas
            noise = self._measurement_noise(cov)
            graph.add(_mean_velocity_factor([V(i) for i in indices], weights, z, noise))

        values = gtsam.Values()
        values.insert(X(k), pose_guess)
        values.insert(V(k), twist_guess)
        pose, twist, covariance = self.backend.add(graph, values, k, t - self._times[0])
        self._pose, self._twist = pose, twist
        return StateEstimate(
            index=k,
            t=t,
            rotation=pose.rotation().matrix(),
            position=np.asarray(pose.translation(), dtype=float),
            twist=np.asarray(twist, dtype=float),
            covariance=covariance,
        )

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
        for i, (pose, twist, cov) in enumerate(self.backend.final(self._indices)):
            rotations[i] = pose.rotation().matrix()
            positions[i] = pose.translation()
            twists[i] = twist
            if covariances is not None:
                assert cov is not None
                covariances[i] = cov
        return Trajectory(
            t=np.array(self._times),
            rotations=rotations,
            positions=positions,
            twists=twists,
            covariances=covariances,
        )


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
