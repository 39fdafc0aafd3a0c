"""Frame numbers, times and track ids are labels: a sequence numbered from frame 100, timed
in Unix seconds and with other ids must give the trajectory of the same sequence numbered
from 0 (the contract allows any frame >= 0 and any increasing times)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hvo_graph.pipeline import run_estimate
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import FrameObservations

FIRST_FRAME = 100
EPOCH = 1.7e9  # seconds: a recording timed by the wall clock


@pytest.fixture(scope="module")
def sequences():
    s = simulate(paper_scenario(duration=3.0, num_points=6, seed=2))
    relabelled = [
        FrameObservations(o.index + FIRST_FRAME, o.t + EPOCH, 7 * o.ids + 3, o.uv)
        for o in s.observations
    ]
    return s, dataclasses.replace(s, observations=relabelled)


@pytest.mark.parametrize(
    "method",
    ["smoother", "batch", "fixed-lag", "kalman", "measurements", "tight", "tight-fixed-lag"],
)
def test_a_sequence_numbered_from_100_in_unix_time_gives_the_same_trajectory(sequences, method):
    plain, relabelled = sequences
    # (fixed-lag: its window's blocks end on frame times, which Unix times round off)
    a = run_estimate(plain.observations, plain, method=method).trajectory
    b = run_estimate(relabelled.observations, relabelled, method=method).trajectory
    np.testing.assert_allclose(b.t - EPOCH, a.t, atol=1e-6)
    # times near 1.7e9 s keep ~2e-7 s of resolution: dt (and the result) moves that little
    np.testing.assert_allclose(b.positions, a.positions, atol=1e-6)
    np.testing.assert_allclose(b.rotations, a.rotations, atol=1e-6)
    np.testing.assert_allclose(b.twists, a.twists, atol=1e-4)
