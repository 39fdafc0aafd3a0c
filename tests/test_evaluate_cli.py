"""``hvo-graph evaluate``: association, velocities by time, several estimates, formats, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.eval.association import associate, associate_velocity, nearest_within
from hvo_graph.io.trajectory import (
    read_groundtruth_dir,
    read_tum,
    write_estimate_dir,
    write_run_record,
    write_tum,
    write_velocity,
)
from hvo_graph.io.trajectory_paths import read_euroc_groundtruth
from hvo_graph.sim.scenario import ScenarioConfig, simulate
from hvo_graph.types import Trajectory


@pytest.fixture(scope="module")
def truth() -> Trajectory:
    """The paper scenario's ground truth, 3 s at 30 fps, with twists."""
    return simulate(ScenarioConfig(duration=3.0, seed=0)).groundtruth


def perturbed(traj: Trajectory, shift: float, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(
        t=traj.t.copy(),
        rotations=traj.rotations.copy(),
        positions=traj.positions
        + np.array([shift, 0.0, 0.0])
        + rng.normal(0, 0.002, (len(traj), 3)),
        twists=traj.twists + rng.normal(0, 0.01, traj.twists.shape),
    )


def run_cli(capsys, *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["evaluate", *args])
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------ association


def test_association_pairs_nearest_within_tolerance_ties_to_the_earlier():
    i, j = nearest_within(np.array([0.0, 0.5, 1.0, 9.0]), np.array([0.25, 0.75, 1.0]), 0.25)
    # 0.0 -> 0.25 (0.25 away, allowed); 0.5 is 0.25 from both: the earlier wins;
    # 9.0 is beyond the last stamp + tolerance.
    assert i.tolist() == [0, 1, 2] and j.tolist() == [0, 0, 2]


def test_association_walks_the_shorter_trajectory_and_applies_the_offset():
    t_gt = np.arange(0.0, 1.0, 0.01) + 0.004  # 100 Hz, 4 ms ahead
    t_est = np.arange(0.0, 1.0, 0.1)  # 10 Hz
    i_gt, i_est = associate(t_gt, t_est, max_diff=0.001, offset=0.004)
    assert i_est.tolist() == list(range(10))
    np.testing.assert_allclose(t_gt[i_gt] - t_est[i_est], 0.004, atol=1e-12)
    # Without the offset, 4 ms is beyond a 1 ms tolerance: nothing matches.
    with pytest.raises(InputError, match=r"no estimate timestamp is within 0\.001 s"):
        associate(t_gt, t_est, max_diff=0.001)
    # The longer estimate is walked from the ground truth's side: one pair per gt pose.
    i_gt, i_est = associate(t_est, t_gt, max_diff=0.01, offset=-0.004)
    assert i_gt.tolist() == list(range(10)) and len(set(i_est.tolist())) == 10


def test_velocity_association_skips_nan_rows():
    t_vel = np.array([0.0, 0.1, 0.2, 0.3])
    twists = np.arange(24.0).reshape(4, 6)
    twists[2] = np.nan
    out = associate_velocity(np.array([0.0, 0.19, 0.3, 0.5]), t_vel, twists, max_diff=0.1)
    np.testing.assert_array_equal(out[0], twists[0])
    # 0.19 would take the NaN row at 0.2; it is skipped, so the row at 0.1 is nearest.
    np.testing.assert_array_equal(out[1], twists[1])
    np.testing.assert_array_equal(out[2], twists[3])
    assert np.isnan(out[3]).all()


# ------------------------------------------------------------------ velocities


def test_groundtruth_velocity_rows_need_not_match_the_poses(tmp_path, truth, capsys):
    gt = tmp_path / "gt"
    gt.mkdir()
    every_other = np.arange(0, len(truth), 2)
    write_tum(
        gt / "groundtruth.txt",
        Trajectory(
            truth.t[every_other], truth.rotations[every_other], truth.positions[every_other]
        ),
    )
    twists = truth.twists.copy()
    twists[4] = np.nan  # an unknown velocity: skipped, not an error
    write_velocity(gt / "groundtruth_velocity.csv", truth.t, twists)
    est = tmp_path / "est"
    write_estimate_dir(est, truth)

    loaded = read_groundtruth_dir(gt)  # used to refuse: more velocity rows than poses
    np.testing.assert_array_equal(loaded.twists, twists[every_other])

    code, out, _ = run_cli(capsys, str(est), "--groundtruth", str(gt), "--json")
    result = json.loads(out)
    assert code == 0 and result["frames"] == len(every_other)
    assert result["linear_velocity_mps"] == {"rmse": 0.0, "max": 0.0}
    # With a wider tolerance frame 4 takes the nearest known row, frame 3's (the NaN
    # row is skipped; 3 and 5 tie, the earlier wins): its error is the only one.
    code, out, _ = run_cli(
        capsys, str(est), "--groundtruth", str(gt), "--json", "--t-max-diff", "0.04"
    )
    result = json.loads(out)
    lin = np.linalg.norm(truth.twists[4, 3:] - truth.twists[3, 3:])
    ang = np.linalg.norm(truth.twists[4, :3] - truth.twists[3, :3])
    assert result["linear_velocity_mps"]["max"] == pytest.approx(lin, rel=1e-12)
    assert result["angular_velocity_radps"]["max"] == pytest.approx(ang, rel=1e-12)


# ------------------------------------------------------------------ several estimates


def test_several_estimates_one_table_named_by_run_json(tmp_path, truth, capsys):
    write_tum(tmp_path / "gt.txt", truth)
    paths = []
    for k, method in enumerate(("smoother", "kalman", "measurements")):
        d = tmp_path / f"run{k}"
        write_estimate_dir(d, perturbed(truth, 0.01 * k, k))
        write_run_record(d, {"method": method})
        paths.append(str(d))
    plain = tmp_path / "mine"
    write_estimate_dir(plain, perturbed(truth, 0.05, 9))
    paths.append(str(plain / "trajectory.txt"))
    code, out, _ = run_cli(capsys, *paths, "--groundtruth", str(tmp_path / "gt.txt"))
    assert code == 0
    first, second = out.split("\n\n")
    names = [line.split()[0] for line in first.splitlines()[1:]]
    assert names == ["smoother", "kalman", "measurements", "mine"]
    assert [line.split()[0] for line in second.splitlines()[1:]] == names
    # A TUM ground truth carries no velocities: those cells are '-'.
    assert first.splitlines()[1].split()[5:9] == ["-", "-", "-", "-"]

    code, out, _ = run_cli(capsys, *paths, "--groundtruth", str(tmp_path / "gt.txt"), "--json")
    result = json.loads(out)
    assert [e["method"] for e in result["estimates"]] == names
    # The position RMSE is the APE translation RMSE; offsets of 0, 1 and 2 cm show.
    rmse = [e["position_m"]["rmse"] for e in result["estimates"]]
    assert rmse == [e["ape"]["trans_m"]["rmse"] for e in result["estimates"]]
    assert rmse[0] < 0.005 and 0.009 < rmse[1] < 0.012 and 0.019 < rmse[2] < 0.022

    # Two runs of one method are told apart by their path.
    code, out, _ = run_cli(capsys, paths[0], paths[0], "--groundtruth", str(tmp_path / "gt.txt"))
    assert f"smoother ({paths[0]})" in out


def test_csv_has_one_row_per_estimate_matching_the_json(tmp_path, truth, capsys):
    write_tum(tmp_path / "gt.txt", truth)
    for k in range(2):
        write_estimate_dir(tmp_path / f"e{k}", perturbed(truth, 0.0, k))
    args = (str(tmp_path / "e0"), str(tmp_path / "e1"), "--groundtruth", str(tmp_path / "gt.txt"))
    _, out, _ = run_cli(capsys, *args, "--csv", "--delta", "5")
    lines = out.splitlines()
    assert len(lines) == 3
    header = lines[0].split(",")
    assert header[:4] == ["method", "frames", "position_m_rmse", "position_m_max"]
    assert "ape_trans_m_rmse" in header and "rpe_rot_deg_median" in header
    _, js, _ = run_cli(capsys, *args, "--json", "--delta", "5")
    for line, entry in zip(lines[1:], json.loads(js)["estimates"], strict=True):
        row = dict(zip(header, line.split(","), strict=True))
        assert row["method"] == entry["method"] and int(row["frames"]) == entry["frames"]
        assert float(row["rpe_trans_m_rmse"]) == entry["rpe"]["trans_m"]["rmse"]
        assert int(row["rpe_pairs"]) == entry["rpe"]["pairs"] == (len(truth) - 1) // 5
        assert row["linear_velocity_mps_rmse"] == ""


def test_rpe_delta_in_seconds_picks_the_same_pairs_as_frames(tmp_path, truth, capsys):
    write_tum(tmp_path / "gt.txt", truth)
    write_estimate_dir(tmp_path / "e", perturbed(truth, 0.0, 1))
    base = (str(tmp_path / "e"), "--groundtruth", str(tmp_path / "gt.txt"), "--json")
    _, frames, _ = run_cli(capsys, *base, "--delta", "10")
    _, seconds, _ = run_cli(capsys, *base, "--delta", "0.3333", "--delta-unit", "s")
    assert json.loads(frames)["rpe"] == json.loads(seconds)["rpe"]


def test_plot_writes_the_three_figures(tmp_path, truth, capsys):
    write_tum(tmp_path / "gt.txt", truth)
    write_estimate_dir(tmp_path / "e", perturbed(truth, 0.0, 1))
    code, _, _ = run_cli(
        capsys,
        str(tmp_path / "e"),
        "--groundtruth",
        str(tmp_path / "gt.txt"),
        "--plot",
        str(tmp_path / "figs"),
        "--align",
        "se3",
    )
    assert code == 0
    names = sorted(p.name for p in (tmp_path / "figs").iterdir())
    assert names == [
        f"{n}.{e}"
        for n in ("error_distribution", "error_over_time", "top_view")
        for e in ("png", "svg")
    ]
    assert all((tmp_path / "figs" / n).stat().st_size > 1000 for n in names)


def test_euroc_groundtruth_reads_like_the_tum_file(tmp_path, truth):
    write_tum(tmp_path / "gt.txt", truth)
    tum = read_tum(tmp_path / "gt.txt")
    # The TUM file's own numbers, reordered the EuRoC way (ns, p, q_w first, then more).
    rows = []
    for line in (tmp_path / "gt.txt").read_text().splitlines()[1:]:
        t, x, y, z, qx, qy, qz, qw = line.split()
        rows.append(f"{round(float(t) * 1e9)},{x},{y},{z},{qw},{qx},{qy},{qz},0,0,0,0,0,0,0,0,0")
    header = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], ..."
    (tmp_path / "data.csv").write_text("\n".join([header, *rows]) + "\n")
    euroc = read_euroc_groundtruth(tmp_path / "data.csv")
    np.testing.assert_allclose(euroc.t, tum.t, atol=1e-9)
    np.testing.assert_array_equal(euroc.positions, tum.positions)
    np.testing.assert_allclose(euroc.rotations, tum.rotations, atol=1e-15)
    (tmp_path / "bad.csv").write_text(header + "\n1,2,3\n")
    with pytest.raises(InputError, match=r"bad\.csv:2: expected at least 8 comma-separated"):
        read_euroc_groundtruth(tmp_path / "bad.csv")


