"""The paper's Kalman filter over a whole known sequence: the offline ``run``.

:meth:`KalmanBaseline.run <hvo_graph.estimators.kalman.KalmanBaseline.run>` with the
paper's R_k presets filters every frame with the arithmetic of ``update`` (the same numpy
calls on the same 12 x 12 arrays, so the same numbers bit for bit:
tests/test_kalman_fast.py), without what ``update`` pays per frame in the interpreter:
the frame's measurement y_k is converted for all frames at once before the loop, the
loop keeps x (12,) and P (12, 12) in preallocated arrays, and the conversion of the
estimates to the contract's form (R_wc, the tangent Jacobian J and J P J^T) is done for
all frames at once after it.

A frame the loop does not handle (a keyframe-relative pose, which needs the online
estimate of its keyframe in the contract's form) hands the rest of the sequence over
to ``update``; an error leaves the filter as ``update`` would have: the frames before
it estimated and logged.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.kalman_model import (
    MAX_ABS_PITCH,
    PAPER_R_NOISE_FREE,
    PAPER_R_NOISY,
    _check_pitch,
    _euler_rates,
    _prepared_arrays,
    _selection,
    _state_measurement,
    _wrap_angles,
    transition_matrix,
)
from hvo_graph.types import FrameMeasurement

try:  # numpy's LAPACK solve itself: np.linalg.solve wraps it in checks that cost as much
    from numpy.linalg._umath_linalg import solve as _solve
except ImportError:  # pragma: no cover - a numpy without it: the public function
    _solve = np.linalg.solve

if TYPE_CHECKING:
    from hvo_graph.estimators.kalman import KalmanBaseline

_I12 = np.eye(12)
_I12.setflags(write=False)
#: [w; v] of the state (body-frame velocity): x[9:12], x[6:9].
_TWIST_ROWS = np.r_[9:12, 6:9]
#: Flat indices in F_k of x += dt v (3) and of dt E's non-zero entries (row by row).
_F_ENTRIES = np.ravel_multi_index(
    ([0, 1, 2, 3, 3, 4, 4, 5, 5, 5], [6, 7, 8, 9, 10, 9, 10, 9, 10, 11]), (12, 12)
)


def fast_run_applies(kf: KalmanBaseline) -> bool:
    """Whether :func:`filter_frames` does what ``update`` would: the paper's R_k presets
    (no measured variances), body-frame velocity, every twist used."""
    return (
        kf.r_preset != "measured"
        and not kf.world_frame_velocity
        and kf.velocity_updates == "all"
        and not kf._shared_nonzero
    )


def filter_frames(kf: KalmanBaseline, frames: Sequence[FrameMeasurement]) -> int:
    """Filter the leading frames of ``frames`` as ``kf.update`` would, log their estimates
    and leave ``kf`` in ``update``'s state; returns how many (fewer than all at the first
    keyframe-relative pose: the caller updates the rest one by one)."""
    n = len(frames)
    X = np.empty((n, 12))
    P_all = np.empty((n, 12, 12))
    done = [0]
    try:
        _loop(kf, frames, X, P_all, done)
    finally:
        if done[0]:  # the frames estimated, also when a later one raised
            _log(kf, frames, X, P_all, done[0])
    return done[0]


def _loop(
    kf: KalmanBaseline,
    frames: Sequence[FrameMeasurement],
    X: np.ndarray,
    P_all: np.ndarray,
    done: list[int],
) -> None:
    """The filter's steps of ``update`` per frame, in its order (its state set where
    ``update`` sets it, so an error leaves the same); x, P of frame k into X[k],
    P_all[k]; ``done[0]``: the frames estimated so far."""
    full_r = PAPER_R_NOISY if kf.r_preset == "paper-noisy" else PAPER_R_NOISE_FREE
    R_full = np.diag(full_r)  # as correct() builds it (diag of the preset's rows)
    H_full = _selection(np.arange(12))[0]
    prepared, Z = _prepared_arrays(frames)
    prepared = prepared.tolist()  # indexed per frame
    # np.dot: the same BLAS products as ``@`` for these 2-D arrays, at less cost per call.
    dot = np.dot
    x, P = kf.x, kf.P
    t_prev = kf._t_prev
    last = kf._online.last() if kf._online else None
    for k, frame in enumerate(frames):
        if last is not None and (frame.index <= last[0] or frame.t <= last[1]):
            raise InputError(
                f"frame {frame.index} (t={frame.t}) does not follow frame "
                f"{last[0]} (t={last[1]}): frames must arrive in increasing order"
            )
        pose = frame.pose
        if pose is not None and pose.reference != 0:
            break  # pose_in_world needs the keyframe's logged estimate: update() does it
        t = float(frame.t)
        if not math.isfinite(t):
            raise InputError(f"frame {frame.index}: t is not finite ({frame.t})")
        if t_prev is not None:  # predict (KalmanBaseline.predict, _transition)
            dt = t - t_prev
            if not 0.0 < dt < math.inf:
                transition_matrix(x[5], x[3], dt)  # raises with its message
            F = _transition(x, dt)
            Q = kf._process_covariance(dt)
            x = dot(F, x)
            _wrap_angles(x)
            P = dot(dot(F, P), F.T) + Q
            kf.x, kf.P, kf.F, kf.Q = x, P, F, Q
        kf._t_prev = t_prev = t
        kf.H = kf.R = kf.y = kf.S = kf.K = None
        if pose is not None:
            kf._last_pose = (frame.index, pose.reference)
        if prepared[k]:  # pose and twist: correct() with every row measured
            y = Z[k] - x
            _wrap_angles(y)  # the angle rows of y: y[3:6], as in x
            S = P + R_full
            K = _solve(S, P).T  # S = P + R, R > 0: never singular
            x = x + dot(K, y)
            _wrap_angles(x)
            I_KH = _I12 - K
            P = dot(dot(I_KH, P), I_KH.T) + dot(K * full_r, K.T)
            P = 0.5 * (P + P.T)
            kf.x, kf.P = x, P
            kf.H, kf.R, kf.y, kf.S, kf.K = H_full, R_full, y, S, K
        else:
            meas = _state_measurement(frame, False, None, variances=False)
            if meas.rows.size:
                kf.correct(meas.z, meas.rows, kf._r_diagonal(meas, frame.index))
                x, P = kf.x, kf.P
        _check_pitch(float(x[3]), f"frame {frame.index}: estimated state")
        X[k] = x
        P_all[k] = P
        last = (int(frame.index), t)
        done[0] = k + 1


def _transition(x: np.ndarray, dt: float) -> np.ndarray:
    """``KalmanBaseline._transition``: F_k at the (r, p) of x, dt checked; its entries
    dt E (E = :func:`~hvo_graph.estimators.kalman_model.euler_rate_matrix`) are the same
    float products, put in place without building E."""
    p, _, r = x[3:6].tolist()
    if not (math.isfinite(p) and -MAX_ABS_PITCH <= p <= MAX_ABS_PITCH):
        _euler_rates(r, p, "euler_rate_matrix")  # raises with its message
    sr, cr, cp, tp = math.sin(r), math.cos(r), math.cos(p), float(np.tan(p))
    F = _I12.copy()
    F.put(
        _F_ENTRIES,
        (dt, dt, dt, dt * cr, dt * -sr, dt * (sr / cp), dt * (cr / cp), dt * (sr * tp),
         dt * (cr * tp), dt * 1.0),
    )  # fmt: skip
    return F


def _log(
    kf: KalmanBaseline,
    frames: Sequence[FrameMeasurement],
    X: np.ndarray,
    P_all: np.ndarray,
    n: int,
) -> None:
    """``kf.state_estimate`` of the first ``n`` frames, all at once, into its log."""
    X, P_all = X[:n], P_all[:n]
    p, w, r = X[:, 3].tolist(), X[:, 4].tolist(), X[:, 5].tolist()
    # math's sin and cos, as state_estimate calls them (numpy's may round differently);
    # the products below are the same IEEE operations in the same order.
    sr, cr = np.array([math.sin(a) for a in r]), np.array([math.cos(a) for a in r])
    sp, cp = np.array([math.sin(a) for a in p]), np.array([math.cos(a) for a in p])
    sw, cw = np.array([math.sin(a) for a in w]), np.array([math.cos(a) for a in w])
    R_wc = np.empty((n, 3, 3))  # kalman_model._rotation
    R_wc[:, 0, 0] = cw * cr + sw * sp * sr
    R_wc[:, 0, 1] = -cw * sr + sw * sp * cr
    R_wc[:, 0, 2] = sw * cp
    R_wc[:, 1, 0] = cp * sr
    R_wc[:, 1, 1] = cp * cr
    R_wc[:, 1, 2] = -sp
    R_wc[:, 2, 0] = -sw * cr + cw * sp * sr
    R_wc[:, 2, 1] = sw * sr + cw * sp * cr
    R_wc[:, 2, 2] = cw * cp
    J = np.broadcast_to(kf._J, (n, 12, 12)).copy()
    E_inv = J[:, 0:3, 3:6]  # kalman_model._euler_rates_inverse
    E_inv[:, 0, 0], E_inv[:, 0, 1], E_inv[:, 0, 2] = cr, sr * cp, 0.0
    E_inv[:, 1, 0], E_inv[:, 1, 1], E_inv[:, 1, 2] = -sr, cr * cp, 0.0
    E_inv[:, 2, 0], E_inv[:, 2, 1], E_inv[:, 2, 2] = 0.0, -sp, 1.0
    J[:, 3:6, 0:3] = np.swapaxes(R_wc, 1, 2)
    cov = J @ P_all @ np.swapaxes(J, 1, 2)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    kf._J[:] = J[-1]  # as state_estimate leaves it
    index = np.array([f.index for f in frames[:n]], dtype=np.int64)
    t = np.array([float(f.t) for f in frames[:n]])
    kf._online.extend(index, t, R_wc, X[:, :3], X[:, _TWIST_ROWS], cov)
