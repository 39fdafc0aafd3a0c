"""``hvo-graph evaluate`` against evo, the field's reference (evo_ape / evo_rpe's Python API).

The ground truth runs on another clock (offset by 4 ms) at another rate (100 Hz
against the estimate's 30 Hz); the estimate is noisy, rotated, shifted and
scaled so that every alignment has work to do. Each statistic must agree with
evo's to 1e-9.
"""

from __future__ import annotations

import json
import os
import sys

import gtsam
import numpy as np
import pytest

from hvo_graph.cli import main
from hvo_graph.eval.alignment import umeyama
from hvo_graph.io.trajectory import write_tum
from hvo_graph.types import Trajectory

evo = pytest.importorskip("evo", reason="evo is a test dependency: pip install -e .[test]")
from evo.core import geometry, metrics, sync  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402
from evo.tools import file_interface  # noqa: E402

GT_OFFSET = 0.004  # the ground truth's clock runs 4 ms ahead
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")
RELATIONS = {
    "trans_m": metrics.PoseRelation.translation_part,
    "rot_deg": metrics.PoseRelation.rotation_angle_deg,
    "full": metrics.PoseRelation.full_transformation,
}


def motion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A smooth, non-planar camera motion: (K, 3, 3) R_wc and (K, 3) p_wc."""
    p = np.column_stack((np.sin(0.8 * t), 0.3 * np.cos(0.5 * t) - 0.3, 0.25 * t))
    R = np.array(
        [
            gtsam.Rot3.Expmap(np.array([0.2 * np.sin(0.6 * s), 0.15 * s, 0.1 * np.cos(s)])).matrix()
            for s in t
        ]
    )
    return R, p


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    rng = np.random.default_rng(7)
    d = tmp_path_factory.mktemp("evo")
    t_est = np.arange(0.0, 6.0, 1.0 / 30.0)
    R, p = motion(t_est)
    # Noise, then a similarity of the whole estimate (its own world frame and scale).
    R = np.array([Rk @ gtsam.Rot3.Expmap(rng.normal(0, 0.01, 3)).matrix() for Rk in R])
    p = p + rng.normal(0, 0.01, p.shape)
    Ra = gtsam.Rot3.Expmap(np.array([0.1, -0.2, 0.3])).matrix()
    est = Trajectory(t_est, np.einsum("ij,kjl->kil", Ra, R), 1.3 * p @ Ra.T + [0.5, -0.2, 0.1])
    t_true = np.arange(-0.1, 6.1, 0.01)
    R_gt, p_gt = motion(t_true)
    gt = Trajectory(t_true + GT_OFFSET, R_gt, p_gt)
    write_tum(d / "est.txt", est)
    write_tum(d / "gt.txt", gt)
    return d / "est.txt", d / "gt.txt"


def evaluate_json(capsys, est, gt, *options: str) -> dict:
    capsys.readouterr()
    assert main(["evaluate", str(est), "--groundtruth", str(gt), "--json", *options]) == 0
    return json.loads(capsys.readouterr().out)


def evo_trajectories(est, gt, max_diff: float, offset: float):
    ref = file_interface.read_tum_trajectory_file(str(gt))
    traj = file_interface.read_tum_trajectory_file(str(est))
    return sync.associate_trajectories(ref, traj, max_diff=max_diff, offset_2=offset)


ALIGN = {  # our --align: evo's (align, correct_scale, align_origin)
    "none": (False, False, False),
    "origin": (False, False, True),
    "se3": (True, False, False),
    "sim3": (True, True, False),
}


def assert_stats(ours: dict, theirs: dict) -> None:
    for s in STATS:
        assert ours[s] == pytest.approx(theirs[s], abs=1e-9, rel=1e-12), s


@pytest.mark.parametrize("align", ["none", "origin", "se3", "sim3"])
@pytest.mark.parametrize("offset", [0.0, GT_OFFSET])
def test_ape_agrees_with_evo_ape(files, capsys, align, offset):
    est, gt = files
    ours = evaluate_json(capsys, est, gt, "--align", align, "--t-offset", str(offset))
    flags = ALIGN[align]
    for key, relation in RELATIONS.items():
        ref, traj = evo_trajectories(est, gt, 0.01, offset)
        result = evo_ape(
            ref, traj, relation, align=flags[0], correct_scale=flags[1], align_origin=flags[2]
        )
        assert_stats(ours["ape"][key], result.stats)
    assert ours["frames"] == ours["association"]["matched"] == 180


def test_ape_on_the_first_poses_agrees_with_evo(files, capsys):
    est, gt = files
    ours = evaluate_json(
        capsys,
        est,
        gt,
        "--align",
        "sim3",
        "--n-to-align",
        "40",
        "--t-offset",
        str(GT_OFFSET),
        "--t-max-diff",
        "0.005",
    )
    ref, traj = evo_trajectories(est, gt, 0.005, GT_OFFSET)
    result = evo_ape(ref, traj, RELATIONS["trans_m"], align=True, correct_scale=True, n_to_align=40)
    assert_stats(ours["ape"]["trans_m"], result.stats)
    assert ours["alignment"]["poses"] == 40


@pytest.mark.parametrize(
    ("delta", "unit", "all_pairs", "align"),
    [
        (1, "f", False, "none"),
        (10, "f", False, "se3"),
        (10, "f", True, "sim3"),
        (0.5, "m", False, "none"),
        (0.5, "m", True, "sim3"),
        (0.3, "m", False, "sim3"),
    ],
)
def test_rpe_agrees_with_evo_rpe(files, capsys, delta, unit, all_pairs, align):
    est, gt = files
    extra = ["--all-pairs"] if all_pairs else []
    ours = evaluate_json(
        capsys,
        est,
        gt,
        "--delta",
        str(delta),
        "--delta-unit",
        unit,
        "--align",
        align,
        "--t-offset",
        str(GT_OFFSET),
        *extra,
    )
    evo_unit = metrics.Unit.frames if unit == "f" else metrics.Unit.meters
    flags = ALIGN[align]
    for key, relation in RELATIONS.items():
        ref, traj = evo_trajectories(est, gt, 0.01, GT_OFFSET)
        result = evo_rpe(
            ref,
            traj,
            relation,
            delta=delta,
            delta_unit=evo_unit,
            all_pairs=all_pairs,
            align=flags[0],
            correct_scale=flags[1],
        )
        assert_stats(ours["rpe"][key], result.stats)
        assert ours["rpe"]["pairs"] == len(result.np_arrays["error_array"])


def test_umeyama_matches_evo_and_recovers_a_known_similarity():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(50, 3))
    R = gtsam.Rot3.Expmap(np.array([0.4, -1.1, 2.0])).matrix()
    y = 0.7 * x @ R.T + [1.0, 2.0, -3.0]
    # Textbook: exact data gives back the similarity that made it.
    R_hat, t_hat, s_hat = umeyama(x, y, with_scale=True)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, [1.0, 2.0, -3.0], atol=1e-12)
    assert s_hat == pytest.approx(0.7, abs=1e-12)
    # Noisy data: the same answer as evo's implementation.
    y_noisy = y + rng.normal(0, 0.05, y.shape)
    for with_scale in (False, True):
        ours = umeyama(x, y_noisy, with_scale=with_scale)
        theirs = geometry.umeyama_alignment(x.T, y_noisy.T, with_scale)
        for a, b in zip(ours, theirs, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-12)


def test_to_evo_and_back(files):
    from hvo_graph.io.trajectory import read_tum

    est, _ = files
    traj = read_tum(est)
    ev = traj.to_evo(name="smoother")
    reference = file_interface.read_tum_trajectory_file(str(est))
    np.testing.assert_allclose(ev.positions_xyz, reference.positions_xyz, atol=0)
    np.testing.assert_allclose(
        np.asarray(ev.poses_se3), np.asarray(reference.poses_se3), atol=1e-15
    )
    back = Trajectory.from_evo(ev)
    np.testing.assert_array_equal(back.t, traj.t)
    np.testing.assert_array_equal(back.rotations, traj.rotations)
    np.testing.assert_array_equal(back.positions, traj.positions)


def test_to_evo_without_evo_is_a_clear_error(monkeypatch):
    from hvo_graph.errors import InputError

    monkeypatch.setitem(sys.modules, "evo.core", None)  # as if evo were not installed
    traj = Trajectory(np.zeros(1), np.eye(3)[None], np.zeros((1, 3)))
    with pytest.raises(InputError, match=r"evo is not installed: pip install evo"):
        traj.to_evo()


@pytest.mark.parametrize(
    ("command", "evo_flags", "our_flags", "kind", "key"),
    [
        ("evo_ape", ["-as"], ["--align", "sim3"], "ape", "trans_m"),
        ("evo_ape", ["-r", "full", "--align_origin"], ["--align", "origin"], "ape", "full"),
        (
            "evo_rpe",
            ["-a", "-r", "angle_deg", "--delta", "0.5", "--delta_unit", "m"],
            ["--align", "se3", "--delta", "0.5", "--delta-unit", "m"],
            "rpe",
            "rot_deg",
        ),
    ],
)
def test_the_evo_commands_themselves_agree(
    files, capsys, tmp_path, command, evo_flags, our_flags, kind, key
):
    import subprocess
    import zipfile
    from pathlib import Path

    est, gt = files
    exe = Path(sys.executable).parent / command
    results = tmp_path / "results.zip"
    env = {**os.environ, "HOME": str(tmp_path)}  # evo keeps its settings under ~/.evo
    subprocess.run(
        [
            str(exe),
            "tum",
            str(gt),
            str(est),
            *evo_flags,
            "--t_offset",
            str(GT_OFFSET),
            "--save_results",
            str(results),
            "--no_warnings",
        ],
        check=True,
        capture_output=True,
        env=env,
        timeout=120,
    )
    with zipfile.ZipFile(results) as z:
        theirs = json.loads(z.read("stats.json"))
    ours = evaluate_json(capsys, est, gt, *our_flags, "--t-offset", str(GT_OFFSET))
    assert_stats(ours[kind][key], theirs)
