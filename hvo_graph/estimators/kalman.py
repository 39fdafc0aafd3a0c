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
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_covariance, as_integer, as_matrix, as_number, as_vector
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.measurement_checks import checked_reference_covariance
from hvo_graph.estimators.noise_estimation import estimate_process_noise
from hvo_graph.estimators.process_noise import (
    DEFAULT_ACCELERATION_SIGMA,
    DEFAULT_PROCESS_NOISE,
    kalman_process_noise,
    white_noise_blocks,
)
from hvo_graph.estimators.registry import KALMAN_R_PRESETS
from hvo_graph.geometry.rotation import euler_to_rotation, rotation_to_euler, skew, wrap_angle
from hvo_graph.types import FrameMeasurement, StateEstimate, Trajectory

#: Names of the 12 state components, in state order.
STATE_NAMES: tuple[str, ...] = ("x", "y", "z", "p", "w", "r", "vx", "vy", "vz", "wx", "wy", "wz")

POSITION = slice(0, 3)
ANGLES = slice(3, 6)  # p, w, r (pitch, yaw, roll)
LINEAR_VELOCITY = slice(6, 9)
ANGULAR_VELOCITY = slice(9, 12)
_ANGLE_ROWS = np.array([3, 4, 5])

#: R_k diagonal of the paper's noise-free run (Section IV), state order.
PAPER_R_NOISE_FREE: np.ndarray = np.array(
    [1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5]
)
PAPER_R_NOISE_FREE.setflags(write=False)

#: R_k diagonal of the paper's noisy run (Section IV, 0.05 px^2 pixel noise), state order.
PAPER_R_NOISY: np.ndarray = np.array(
    [0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3, 0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3]
)
PAPER_R_NOISY.setflags(write=False)

#: The R_k presets (:data:`hvo_graph.estimators.registry.KALMAN_R_PRESETS`).
R_PRESETS: tuple[str, ...] = KALMAN_R_PRESETS

#: Default P_0: the distribution the random initial state is drawn from (zero mean),
#: and the initial covariance. Standard deviations 0.5 m, 0.2 rad (11.5 deg),
#: 0.5 m/s, 0.5 rad/s.
DEFAULT_INITIAL_COVARIANCE: np.ndarray = np.diag(
    np.array([0.5] * 3 + [0.2] * 3 + [0.5] * 3 + [0.5] * 3) ** 2
)
DEFAULT_INITIAL_COVARIANCE.setflags(write=False)

