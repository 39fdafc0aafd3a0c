"""The smoother's motion models, one place that builds their factors between two frames.

- ``"wna"``, white-noise acceleration: per frame X(k), V(k); the trapezoidal
  motion factor (:func:`~hvo_graph.estimators.factors.motion_factor`, Brownian
  bridge Q dt^3 / 12) and the twist random walk V(k-1) -> V(k) (Q dt). Q is the
  spectral density of the acceleration.
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
from hvo_graph.estimators.process_noise import MotionNoise

__all__ = ["MOTION_MODELS", "MotionFactors", "check_motion_model", "twist_keys"]

#: The smoother's motion models ("auto": chosen per sequence by the likelihood).
MOTION_MODELS: tuple[str, ...] = ("wna", "wnj")

_ZERO6 = np.zeros(6)


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
        self._noise: dict[tuple[str, tuple[float, float]], MotionNoise | JerkNoise] = {}

    def __call__(
        self, model: str, previous: int, k: int, dt: float, sigma: tuple[float, float]
    ) -> list[gtsam.NonlinearFactor]:
        """The factors of ``model`` between frames ``previous`` and ``k``, dt apart."""
        noise = self._noise.get((model, sigma))
        if noise is None:
            if len(self._noise) > 16:
                self._noise.clear()
            noise = MotionNoise(sigma) if model == "wna" else JerkNoise(sigma)
            self._noise[(model, sigma)] = noise
        if model == "wna":
            motion_noise, walk_noise = noise(dt)  # type: ignore[misc]
            return [
                # dt > 0 (frames in time order) and the noise is 6-D: built unchecked.
                _motion_factor((X(previous), X(k), V(previous), V(k)), dt, motion_noise),
                gtsam.BetweenFactorVector(V(previous), V(k), _ZERO6, walk_noise),
            ]
        keys = (X(previous), X(k), V(previous), V(k), A(previous), A(k))
        return [
            jerk_motion_factor(keys, dt, noise(dt)),  # type: ignore[arg-type]
            twist_rate_factor((V(previous), A(previous), V(k), A(k)), dt, noise.q),
        ]