# ------------------------------------------------------------------ bad input


def test_bad_input_exits_2_with_one_line(tmp_path, truth, capsys):
    gt = tmp_path / "gt.txt"
    write_tum(gt, truth)
    write_estimate_dir(tmp_path / "e", truth)
    est = str(tmp_path / "e")
    line = Trajectory(
        truth.t, np.tile(np.eye(3), (len(truth), 1, 1)), np.outer(truth.t, [1.0, 0.0, 0.0])
    )
    write_tum(tmp_path / "line.txt", line)
    late = Trajectory(truth.t + 100.0, truth.rotations, truth.positions)
    write_tum(tmp_path / "late.txt", late)
    cases = [
        (
            (" --groundtruth " + str(gt)).split(),
            "evaluate: expected at least one estimate (EST or --estimate PATH)",
        ),
        (
            [str(tmp_path / "nope"), "--groundtruth", str(gt)],
            f"{tmp_path / 'nope'}: expected a directory or a trajectory file, found nothing",
        ),
        (
            [est, "--groundtruth", str(gt), "--n-to-align", "10"],
            "--n-to-align: applies to --align se3 or sim3, not none",
        ),
        (
            [est, "--groundtruth", str(gt), "--delta", "1.5"],
            "--delta: expected a whole number of frames, got 1.5",
        ),
        (
            [
                str(tmp_path / "line.txt"),
                "--groundtruth",
                str(tmp_path / "line.txt"),
                "--align",
                "se3",
            ],
            f"alignment: the {len(truth)} estimate positions used do not fix a rotation",
        ),
        (
            [str(tmp_path / "late.txt"), "--groundtruth", str(gt)],
            "no estimate timestamp is within 0.01 s of a ground-truth timestamp",
        ),
        (
            [est, "--groundtruth", str(gt), "--delta", "100", "--delta-unit", "m"],
            f"--delta 100 m: no pose pair of the estimate ({len(truth)} associated poses)",
        ),
        (
            [est, "--groundtruth", str(tmp_path)],
            f"{tmp_path}: expected groundtruth.txt, trajectory.txt or",
        ),
    ]
    for args, message in cases:
        code, out, err = run_cli(capsys, *[a for a in args if a])
        assert code == 2 and out == "", args
        assert err.count("\n") == 1 and err.startswith("hvo-graph: error: "), err
        assert message in err, (message, err)
    assert main(["evaluate", est, "--groundtruth", str(gt), "--json", "--csv"]) == 2
    assert "--csv: not allowed with argument --json" in capsys.readouterr().err


