"""Custom GTSAM factors of the hvo_graph smoother, with analytic Jacobians.

Factors that are not in GTSAM are written here (docs/smoother.md gives the
derivations):

- the **trapezoidal motion factor** on (X_{k-1}, X_k, V_{k-1}, V_k)::

      e = Log(X_{k-1}^-1 X_k) - dt/2 (V_{k-1} + V_k)                (6,)

  the SE(3) exponential of the interval's mean body twist, which under a
  white-noise-acceleration prior is the trapezoid of the end-point twists
  (the Brownian-bridge mean). With the twist random walk it is, to first order,
  the prior GTSAM's ``WnoaMotionFactorPose3`` states in C++, which the homography
  smoother uses (:func:`~hvo_graph.estimators.motion_model.wna_factor`); the
  tightly coupled graph uses this pair (``"wna-pair"`` of ``MotionFactors``);
- the **mean-velocity factor** on V_{i..j}::

      e = sum_i w_i V_i - z                                            (6,)

  the measured twist z (from the continuous homography H_c over [t - dt/2,
  t + dt/2]) against the time average of the piecewise-linear twist between
  the frame nodes; for the usual interval [t_{k-1}, t_k] the weights are
  (1/2, 1/2).

They are ``gtsam.CustomFactor``: a Python callback per linearization. GTSAM
passes the callback the optimizer's ``Values``; pybind11 *copies* a C++
``Values`` into Python unless a Python object already wraps that very
instance, so a solver must hold a Python reference to its linearization point
(see :mod:`hvo_graph.estimators.smoother`) or every callback costs O(size of
the problem).

Conventions: poses T_wc (gtsam.Pose3), tangent order [rot; trans], right
perturbation T Exp(delta) (GTSAM's retract); twists [w; v] in the body frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from hvo_graph.errors import InputError, as_number
from hvo_graph.geometry._fit import plane_basis
from hvo_graph.geometry.rotation import skew
from hvo_graph.types import TiltMeasurement

__all__ = [
    "interval_weights",
    "log_between",
    "mean_velocity_factor",
    "mean_velocity_residual",
    "motion_factor",
    "motion_residual",
    "tilt_factor",
    "tilt_residual",
]


_EYE6 = np.eye(6)


def log_between(
    pose_prev: gtsam.Pose3, pose: gtsam.Pose3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """phi = Log(T_{k-1}^-1 T_k) and its (6, 6) Jacobians for right perturbations of
    T_{k-1} and T_k: -J_r^-1(phi) Ad(Exp(-phi)) and J_r^-1(phi) (GTSAM's ``between``
    and ``Logmap`` derivatives), shared by the motion factors."""
    d_between = np.empty((6, 6), order="F")
    relative = pose_prev.between(pose, d_between, None)  # d_between = -Ad(relative^-1)
    d_log = np.empty((6, 6), order="F")
    phi = gtsam.Pose3.Logmap(relative, d_log)  # d_log = J_r^-1(phi)
    return phi, d_log @ d_between, d_log


def motion_residual(
    pose_prev: gtsam.Pose3,
    pose: gtsam.Pose3,
    twist_prev: np.ndarray,
    twist: np.ndarray,
    dt: float,
    jacobians: bool = False,
) -> np.ndarray | tuple[np.ndarray, list[np.ndarray]]:
    """Trapezoidal motion residual e = Log(T_{k-1}^-1 T_k) - dt/2 (xi_{k-1} + xi_k).

    With phi = Log(T_{k-1}^-1 T_k) and right perturbations of both poses,

        de/dT_{k-1} = -J_r^-1(phi) Ad(Exp(-phi)),   de/dT_k = J_r^-1(phi),
        de/dxi_{k-1} = de/dxi_k = -dt/2 I_6,

    where J_r^-1 is GTSAM's ``Pose3.LogmapDerivative`` (the inverse right
    Jacobian of SE(3)) and Ad the 6x6 adjoint in [rot; trans] order.

    Args:
        pose_prev: T_{k-1}, T_wc at frame k-1.
        pose: T_k, T_wc at frame k.
        twist_prev: (6,) xi_{k-1} = [w; v] body twist at frame k-1.
        twist: (6,) xi_k at frame k.
        dt: t_k - t_{k-1}, seconds.
        jacobians: also return the four (6, 6) Jacobians.
    Returns:
        e (6,), or (e, [dE/dT_{k-1}, dE/dT_k, dE/dxi_{k-1}, dE/dxi_k]).
    """
    if not jacobians:
        return gtsam.Pose3.Logmap(pose_prev.between(pose)) - (0.5 * dt) * (twist_prev + twist)
    phi, d_prev, d_pose = log_between(pose_prev, pose)
    d_twist = (-0.5 * dt) * np.eye(6)
    return phi - (0.5 * dt) * (twist_prev + twist), [d_prev, d_pose, d_twist, d_twist]


def motion_factor(
    pose_prev_key: int,
    pose_key: int,
    twist_prev_key: int,
    twist_key: int,
    dt: float,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """The trapezoidal motion factor on (X_{k-1}, X_k, V_{k-1}, V_k); see :func:`motion_residual`.

    Args:
        pose_prev_key, pose_key: keys of the Pose3 variables X_{k-1}, X_k.
        twist_prev_key, twist_key: keys of the 6-vector variables V_{k-1}, V_k.
        dt: t_k - t_{k-1} > 0, seconds.
        noise: 6-dimensional noise model of e (the smoother uses the Brownian-bridge
            covariance q dt^3 / 12, docs/smoother.md).
    Returns:
        A ``gtsam.CustomFactor`` with keys [X_{k-1}, X_k, V_{k-1}, V_k].
    """
    dt = as_number(dt, "dt", above=0.0)
    if noise.dim() != 6:
        raise InputError(
            f"noise: expected a 6-dimensional noise model, got dimension {noise.dim()}"
        )
    return _motion_factor((pose_prev_key, pose_key, twist_prev_key, twist_key), dt, noise)


_TWIST_JACOBIANS: dict[float, np.ndarray] = {}  # -dt/2 I_6 by dt (read only)


def _motion_factor(
    keys: tuple[int, int, int, int], dt: float, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """:func:`motion_factor` without the argument checks (dt > 0 and a 6-D noise given)."""
    half_dt = 0.5 * dt
    d_twist = _TWIST_JACOBIANS.get(dt)
    if d_twist is None:
        if len(_TWIST_JACOBIANS) > 64:  # irregular frame times: keep the cache small
            _TWIST_JACOBIANS.clear()
        d_twist = _TWIST_JACOBIANS[dt] = -half_dt * _EYE6
    kp, kc, vp, vc = keys

    # Kept lean: this runs on every (re)linearization.
    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        mean = half_dt * (values.atVector(vp) + values.atVector(vc))
        if H is None:
            return gtsam.Pose3.Logmap(values.atPose3(kp).between(values.atPose3(kc))) - mean
        phi, H[0], H[1] = log_between(values.atPose3(kp), values.atPose3(kc))
        H[2] = d_twist
        H[3] = d_twist
        return phi - mean

    return gtsam.CustomFactor(noise, list(keys), error)


def mean_velocity_residual(
    twists: Sequence[np.ndarray], weights: Sequence[float], measured: np.ndarray
) -> np.ndarray:
    """e = sum_i w_i xi_i - z, the residual of :func:`mean_velocity_factor` (Jacobians w_i I_6)."""
    total = np.zeros(6)
    for w, xi in zip(weights, twists, strict=True):
        total += w * np.asarray(xi, dtype=float)
    return total - np.asarray(measured, dtype=float)


def mean_velocity_factor(
    twist_keys: Sequence[int],
    weights: Sequence[float],
    measured: np.ndarray,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """A measured mean twist z against the weighted twists of frame nodes: e = sum w_i V_i - z.

    Args:
        twist_keys: keys of the 6-vector variables V_i (at least one, distinct).
        weights: w_i, one per key, summing to 1 (a time average; see
            :func:`interval_weights`).
        measured: (6,) the measured twist z = [w; v].
        noise: 6-dimensional noise model of z (full covariance from the front end,
            possibly robust).
    Returns:
        A ``gtsam.CustomFactor`` with keys ``twist_keys``; its Jacobians are the
        constants w_i I_6.
    """
    keys = [int(k) for k in twist_keys]
    w = np.asarray(weights, dtype=float)
    if not keys or len(set(keys)) != len(keys) or w.shape != (len(keys),):
        raise InputError(
            f"twist_keys, weights: expected the same number (>= 1) of distinct keys and "
            f"weights, got {len(keys)} keys and {w.size} weights"
        )
    if not (np.all(np.isfinite(w)) and abs(w.sum() - 1.0) < 1e-9):
        raise InputError(f"weights: expected finite weights summing to 1, got {w.tolist()}")
    z = np.array(measured, dtype=float)
    if z.shape != (6,) or not np.all(np.isfinite(z)):
        raise InputError(f"measured: expected a finite (6,) twist, got shape {z.shape}")
    if noise.dim() != 6:
        raise InputError(
            f"noise: expected a 6-dimensional noise model, got dimension {noise.dim()}"
        )
    return _mean_velocity_factor(keys, [float(x) for x in w], z, noise)


_HALF_EYE = 0.5 * np.eye(6)


def _mean_velocity_factor(
    keys: list[int], weights: list[float], z: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """:func:`mean_velocity_factor` without the argument checks (for validated input)."""
    if len(keys) == 2:  # the usual interval [t_{k-1}, t_k]: no loop in the callback
        k0, k1 = keys
        w0, w1 = weights
        b0 = _HALF_EYE if w0 == 0.5 else w0 * np.eye(6)
        b1 = _HALF_EYE if w1 == 0.5 else w1 * np.eye(6)

        def error2(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
            if H is not None:
                H[0] = b0
                H[1] = b1
            return w0 * values.atVector(k0) + w1 * values.atVector(k1) - z

        return gtsam.CustomFactor(noise, keys, error2)

    blocks = [wi * np.eye(6) for wi in weights]

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        if H is not None:
            for i, block in enumerate(blocks):
                H[i] = block
        total = -z
        for wi, key in zip(weights, keys, strict=True):
            total = total + wi * values.atVector(key)
        return total

    return gtsam.CustomFactor(noise, keys, error)


def interval_weights(
    node_times: Sequence[float], start: float, end: float, *, tolerance: float = 1e-9
) -> list[tuple[int, float]]:
    """Weights w_i with sum_i w_i xi_i = time average of the twist over [start, end].

    The twist between frame nodes is taken as piecewise linear in time (the
    mean of the white-noise-acceleration prior given the node twists), and as
    constant before the first and after the last node. For start == end the
    weights interpolate the twist at that instant.

    Args:
        node_times: (K,) strictly increasing times of the frame nodes, seconds.
        start, end: the interval, start <= end.
        tolerance: weights below this are dropped (the rest renormalized), so
            float round-off at an interval end does not pull in a neighbour.
    Returns:
        [(i, w_i)] with indices into ``node_times`` in increasing order and
        weights summing to 1.
    """
    t = np.asarray(node_times, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise InputError("node_times: expected at least one node time")
    if not end >= start:
        raise InputError(f"interval: expected start <= end, got [{start}, {end}]")
    n = t.size
    acc = np.zeros(n)
    length = end - start
    if length <= tolerance * max(1.0, abs(end)):
        # Instantaneous: linear interpolation at `start`, clamped at the ends.
        j = int(np.searchsorted(t, start, side="right"))
        if j == 0:
            acc[0] = 1.0
        elif j == n:
            acc[-1] = 1.0
        else:
            s = (start - t[j - 1]) / (t[j] - t[j - 1])
            acc[j - 1], acc[j] = 1.0 - s, s
    else:
        # Constant extrapolation outside the nodes.
        if start < t[0]:
            acc[0] += min(end, t[0]) - start
        if end > t[-1]:
            acc[-1] += end - max(start, t[-1])
        first = max(int(np.searchsorted(t, start, side="right")) - 1, 0)
        for i in range(first, n - 1):
            lo, hi = max(start, t[i]), min(end, t[i + 1])
            if hi <= lo:
                if t[i] >= end:
                    break
                continue
            s_mid = (0.5 * (lo + hi) - t[i]) / (t[i + 1] - t[i])
            acc[i] += (hi - lo) * (1.0 - s_mid)
            acc[i + 1] += (hi - lo) * s_mid
        acc /= length
    acc[acc < tolerance] = 0.0
    acc /= acc.sum()
    return [(int(i), float(acc[i])) for i in np.flatnonzero(acc)]


def replace_keyframe_plane(
    measured: gtsam.Pose3,
    assumed_keyframe: gtsam.Pose3,
    plane_jacobian: np.ndarray,
    keyframe: gtsam.Pose3,
) -> gtsam.Pose3:
    """A keyframe-relative pose Z = T_rc re-measured with the plane placed at ``keyframe``.

    The front end placed the plane in the keyframe with its own keyframe pose A;
    at a keyframe estimate X_r the measurement becomes, to first order,
    Z(X_r) = Z Exp(J Log(A^-1 X_r)) (J: ``PoseMeasurement.plane_jacobian``).
    """
    xi = gtsam.Pose3.Logmap(assumed_keyframe.between(keyframe))
    return measured.compose(gtsam.Pose3.Expmap(np.asarray(plane_jacobian) @ xi))


def keyframe_between_residual(
    keyframe: gtsam.Pose3,
    pose: gtsam.Pose3,
    measured: gtsam.Pose3,
    assumed_keyframe: gtsam.Pose3,
    plane_jacobian: np.ndarray,
    jacobians: bool = False,
) -> np.ndarray | tuple[np.ndarray, list[np.ndarray]]:
    """Between residual of a keyframe-relative H_d pose whose plane moves with the keyframe.

    The front end measured Z = T_rc with the plane placed by an assumed keyframe pose A;
    at the keyframe estimate X_r the plane moves, and so does the measurement:
    Z(X_r) = Z Exp(J xi), xi = Log(A^-1 X_r). The residual is

        e = Log(Z(X_r)^-1 X_r^-1 X_k),
        de/dX_k = H_E,   de/dX_r = -H_E (Ad(B^-1) + Ad(E^-1) J_r(J xi) J H_xi),

    with B = X_r^-1 X_k, E = Z(X_r)^-1 B, H_E = J_r^-1(e), H_xi = J_r^-1(xi).
    """
    d_xi = np.empty((6, 6), order="F")
    xi = gtsam.Pose3.Logmap(assumed_keyframe.between(keyframe), d_xi)
    eta = plane_jacobian @ xi
    corrected = measured.compose(gtsam.Pose3.Expmap(eta))
    relative = keyframe.between(pose)
    error_pose = corrected.between(relative)
    d_e = np.empty((6, 6), order="F")
    e = gtsam.Pose3.Logmap(error_pose, d_e)
    if not jacobians:
        return e
    d_pose = d_e
    d_keyframe = -d_e @ (
        relative.inverse().AdjointMap()
        + error_pose.inverse().AdjointMap()
        @ gtsam.Pose3.ExpmapDerivative(eta)
        @ plane_jacobian
        @ d_xi
    )
    return e, [d_keyframe, d_pose]


def keyframe_between_factor(
    keyframe_key: int,
    pose_key: int,
    measured: gtsam.Pose3,
    assumed_keyframe: gtsam.Pose3,
    plane_jacobian: np.ndarray,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """:func:`keyframe_between_residual` as a factor on (X_r, X_k)."""
    J = np.array(plane_jacobian, dtype=float)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        out = keyframe_between_residual(
            values.atPose3(keyframe_key),
            values.atPose3(pose_key),
            measured,
            assumed_keyframe,
            J,
            jacobians=H is not None,
        )
        if H is None:
            return out
        e, (H[0], H[1]) = out
        return e

    return gtsam.CustomFactor(noise, [keyframe_key, pose_key], error)


def measurement_noise(
    covariance: np.ndarray, robust: str | None, threshold: float
) -> gtsam.noiseModel.Base:
    """The noise model of a measurement factor: Gaussian with ``covariance`` (6, 6), under
    a Huber or Cauchy loss with ``threshold`` on the whitened residual when ``robust``."""
    gaussian = gtsam.noiseModel.Gaussian.Covariance(covariance)
    if robust is None:
        return gaussian
    if robust == "huber":
        loss = gtsam.noiseModel.mEstimator.Huber.Create(threshold)
    else:
        loss = gtsam.noiseModel.mEstimator.Cauchy.Create(threshold)
    return gtsam.noiseModel.Robust.Create(loss, gaussian)


def keyframe_pose_factor(
    k: int,
    ref: int,
    measured: gtsam.Pose3,
    noise: gtsam.noiseModel.Base,
    plane_model: tuple[gtsam.Pose3, np.ndarray] | None,
    reference_pose: gtsam.Pose3,
    reference_in_graph: bool,
) -> tuple[gtsam.NonlinearFactor, gtsam.Pose3]:
    """The H_d factor of frame k measured against keyframe ``ref``, and frame k's pose value.

    With the keyframe in the graph: :func:`keyframe_between_factor` (the plane re-placed at
    the keyframe's estimate) when ``plane_model`` (assumed keyframe pose, plane Jacobian) is
    given, else a ``BetweenFactorPose3``. Keyframe already out of a fixed-lag window: a
    prior at its frozen estimate composed with the measurement (the keyframe's own
    uncertainty is not propagated).
    """
    if reference_in_graph and plane_model is not None:
        # Start where the front end put the frame: its keyframe placement is corrected
        # by the keyframe's own frames (keyframe tilt); an offline run's initial chain of
        # keyframe estimates is not, and Levenberg-Marquardt from it can stop far away.
        factor = keyframe_between_factor(X(ref), X(k), measured, *plane_model, noise)
        return factor, plane_model[0].compose(measured)
    measured_here = (
        measured
        if plane_model is None
        else replace_keyframe_plane(measured, *plane_model, reference_pose)
    )
    pose_guess = reference_pose.compose(measured_here)
    if reference_in_graph:
        factor = gtsam.BetweenFactorPose3(X(ref), X(k), measured, noise)
    else:
        factor = gtsam.PriorFactorPose3(X(k), pose_guess, noise)
    return factor, pose_guess


def tilt_residual(R_wr: np.ndarray, tilt: TiltMeasurement) -> tuple[np.ndarray, np.ndarray]:
    """e = B (R_wr^T n*): the plane normal the keyframe's attitude predicts in its camera
    frame, in the tangent basis B (2, 3) of the measured n_r (zero at the truth).

    Args:
        R_wr: (3, 3) the keyframe's rotation.
        tilt: the measurement (n_r, n*).
    Returns:
        e (2,), and its (2, 6) Jacobian for a right perturbation of the keyframe's pose:
        [B [c]_x, 0] with c = R_wr^T n* (R_wr Exp(phi) turns c by -phi).
    """
    basis = plane_basis(np.asarray(tilt.normal, dtype=float))
    c = R_wr.T @ np.asarray(tilt.world_normal, dtype=float)
    H = np.zeros((2, 6))
    H[:, :3] = basis @ skew(c)
    return basis @ c, H


def tilt_factor(tilt: TiltMeasurement) -> gtsam.CustomFactor:
    """The keyframe attitude a :class:`~hvo_graph.types.TiltMeasurement` measures, on X(r)
    (:func:`tilt_residual`; noise: n_r's covariance in the basis B, B Sigma B^T).

    n* is known in the first camera frame; the smoother's graph estimates that frame's
    pose (the anchor X(k0), the reference noise's offset) and the factor takes it as W,
    as the chain of the smoother's error covariance takes every factor's far end as
    known: the anchor's rotation error (the first frame's pixel noise) is left out.
    """
    normal = np.asarray(tilt.normal, dtype=float)
    basis = plane_basis(normal)
    noise = gtsam.noiseModel.Gaussian.Covariance(basis @ tilt.covariance @ basis.T)
    key = X(int(tilt.frame))

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        e, H_r = tilt_residual(values.atPose3(key).rotation().matrix(), tilt)
        if H is not None:
            H[0] = H_r
        return e

    return gtsam.CustomFactor(noise, [key], error)
