"""The measured-R Kalman filter's twist covariance, calibrated after the run (not the paper).

The filter's motion model is white-noise acceleration; real motions are smooth, and
under a sustained acceleration the filtered twist lags the motion by more than P
says (most along a weakly measured direction such as the tilt-shift ambiguity of a
plane seen head-on, where the filter leans on the model longest). No causal probe
measures that lag reliably. Once the whole sequence is filtered, the
Rauch-Tung-Striebel smoother of the same model does: its estimate uses the frames on
both sides, so a lag cancels to first order (a constant acceleration leaves the
smoothed twist unbiased), and

    b_k = V^f_k - V^s_k

is the filter's twist error less the (much smaller) smoothed one. In the metric of
the reported covariance C_k = L_k L_k^T (L_k any square root), the whitened
z_k = L_k^-1 b_k have second moment

    S = mean_k z_k z_k^T   (6 x 6, one per sequence),

which is I when C_k describes the errors; the reported twist covariance becomes
C_k^1/2 S C_k^1/2 (its cross-covariance with the pose follows by the
same congruence). S may also shrink C_k: the fitted process noise is chosen at the
upper end of its likelihood interval and over-covers where the motion is smooth.
But b misses what the filter and the smoother share: an error of the reference
frame that scales or tilts every velocity, a slow drift both follow, the last
frames (where the two estimates coincide). So the eigenvalues of S are floored at
:data:`CALIBRATION_FLOOR`, and the filter is left as it is when its process noise
is at the fit's lower bound (:func:`resolves_acceleration`): the fit found no
acceleration, so there is no lag to find, and what b sees is the model's noise
(on a near-hover, where both estimates follow the same slow drift, S only shrank
a covariance that was right).

The filter's estimates and its online covariances are unchanged; only
:meth:`~hvo_graph.estimators.kalman.KalmanBaseline.trajectory` after ``run`` reports
the calibrated covariance.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hvo_graph.estimators.kalman_model import (
    ANGLES,
    state_to_tangent_jacobian,
    transition_matrix,
)
from hvo_graph.estimators.noise_estimation import MIN_SPECTRAL_DENSITY, NEAR_BOUND

#: Smallest eigenvalue of S (module docstring). Over 16 draws of each of the eleven
#: scenario families the filter's twist NEES per dof was 0.76-1.26 with 0.3 (the
#: near-hover family left as it is); no floor: 0.94-1.79 (a draw of few noisy points with
#: a velocity error the smoother shares went from 7.4 to 11.9); 0.5: 0.67-1.03.
CALIBRATION_FLOOR: float = 0.3

#: Fewest filtered frames for a calibration; fewer keep the filter's own covariance.
MIN_FRAMES: int = 30

#: Frames the smoother's backward pass holds its 12 x 12 matrices for at a time.
_BLOCK: int = 4096


def resolves_acceleration(process_noise: np.ndarray) -> bool:
    """Whether the filter's Q has an acceleration density above the fit's lower bound
    (:data:`~hvo_graph.estimators.noise_estimation.MIN_SPECTRAL_DENSITY` times
    :data:`~hvo_graph.estimators.noise_estimation.NEAR_BOUND`); (6,) the paper's s_i."""
    return bool(np.any(np.asarray(process_noise) > NEAR_BOUND * MIN_SPECTRAL_DENSITY))


