"""Estimators over per-frame measurement records.

- ``measurements``: the raw per-frame homography estimates, no fusion;
- ``kalman``: the paper's 12-state Kalman filter (the baseline);
- ``smoother`` / ``batch`` / ``fixed-lag``: the GTSAM factor graph solved with
  ISAM2, Levenberg-Marquardt, or a fixed-lag smoother.
"""

from hvo_graph.estimators.base import Estimator

__all__ = ["Estimator"]
