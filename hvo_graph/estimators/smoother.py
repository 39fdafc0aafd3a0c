"""The factor-graph smoother: H_d poses and H_c twists fused in GTSAM (ISAM2 by default).

Variables per frame k (keys from ``gtsam.symbol_shorthand``): X(k), the pose
T_wc (``gtsam.Pose3``), and V(k), the body twist [w; v] (6-vector, contract
sign: d/dt T_wc = T_wc [w; v]^). Factors (docs/smoother.md has the equations
and the reasons for every default):

- anchor: X(k0) = I at the first frame k0 (W = the first camera frame). Every
  H_d pose against frame k0 carries one shared draw of that frame's pixel noise
  (``shared_reference_noise``): the prior's covariance is that noise, so X(k0)
  estimates the shared offset, and poses are reported relative to it,
  X_k = X(k0)^-1 X(k) (else, or when frame k0 has no pose and a keyframe's come first:
  std ``world_sigma``). Weak zero-mean priors on V(k0) (and A(k0)) (``initial_twist_sigma``);
- pose measurement from the discrete homography H_d: with reference 0 (W) a
  ``PriorFactorPose3`` on X(k); with a keyframe reference r a between factor
  X(r) -> X(k); noise ``Gaussian.Covariance`` of the frame's own pixels
  (tangent [rot; trans], right perturbation);
- twist measurement from the continuous homography H_c over [t - dt/2,
  t + dt/2]: :func:`~hvo_graph.estimators.factors.mean_velocity_factor` on the
  time average of the piecewise-linear twist ((V(k-1) + V(k)) / 2 for the usual
  interval), full covariance; only where two H_d poses do not already span the
  interval (the flow and those poses are made of the same pixels);
- motion (``motion_model``, :mod:`~hvo_graph.estimators.motion_model`): white-noise
  acceleration (default) or white-noise jerk (a third variable A(k), the twist
  rate), or the one the poses make more likely ("auto"); Q = diag(s_w^2 I_3, s_v^2 I_3) from
  ``acceleration_sigma``, by default fitted (:mod:`.noise_estimation`);
- a keyframe's attitude against the plane, when the front end fitted it (its n_r,
  ``FrameMeasurement.keyframe_tilt``): :func:`~.factors.tilt_factor` on X(r);
- optional robust loss (Huber or Cauchy) on the two measurement factors.

Solvers ("isam2": ``--method smoother``; "batch"; "fixed-lag"): the back ends of
:mod:`hvo_graph.estimators.solvers` (what their online and final estimates are).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, V, X

from hvo_graph.errors import InputError, as_choice, as_integer, as_number
from hvo_graph.estimators import measurement_checks
from hvo_graph.estimators._world_runs import add_records, add_table
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.choices import (
    ANCHOR_START_SIGMA,
    DEFAULT_INITIAL_TWIST_SIGMA,
    DEFAULT_RELINEARIZE_SKIP,
    DEFAULT_RELINEARIZE_THRESHOLD,
    DEFAULT_ROBUST_THRESHOLD,
    DEFAULT_WORLD_SIGMA,
    ROBUST_LOSSES,
    SOLVERS,
    VELOCITY_FACTOR_POLICIES,
)
from hvo_graph.estimators.factor_record import FactorRecord
from hvo_graph.estimators.factors import (
    _mean_velocity_factor,
    keyframe_pose_factor,
    measurement_noise,
    tilt_factor,
)
from hvo_graph.estimators.measurement_checks import CheckedFrame, poses_span
from hvo_graph.estimators.measurement_screen import Screened
from hvo_graph.estimators.motion_model import MotionFactors, check_motion_model, twist_keys
from hvo_graph.estimators.noise_estimation import ProcessNoiseSchedule
from hvo_graph.estimators.process_noise import DEFAULT_ACCELERATION_SIGMA
from hvo_graph.estimators.solvers import (
    MARGINALIZATION_BLOCKS,
    Backend,
    levenberg_marquardt,
    make_backend,
)
from hvo_graph.estimators.state_log import SortedIndices
from hvo_graph.measurement_table import MeasurementTable
from hvo_graph.types import FrameMeasurement, PoseMeasurement, StateEstimate, Trajectory

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

_ZERO6 = np.zeros(6)
_ZERO66 = np.zeros((6, 6))  # one shared array, not one per frame (never written to)


class FactorGraphSmoother(Estimator):
    """Pose (H_d) and twist (H_c) measurements fused in a GTSAM factor graph.

    Args:
        solver: "isam2" (default; ``--method smoother``), "batch" or "fixed-lag".
        lag: window of the fixed-lag smoother, seconds (> 0; used by "fixed-lag").
        acceleration_sigma: (s_w, s_v), square roots of the spectral densities of
            the motion model's white noise, angular and linear (acceleration: rad
            s^-3/2, m s^-3/2; jerk: rad s^-5/2, m s^-5/2); a single number sets
            both. "auto" (default): the maximum-likelihood values of the sequence
            (:func:`~hvo_graph.estimators.noise_estimation.estimate_process_noise`):
            :meth:`run` fits them on the whole sequence first; frame-by-frame
            :meth:`update` starts from :data:`DEFAULT_ACCELERATION_SIGMA` and refits
            on the frames so far after 30, 60, 120, ... frames (later motion factors
            use the new values). The values in force: :attr:`acceleration_sigma`.
        shared_reference_noise: True (default): an H_d factor carries only its own
            frame's pixel noise (``covariance - reference_covariance``); the
            reference frame's share, one offset common to every pose measured
            against frame k0, is estimated as X(k0) (module docstring); a
            keyframe's share is added to the reported pose covariance. False: the
            full covariance in every factor, X(k0) = I.
        velocity_factors: "gaps" (default): an H_c twist factor only where no two
            H_d poses against the same reference already span its interval (the
            flow is made of the same pixels as those two poses, which would count
            them twice); "all": every H_c twist.
        robust: None, "huber" or "cauchy": robust loss on the measurement factors.
        robust_threshold: M-estimator threshold on the whitened residual norm;
            default :data:`DEFAULT_ROBUST_THRESHOLD`.
        compute_covariance: also return the 12x12 covariance of [pose tangent;
            twist] per frame. Smoothed (:meth:`trajectory`): the covariance of the
            errors over the pixel noise, own and shared, plus the motion model's
            bias measured from the data (:mod:`.error_covariance`). Online: the
            ISAM2 marginal after the frame's update (conservative: it counts the
            anchor's full uncertainty); batch online estimates have none.
        initial_twist_sigma: standard deviation of the zero-mean prior on the first twist.
        world_sigma: standard deviation of the prior X(k0) = I.
        relinearize_threshold: ISAM2 relinearizes a variable whose delta exceeds this.
        relinearize_skip: ISAM2 checks for relinearization every this many updates.
        max_iterations: most Levenberg-Marquardt iterations ("batch").
        motion_model: "wna" (default; white-noise acceleration), "wnj" (white-noise
            jerk) or "auto": with fitted ``acceleration_sigma``, the model of the
            larger maximised likelihood on the whole sequence (:meth:`run`;
            streamed frames keep "wnj"); with fixed values, "wna". In force:
            :attr:`motion_model`.
    """

    name = "smoother"

    def __init__(
        self,
        *,
        solver: str = "isam2",
        lag: float = 1.0,
        acceleration_sigma: float | Sequence[float] | str = "auto",
        shared_reference_noise: bool = True,
        velocity_factors: str = "gaps",
        robust: str | None = None,
        robust_threshold: float | None = None,
        compute_covariance: bool = False,
        initial_twist_sigma: float = DEFAULT_INITIAL_TWIST_SIGMA,
        world_sigma: float = DEFAULT_WORLD_SIGMA,
        relinearize_threshold: float = DEFAULT_RELINEARIZE_THRESHOLD,
        relinearize_skip: int = DEFAULT_RELINEARIZE_SKIP,
        max_iterations: int = 100,
        motion_model: str = "wna",
    ) -> None:
        super().__init__()
        as_choice(solver, "solver", SOLVERS)
        self.solver = solver
        self.name = SOLVERS[solver]
        self.lag = as_number(lag, "lag", above=0.0)
        #: The process noise in force: fixed, or fitted ("auto"; ``.fit`` has the fit).
        self.process_noise = ProcessNoiseSchedule(
            acceleration_sigma, DEFAULT_ACCELERATION_SIGMA, check_motion_model(motion_model)
        )
        self._motion = MotionFactors()
        #: (s_w, s_v) of the motion factors added from now on.
        self.acceleration_sigma = self.process_noise.sigma
        self.shared_reference_noise = bool(shared_reference_noise)
        as_choice(velocity_factors, "velocity_factors", VELOCITY_FACTOR_POLICIES)
        self.velocity_factors = velocity_factors
        #: H_c twist factors added, and left out by the "gaps" policy.
        self.velocity_factor_counts = {"used": 0, "skipped": 0}
        self._reference_cov: list[np.ndarray] = []  # of each frame's latest pose, by position
        self._last_reference: int | None = None  # of the latest frame's pose (None: none)
        as_choice(robust, "robust", ROBUST_LOSSES, none=True)
        self.robust = robust
        self.robust_threshold = (
            DEFAULT_ROBUST_THRESHOLD
            if robust_threshold is None
            else as_number(robust_threshold, "robust_threshold", above=0.0)
        )
        self.compute_covariance = bool(compute_covariance)
        self._pose_noise = functools.partial(
            measurement_noise, robust=robust, threshold=self.robust_threshold
        )
        #: The factors by role, for the smoothed error covariance (with covariances).
        self.record: FactorRecord | None = FactorRecord() if self.compute_covariance else None
        self._anchored = False  # X(k0) has its prior from the reference frame's noise
        self._world_posed = False  # a pose against W (frame k0) came in
        self._anchor_covariance = np.zeros((6, 6))  # its latest marginal (online)
        self._anchor_start = gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_START_SIGMA)
        self._world_sigma = as_number(world_sigma, "world_sigma", above=0.0)
        self._world_noise = gtsam.noiseModel.Isotropic.Sigma(6, self._world_sigma)
        self._twist_prior_noise = gtsam.noiseModel.Isotropic.Sigma(
            6, as_number(initial_twist_sigma, "initial_twist_sigma", above=0.0)
        )
        max_iterations = as_integer(max_iterations, "max_iterations", 1)
        relinearize_skip = as_integer(relinearize_skip, "relinearize_skip", 1)
        threshold = as_number(relinearize_threshold, "relinearize_threshold", above=0.0)

        # Frame bookkeeping: index and time of every frame, position by index.
        self._indices: list[int] = []
        self._times: list[float] = []
        self._known = SortedIndices(self._indices)
        self._pose = gtsam.Pose3()  # latest online estimate (for predictions)
        self._twist = _ZERO6
        self._screened: tuple[FrameMeasurement, Screened | None] | None = None  # from run()

        #: The solver's back end (:mod:`hvo_graph.estimators.solvers`).
        self.backend: Backend = make_backend(
            solver,
            lag=self.lag,
            relinearize_threshold=threshold,
            relinearize_skip=relinearize_skip,
            max_iterations=max_iterations,
            compute_covariance=self.compute_covariance,
            pose_noise=self._pose_noise,
        )

    @property
    def iterations(self) -> int:
        """Levenberg-Marquardt iterations of the last batch solve (0 for the other solvers)."""
        return getattr(self.backend, "iterations", 0)

    @property
    def motion_model(self) -> str:
        """The motion model in force, "wna" or "wnj" (fixed once a frame is in)."""
        return self.process_noise.model

    def run(self, frames: Iterable[FrameMeasurement], *, online: bool = True) -> Trajectory:
        """Fuse a whole sequence; "auto" process noise is fitted on all of it first. The
        frames' numbers are checked a block at a time (:func:`.screen_frames`), and runs of
        frames posed against the world skip the per-frame checks (no robust loss, no
        covariances: :mod:`._world_runs`). ``online`` False (ISAM2, no robust loss: it needs
        the window's predictions): no window, the final solve starts from the measurements
        (same optimum, a third sooner)."""
        frames = frames if isinstance(frames, Sequence) else list(frames)  # a table: as is
        if not self._indices:
            self.process_noise.fit_all(frames)
            self.acceleration_sigma = self.process_noise.sigma
            # Only ISAM2 can skip its window: the fixed-lag smoother is its window.
            self.backend.windowed = online or self.robust is not None or self.solver != "isam2"
        # Frames posed against the world: offline, no update of their own; else an update
        # without the per-frame checks (_world_runs).
        bulk = self.record is None and self.robust is None
        if bulk and isinstance(frames, MeasurementTable):  # its runs straight from its arrays
            add_table(self, frames)
        else:
            add_records(self, frames, bulk=bulk)
        return self.trajectory()

    def _checked_frame(self, frame: FrameMeasurement) -> CheckedFrame:
        """(k, t, checked pose, checked twist with its nodes): every check before any change."""
        given, self._screened = self._screened, None  # streamed frames: checked here alone
        screened = given[1] if given is not None and given[0] is frame else None
        state = (self._times, self._indices, self.backend.in_graph, self.lag)
        split = self.shared_reference_noise
        return measurement_checks.checked_frame(
            frame, *state, known=self._known, split_reference=split, screened=screened
        )

    def _add_pose_factor(
        self,
        graph: gtsam.NonlinearFactorGraph,
        k: int,
        pose: PoseMeasurement,
        pose_meas: tuple,  # (measured, covariance, reference[, shared covariance])
    ) -> gtsam.Pose3:
        """The H_d factor of frame k (prior, between, or keyframe between); its pose value."""
        measured, cov, ref = pose_meas[:3]
        if ref == 0:
            self._world_posed = True
            factor = None
            if self.backend.windowed or self.record is not None:  # else: the store's numbers
                factor = gtsam.PriorFactorPose3(X(k), measured, self._pose_noise(cov))
                graph.add(factor)
            self.backend.store.add_pose_prior(measured, cov)
            shared = pose_meas[3] if len(pose_meas) > 3 else None
            if shared is not None and not self._anchored:
                self._anchor(graph, shared)
            if factor is not None:
                self._record_pose(factor, pose, pose_meas)
            return measured
        noise = self._pose_noise(cov)
        if self.shared_reference_noise and not self._world_posed and not self._anchored:
            self._anchor(graph, _ZERO66)  # frame k0 had no pose: W is its frame all the same
        model = measurement_checks.keyframe_model(pose, k)
        args = (k, ref, measured, noise, model, self.backend.current_pose(ref))
        factor, pose_guess = keyframe_pose_factor(*args, in_graph := self.backend.in_graph(ref))
        self._add(graph, factor, "")  # the record: coupled, where a fixed-lag window froze r
        coupled = factor if in_graph or not self.record else keyframe_pose_factor(*args, True)[0]
        self._record_pose(coupled, pose, pose_meas)
        return pose_guess

    def _record_pose(self, factor: object, pose: PoseMeasurement, pose_meas: tuple) -> None:
        """The record's H_d factor, with the noise of its reference's pixels where known."""
        split = len(pose_meas) > 3 and pose_meas[3] is not None
        if self.record is not None and split and pose.reference_jacobian is not None:
            ids, J = np.asarray(pose.reference_ids), pose.reference_jacobian
            self.record.add_shared(factor, pose_meas[1], J, ids, pose_meas[2])  # type: ignore[arg-type]
        elif self.record is not None:
            self.record.measurement.append(factor)

    def _anchor(self, graph: gtsam.NonlinearFactorGraph, reference: np.ndarray) -> None:
        """X(k0) = I with the reference frame's noise: the H_d poses all carry its one draw,
        estimated as X(k0); poses are reported relative to it (:meth:`_relative`)."""
        covariance = reference + self._world_sigma**2 * np.eye(6)
        noise = gtsam.noiseModel.Gaussian.Covariance(covariance)
        self._add(graph, gtsam.PriorFactorPose3(X(self._indices[0]), gtsam.Pose3(), noise), "fixed")
        self._anchored = True

    def _add(self, graph: gtsam.NonlinearFactorGraph, factor: object, role: str, stored=False):
        """Add a factor to the graph, the back end's store (unless ``stored``), the record
        (as ``role``; "": not)."""
        graph.add(factor)
        if not stored:
            self.backend.store.add_factor(factor)
        if self.record is not None and role:
            getattr(self.record, role).append(factor)

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        k, t, pose_meas, twist_meas = self._checked_frame(frame)
        # Everything is checked: from here on the state changes.
        if self.process_noise.observe(frame):
            self.acceleration_sigma = self.process_noise.sigma
        if twist_meas is not None and self._poses_span(k, pose_meas, twist_meas[2]):
            twist_meas = None
            self.velocity_factor_counts["skipped"] += 1
        graph = gtsam.NonlinearFactorGraph()
        first = not self._indices
        dt = 0.0 if first else t - self._times[-1]
        self._add_start_or_motion(graph, k, dt)
        self._indices.append(k)
        self._times.append(t)
        self._last_reference = pose_meas[2] if pose_meas is not None else None
        if self.record is not None:
            self.record.add_frame(self._last_reference)
        shared = pose_meas[3] if pose_meas is not None and len(pose_meas) > 3 else None
        if shared is not None and pose_meas is not None and pose_meas[2] == 0:
            shared = _ZERO66  # in the graph: the anchor X(k0) carries it
        if shared is None:  # no new pose: the latest one's reference noise still applies
            shared = self._reference_cov[-1] if self._reference_cov else _ZERO66
        self._reference_cov.append(shared)

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
        if frame.keyframe_tilt is not None and self.backend.in_graph(frame.keyframe_tilt.frame):
            self._add(graph, tilt_factor(frame.keyframe_tilt), "measurement")
        if first:
            pose_guess = gtsam.Pose3()
        elif pose_guess is None or not use_measured:
            pose_guess = self._pose.compose(
                gtsam.Pose3.Expmap((0.5 * dt) * (self._twist + twist_guess))
            )
        if twist_meas is not None:
            self.velocity_factor_counts["used"] += 1
            z, cov, indices, weights = twist_meas
            noise = measurement_noise(cov, self.robust, self.robust_threshold)
            factor = _mean_velocity_factor([V(i) for i in indices], weights, z, noise)
            self._add(graph, factor, "measurement")

        values = gtsam.Values()
        values.insert(X(k), pose_guess)
        values.insert(V(k), twist_guess)
        if self.motion_model == "wnj":
            values.insert(A(k), _ZERO6)  # every factor is linear in A: any start is exact
        pose, twist, covariance = self.backend.add(graph, values, k, t - self._times[0])
        anchor = self.backend.current_pose(self._indices[0])
        if covariance is not None:
            covariance = self._with_reference_noise(len(self._indices) - 1, covariance)
            if self._anchored:
                covariance = self._with_anchor_noise(covariance, pose, anchor)
        self._pose, self._twist = pose, twist
        pose = self._relative(pose, anchor)
        position, v = np.asarray(pose.translation(), dtype=float), np.asarray(twist, dtype=float)
        return StateEstimate(k, t, pose.rotation().matrix(), position, v, covariance)

    def _add_start_or_motion(self, graph: gtsam.NonlinearFactorGraph, k: int, dt: float) -> None:
        """The first frame's priors, or the motion factors from the previous frame (as
        numbers in the store; as factors only for the window and the record)."""
        self.backend.store.add_frame(k)
        if not self._indices:
            world = self._anchor_start if self.shared_reference_noise else self._world_noise
            self._add(graph, gtsam.PriorFactorPose3(X(k), gtsam.Pose3(), world), "fixed")
            for key in twist_keys(self.motion_model, k):  # V(k) (and A(k))
                prior = gtsam.PriorFactorVector(key, _ZERO6, self._twist_prior_noise)
                self._add(graph, prior, "fixed")
            return
        previous, sigma = self._indices[-1], self.acceleration_sigma
        if self.backend.windowed or self.record is not None:
            for factor in self._motion(self.motion_model, previous, k, dt, sigma):
                self._add(graph, factor, "motion", stored=True)
        self.backend.store.add_motion(dt, sigma, self.motion_model)

    def _poses_span(self, k: int, pose_meas: tuple | None, nodes: list[int]) -> bool:
        """Whether H_d poses of the previous frame and of frame k already measure the H_c
        interval (against one reference, or frame k's against the previous frame)."""
        if self.velocity_factors == "all" or pose_meas is None or len(self._indices) == 0:
            return False
        previous = self._indices[-1]
        return nodes == [previous, k] and poses_span(previous, self._last_reference, pose_meas[2])

    def _with_anchor_noise(
        self, covariance: np.ndarray, pose: gtsam.Pose3, anchor: gtsam.Pose3
    ) -> np.ndarray:
        """Online poses are relative to the anchor's estimate: add its marginal, moved to X(k)."""
        isam = getattr(self.backend, "isam", None)
        if isam is not None and isam.valueExists(X(self._indices[0])):
            self._anchor_covariance = isam.marginalCovariance(X(self._indices[0]))
        Ad = pose.between(anchor).AdjointMap()
        covariance = covariance.copy()
        covariance[:6, :6] += Ad @ self._anchor_covariance @ Ad.T
        return covariance

    def _relative(self, pose: gtsam.Pose3, anchor: gtsam.Pose3) -> gtsam.Pose3:
        """The pose in W: X_k = Y_0^-1 Y_k, with Y the graph's (anchored) poses."""
        return anchor.between(pose) if self._anchored else pose

    def _with_reference_noise(self, position: int, covariance: np.ndarray) -> np.ndarray:
        """The 12x12 marginal plus the shared reference noise the factors left out."""
        shared = self._reference_cov[position] if self.shared_reference_noise else _ZERO66
        return covariance + np.pad(shared, (0, 6))

    # -- results ----------------------------------------------------------------------------

    def online_trajectory(self) -> Trajectory:
        if not self.backend.windowed:
            raise InputError("online_trajectory: the run kept no online estimates (online=False)")
        return super().online_trajectory()

    def trajectory(self) -> Trajectory:
        """The smoothed estimate of every frame so far (see the class docstring per solver)."""
        n = len(self._indices)
        rotations = np.empty((n, 3, 3))
        positions = np.empty((n, 3))
        twists = np.empty((n, 6))
        covariances = np.empty((n, 12, 12)) if self.compute_covariance else None
        if n == 0:
            return Trajectory(np.empty(0), rotations, positions, twists, covariances)
        # The back end's marginals are not the smoothed covariance (error_covariance).
        finals = [
            (p, np.asarray(v)) for p, v, _ in self.backend.final(self._indices, marginals=False)
        ]
        anchor = finals[0][0]
        for i, (pose, twist) in enumerate(finals):
            relative = self._relative(pose, anchor)
            rotations[i] = relative.rotation().matrix()
            positions[i] = relative.translation()
            twists[i] = twist
        if covariances is not None:
            assert self.record is not None
            smoothed = self.record.covariances(
                finals, self._indices, self._times, anchored=self._anchored
            )
            smoothed[:, :6, :6] += self._world_sigma**2 * np.eye(6)
            modelled = self.record.shared_references  # their reference noise is in the chain
            for i, (c, r) in enumerate(zip(smoothed, self.record.keyframes, strict=True)):
                covariances[i] = c if r in modelled else self._with_reference_noise(i, c)
        return Trajectory(np.array(self._times), rotations, positions, twists, covariances)


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
