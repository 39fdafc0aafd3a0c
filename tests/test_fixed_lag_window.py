"""The fixed-lag smoother's window (hvo_graph.estimators.solvers.FixedLagBackend): a
frame's final values are its full estimate as it left the window. Independent
reference: ISAM2's full back-substitution (``calculateBestEstimate``) taken before
every update."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from hvo_graph.estimators.smoother import FixedLagSmoother
from hvo_graph.frontend import measure_sequence
from hvo_graph.sim.families import draw


class _BeforeEachUpdate:
    """GTSAM's fixed-lag smoother, with ISAM2's full estimate kept before every update."""

    def __init__(self, smoother: gtsam.IncrementalFixedLagSmoother, isam: gtsam.ISAM2):
        self.smoother, self.isam = smoother, isam
        self.estimates: list[gtsam.Values] = []

    def update(self, graph, values, stamps) -> None:
        self.estimates.append(self.isam.calculateBestEstimate())
        self.smoother.update(graph, values, stamps)


def test_each_frame_leaves_the_window_with_its_full_estimate():
    scenario = draw("agile", 3).scenario  # fast motion: the window's estimates move
    frames = measure_sequence(
        scenario.observations, scenario.camera, scenario.plane, pixel_sigma=scenario.pixel_sigma
    )
    smoother = FixedLagSmoother(lag=0.5)
    backend = smoother.backend
    recorder = _BeforeEachUpdate(backend.smoother, backend.isam)
    backend.smoother = recorder
    smoother.run(frames)
    frozen = dict(backend.frozen)
    assert len(frozen) > 0.9 * len(frames)  # every frame but the last window's
    # The estimate before the update that marginalized a frame: the last one holding it.
    left = {}
    for estimate in recorder.estimates:
        for key in estimate.keys():
            if gtsam.Symbol(key).chr() == ord("x"):
                left[gtsam.Symbol(key).index()] = estimate
    for index, (pose, twist, _) in frozen.items():
        estimate = left[index]
        assert np.array_equal(pose.matrix(), estimate.atPose3(X(index)).matrix()), index
        assert np.array_equal(twist, estimate.atVector(V(index))), index
