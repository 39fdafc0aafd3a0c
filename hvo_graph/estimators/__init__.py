"""Estimators over per-frame measurement records.

- ``measurements``: the raw per-frame homography estimates, no fusion;
- ``kalman``: the paper's 12-state Kalman filter (the baseline);
- ``smoother`` / ``batch`` / ``fixed-lag``: the GTSAM factor graph solved with
  ISAM2, Levenberg-Marquardt, or a fixed-lag smoother (custom factors in
  ``factors``).

The estimator classes and the custom factors are re-exported here and
imported on first use, so ``import hvo_graph.estimators`` does not load GTSAM.
"""

from hvo_graph import _lazy_exports

__all__, __getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "hvo_graph.estimators.base": ("Estimator",),
        "hvo_graph.estimators.measurements": ("RawMeasurements",),
        "hvo_graph.estimators.kalman": ("KalmanBaseline",),
        "hvo_graph.estimators.smoother": (
            "FactorGraphSmoother",
            "BatchSmoother",
            "FixedLagSmoother",
        ),
        "hvo_graph.estimators.factors": (
            "motion_factor",
            "mean_velocity_factor",
            "interval_weights",
        ),
    },
)
