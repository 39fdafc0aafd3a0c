"""Fixtures shared by the test modules: the paper's two runs through the front end.

Simulating and measuring the paper's 10 s scenario takes a few seconds; the
session-scoped fixtures do it once for every module that needs it. Tests must
not modify what they get.
"""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

from hvo_graph.frontend import measure_sequence
from hvo_graph.sim.scenario import Scenario, paper_scenario, simulate
from hvo_graph.types import FrameMeasurement

# The property tests draw the same examples on every run (and in CI): a failure is then
# a change of the code, never the luck of the draw. HYPOTHESIS_PROFILE=explore draws anew.
settings.register_profile("repeatable", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))


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
