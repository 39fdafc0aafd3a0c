"""The white-noise-jerk (constant-acceleration) motion model of the smoother.

States per frame k: X(k) (pose T_wc), V(k) (body twist [w; v]) and A(k) (its
rate, a 6-vector, rad/s^2 and m/s^2). The twist rate is Brownian motion,
dA = sqrt(Q) dW, Q = diag(q_w I_3, q_v I_3) (spectral densities of the angular
and linear jerk). Per axis, over an interval dt, the increments

    e_p = int V dt - dt V_{k-1} - dt^2/2 A_{k-1},
    e_v = V_k - V_{k-1} - dt A_{k-1},   e_a = A_k - A_{k-1}

are Gaussian with covariance q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3,
dt^2/2], [dt^3/6, dt^2/2, dt]]. The prior p(X(k), V(k), A(k) | X(k-1),
V(k-1), A(k-1)) is split exactly into two factors:

- the **twist-rate factor** on (V(k-1), A(k-1), V(k), A(k)): (e_v, e_a) with
  covariance q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (linear in the variables:
  :func:`twist_rate_factor`, a GTSAM linear factor, no Python callback);
- the **pose factor** on all six, e_p given (e_v, e_a): its conditional mean
  is dt/2 e_v - dt^2/12 e_a, so with Log(X(k-1)^-1 X(k)) for int V dt,

      e = Log(X(k-1)^-1 X(k)) - dt/2 (V(k-1) + V(k)) - dt^2/12 (A(k-1) - A(k)),

  variance q dt^5/720 (:func:`jerk_motion_factor`).

Conventions are those of :mod:`hvo_graph.estimators.factors`.
"""

from __future__ import annotations

import gtsam
import numpy as np

from hvo_graph.errors import InputError, as_number
from hvo_graph.estimators.factors import log_between

__all__ = [
    "JerkNoise",
    "jerk_motion_factor",
    "jerk_motion_residual",
    "jerk_process_covariance",
    "twist_rate_factor",
]