# ------------------------------------------------------------------ end to end


def test_one_command_compares_the_methods_with_the_experiments_numbers(tmp_path, capsys):
    """simulate -> estimate (three methods) -> one evaluate: one table, one set of figures,
    and the numbers the experiments compute (error_series + summarize) for the same runs."""
    from hvo_graph.eval.metrics import error_series, summarize
    from hvo_graph.io.trajectory import read_estimate_dir

    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--duration", "2", "--seed", "3"]) == 0
    methods = ("smoother", "kalman", "measurements")
    for m in methods:
        assert (
            main(
                [
                    "estimate",
                    "--camera",
                    str(sim / "camera.yaml"),
                    "--tracks",
                    str(sim / "tracks.csv"),
                    "--method",
                    m,
                    "--out",
                    str(tmp_path / m),
                ]
            )
            == 0
        )
    code, out, _ = run_cli(
        capsys,
        *(str(tmp_path / m) for m in methods),
        "--groundtruth",
        str(sim),
        "--skip",
        "1",
        "--json",
        "--plot",
        str(tmp_path / "figs"),
    )
    assert code == 0 and len(list((tmp_path / "figs").glob("*.png"))) == 3
    result = json.loads(out)["estimates"]
    assert [e["method"] for e in result] == list(methods)
    truth = read_groundtruth_dir(sim)
    for entry, m in zip(result, methods, strict=True):
        expected = summarize(
            error_series(read_estimate_dir(tmp_path / m), truth), t_start=truth.t[0] + 1.0
        ).as_dict()
        for key, value in expected.items():
            if isinstance(value, dict):
                assert entry[key] == pytest.approx(value, rel=1e-12, abs=1e-15), (m, key)
            else:
                assert entry[key] == value, (m, key)


