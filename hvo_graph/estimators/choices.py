"""The choice sets of the estimators' options and the smoothers' shared defaults, defined once.

The registry (:mod:`hvo_graph.estimators.registry`) builds its table and the
command line its choices from these; the estimators check their arguments
against them. Kept apart from the registry so that the estimators need not
import the table that imports them.
"""

from __future__ import annotations

import math
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

#: Default robust threshold on the whitened residual norm (GTSAM applies the
#: M-estimator to sqrt(e^T Sigma^-1 e)): sqrt of the 95 % quantile of chi^2 with
#: 6 degrees of freedom, so an inlier 6-vector is down-weighted 5 % of the time.
DEFAULT_ROBUST_THRESHOLD: float = math.sqrt(12.591587243743977)

#: Standard deviation (rad, m) of the prior X(k0) = I that defines the world frame.
DEFAULT_WORLD_SIGMA: float = 1e-6

#: Std (rad, m) of X(k0) = I until a pose tells the reference noise (shared_reference_noise).
ANCHOR_START_SIGMA: float = 1.0

#: Standard deviation (rad/s, m/s) of the zero-mean prior on the first twist V(k0).
DEFAULT_INITIAL_TWIST_SIGMA: float = 10.0

#: ISAM2 relinearizes a pose whose accumulated delta exceeds this (rad, m): the initial
#: values (the measurements) are within noise (~2 cm, 0.5 deg) of the optimum, so the
#: linearization error O(delta^2) stays far below the noise (docs/smoother.md).
DEFAULT_RELINEARIZE_THRESHOLD: float = 0.05

#: ISAM2 checks for relinearization every this many updates (GTSAM's default).
DEFAULT_RELINEARIZE_SKIP: int = 10
