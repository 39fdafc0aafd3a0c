"""The white-noise-acceleration process model shared by the Kalman filter and the smoother.

A velocity u driven by white noise of spectral density q (per component) over a
step dt (filterpy's ``Q_discrete_white_noise`` with the continuous model)::

    Cov[position] = q dt^3 / 3,   Cov[position, velocity] = q dt^2 / 2,   Cov[velocity] = q dt

The Kalman filter's Q_k (:func:`~hvo_graph.estimators.kalman.process_covariance`)
is these three blocks per (position, velocity) pair; the factor graph's motion
factor (GTSAM's ``WnoaMotionFactorPose3``, :func:`~hvo_graph.estimators.motion_model.wna_factor`)
has the same covariance per (pose, twist) pair.

Both estimators take their defaults from here: q = a_max^2 dt (Bar-Shalom's
rule) with a_max = 0.3 m/s^2 (rad/s^2), just above the paper scenario's
largest linear and angular accelerations (0.28, 0.25), and dt = 1/30 s:
q = 3e-3 on every axis (docs/kalman.md, docs/smoother.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from hvo_graph.errors import InputError

#: Spectral density q of the white-noise acceleration on every axis, m^2/s^3 and
#: rad^2/s^3: Bar-Shalom's a_max^2 dt with a_max = 0.3 and dt = 1/30 s.
DEFAULT_SPECTRAL_DENSITY: float = 3e-3

#: Default white-noise-acceleration strengths (s_w, s_v) of the smoother: square
#: roots of the spectral densities q of the angular (rad s^-3/2) and linear
#: (m s^-3/2) acceleration; over dt the twist random walk has standard deviation
#: s sqrt(dt). Checked on 20 seeds of the paper's noisy run (docs/smoother.md).
DEFAULT_ACCELERATION_SIGMA: tuple[float, float] = (
    math.sqrt(DEFAULT_SPECTRAL_DENSITY),
    math.sqrt(DEFAULT_SPECTRAL_DENSITY),
)

#: Default white-noise-jerk strengths (s_w, s_v) of the smoother's WNA alternative
#: (rad s^-5/2, m s^-5/2), by the same rule: q = j_max^2 dt with j_max = 0.6
#: (m/s^3, rad/s^3; the paper scenario's largest jerk is 0.53) and dt = 1/30 s.
DEFAULT_JERK_SIGMA: tuple[float, float] = (math.sqrt(0.36 / 30.0), math.sqrt(0.36 / 30.0))

#: Default Q_k scalars s_i = (sigma_x, sigma_y, sigma_z, sigma_p, sigma_w, sigma_r) of
#: the Kalman filter: the spectral density driving each pair (i, i+6), the same q.
DEFAULT_PROCESS_NOISE: np.ndarray = np.full(6, DEFAULT_SPECTRAL_DENSITY)
DEFAULT_PROCESS_NOISE.setflags(write=False)


def acceleration_sigma(value: float | Sequence[float]) -> tuple[float, float]:
    """(s_w, s_v) from one number (both) or two (angular, linear), each finite and > 0."""
    sigma = np.atleast_1d(np.asarray(value, dtype=float))
    if sigma.shape == (1,):
        sigma = np.repeat(sigma, 2)
    if sigma.shape != (2,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise InputError(
            "acceleration_sigma: expected one or two finite numbers > 0 (angular, linear), "
            f"got {value!r}"
        )
    return float(sigma[0]), float(sigma[1])


def twist_spectral_density(sigma: tuple[float, float]) -> np.ndarray:
    """(6,) diag(Q) of the twist [w; v]: (s_w^2 x3, s_v^2 x3)."""
    return np.repeat(np.asarray(sigma, dtype=float) ** 2, 3)


def kalman_process_noise(sigma: tuple[float, float] = DEFAULT_ACCELERATION_SIGMA) -> np.ndarray:
    """(6,) Q_k scalars of the Kalman filter matching the smoother's (s_w, s_v).

    The filter's pairs are ordered (x, y, z, p, w, r): s = (s_v^2 x3, s_w^2 x3).
    (It pairs Euler angles with body rates, equal to first order near the identity.)
    """
    s_w, s_v = sigma
    return np.array([s_v**2] * 3 + [s_w**2] * 3)


def white_noise_blocks(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position, cross, velocity) covariances over dt: q dt^3 / 3, q dt^2 / 2, q dt."""
    return q * dt**3 / 3.0, q * dt**2 / 2.0, velocity_variance(q, dt)


def velocity_variance(q: np.ndarray, dt: float) -> np.ndarray:
    """Variance of the velocity's random walk over dt: q dt."""
    return q * dt
