"""A track off the plane, added to a simulated scenario's tracks (tests of the tight
smoother's off-plane rejection)."""

from __future__ import annotations

import numpy as np

from hvo_graph.types import FrameObservations


def with_off_plane_track(scenario, track=99, height=0.4):
    """The scenario's tracks plus one point ``height`` m in front of the plane, projected
    with the scenario's pixel noise (seeded)."""
    n = scenario.plane.normal
    point = scenario.points_world.mean(axis=0) + 0.1 * np.cross(n, [1.0, 0.0, 0.0]) - height * n
    truth = scenario.groundtruth
    rng = np.random.default_rng(7)
    out = []
    for k, obs in enumerate(scenario.observations):
        c = truth.rotations[k].T @ (point - truth.positions[k])
        uv = scenario.camera.project(c[None])[0] + scenario.pixel_sigma * rng.standard_normal(2)
        out.append(
            FrameObservations(obs.index, obs.t, np.append(obs.ids, track), np.vstack((obs.uv, uv)))
        )
    return out
