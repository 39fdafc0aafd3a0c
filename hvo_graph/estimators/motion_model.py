"""The smoother's motion models, one place that builds their factors between two frames.

- ``"wna"``, white-noise acceleration: per frame X(k), V(k); GTSAM's
  ``WnoaMotionFactorPose3`` between consecutive frames (:func:`wna_factor`, the
  Gaussian-process prior of Anderson and Barfoot in C++); ``"wna-pair"``, the same
  prior as the trapezoid and the twist random walk (the tightly coupled graph's
  form). Q is the spectral density of the acceleration.
- ``"wnj"``, white-noise jerk (constant acceleration): per frame X(k), V(k) and
  A(k), the twist rate; the pose factor and the linear twist-rate factor of
  :mod:`hvo_graph.estimators.jerk`. Q is the spectral density of the jerk.

``acceleration_sigma`` (s_w, s_v) = (sqrt(q_w), sqrt(q_v)) is the strength of
the model's white noise in both cases (rad s^-3/2, m s^-3/2 for WNA; rad
s^-5/2, m s^-5/2 for WNJ).
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, V, X

from hvo_graph.errors import InputError
from hvo_graph.estimators.choices import MOTION_MODEL_CHOICES
from hvo_graph.estimators.factors import _motion_factor
from hvo_graph.estimators.jerk import JerkNoise, jerk_motion_factor, twist_rate_factor
from hvo_graph.estimators.process_noise import twist_spectral_density, velocity_variance

__all__ = [
    "MOTION_MODELS",
    "STORED_FORMS",
    "MotionFactors",
    "check_motion_model",
    "twist_keys",
    "wna_factor",
]

#: The smoother's motion models ("auto": chosen per sequence by the likelihood).
MOTION_MODELS: tuple[str, ...] = ("wna", "wnj")

#: The forms :class:`MotionFactors` builds: the models, then "wna-pair", the WNA prior as
#: the trapezoid and the twist random walk (the tightly coupled graph's form).
STORED_FORMS: tuple[str, ...] = (*MOTION_MODELS, "wna-pair")

_ZERO6 = np.zeros(6)


def wna_factor(previous: int, k: int, dt: float, q: np.ndarray) -> gtsam.NonlinearFactor:
    """The white-noise-acceleration prior between frames ``previous`` and ``k``, dt apart.

    GTSAM's ``WnoaMotionFactorPose3`` on X(previous), V(previous), X(k), V(k), with
    xi = Log(X(previous)^-1 X(k)):

        e = [xi - dt V(previous);  J_r^-1(xi) V(k) - V(previous)]          (12,)
        Cov(e) = [[Q dt^3/3, Q dt^2/2], [Q dt^2/2, Q dt]]

    (J_r^-1 the inverse right Jacobian of SE(3): V(k) carried into the interval's start,
    I to first order). To first order it is the trapezoid Log(X(previous)^-1 X(k)) = dt
    (V(previous) + V(k)) / 2 with variance Q dt^3 / 12 and the random walk V(k) -
    V(previous) ~ N(0, Q dt), a linear transform of (e1, e2) (docs/smoother.md); a C++
    factor, linearized without a Python callback.

    Args:
        previous, k: frame indices (keys X(.), V(.)).
        dt: t_k - t_previous > 0, seconds (not checked: the callers' frames are in order).
        q: (6,) diag(Q) [rot x3; trans x3] (:func:`~.process_noise.twist_spectral_density`).
    """
    return gtsam.WnoaMotionFactorPose3(
        gtsam.StateData(X(previous), V(previous), 0.0), gtsam.StateData(X(k), V(k), dt), q
    )


def check_motion_model(value: object) -> str:
    """``value`` if it is one of :data:`MOTION_MODEL_CHOICES`, else InputError."""
    allowed = MOTION_MODEL_CHOICES
    if value not in allowed:
        raise InputError(f"motion_model: expected one of {', '.join(allowed)}, got {value!r}")
    return str(value)


def twist_keys(model: str, k: int) -> tuple[int, ...]:
    """The vector variables of frame k under ``model``: (V(k),) or (V(k), A(k))."""
    return (V(k), A(k)) if model == "wnj" else (V(k),)


class MotionFactors:
    """The motion factors between frames, noise models cached per (model, sigma, dt)."""

    def __init__(self) -> None:
        self._noise: dict[tuple[str, tuple[float, float]], np.ndarray | JerkNoise] = {}
        self._pair: dict[tuple[tuple[float, float], float], tuple] = {}

    def __call__(
        self, model: str, previous: int, k: int, dt: float, sigma: tuple[float, float]
    ) -> list[gtsam.NonlinearFactor]:
        """The factors of ``model`` (one of :data:`STORED_FORMS`) between frames ``previous``
        and ``k``, dt apart."""
        noise = self._noise.get((model, sigma))
        if noise is None:
            if len(self._noise) > 16:
                self._noise.clear()
            noise = JerkNoise(sigma) if model == "wnj" else twist_spectral_density(sigma)
            self._noise[(model, sigma)] = noise
        if model == "wna":
            return [wna_factor(previous, k, dt, noise)]  # type: ignore[arg-type]
        if model == "wna-pair":
            bridge, walk = self._pair_noise(noise, sigma, dt)  # type: ignore[arg-type]
            return [
                # dt > 0 (frames in time order) and the noise is 6-D: built unchecked.
                _motion_factor((X(previous), X(k), V(previous), V(k)), dt, bridge),
                gtsam.BetweenFactorVector(V(previous), V(k), _ZERO6, walk),
            ]
        keys = (X(previous), X(k), V(previous), V(k), A(previous), A(k))
        return [
            jerk_motion_factor(keys, dt, noise(dt)),  # type: ignore[arg-type]
            twist_rate_factor((V(previous), A(previous), V(k), A(k)), dt, noise.q),
        ]

    def _pair_noise(self, q: np.ndarray, sigma: tuple[float, float], dt: float) -> tuple:
        """The trapezoid's Q dt^3 / 12 (Brownian bridge) and the random walk's Q dt."""
        cached = self._pair.get((sigma, dt))
        if cached is None:
            if len(self._pair) > 64:  # irregular frame times: keep the cache small
                self._pair.clear()
            cached = self._pair[(sigma, dt)] = (
                gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(q * dt**3 / 12.0)),
                gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(velocity_variance(q, dt))),
            )
        return cached
