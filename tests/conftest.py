"""Fixtures shared by the test modules: the paper's two runs through the front end.

Simulating and measuring the paper's 10 s scenario takes a few seconds; the
session-scoped fixtures do it once for every module that needs it. Tests must
not modify what they get.
"""

from __future__ import annotations

import pytest

from hvo_graph.frontend import measure_sequence
from hvo_graph.sim.scenario import Scenario, paper_scenario, simulate
from hvo_graph.types import FrameMeasurement


@pytest.fixture(scope="session")
def noise_free_run() -> tuple[Scenario, list[FrameMeasurement]]:
    """The paper's noise-free run (seed 0) and its measurements.

    Noise-free data are given a small pixel sigma (the front end needs one > 0 for its
    covariances), as the paper gives its filter the small noise-free R.
    """
    scenario = simulate(paper_scenario(noisy=False))
    return scenario, measure_sequence(
        scenario.observations, scenario.camera, scenario.plane, pixel_sigma=1e-3
    )


@pytest.fixture(scope="session")
def noisy_run() -> tuple[Scenario, list[FrameMeasurement]]:
    """The paper's noisy run (0.05 px^2, seed 0) and its measurements."""
    scenario = simulate(paper_scenario(noisy=True, seed=0))
    return scenario, measure_sequence(
        scenario.observations, scenario.camera, scenario.plane, pixel_sigma=scenario.pixel_sigma
    )


@pytest.fixture(scope="session")
def paper(noisy_run: tuple[Scenario, list[FrameMeasurement]]) -> Scenario:
    """The paper's noisy scenario (``simulate()`` with its defaults)."""
    return noisy_run[0]