def jerk_process_covariance(q: float, dt: float) -> np.ndarray:
    """(3, 3) covariance of (e_p, e_v, e_a) over dt of one axis with jerk density q."""
    return q * np.array(
        [
            [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
            [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
            [dt**3 / 6.0, dt**2 / 2.0, dt],
        ]
    )


def jerk_motion_residual(
    pose_prev: gtsam.Pose3,
    pose: gtsam.Pose3,
    twist_prev: np.ndarray,
    twist: np.ndarray,
    rate_prev: np.ndarray,
    rate: np.ndarray,
    dt: float,
    jacobians: bool = False,
) -> np.ndarray | tuple[np.ndarray, list[np.ndarray]]:
    """e = Log(T_{k-1}^-1 T_k) - dt/2 (xi_{k-1} + xi_k) - dt^2/12 (a_{k-1} - a_k).

    Jacobians (right perturbations, phi = Log(T_{k-1}^-1 T_k)):
    de/dT_{k-1} = -J_r^-1(phi) Ad(Exp(-phi)), de/dT_k = J_r^-1(phi),
    de/dxi = -dt/2 I_6 (both), de/da_{k-1} = -dt^2/12 I_6, de/da_k = dt^2/12 I_6.

    Args:
        pose_prev, pose: T_{k-1}, T_k (T_wc).
        twist_prev, twist: (6,) body twists xi = [w; v].
        rate_prev, rate: (6,) twist rates a = d xi / dt.
        dt: t_k - t_{k-1}, seconds.
        jacobians: also return the six (6, 6) Jacobians.
    Returns:
        e (6,), or (e, [dT_{k-1}, dT_k, dxi_{k-1}, dxi_k, da_{k-1}, da_k]).
    """
    mean = (0.5 * dt) * (np.asarray(twist_prev) + np.asarray(twist)) + (dt * dt / 12.0) * (
        np.asarray(rate_prev) - np.asarray(rate)
    )
    if not jacobians:
        return gtsam.Pose3.Logmap(pose_prev.between(pose)) - mean
    phi, d_prev, d_pose = log_between(pose_prev, pose)
    d_twist = (-0.5 * dt) * np.eye(6)
    d_rate = (dt * dt / 12.0) * np.eye(6)
    return phi - mean, [d_prev, d_pose, d_twist, d_twist, -d_rate, d_rate]


def jerk_motion_factor(
    keys: tuple[int, int, int, int, int, int], dt: float, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """The WNJ pose factor on (X_{k-1}, X_k, V_{k-1}, V_k, A_{k-1}, A_k); see
    :func:`jerk_motion_residual`.

    Args:
        keys: the six keys, in that order.
        dt: t_k - t_{k-1} > 0, seconds.
        noise: 6-dimensional noise model (the smoother: variance Q dt^5 / 720).
    """
    dt = as_number(dt, "dt", above=0.0)
    if noise.dim() != 6:
        raise InputError(
            f"noise: expected a 6-dimensional noise model, got dimension {noise.dim()}"
        )
    half_dt, c = 0.5 * dt, dt * dt / 12.0
    d_twist = -half_dt * np.eye(6)
    d_rate = c * np.eye(6)
    kp, kc, vp, vc, ap, ac = keys

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        mean = half_dt * (values.atVector(vp) + values.atVector(vc)) + c * (
            values.atVector(ap) - values.atVector(ac)
        )
        if H is None:
            return gtsam.Pose3.Logmap(values.atPose3(kp).between(values.atPose3(kc))) - mean
        phi, H[0], H[1] = log_between(values.atPose3(kp), values.atPose3(kc))
        H[2] = d_twist
        H[3] = d_twist
        H[4] = -d_rate
        H[5] = d_rate
        return phi - mean

    return gtsam.CustomFactor(noise, list(keys), error)


_ZERO6 = np.zeros(6)

#: Standard deviation (rad, m) added to the pose factor's Q dt^5 / 720 (quadrature).
POSE_FLOOR: float = 1e-5


def twist_rate_factor(
    keys: tuple[int, int, int, int], dt: float, q: np.ndarray
) -> gtsam.LinearContainerFactor:
    """The WNJ prior p(V_k, A_k | V_{k-1}, A_{k-1}) as a GTSAM linear factor.

    Residual (12,) [V_k - V_{k-1} - dt A_{k-1}; A_k - A_{k-1}] with covariance
    Q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis. The factor is linear in vector
    variables, so a ``LinearContainerFactor`` (linearized at zero; a vector's local
    coordinates are its difference) is exact at every value.

    Args:
        keys: (V_{k-1}, A_{k-1}, V_k, A_k).
        dt: t_k - t_{k-1} > 0, seconds.
        q: (6,) diag(Q), the jerk spectral densities [rot x3; trans x3].
    """
    dt = as_number(dt, "dt", above=0.0)
    # Whitened per axis: (e_v, e_a) = L r with L L^T = the 2x2 covariance, so the
    # information is J^T C^-1 J; built as three HessianFactors on at most three keys
    # (pybind exposes no 4-key constructor) and summed into one.
    eye = np.eye(6)
    z = np.zeros((6, 6))
    # Residual Jacobians per variable (12 x 6): [dv; da].
    J = {
        "vp": np.vstack([-eye, z]),
        "ap": np.vstack([-dt * eye, -eye]),
        "vc": np.vstack([eye, z]),
        "ac": np.vstack([z, eye]),
    }
    info = np.zeros((12, 12))
    block = np.linalg.inv(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]))
    for i in range(2):
        for j in range(2):
            info[6 * i : 6 * i + 6, 6 * j : 6 * j + 6] = block[i, j] * np.diag(1.0 / q)
    names = ("vp", "ap", "vc", "ac")
    G = {(a, b): J[a].T @ info @ J[b] for a in names for b in names}
    kvp, kap, kvc, kac = keys
    key = dict(zip(names, keys, strict=True))
    g0 = np.zeros(6)
    parts = gtsam.GaussianFactorGraph()
    # (vp, ap, vc): their mutual blocks; (vp, ap, ac) adds ac's pairs with vp, ap and
    # its diagonal; (vc, ac) the last pair. Each pair counted once.
    parts.push_back(
        gtsam.HessianFactor(
            kvp, kap, kvc,
            G["vp", "vp"], G["vp", "ap"], G["vp", "vc"], g0,
            G["ap", "ap"], G["ap", "vc"], g0,
            G["vc", "vc"], g0, 0.0,
        )
    )  # fmt: skip
    parts.push_back(
        gtsam.HessianFactor(
            kvp, kap, kac,
            z, z, G["vp", "ac"], g0,
            z, G["ap", "ac"], g0,
            G["ac", "ac"], g0, 0.0,
        )
    )  # fmt: skip
    parts.push_back(gtsam.HessianFactor(kvc, kac, z, G["vc", "ac"], g0, z, g0, 0.0))
    # As a JacobianFactor (GTSAM's careful Cholesky of the summed information): with
    # only Jacobian factors a linear system is eliminated by QR, not by Cholesky, whose
    # squared condition number failed on the stiff pose factor (Q dt^5 / 720).
    linear = gtsam.JacobianFactor(gtsam.HessianFactor(parts))
    point = gtsam.Values()
    for k in key.values():
        point.insert(k, _ZERO6)
    return gtsam.LinearContainerFactor(linear, point)


class JerkNoise:
    """The WNJ factors' noise over an interval dt, cached per dt.

    Args:
        sigma: (s_w, s_v), square roots of the jerk spectral densities (rad s^-5/2, m s^-5/2).
    """

    def __init__(self, sigma: tuple[float, float]) -> None:
        #: diag(Q): jerk spectral densities, [rot x3; trans x3].
        self.q = np.repeat(np.asarray(sigma, dtype=float) ** 2, 3)
        self._cache: dict[float, gtsam.noiseModel.Base] = {}

    def __call__(self, dt: float) -> gtsam.noiseModel.Base:
        """The pose factor's noise over dt: Q dt^5 / 720."""
        cached = self._cache.get(dt)
        if cached is None:
            if len(self._cache) > 64:
                self._cache.clear()
            variance = self.q * dt**5 / 720.0 + POSE_FLOOR**2
            cached = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(variance))
            self._cache[dt] = cached
        return cached
