"""Every knob reachable (command line, --config, pipeline), none silently ignored; run.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.io.trajectory import read_estimate_dir
from hvo_graph.pipeline import estimate, measure, run_estimate
from hvo_graph.sim.scenario import paper_scenario, simulate


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--out", str(out), "--duration", "3"]) == 0
    return out


@pytest.fixture(scope="module")
def scenario():
    return simulate(paper_scenario(duration=3.0))


def estimate_args(sim_dir, out, *extra):
    return [
        "estimate",
        "--camera",
        str(sim_dir / "camera.yaml"),
        "--tracks",
        str(sim_dir / "tracks.csv"),
        "--out",
        str(out),
        *extra,
    ]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            ["--method", "smoother", "--lag", "2"],
            "--lag: does not apply to method 'smoother' (it applies to fixed-lag, tight-fixed-lag)",
        ),
        (
            ["--method", "kalman", "--robust", "huber"],
            "--robust: does not apply to method 'kalman' "
            "(it applies to smoother, batch, fixed-lag)",
        ),
        (
            ["--method", "measurements", "--online"],
            "--online: does not apply to method 'measurements' "
            "(it applies to smoother, batch, fixed-lag, tight, tight-batch, tight-fixed-lag)",
        ),
        (
            ["--method", "measurements", "--covariance"],
            "--covariance: does not apply to method 'measurements' (it applies to smoother, "
            "batch, fixed-lag, kalman, tight, tight-batch, tight-fixed-lag)",
        ),
        (
            ["--method", "batch", "--relinearize-skip", "3"],
            "--relinearize-skip: does not apply to method 'batch' "
            "(it applies to smoother, fixed-lag, tight, tight-fixed-lag)",
        ),
        (
            ["--method", "kalman", "--independent-poses"],
            "--independent-poses: does not apply to method 'kalman'",
        ),
        (["--no-ransac", "--ransac-px", "2"], "--no-ransac: contradicts --ransac-px"),
    ],
)
def test_a_flag_that_does_not_apply_is_an_error(sim_dir, tmp_path, capsys, extra, message):
    assert main(estimate_args(sim_dir, tmp_path / "out", *extra)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"hvo-graph: error: {message}"] or err[0].startswith(
        f"hvo-graph: error: {message}"
    )
    assert not (tmp_path / "out").exists()  # nothing written


def test_run_json_records_method_options_noise_and_counts(sim_dir, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["--method", "fixed-lag", "--lag", "0.5", "--covariance", "--gate-chi2", "20"]
    assert main(estimate_args(sim_dir, out, *args)) == 0
    record = json.loads((out / "run.json").read_text())
    assert record["method"] == "fixed-lag"
    assert record["options"]["lag"] == 0.5 and record["options"]["covariance"] is True
    assert record["options"]["acceleration_sigma_fitted"] is True
    s_w, s_v = record["options"]["acceleration_sigma"]
    assert 1e-3 < s_w < 1.0 and 1e-3 < s_v < 1.0
    assert record["front_end"]["outlier_chi2"] == 20.0
    assert record["counts"]["frames"] == 91 and record["counts"]["rejected_points"] == 0
    assert record["inputs"]["tracks"].endswith("tracks.csv")
    assert "gtsam" in record["software"] and record["wall_time_s"] >= 0
    # the noise it reports is the one the estimate used
    trajectory = read_estimate_dir(out)
    assert trajectory.covariances is not None and len(trajectory) == 91


def test_config_file_sets_options_and_the_command_line_wins(sim_dir, tmp_path, capsys):
    config = tmp_path / "run.yaml"
    config.write_text("acceleration-sigma: 0.2\nvelocity_factors: all\ncovariance: true\n")
    out = tmp_path / "out"
    extra = ["--config", str(config), "--acceleration-sigma", "0.1,0.3"]
    assert main(estimate_args(sim_dir, out, *extra)) == 0
    options = json.loads((out / "run.json").read_text())["options"]
    assert options["acceleration_sigma"] == [0.1, 0.3]
    assert options["velocity_factors"] == "all" and options["covariance"] is True
    assert (out / "covariance.csv").is_file()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("speed: 2\n", "speed: unknown option, expected one of acceleration-sigma,"),
        ("acceleration-sigma: fast\n", "acceleration-sigma: expected a number, got 'fast'"),
        ("velocity-factors: some\n", "velocity-factors: expected one of gaps, all, got 'some'"),
        ("covariance: 3\n", "covariance: expected true or false, got 3"),
        ("- 1\n- 2\n", "expected a mapping of option names to values"),
    ],
)
def test_bad_config_file_names_file_and_key(sim_dir, tmp_path, capsys, text, message):
    config = tmp_path / "run.yaml"
    config.write_text(text)
    assert main(estimate_args(sim_dir, tmp_path / "out", "--config", str(config))) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"hvo-graph: error: {config}: ") and message in err
    assert "\n" not in err


def test_pipeline_takes_every_knob(scenario):
    fixed = estimate(scenario.observations, scenario, acceleration_sigma=0.1, covariance=True)
    run = run_estimate(scenario.observations, scenario, acceleration_sigma=0.1)
    assert run.estimator.acceleration_sigma == (0.1, 0.1)
    assert fixed.covariances is not None
    # the same as building the smoother by hand with that noise (run as the pipeline runs it)
    frames = measure(scenario.observations, scenario)
    direct = FactorGraphSmoother(acceleration_sigma=0.1).run(frames, online=False)
    np.testing.assert_allclose(run.trajectory.positions, direct.positions, atol=1e-12)
    with pytest.raises(InputError, match=r"^lag: does not apply to method 'smoother'"):
        estimate(scenario.observations, scenario, lag=2.0)
    with pytest.raises(InputError, match=r"^speed: unknown option"):
        estimate(scenario.observations, scenario, speed=2.0)
    no_ransac = run_estimate(scenario.observations, scenario, ransac=False, outlier_chi2=None)
    assert no_ransac.front_end.ransac_px is None and no_ransac.front_end.outlier_chi2 is None


def test_the_solver_names_agree_with_the_method_table():
    from hvo_graph.estimators.choices import SOLVERS, TIGHT_SOLVERS
    from hvo_graph.estimators.registry import METHODS

    graphs = [m for m in METHODS if m.solver]
    homography = {m.solver: m.name for m in graphs if not m.name.startswith("tight")}
    assert homography == dict(SOLVERS)
    assert {m.solver: m.name for m in graphs if m.name.startswith("tight")} == dict(TIGHT_SOLVERS)