def smoothed_states(
    times: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    process_covariance: Callable[[float], np.ndarray],
) -> np.ndarray:
    """Rauch-Tung-Striebel means of the paper's 12-state model over a filtered sequence.

    With x^-_{k+1} = F_{k+1} x_k, P^-_{k+1} = F_{k+1} P_k F_{k+1}^T + Q_{k+1} (F at x_k's
    roll and pitch, :func:`~hvo_graph.estimators.kalman_model.transition_matrix`)::

        G_k = P_k F_{k+1}^T (P^-_{k+1})^-1,   x^s_k = x_k + G_k (x^s_{k+1} - x^-_{k+1}),

    the Euler-angle rows of the difference wrapped to (-pi, pi].

    Args:
        times: (K,) the filtered frames' times, increasing.
        x: (K, 12) filtered states x_k (after each frame's update).
        P: (K, 12, 12) their covariances P_k.
        process_covariance: Q_k of a time step dt.
    Returns:
        (K, 12) x^s_k (the last frame's is the filter's).
    """
    K = len(times)
    x_s = x.copy()
    # Backwards in blocks: F, Q, P^- and G of a block at a time (O(block) memory).
    for start in range(max(K - 1 - _BLOCK, 0), -_BLOCK, -_BLOCK):
        ks = np.arange(max(start, 0), min(start + _BLOCK, K - 1))  # k of G_k in this block
        if not len(ks):
            continue
        F = np.array(
            [
                transition_matrix(float(x[k, 5]), float(x[k, 3]), float(times[k + 1] - times[k]))
                for k in ks
            ]
        )
        Q = np.array([process_covariance(float(times[k + 1] - times[k])) for k in ks])
        predicted = np.einsum("kij,kj->ki", F, x[ks])
        P_predicted = F @ P[ks] @ np.swapaxes(F, 1, 2) + Q
        # G_k^T = (P^-_{k+1})^-1 F_{k+1} P_k (P^- and P symmetric)
        G = np.swapaxes(np.linalg.solve(P_predicted, F @ P[ks]), 1, 2)
        for i in range(len(ks) - 1, -1, -1):
            k = ks[i]
            d = x_s[k + 1] - predicted[i]
            d[ANGLES] = (d[ANGLES] + np.pi) % (2 * np.pi) - np.pi
            x_s[k] = x[k] + G[i] @ d
    return x_s


def twist_differences(x: np.ndarray, x_s: np.ndarray, *, world_frame_velocity: bool) -> np.ndarray:
    """(K, 6) b_k = V^f_k - V^s_k in the contract's body twist [w; v], to first order
    through :func:`~hvo_graph.estimators.kalman_model.state_to_tangent_jacobian` at the
    filtered state (with ``world_frame_velocity`` the states' v is in W).

    Args:
        x, x_s: (K, 12) filtered and smoothed states.
    """
    d = x - x_s
    d[:, ANGLES] = (d[:, ANGLES] + np.pi) % (2 * np.pi) - np.pi
    J = np.array(
        [state_to_tangent_jacobian(xk, world_frame_velocity=world_frame_velocity)[6:] for xk in x]
    )
    return np.einsum("kij,kj->ki", J, d)


def calibration_matrix(
    differences: np.ndarray, covariances: np.ndarray, floor: float = CALIBRATION_FLOOR
) -> np.ndarray | None:
    """S = mean_k z_k z_k^T, z_k = C_k^-1/2 b_k, its eigenvalues floored at ``floor``.

    Args:
        differences: (K, 6) b_k.
        covariances: (K, 6, 6) the filter's reported twist covariances C_k.
        floor: smallest eigenvalue of S (1: S only inflates).
    Returns:
        (6, 6) S, or None with fewer than :data:`MIN_FRAMES` frames.
    """
    if len(differences) < MIN_FRAMES:
        return None
    z = np.einsum("kij,kj->ki", _roots(covariances, inverse=True), differences)
    w, u = np.linalg.eigh(z.T @ z / len(z))
    return (u * np.maximum(w, floor)) @ u.T


def calibrated(covariances: np.ndarray, S: np.ndarray) -> np.ndarray:
    """(K, 12, 12) the covariances with the twist rows mapped by T_k = C_k^1/2 S^1/2 C_k^-1/2
    (C_k the twist block): twist block C_k^1/2 S C_k^1/2, pose-twist block C_pv T_k^T,
    pose block unchanged (a congruence: each matrix stays positive semidefinite)."""
    w, u = np.linalg.eigh(S)
    twist = covariances[:, 6:, 6:]
    T = _roots(twist) @ ((u * np.sqrt(w)) @ u.T) @ _roots(twist, inverse=True)
    out = covariances.copy()
    out[:, :6, 6:] = covariances[:, :6, 6:] @ np.swapaxes(T, 1, 2)
    out[:, 6:, :6] = np.swapaxes(out[:, :6, 6:], 1, 2)
    out[:, 6:, 6:] = T @ twist @ np.swapaxes(T, 1, 2)
    return _symmetric(out)


def _symmetric(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def _roots(C: np.ndarray, *, inverse: bool = False) -> np.ndarray:
    """(K, n, n) symmetric square roots C^1/2 (or C^-1/2), eigenvalues floored relative to
    each matrix's largest (a direction without noise would otherwise blow up)."""
    w, v = np.linalg.eigh(_symmetric(C))
    w = np.maximum(w, 1e-12 * w[:, -1:] + 1e-300)
    scale = w**-0.5 if inverse else np.sqrt(w)
    return (v * scale[:, None, :]) @ np.swapaxes(v, 1, 2)
