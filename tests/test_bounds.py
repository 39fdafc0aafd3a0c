"""Cramér-Rao bounds (hvo_graph.eval.bounds) and experiments/bounds.py.

Independent reference: the front end's first-order pose covariance of H_d
(hvo_graph.geometry.transfer, the transfer error propagated by hand), which for
frames 0 and k is the memoryless bound computed here from GTSAM's Fisher
information; and the ordering of information (more information, smaller bound).
"""

from __future__ import annotations

import numpy as np
import pytest
from script_helpers import load_script

from hvo_graph.errors import InputError
from hvo_graph.eval.bounds import memoryless_bound, posterior_bound
from hvo_graph.frontend import FrontEndConfig, measure_sequence
from hvo_graph.sim.scenario import paper_scenario, simulate


@pytest.fixture(scope="module")
def scenario():
    return simulate(paper_scenario(duration=2.0, num_points=6))


def test_memoryless_bound_is_the_front_ends_pose_covariance(scenario):
    config = FrontEndConfig(pixel_sigma=scenario.pixel_sigma, ransac=False, outlier_chi2=None)
    frames = measure_sequence(scenario.clean_observations, scenario.camera, scenario.plane, config)
    bound = memoryless_bound(scenario)
    for k in (5, 30, 60):
        C = frames[k].pose.covariance
        assert bound.position[k] == pytest.approx(np.sqrt(np.trace(C[3:, 3:])), rel=0.03)
        ori = np.rad2deg(np.sqrt(np.trace(C[:3, :3])))
        assert bound.orientation[k] == pytest.approx(ori, rel=0.03)


def test_the_motion_prior_lowers_the_bound(scenario):
    memoryless = memoryless_bound(scenario)
    loose = posterior_bound(scenario, 10.0)
    tight = posterior_bound(scenario, 0.05)
    assert loose.position[0] < 1e-5 and tight.position[0] < 1e-5  # X(0) = I is known
    later = slice(1, None)
    assert np.all(tight.position[later] < loose.position[later])
    assert np.all(loose.position[later] <= memoryless.position[later] * 1.0001)
    assert np.all(loose.orientation[later] <= memoryless.orientation[later] * 1.0001)
    assert tight.rmse(1.0)[0] < 0.6 * memoryless.rmse(1.0)[0]
    with pytest.raises(InputError, match=r"t_start: 5\.0 s leaves no frame"):
        tight.rmse(5.0)


def test_bounds_script_writes_its_table(tmp_path, capsys):
    bounds = load_script("bounds")
    args = ["--seeds", "1", "--duration", "1.5", "--skip", "0.5", "--out-dir", str(tmp_path)]
    assert bounds.main(args) == 0
    page = (tmp_path / "bounds.md").read_text()
    for row in ("posterior bound", "memoryless bound", "tight ISAM2 smoothed", "ISAM2 smoothed"):
        assert f"| {row} " in page
    lines = (tmp_path / "bounds.csv").read_text().splitlines()
    assert lines[0].startswith("t,posterior_position_m") and len(lines) == 1 + 46
    assert bounds.main(["--duration", "1", "--skip", "2", "--out-dir", str(tmp_path)]) == 2
    assert "--skip 2.0 leaves no frame" in capsys.readouterr().err
