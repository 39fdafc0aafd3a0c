"""The choice sets of the estimators' options, defined once.

The registry (:mod:`hvo_graph.estimators.registry`) builds its table and the
command line its choices from these; the estimators check their arguments
against them. Kept apart from the registry so that the estimators need not
import the table that imports them.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

#: Kalman filter R_k presets: the paper's two diagonals, and "measured" (the diagonal
#: of the front end's per-frame covariances, converted to state coordinates).
KALMAN_R_PRESETS: tuple[str, ...] = ("paper-noisy", "paper-noise-free", "measured")

#: Robust losses of the smoother's measurement factors (``gtsam.noiseModel.mEstimator``).
ROBUST_LOSSES: tuple[str, ...] = ("huber", "cauchy")

#: Window of the fixed-lag smoother, seconds, unless told otherwise.
DEFAULT_LAG: float = 1.0

#: ``velocity_factors`` choices of the factor-graph smoothers.
VELOCITY_FACTOR_POLICIES: tuple[str, ...] = ("gaps", "all")

#: ``motion_model`` choices of the factor-graph smoother: the one of the larger
#: likelihood on the sequence ("auto"), white-noise acceleration, white-noise jerk.
MOTION_MODEL_CHOICES: tuple[str, ...] = ("auto", "wna", "wnj")

#: The factor-graph smoother's back ends and their ``--method`` names.
SOLVERS: Mapping[str, str] = MappingProxyType(
    {"isam2": "smoother", "batch": "batch", "fixed-lag": "fixed-lag"}
)

#: The tightly coupled smoother's back ends and their ``--method`` names.
TIGHT_SOLVERS: Mapping[str, str] = MappingProxyType(
    {"isam2": "tight", "batch": "tight-batch", "fixed-lag": "tight-fixed-lag"}
)
