"""The white-noise-acceleration process model shared by the Kalman filter and the smoother.

A velocity u driven by white noise of spectral density q (per component) over a
step dt (filterpy's ``Q_discrete_white_noise`` with the continuous model)::

    Cov[position] = q dt^3 / 3,   Cov[position, velocity] = q dt^2 / 2,   Cov[velocity] = q dt

The Kalman filter's Q_k (:func:`~hvo_graph.estimators.kalman.process_covariance`)
is these three blocks per (position, velocity) pair. The factor graph uses the
velocity block for the twist random walk V(k-1) -> V(k), and, for the
trapezoidal motion factor, the position error given the velocities at *both*
ends (a Brownian bridge): q dt^3 / 12.

Both estimators take their defaults from here: q = a_max^2 dt (Bar-Shalom's
rule) with a_max = 0.3 m/s^2 (rad/s^2), just above the paper scenario's
largest linear and angular accelerations (0.28, 0.25), and dt = 1/30 s:
q = 3e-3 on every axis (docs/kalman.md, docs/smoother.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gtsam
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


def bridge_variance(q: np.ndarray, dt: float) -> np.ndarray:
    """Variance of the trapezoidal position step given both end velocities: q dt^3 / 12."""
    return q * dt**3 / 12.0


class MotionNoise:
    """The smoother's motion-factor noise models over an interval dt, cached per dt.

    Args:
        sigma: (s_w, s_v) of :func:`acceleration_sigma`.
    """

    def __init__(self, sigma: tuple[float, float]) -> None:
        #: diag(Q): white-noise-acceleration spectral densities, [rot x3; trans x3].
        self.q = twist_spectral_density(sigma)
        self._cache: dict[float, tuple[gtsam.noiseModel.Base, gtsam.noiseModel.Base]] = {}

    def __call__(self, dt: float) -> tuple[gtsam.noiseModel.Base, gtsam.noiseModel.Base]:
        """(motion, random walk) noise over dt: Q dt^3 / 12 (Brownian bridge) and Q dt."""
        cached = self._cache.get(dt)
        if cached is None:
            if len(self._cache) > 64:  # irregular frame times: keep the cache small
                self._cache.clear()
            cached = (
                gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(bridge_variance(self.q, dt))),
                gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(velocity_variance(self.q, dt))),
            )
            self._cache[dt] = cached
        return cached
