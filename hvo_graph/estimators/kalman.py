"""The paper's 12-state Kalman filter (Tick, Shen, Gans, eqs. 6-7 and appendix): the baseline.

This is the filter *as written* in the paper (restated in paper/NOTES.md
section 5), not an improved one; docs/kalman.md explains every choice.

State (index 0..11)::

    x = [x, y, z, p, w, r, vx, vy, vz, wx, wy, wz]

position in the world frame W, pitch p, yaw w, roll r (R_wc = R_y(w) R_x(p) R_z(r)),
linear velocity v and angular velocity w of the camera. Model (eqs. 6-7)::

    x_k = F_k x_{k-1} + q_k,   q_k ~ N(0, Q_k)
    y_k = C_k x_k + r_k,       r_k ~ N(0, R_k),  C_k = I_12

with F_k from :func:`transition_matrix` (evaluated at the previous estimate's
r, p) and Q_k from :func:`process_covariance`. The update is the textbook one
(filterpy names: x, P, F, Q, H = C, R, y = innovation, S, K) with the Joseph
form of the covariance update.

The paper's simplification (kept by default): the body-frame linear velocity
measured from H_c is integrated straight into the world position
(x += dt vx). ``world_frame_velocity=True`` is the separate, documented option
that rotates the measured v into W first.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence

import numpy as np

from hvo_graph.errors import InputError, as_covariance, as_integer, as_vector
from hvo_graph.estimators._kalman_run import fast_run_applies, filter_frames
from hvo_graph.estimators.base import Estimator, placed_world_pose
from hvo_graph.estimators.kalman_calibration import (
    MIN_FRAMES,
    calibrated,
    calibration_matrix,
    resolves_acceleration,
    smoothed_states,
    twist_differences,
)
from hvo_graph.estimators.kalman_keyframes import (
    KeyframeErrors,
    tangent_to_pose_state,
    world_pose_jacobian,
)
from hvo_graph.estimators.kalman_model import (
    ANGLES,
    ANGULAR_VELOCITY,
    DEFAULT_INITIAL_COVARIANCE,
    LINEAR_VELOCITY,
    PAPER_R_NOISE_FREE,
    PAPER_R_NOISY,
    POSITION,
    R_PRESETS,
    STATE_NAMES,
    StateMeasurement,
    _check_pitch,
    _check_process_noise,
    _euler_rates,
    _euler_rates_inverse,
    _prepared_measurements,
    _rotation,
    _selection,
    _state_measurement,
    _wrap,
    _wrap_angles,
    _wrap_entries,
    process_covariance,
    state_measurement,
    state_to_tangent_jacobian,
    transition_matrix,
)
from hvo_graph.estimators.measurement_checks import checked_reference_covariance, poses_span
from hvo_graph.estimators.noise_estimation import filter_process_noise
from hvo_graph.estimators.process_noise import (
    DEFAULT_ACCELERATION_SIGMA,
    DEFAULT_PROCESS_NOISE,
    kalman_process_noise,
)
from hvo_graph.geometry.rotation import euler_to_rotation
from hvo_graph.types import FrameMeasurement, PoseMeasurement, StateEstimate, Trajectory

#: R_k diagonals of the paper's presets by (id of the row pattern, preset): constant.
_PRESET_ROWS: dict[tuple[int, str], tuple] = {}
#: [w; v] of the state (body-frame velocity): x[9:12], x[6:9].
_TWIST_ROWS = np.r_[ANGULAR_VELOCITY, LINEAR_VELOCITY]
_I12 = np.eye(12)
_I12.setflags(write=False)
#: state_to_tangent_jacobian's constant entries (body-frame velocity state).
_J_TEMPLATE = np.zeros((12, 12))
_J_TEMPLATE[6:9, ANGULAR_VELOCITY] = np.eye(3)
_J_TEMPLATE[9:12, LINEAR_VELOCITY] = np.eye(3)
_J_TEMPLATE.setflags(write=False)


class KalmanBaseline(Estimator):
    """The paper's 12-state Kalman filter over front-end measurement records.

    Per frame: predict with F_k, Q_k over dt = t_k - t_{k-1} (not at the first
    frame), then update with the measured rows of C_k = I_12 (pose rows 0..5 from
    H_d, velocity rows 6..11 from H_c; a frame without either is predict-only).

    Attributes (filterpy names, after the latest step): ``x`` (12,) state,
    ``P`` (12, 12) covariance, ``F``, ``Q`` of the latest predict, ``H``, ``R``,
    ``y`` (innovation), ``S`` (innovation covariance), ``K`` (gain) of the latest
    update (None before the first update or on predict-only frames).

    Args:
        r_preset: "paper-noisy" (default), "paper-noise-free" (the paper's two R_k
            diagonals), or "measured": not the paper, the front end's noise model
            given to the filter as it is given to the smoother. R_k is the diagonal
            of each pose's own-pixel covariance (``covariance -
            reference_covariance``) in state coordinates; the reference frame's
            shared noise is added to the reported pose covariance. Poses against
            keyframes: the reported covariance is that of the filter's errors, the
            keyframes' errors cloned in (:mod:`.kalman_keyframes`); the estimates
            are the same.
        process_noise: (6,) Q_k scalars (sigma_x, sigma_y, sigma_z, sigma_p,
            sigma_w, sigma_r); default DEFAULT_PROCESS_NOISE. "auto": the
            maximum-likelihood white-noise acceleration of the sequence, fitted
            by :meth:`run` before filtering (the filter stays causal given it;
            :func:`~hvo_graph.estimators.noise_estimation.filter_process_noise`).
        seed: seed of the random initial state (None: fresh entropy).
        random_init: draw x_0 ~ N(0, P_0), as the paper starts "from a random
            initial state"; False: x_0 = 0 (the world frame is the first camera
            frame, so zero pose is exact at t_0).
        initial_state: (12,) x_0, used as given (random_init is then ignored).
        initial_covariance: (12, 12) P_0, symmetric positive definite; default
            DEFAULT_INITIAL_COVARIANCE.
        velocity_updates: "all" (the paper): every H_c twist updates the filter;
            "gaps": only where two poses against the same reference do not already
            span its interval (front-end twists are made of the same pixels as
            those poses, and would count them twice).
        world_frame_velocity: not the paper: rotate the measured body-frame v into
            W with the measured R_wc before the update, so the state's v is world
            velocity and x += dt v is exact to first order. The output twist is
            rotated back to the body frame.
        calibrate_twist: with "measured" R, :meth:`run` reports a twist covariance
            calibrated against the Rauch-Tung-Striebel smoother of the same model
            (:mod:`.kalman_calibration`: the filter's lag under smooth motion, which P
            leaves out); the estimates and :meth:`online_trajectory` are unchanged.
            Ignored with the paper's presets.
    """

    name = "kalman"

    def __init__(
        self,
        *,
        r_preset: str = "paper-noisy",
        process_noise: Sequence[float] | np.ndarray | str | None = None,
        seed: int | None = 0,
        random_init: bool = True,
        initial_state: np.ndarray | None = None,
        initial_covariance: np.ndarray | None = None,
        world_frame_velocity: bool = False,
        velocity_updates: str = "all",
        calibrate_twist: bool = True,
    ) -> None:
        super().__init__()
        self.calibrate_twist = bool(calibrate_twist)
        if velocity_updates not in ("all", "gaps"):
            raise InputError(
                f"velocity_updates: expected 'all' or 'gaps', got {velocity_updates!r}"
            )
        self.velocity_updates = velocity_updates
        if r_preset not in R_PRESETS:
            raise InputError(f"r_preset: expected one of {', '.join(R_PRESETS)}, got {r_preset!r}")
        if seed is not None:
            as_integer(seed, "seed", 0, what="None or an integer")
        self.r_preset = r_preset
        #: Whether Q_k is fitted to the sequence by :meth:`run` ("auto").
        self.auto_process_noise = isinstance(process_noise, str)
        if self.auto_process_noise and process_noise != "auto":
            raise InputError(f"process_noise: expected 'auto' or numbers, got {process_noise!r}")
        self.process_noise = _check_process_noise(
            DEFAULT_PROCESS_NOISE
            if process_noise is None or self.auto_process_noise
            else process_noise
        )
        self._shared = np.zeros((6, 6))  # reference noise of the latest pose ("measured")
        #: "measured": the error covariance with the keyframes' errors in it (None: = P).
        self.keyframe_errors: KeyframeErrors | None = None
        self._shared_nonzero = False
        self._last_pose: tuple[int, int] | None = None  # (frame, reference) of the latest pose
        self._first_pose: int | None = None  # frame of the first pose met by update()
        self.world_frame_velocity = bool(world_frame_velocity)
        P0 = as_covariance(
            DEFAULT_INITIAL_COVARIANCE if initial_covariance is None else initial_covariance,
            "initial_covariance",
            12,
        )
        L = np.linalg.cholesky(P0)
        if initial_state is not None:
            x0 = as_vector(initial_state, "initial_state", 12).copy()
        elif random_init:
            x0 = L @ np.random.default_rng(seed).standard_normal(12)
        else:
            x0 = np.zeros(12)
        x0[ANGLES] = _wrap(x0[ANGLES])
        _check_pitch(x0[3], "initial_state")
        self.x: np.ndarray = x0
        self.P: np.ndarray = np.array(P0, dtype=float)
        self.F: np.ndarray | None = None
        self.Q: np.ndarray | None = None
        self.H: np.ndarray | None = None
        self.R: np.ndarray | None = None
        self.y: np.ndarray | None = None
        self.S: np.ndarray | None = None
        self.K: np.ndarray | None = None
        self._t_prev: float | None = None
        self._q_cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._R_diag: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        self._J = _J_TEMPLATE.copy()  # state_estimate's Jacobian, filled in place
        self._prepared: dict[int, StateMeasurement] = {}  # y_k by id(frame), during run()
        self._steps: list[tuple[float, np.ndarray, np.ndarray]] | None = None  # (t, x, P)
        self._calibrated: Trajectory | None = None  # run()'s, with the twist calibrated

    # -- the textbook steps ---------------------------------------------------------

    def predict(self, dt: float) -> None:
        """x = F x, P = F P F^T + Q, with F_k at the current estimate's (r, p)."""
        F = self._transition(dt)
        Q = self._process_covariance(dt)
        x = F @ self.x
        _wrap_angles(x)
        self.x, self.P, self.F, self.Q = x, F @ self.P @ F.T + Q, F, Q
        if self.keyframe_errors is not None:
            self.keyframe_errors.predict(F, Q)

    def correct(self, z: np.ndarray, rows: np.ndarray, R_diag: np.ndarray) -> None:
        """Update with z = H x + noise, H = rows of I_12, R = diag(R_diag).

        y = z - H x (angle rows wrapped to (-pi, pi]), S = H P H^T + R,
        K = P H^T S^-1, x = x + K y, P = (I - K H) P (I - K H)^T + K R K^T (Joseph form).
        """
        H, angle = _selection(rows)
        r = np.asarray(R_diag, dtype=float)
        R = self._R_diag[1] if self._R_diag[0] is r else np.diag(r)
        self._R_diag = (r, R)  # the presets give the same r array frame after frame
        # H selects rows of I_12, so H v = v[rows], H P = P[rows], K H = K in the columns
        # rows and K R = K r: the same numbers as the products, without the 12 x 12 matmuls.
        P = self.P
        full = len(rows) == 12
        HP = P if full else P[rows]
        y = np.asarray(z, dtype=float) - (self.x if full else self.x[rows])
        if angle is not None:
            _wrap_entries(y, angle)
        S = (HP if full else HP[:, rows]) + R
        K = np.linalg.solve(S, HP).T  # = P H^T S^-1 (P, S symmetric)
        x = self.x + K @ y
        _wrap_angles(x)
        if full:
            I_KH = _I12 - K
        else:
            I_KH = _I12.copy()
            I_KH[:, rows] -= K
        P = I_KH @ P @ I_KH.T + (K * r) @ K.T
        self.x, self.P = x, 0.5 * (P + P.T)
        self.H, self.R, self.y, self.S, self.K = H, R, y, S, K

    def _transition(self, dt: float) -> np.ndarray:
        """:func:`transition_matrix` at the current (r, p), with its checks: F_k."""
        if not (isinstance(dt, float) and 0.0 < dt < math.inf):
            return transition_matrix(self.x[5], self.x[3], dt)  # raises with its message
        p, _, r = self.x[3:6].tolist()
        E = _euler_rates(r, p, "euler_rate_matrix")
        F = _I12.copy()
        F[0, 6] = F[1, 7] = F[2, 8] = dt
        F[3:6, 9:12] = dt * E
        return F

    def _process_covariance(self, dt: float) -> np.ndarray:
        """:func:`process_covariance` (dt, process_noise), kept for the last few dt."""
        cached = self._q_cache.get(dt)
        if cached is None or cached[0] is not self.process_noise:
            if len(self._q_cache) > 64:  # frame intervals take few distinct values
                self._q_cache.clear()
            cached = (self.process_noise, process_covariance(dt, self.process_noise))
            self._q_cache[dt] = cached
        return cached[1]

    # -- the estimator interface ----------------------------------------------------

    def _r_diagonal(self, meas: StateMeasurement, k: int) -> np.ndarray:
        if self.r_preset == "measured":
            if np.any(meas.variance <= 0):
                bad = [STATE_NAMES[i] for i in meas.rows[meas.variance <= 0]]
                raise InputError(
                    f"frame {k}: r_preset 'measured' needs positive measurement variances, "
                    f"got <= 0 for {', '.join(bad)}"
                )
            return meas.variance
        full = PAPER_R_NOISY if self.r_preset == "paper-noisy" else PAPER_R_NOISE_FREE
        key = (id(meas.rows), self.r_preset)
        kept = _PRESET_ROWS.get(key)  # constant per row pattern: the same array each frame
        if kept is None or kept[0] is not meas.rows:
            kept = _PRESET_ROWS[key] = (meas.rows, full[meas.rows], None)
        return kept[1]

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        t = float(frame.t)
        if not math.isfinite(t):
            raise InputError(f"frame {frame.index}: t is not finite ({frame.t})")
        self._track_keyframe(frame)  # before predict: the state is still the keyframe's
        if self._t_prev is not None:
            self.predict(t - self._t_prev)
        self._t_prev = t
        # predict-only frames leave the last update's H, R, y, S, K undefined
        self.H = self.R = self.y = self.S = self.K = None
        if frame.pose is not None and self._last_pose is None:
            self._first_pose = frame.index
        frame = self._own_noise(frame)
        against = None  # (clone slot, dg/dc) of a pose against a tracked keyframe
        if frame.pose is not None and frame.pose.reference != 0:
            tracked = self.keyframe_errors
            slot = None if tracked is None else tracked.find(frame.pose.reference)
            if slot is not None:
                assert tracked is not None
                against = (slot, world_pose_jacobian(frame.pose, tracked.poses[slot]))
            frame = dataclasses.replace(frame, pose=self._world_pose(frame.pose))
        if self.world_frame_velocity:
            p, w, r = self.x[ANGLES]
            meas = state_measurement(
                frame, world_frame_velocity=True, fallback_rotation=euler_to_rotation(r, p, w)
            )
        else:  # the paper's R_k presets read no measured variances
            meas = self._prepared.pop(id(frame), None)  # (run: converted at once)
            if meas is None:
                measured = self.r_preset == "measured"
                meas = _state_measurement(frame, False, None, variances=measured)
        if meas.rows.size:
            R_diag = self._r_diagonal(meas, frame.index)
            self.correct(meas.z, meas.rows, R_diag)
            if self.keyframe_errors is not None:
                self.keyframe_errors.correct(self.K, meas.rows, R_diag, against)
        _check_pitch(float(self.x[3]), f"frame {frame.index}: estimated state")
        if self._steps is not None:
            self._steps.append((t, self.x.copy(), self.P.copy()))
        return self.state_estimate(frame.index, t)

    def run(self, frames: Iterable[FrameMeasurement], *, online: bool = True) -> Trajectory:
        """Filter a whole sequence; "auto" process noise is fitted on it first (a filter's
        final estimates are its online ones: ``online`` changes nothing)."""
        frames = list(frames)
        if self.auto_process_noise and not self._online:
            sigma = filter_process_noise(frames, default=DEFAULT_ACCELERATION_SIGMA)
            self.process_noise = kalman_process_noise(sigma)
        if fast_run_applies(self):  # every frame up to the first keyframe-relative pose
            frames = frames[filter_frames(self, frames) :]
            if not frames:
                return self.trajectory()
        if not self.world_frame_velocity and self.r_preset != "measured":
            # y_k of every frame converted at once; update() takes each frame's own (the
            # frame objects stay alive in ``frames``, so their ids stay theirs).
            self._prepared = _prepared_measurements(frames)
        calibrate = self.calibrate_twist and self.r_preset == "measured" and not self._online
        self._steps = [] if calibrate else None
        try:
            super().run(frames)
            if calibrate:
                self._calibrate()
            return self.trajectory()
        finally:
            self._prepared = {}
            self._steps = None

    def trajectory(self) -> Trajectory:
        """The filtered estimates; after :meth:`run` with "measured" R, with the twist
        covariance calibrated (``calibrate_twist``), until the next update."""
        online = self.online_trajectory()
        calibrated = self._calibrated
        if calibrated is not None and len(calibrated) == len(online):
            return calibrated
        return online

    def _calibrate(self) -> None:
        """:mod:`.kalman_calibration` over the frames :meth:`run` filtered."""
        assert self._steps is not None
        online = self.online_trajectory()
        if not resolves_acceleration(self.process_noise):
            return  # no acceleration found: no lag to find (module docstring)
        if online.covariances is None or not MIN_FRAMES <= len(self._steps) == len(online):
            return
        times = np.array([step[0] for step in self._steps])
        x = np.array([step[1] for step in self._steps])
        P = np.array([step[2] for step in self._steps])
        x_s = smoothed_states(times, x, P, self._process_covariance)
        b = twist_differences(x, x_s, world_frame_velocity=self.world_frame_velocity)
        S = calibration_matrix(b, online.covariances[:, 6:, 6:])
        if S is not None:
            self._calibrated = dataclasses.replace(
                online, covariances=calibrated(online.covariances, S)
            )

    def _track_keyframe(self, frame: FrameMeasurement) -> None:
        """Measured R: when poses start to come against the frame just filtered, its error
        enters the error covariance as a clone (:mod:`.kalman_keyframes`), and when they
        move to another reference, the shared noise of the poses so far enters the
        state's error (they all carried it)."""
        pose = frame.pose
        if self.r_preset != "measured" or pose is None or self._last_pose is None:
            return
        if pose.reference == self._last_pose[1]:
            return
        tracked = self.keyframe_errors
        if tracked is None:
            tracked = self.keyframe_errors = KeyframeErrors([], [], self.P.copy())
        T = tangent_to_pose_state(self.x[:6])
        offset = T @ self._shared @ T.T
        self._shared = np.zeros((6, 6))
        latest = self._online.last()[0] if self._online else None
        if pose.reference != 0 and pose.reference == latest:
            tracked.add(pose.reference, self.x[:6], offset)
        else:
            tracked.covariance[:6, :6] += offset

    def _world_pose(self, pose: PoseMeasurement) -> PoseMeasurement:
        """:meth:`pose_in_world`, except for a keyframe older than the first pose (the
        first frame saw too few points): the filter's estimate of it is then its random
        initial state, the front end's (predicted from W = frame 0 on) is far closer."""
        early = self._first_pose is not None and pose.reference < self._first_pose
        placed = placed_world_pose(pose) if early else None
        return self.pose_in_world(pose) if placed is None else placed

    def _own_noise(self, frame: FrameMeasurement) -> FrameMeasurement:
        """The frame as the filter uses it: with "measured" R, the pose's own-pixel
        covariance (the shared reference part kept for the output); with "gaps", no
        twist the poses already span."""
        pose, velocity = frame.pose, frame.velocity
        previous = self._last_pose
        if pose is not None:
            self._last_pose = (frame.index, pose.reference)
            if self.r_preset == "measured" and pose.reference_covariance is not None:
                self._shared = checked_reference_covariance(pose, frame.index)
                self._shared_nonzero = True
                pose = dataclasses.replace(pose, covariance=pose.covariance - self._shared)
            gaps = self.velocity_updates == "gaps"
            if gaps and velocity is not None and previous is not None and self._online:
                last = self._online[-1].index
                before = previous[1] if previous[0] == last else None
                velocity = None if poses_span(last, before, pose.reference) else velocity
        if pose is frame.pose and velocity is frame.velocity:
            return frame
        return dataclasses.replace(frame, pose=pose, velocity=velocity)

    def state_estimate(self, index: int, t: float) -> StateEstimate:
        """The current state in the contract's form (R_wc, p_wc, body twist [w; v]).

        The covariance is J P J^T with J = :func:`state_to_tangent_jacobian`: a
        first-order map of the Euler-angle covariance to the right-perturbation
        rotation tangent (and, with world_frame_velocity, of v to the body frame).
        """
        x = self.x
        if self.world_frame_velocity:
            p, w, r = x[ANGLES]
            R_wc = euler_to_rotation(r, p, w)
            v = R_wc.T @ x[LINEAR_VELOCITY]
            J = state_to_tangent_jacobian(x, world_frame_velocity=True)
        else:  # the same arithmetic without the argument checks
            p, w, r = x[3:6].tolist()
            R_wc = _rotation(r, p, w)
            v = None  # the state's body velocity: twist = x[_TWIST_ROWS]
            J = self._J  # only its two blocks change (the rest: _J_TEMPLATE)
            J[0:3, 3:6] = _euler_rates_inverse(r, p, "euler_rate_matrix")
            J[3:6, 0:3] = R_wc.T
        error = self.P if self.keyframe_errors is None else self.keyframe_errors.state
        cov = J @ error @ J.T
        if self._shared_nonzero:  # "measured" with reference covariances
            cov[:6, :6] += self._shared
        return StateEstimate(
            index=index,
            t=t,
            rotation=R_wc,
            position=x[POSITION].copy(),
            twist=x[_TWIST_ROWS] if v is None else np.concatenate((x[ANGULAR_VELOCITY], v)),
            covariance=0.5 * (cov + cov.T),
        )