#: |pitch| above this (89 deg) is refused: eqs. 3-5 (and so F_k) are singular at
#: p = +-90 deg, and sec p > 57 already turns tiny body rates into huge yaw/roll rates.
MAX_ABS_PITCH: float = float(np.deg2rad(89.0))


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]; values already inside are returned bit for bit."""
    a = np.asarray(a, dtype=float)
    return np.where((a > -np.pi) & (a <= np.pi), a, wrap_angle(a))


def _check_pitch(p: float, what: str) -> None:
    if not np.isfinite(p):
        raise InputError(f"{what}: pitch is not finite ({p})")
    pw = float(_wrap(p))
    if abs(pw) > MAX_ABS_PITCH:
        raise InputError(
            f"{what}: pitch p = {np.rad2deg(pw):.3f} deg is within "
            f"{90.0 - np.rad2deg(MAX_ABS_PITCH):.0f} deg of +-90 deg, where the Euler rate "
            "equations (paper eqs. 3-5) and F_k are singular; the paper's Kalman filter "
            "cannot represent this orientation"
        )


def euler_rate_matrix(r: float, p: float) -> np.ndarray:
    """(3, 3) E with [pdot, wdot, rdot] = E [wx, wy, wz]: paper eqs. 3-5 in state order.

    Rows: pitch (eq. 4), yaw (eq. 5), roll (eq. 3); columns: body rates wx, wy, wz.
    Also the first-order map from a body-frame rotation perturbation delta
    (R_true = R Exp(delta)) to the Euler angle perturbation (dp, dw, dr).

    Raises:
        InputError: when |p| > MAX_ABS_PITCH (near gimbal lock).
    """
    _check_pitch(p, "euler_rate_matrix")
    sr, cr, cp, tp = np.sin(r), np.cos(r), np.cos(p), np.tan(p)
    return np.array(
        [
            [cr, -sr, 0.0],  # pdot = wx cos r - wy sin r
            [sr / cp, cr / cp, 0.0],  # wdot = (wx sin r + wy cos r) sec p
            [sr * tp, cr * tp, 1.0],  # rdot = (wx sin r + wy cos r) tan p + wz
        ]
    )


def transition_matrix(r: float, p: float, dt: float) -> np.ndarray:
    """F_k (12, 12) of the paper's appendix (NOTES section 5), at roll r, pitch p.

    F_k = I_12 with F[0,6] = F[1,7] = F[2,8] = dt (position += dt * velocity, the
    velocity taken as is: the paper's simplification) and the Euler rows
    (eqs. 3-5) multiplying dt::

        F[3,9]  = cos r dt          F[3,10] = -sin r dt
        F[4,9]  = sin r / cos p dt  F[4,10] = cos r / cos p dt
        F[5,9]  = sin r tan p dt    F[5,10] = cos r tan p dt    F[5,11] = dt

    Args:
        r: roll (rad) of the previous estimate.
        p: pitch (rad) of the previous estimate.
        dt: time step (s), > 0.

    Raises:
        InputError: dt not finite and > 0, or |p| > MAX_ABS_PITCH (near gimbal lock).
    """
    dt = _check_dt(dt)
    if not np.isfinite(r):
        raise InputError(f"transition_matrix: roll is not finite ({r})")
    E = euler_rate_matrix(r, p)
    F = np.eye(12)
    F[POSITION, LINEAR_VELOCITY] = dt * np.eye(3)
    F[ANGLES, ANGULAR_VELOCITY] = dt * E
    return F


def process_covariance(dt: float, s: Sequence[float] | np.ndarray) -> np.ndarray:
    """Q_k (12, 12) of the paper's appendix (NOTES section 5): white-noise acceleration.

    For each pair (i, i+6), i = 0..5 (x-vx, y-vy, z-vz, p-wx, w-wy, r-wz), with the
    scalar s_i (the paper's sigma_i, used as is, not squared)::

        Q[i, i] = s_i dt^3 / 3,  Q[i, i+6] = Q[i+6, i] = s_i dt^2 / 2,  Q[i+6, i+6] = s_i dt

    Args:
        dt: time step (s), > 0.
        s: (6,) scalars (sigma_x, sigma_y, sigma_z, sigma_p, sigma_w, sigma_r), >= 0.
    """
    dt = _check_dt(dt)
    s = _check_process_noise(s)
    Q = np.zeros((12, 12))
    i = np.arange(6)
    Q[i, i], Q[i, i + 6], Q[i + 6, i + 6] = white_noise_blocks(s, dt)
    Q[i + 6, i] = Q[i, i + 6]
    return Q


def _check_dt(dt: float) -> float:
    return as_number(dt, "dt", above=0.0, what="a finite time step", unit=" s")


def _check_process_noise(s: object) -> np.ndarray:
    s = as_vector(s, "process_noise", 6)
    if np.any(s < 0):
        raise InputError(f"process_noise: expected six values >= 0, got {s.tolist()}")
    return s


@dataclass(frozen=True)
class StateMeasurement:
    """One frame's measurement in the filter's coordinates.

    Attributes:
        rows: (m,) state indices measured (0..5 pose, 6..11 velocity; C_k = the
            rows of I_12).
        z: (m,) measured values y_k in state coordinates (angles in rad).
        variance: (m,) the front end's covariances converted to state
            coordinates, diagonal only (the "measured" R preset).
    """

    rows: np.ndarray
    z: np.ndarray
    variance: np.ndarray


def state_measurement(
    frame: FrameMeasurement,
    *,
    world_frame_velocity: bool = False,
    fallback_rotation: np.ndarray | None = None,
) -> StateMeasurement:
    """Convert a front-end :class:`FrameMeasurement` into y_k (state coordinates).

    - pose (rows 0..5): p_wc and the Euler angles (p, w, r) of R_wc; its
      variance is diag(R_wc Sigma_trans R_wc^T) for position (right-perturbation
      translation is body-frame) and diag(E Sigma_rot E^T) for the angles, E =
      :func:`euler_rate_matrix` at the measured (r, p);
    - velocity (rows 6..11): the twist [w; v] reordered to [v; w]; its variance
      the matching diagonal of the twist covariance.
    - ``world_frame_velocity``: v is rotated into W with the measured R_wc (or
      ``fallback_rotation`` when the frame has no pose), and so is its covariance.

    Raises:
        InputError: a pose whose reference is not the world frame (0): the
            paper's filter has no keyframes; a pitch near +-90 deg; malformed arrays.
    """
    k = frame.index
    rows: list[np.ndarray] = []
    z: list[np.ndarray] = []
    var: list[np.ndarray] = []
    R_wc = fallback_rotation
    if frame.pose is not None:
        pose = frame.pose
        if pose.reference != 0:
            raise InputError(
                f"frame {k}: pose.reference is {pose.reference}, expected 0: the paper's "
                "Kalman filter measures pose against the world frame only (no keyframes)"
            )
        R_wc = as_matrix(pose.rotation, f"frame {k}: pose.rotation", (3, 3))
        p_wc = as_vector(pose.position, f"frame {k}: pose.position", 3)
        cov = as_matrix(pose.covariance, f"frame {k}: pose.covariance", (6, 6))
        roll, pitch, yaw = rotation_to_euler(R_wc)
        _check_pitch(pitch, f"frame {k}: measured pose")
        E = euler_rate_matrix(roll, pitch)
        rows.append(np.arange(0, 6))
        z.append(np.concatenate([p_wc, [pitch, yaw, roll]]))
        var.append(
            np.concatenate([np.diag(R_wc @ cov[3:, 3:] @ R_wc.T), np.diag(E @ cov[:3, :3] @ E.T)])
        )
    if frame.velocity is not None:
        vel = frame.velocity
        twist = as_vector(vel.twist, f"frame {k}: velocity.twist", 6)
        cov = as_matrix(vel.covariance, f"frame {k}: velocity.covariance", (6, 6))
        v, w = twist[3:], twist[:3]
        cov_v = cov[3:, 3:]
        if world_frame_velocity:
            if R_wc is None:
                raise InputError(
                    f"frame {k}: world_frame_velocity needs a rotation (a pose measurement "
                    "or fallback_rotation) to rotate the body-frame velocity into the world"
                )
            v = R_wc @ v
            cov_v = R_wc @ cov_v @ R_wc.T
        rows.append(np.arange(6, 12))
        z.append(np.concatenate([v, w]))
        var.append(np.concatenate([np.diag(cov_v), np.diag(cov[:3, :3])]))
    if not rows:
        return StateMeasurement(np.zeros(0, dtype=int), np.zeros(0), np.zeros(0))
    return StateMeasurement(np.concatenate(rows), np.concatenate(z), np.concatenate(var))


def state_to_tangent_jacobian(x: np.ndarray, *, world_frame_velocity: bool = False) -> np.ndarray:
    """(12, 12) J mapping a state perturbation to [pose tangent; twist] (first order).

    Output order: [delta_rot (3), delta_trans (3), dw (3), dv (3)] with the
    contract's right perturbation T_true = T_est Exp([delta_rot; delta_trans]) and
    the body twist [w; v]::

        delta_rot   = E^-1 d(p, w, r)      E = euler_rate_matrix(r, p)
        delta_trans = R_wc^T d(x, y, z)
        dw          = d(wx, wy, wz)
        dv          = d(vx, vy, vz)                        (body-velocity state)
                    = R_wc^T d(v_world) + [v_body]^ delta_rot   (world_frame_velocity)

    The filter's covariance maps to the contract's as J P J^T.
    """
    x = as_vector(x, "x", 12)
    p, w, r = x[ANGLES]
    R_wc = euler_to_rotation(r, p, w)
    E_inv = np.linalg.inv(euler_rate_matrix(r, p))
    J = np.zeros((12, 12))
    J[0:3, ANGLES] = E_inv
    J[3:6, POSITION] = R_wc.T
    J[6:9, ANGULAR_VELOCITY] = np.eye(3)
    if world_frame_velocity:
        v_body = R_wc.T @ x[LINEAR_VELOCITY]
        J[9:12, LINEAR_VELOCITY] = R_wc.T
        # v_b = (R Exp(d))^T v_w ~ v_b - d^ v_b = v_b + v_b^ d
        J[9:12, ANGLES] = skew(v_body) @ E_inv
    else:
        J[9:12, LINEAR_VELOCITY] = np.eye(3)
    return J


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
            shared noise is added to the reported pose covariance.
        process_noise: (6,) Q_k scalars (sigma_x, sigma_y, sigma_z, sigma_p,
            sigma_w, sigma_r); default DEFAULT_PROCESS_NOISE. "auto": the
            maximum-likelihood white-noise acceleration of the sequence, fitted
            by :meth:`run` before filtering (the filter stays causal given it;
            :func:`~hvo_graph.estimators.noise_estimation.estimate_process_noise`).
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
    ) -> None:
        super().__init__()
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
        self._last_pose: tuple[int, int] | None = None  # (frame, reference) of the latest pose
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

    # -- the textbook steps ---------------------------------------------------------

    def predict(self, dt: float) -> None:
        """x = F x, P = F P F^T + Q, with F_k at the current estimate's (r, p)."""
        p, r = self.x[3], self.x[5]
        F = transition_matrix(r, p, dt)
        Q = process_covariance(dt, self.process_noise)
        x = F @ self.x
        x[ANGLES] = _wrap(x[ANGLES])
        self.x, self.P, self.F, self.Q = x, F @ self.P @ F.T + Q, F, Q

    def correct(self, z: np.ndarray, rows: np.ndarray, R_diag: np.ndarray) -> None:
        """Update with z = H x + noise, H = rows of I_12, R = diag(R_diag).

        y = z - H x (angle rows wrapped to (-pi, pi]), S = H P H^T + R,
        K = P H^T S^-1, x = x + K y, P = (I - K H) P (I - K H)^T + K R K^T (Joseph form).
        """
        rows = np.asarray(rows, dtype=int)
        H = np.eye(12)[rows]
        R = np.diag(np.asarray(R_diag, dtype=float))
        y = np.asarray(z, dtype=float) - H @ self.x
        angle = np.isin(rows, _ANGLE_ROWS)
        y[angle] = _wrap(y[angle])
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T  # = P H^T S^-1 (P, S symmetric)
        x = self.x + K @ y
        x[ANGLES] = _wrap(x[ANGLES])
        I_KH = np.eye(12) - K @ H
        P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.x, self.P = x, 0.5 * (P + P.T)
        self.H, self.R, self.y, self.S, self.K = H, R, y, S, K

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
        return full[meas.rows]

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        t = float(frame.t)
        if not np.isfinite(t):
            raise InputError(f"frame {frame.index}: t is not finite ({frame.t})")
        if self._t_prev is not None:
            self.predict(t - self._t_prev)
        self._t_prev = t
        # predict-only frames leave the last update's H, R, y, S, K undefined
        self.H = self.R = self.y = self.S = self.K = None
        frame = self._own_noise(frame)
        if frame.pose is not None and frame.pose.reference != 0:
            frame = dataclasses.replace(frame, pose=self.pose_in_world(frame.pose))
        p, w, r = self.x[ANGLES]
        meas = state_measurement(
            frame,
            world_frame_velocity=self.world_frame_velocity,
            fallback_rotation=euler_to_rotation(r, p, w),
        )
        if meas.rows.size:
            self.correct(meas.z, meas.rows, self._r_diagonal(meas, frame.index))
        _check_pitch(self.x[3], f"frame {frame.index}: estimated state")
        return self.state_estimate(frame.index, t)

    def run(self, frames: Iterable[FrameMeasurement]) -> Trajectory:
        """Filter a whole sequence; "auto" process noise is fitted on it first."""
        frames = list(frames)
        if self.auto_process_noise and not self._online:
            fit = estimate_process_noise(frames, default=DEFAULT_ACCELERATION_SIGMA)
            self.process_noise = kalman_process_noise(fit.acceleration_sigma)
        return super().run(frames)

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
                pose = dataclasses.replace(pose, covariance=pose.covariance - self._shared)
            gaps = self.velocity_updates == "gaps"
            if gaps and velocity is not None and previous is not None and self._online:
                spanned = previous[0] == self._online[-1].index and (
                    pose.reference in (previous[1], previous[0])
                )
                velocity = None if spanned else velocity
        return dataclasses.replace(frame, pose=pose, velocity=velocity)

    def state_estimate(self, index: int, t: float) -> StateEstimate:
        """The current state in the contract's form (R_wc, p_wc, body twist [w; v]).

        The covariance is J P J^T with J = :func:`state_to_tangent_jacobian`: a
        first-order map of the Euler-angle covariance to the right-perturbation
        rotation tangent (and, with world_frame_velocity, of v to the body frame).
        """
        x = self.x
        p, w, r = x[ANGLES]
        R_wc = euler_to_rotation(r, p, w)
        v = x[LINEAR_VELOCITY]
        if self.world_frame_velocity:
            v = R_wc.T @ v
        J = state_to_tangent_jacobian(x, world_frame_velocity=self.world_frame_velocity)
        cov = J @ self.P @ J.T
        cov[:6, :6] += self._shared  # zero unless "measured" with reference covariances
        return StateEstimate(
            index=index,
            t=t,
            rotation=R_wc,
            position=x[POSITION].copy(),
            twist=np.concatenate([x[ANGULAR_VELOCITY], v]),
            covariance=0.5 * (cov + cov.T),
        )
