"""Small measurement records for the smoother's input-check tests (not a test module)."""

from __future__ import annotations

import numpy as np

from hvo_graph.types import PoseMeasurement, VelocityMeasurement

#: Frame rate of the records' default velocity interval.
FPS = 30.0


def pose_record(**kw: object) -> PoseMeasurement:
    """An H_d pose at the reference (identity, 1e-4 covariance) with fields replaced."""
    base = dict(rotation=np.eye(3), position=np.zeros(3), covariance=np.eye(6) * 1e-4, reference=0)
    base.update(kw)
    return PoseMeasurement(**base)


def velocity_record(**kw: object) -> VelocityMeasurement:
    """An H_c twist of zero (1e-2 covariance) over the first interval at :data:`FPS`."""
    base = dict(twist=np.zeros(6), covariance=np.eye(6) * 1e-2, t=0.5 / FPS, dt=1 / FPS)
    base.update(kw)
    return VelocityMeasurement(**base)
