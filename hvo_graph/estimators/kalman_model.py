"""The paper's Kalman model (eqs. 6-7 and appendix): state layout, F_k, Q_k, R_k, y_k.

The pieces of :mod:`hvo_graph.estimators.kalman` that are the paper's equations
rather than the filter loop: the 12-state layout, the transition matrix F_k,
the process covariance Q_k, the paper's R_k presets, the conversion of a
front-end measurement record into y_k, and the map of the state covariance to
the contract's [pose tangent; twist].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_matrix, as_number, as_vector
from hvo_graph.estimators.choices import KALMAN_R_PRESETS
from hvo_graph.estimators.process_noise import white_noise_blocks
from hvo_graph.geometry.rotation import (
    GIMBAL_LOCK_COS,
    euler_to_rotation,
    rotation_to_euler,
    skew,
    wrap_angle,
)
from hvo_graph.types import FrameMeasurement

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
    if -MAX_ABS_PITCH <= p <= MAX_ABS_PITCH:  # the usual case (False for NaN)
        return
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
    return _euler_rates(float(r), float(p), "euler_rate_matrix")


def _euler_rates(r: float, p: float, what: str) -> np.ndarray:
    """:func:`euler_rate_matrix` of Python floats (the filter's per-frame path)."""
    if not (math.isfinite(p) and -MAX_ABS_PITCH <= p <= MAX_ABS_PITCH):
        _check_pitch(p, what)  # raises unless p is within the bound after wrapping
    sr, cr, cp, tp = math.sin(r), math.cos(r), math.cos(p), float(np.tan(p))
    return np.array(
        [
            [cr, -sr, 0.0],  # pdot = wx cos r - wy sin r
            [sr / cp, cr / cp, 0.0],  # wdot = (wx sin r + wy cos r) sec p
            [sr * tp, cr * tp, 1.0],  # rdot = (wx sin r + wy cos r) tan p + wz
        ]
    )


def _euler_rates_inverse(r: float, p: float, what: str) -> np.ndarray:
    """E^-1 of :func:`_euler_rates` in closed form (body rates from Euler rates):
    wx = cos r pdot + sin r cos p wdot, wy = -sin r pdot + cos r cos p wdot,
    wz = rdot - sin p wdot; the same pitch check."""
    if not (math.isfinite(p) and -MAX_ABS_PITCH <= p <= MAX_ABS_PITCH):
        _check_pitch(p, what)
    sr, cr, sp, cp = math.sin(r), math.cos(r), math.sin(p), math.cos(p)
    return np.array([[cr, sr * cp, 0.0], [-sr, cr * cp, 0.0], [0.0, -sp, 1.0]])


def _rotation(r: float, p: float, w: float) -> np.ndarray:
    """R_wc = R_y(w) R_x(p) R_z(r) of Python floats: the product of
    :func:`~hvo_graph.geometry.rotation.euler_to_rotation`, written out."""
    sr, cr = math.sin(r), math.cos(r)
    sp, cp = math.sin(p), math.cos(p)
    sw, cw = math.sin(w), math.cos(w)
    return np.array(
        [
            [cw * cr + sw * sp * sr, -cw * sr + sw * sp * cr, sw * cp],
            [cp * sr, cp * cr, -sp],
            [-sw * cr + cw * sp * sr, sw * sr + cw * sp * cr, cw * cp],
        ]
    )


#: (H, angle mask or None, rows) of each measured row pattern (pose, velocity, both), by
#: the pattern's bytes and, for the constant patterns, by the id of the array.
_SELECTIONS: dict[bytes | int, tuple] = {}


def _selection(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """H = the rows of I_12, and which of them are angles (None: none), kept per pattern."""
    found = _SELECTIONS.get(id(rows))  # the row patterns of _state_measurement (constants)
    if found is not None and found[2] is rows:
        return found[0], found[1]
    rows = np.asarray(rows, dtype=int)
    key = rows.tobytes()
    found = _SELECTIONS.get(key)
    if found is None:
        H = np.eye(12)[rows]
        H.setflags(write=False)
        angle = np.isin(rows, _ANGLE_ROWS)
        found = (H, angle if angle.any() else None, rows)
        if len(_SELECTIONS) < 64:
            _SELECTIONS[key] = found
    return found[0], found[1]


def _euler_angles(R: np.ndarray) -> tuple[float, float, float]:
    """:func:`~hvo_graph.geometry.rotation.rotation_to_euler` of a checked (3, 3) R."""
    (_, _, r02), (r10, r11, r12), (_, _, r22) = R.tolist()
    pitch = float(np.arcsin(min(max(-r12, -1.0), 1.0)))
    if math.hypot(r10, r11) < GIMBAL_LOCK_COS:
        return rotation_to_euler(R)  # raises with its message
    return math.atan2(r10, r11), pitch, math.atan2(r02, r22)


def _wrap_entries(y: np.ndarray, mask: np.ndarray) -> None:
    """Wrap y[mask] to (-pi, pi] in place (values inside are kept)."""
    values = y[mask]
    pi = math.pi
    if not all(-pi < a <= pi for a in values.tolist()):
        y[mask] = _wrap(values)


def _wrap_angles(x: np.ndarray) -> None:
    """Wrap the state's angles x[3:6] to (-pi, pi] in place (values inside are kept)."""
    p, w, r = x[3:6].tolist()
    pi = math.pi
    if not (-pi < p <= pi and -pi < w <= pi and -pi < r <= pi):
        x[ANGLES] = _wrap(x[ANGLES])


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
    return _state_measurement(frame, world_frame_velocity, fallback_rotation, variances=True)


_POSE_ROWS, _VELOCITY_ROWS, _NO_ROWS = np.arange(0, 6), np.arange(6, 12), np.zeros(0, dtype=int)
_ALL_ROWS, _NOTHING = np.arange(12), np.zeros(0)
for _rows in (_POSE_ROWS, _VELOCITY_ROWS, _NO_ROWS, _ALL_ROWS, _NOTHING):
    _rows.setflags(write=False)


def _state_measurement(
    frame: FrameMeasurement,
    world_frame_velocity: bool,
    fallback_rotation: np.ndarray | None,
    *,
    variances: bool,
) -> StateMeasurement:
    """:func:`state_measurement`; without ``variances`` (the paper's R_k presets do not
    read them) the ``variance`` field is empty and the covariances are neither read nor
    checked."""
    k = frame.index
    rows: list[np.ndarray] = []
    z: list[float] = []  # y_k as floats: one array at the end
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
        roll, pitch, yaw = _euler_angles(R_wc)
        _check_pitch(pitch, f"frame {k}: measured pose")
        rows.append(_POSE_ROWS)
        z += p_wc.tolist()
        z += (pitch, yaw, roll)
        if variances:
            cov = as_matrix(pose.covariance, f"frame {k}: pose.covariance", (6, 6))
            E = euler_rate_matrix(roll, pitch)
            var.append(
                np.concatenate(
                    [np.diag(R_wc @ cov[3:, 3:] @ R_wc.T), np.diag(E @ cov[:3, :3] @ E.T)]
                )
            )
    if frame.velocity is not None:
        vel = frame.velocity
        twist = as_vector(vel.twist, f"frame {k}: velocity.twist", 6)
        v, w = twist[3:], twist[:3]
        if variances:
            cov = as_matrix(vel.covariance, f"frame {k}: velocity.covariance", (6, 6))
            cov_v = cov[3:, 3:]
        if world_frame_velocity:
            if R_wc is None:
                raise InputError(
                    f"frame {k}: world_frame_velocity needs a rotation (a pose measurement "
                    "or fallback_rotation) to rotate the body-frame velocity into the world"
                )
            v = R_wc @ v
            if variances:
                cov_v = R_wc @ cov_v @ R_wc.T
        rows.append(_VELOCITY_ROWS)
        z += v.tolist()
        z += w.tolist()
        if variances:
            var.append(np.concatenate([np.diag(cov_v), np.diag(cov[:3, :3])]))
    if not rows:
        return StateMeasurement(_NO_ROWS, np.zeros(0), np.zeros(0))
    if len(rows) == 1:
        return StateMeasurement(rows[0], np.array(z), var[0] if var else np.zeros(0))
    return StateMeasurement(_ALL_ROWS, np.array(z), np.concatenate(var) if var else np.zeros(0))


def _prepared_measurements(frames: Sequence[FrameMeasurement]) -> dict[int, StateMeasurement]:
    """``_state_measurement(frame, False, None, variances=False)`` of every frame with a
    world-frame pose and a twist, the arrays checked and converted for all frames at
    once; by ``id(frame)``. Frames that fail a check are left out: the per-frame call
    raises its message for them, in frame order."""
    prepared, Z = _prepared_arrays(frames)
    return {
        id(frames[k]): StateMeasurement(_ALL_ROWS, Z[k], _NOTHING)
        for k in np.flatnonzero(prepared).tolist()
    }


def _prepared_arrays(frames: Sequence[FrameMeasurement]) -> tuple[np.ndarray, np.ndarray]:
    """(prepared (K,) bool, Z (K, 12)): y_k of :func:`_prepared_measurements` of frame k in
    Z[k] where ``prepared[k]`` (every row measured); the other frames are left to the
    per-frame conversion."""
    K = len(frames)
    prepared, Z = np.zeros(K, dtype=bool), np.empty((K, 12))
    at = [
        k
        for k, f in enumerate(frames)
        if f.pose is not None and f.velocity is not None and f.pose.reference == 0
    ]
    both = [frames[k] for k in at]
    n = len(both)
    try:
        R = np.array([f.pose.rotation for f in both], dtype=float)  # type: ignore[union-attr]
        p = np.array([f.pose.position for f in both], dtype=float)  # type: ignore[union-attr]
        twist = np.array([f.velocity.twist for f in both], dtype=float)  # type: ignore[union-attr]
    except (ValueError, TypeError):
        return prepared, Z
    if n == 0 or R.shape != (n, 3, 3) or p.shape != (n, 3) or twist.shape != (n, 6):
        return prepared, Z
    ok = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(p).all(axis=1)
    ok &= np.isfinite(twist).all(axis=1)
    pitch = np.arcsin(np.clip(-R[:, 1, 2], -1.0, 1.0))  # as _euler_angles, every frame
    ok &= (-MAX_ABS_PITCH <= pitch) & (pitch <= MAX_ABS_PITCH)
    r02, r22, r10, r11 = (R[:, i, j].tolist() for i, j in ((0, 2), (2, 2), (1, 0), (1, 1)))
    yaw, roll = [0.0] * n, [0.0] * n
    for k in np.flatnonzero(ok).tolist():
        if math.hypot(r10[k], r11[k]) >= GIMBAL_LOCK_COS:
            yaw[k], roll[k] = math.atan2(r02[k], r22[k]), math.atan2(r10[k], r11[k])
        else:
            ok[k] = False
    rows = np.asarray(at, dtype=int)
    Z[rows, 0:3], Z[rows, 3], Z[rows, 4], Z[rows, 5] = p, pitch, yaw, roll
    Z[rows, 6:9], Z[rows, 9:12] = twist[:, 3:], twist[:, :3]
    prepared[rows] = ok
    return prepared, Z


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


for _rows in (_POSE_ROWS, _VELOCITY_ROWS, _ALL_ROWS):
    _H, _angle = _selection(_rows)
    _SELECTIONS[id(_rows)] = (_H, _angle, _rows)