def test_sim3_recovers_the_scale_of_positions_and_linear_velocities(truth):
    from hvo_graph.eval.evaluation import EvaluationOptions, evaluate_trajectory

    # A monocular-style estimate: the whole motion at half scale (positions and v), in
    # its own world frame, rotated by 90 degrees about z.
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    twists = truth.twists.copy()
    twists[:, 3:] *= 0.5
    est = Trajectory(
        truth.t, np.einsum("ij,kjl->kil", Rz, truth.rotations), 0.5 * truth.positions @ Rz.T, twists
    )
    ev = evaluate_trajectory(est, truth, options=EvaluationOptions(align="sim3"))
    assert ev.alignment.scale == pytest.approx(2.0, rel=1e-12)
    assert ev.summary.position_max < 1e-12 and ev.summary.orientation_max < 1e-9
    assert ev.summary.linear_velocity_max < 1e-12 and ev.summary.angular_velocity_max < 1e-12
    se3 = evaluate_trajectory(est, truth, options=EvaluationOptions(align="se3"))
    assert se3.summary.linear_velocity_max > 0.1 * np.abs(truth.twists[:, 3:]).max()


def test_plot_without_matplotlib_is_a_clear_error(tmp_path, truth, capsys, monkeypatch):
    import sys

    write_tum(tmp_path / "gt.txt", truth)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if the extra were missing
    code, out, err = run_cli(
        capsys,
        str(tmp_path / "gt.txt"),
        "--groundtruth",
        str(tmp_path / "gt.txt"),
        "--plot",
        str(tmp_path / "figs"),
    )
    assert code == 2 and out == "" and not (tmp_path / "figs").exists()
    assert err == "hvo-graph: error: --plot: needs matplotlib (pip install 'hvo_graph[figures]')\n"


def test_simulate_estimate_evaluate_need_no_matplotlib(tmp_path):
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['matplotlib'] = None\n"
        "from hvo_graph.cli import main\n"
        f"d = {str(tmp_path)!r}\n"
        "assert main(['simulate', '--out', d + '/sim', '--duration', '1']) == 0\n"
        "assert main(['estimate', '--camera', d + '/sim/camera.yaml', '--tracks',"
        " d + '/sim/tracks.csv', '--method', 'kalman', '--out', d + '/k']) == 0\n"
        "assert main(['evaluate', d + '/k', '--groundtruth', d + '/sim', '--csv']) == 0\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1].startswith("kalman,31,")
