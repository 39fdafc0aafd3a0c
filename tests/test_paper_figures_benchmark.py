"""experiments/paper_figures.py and experiments/benchmark.py end to end on tiny configurations.

Independent references: the paper's figure numbering (Section IV: Figs. 3-6
noise-free, 7-10 noisy, each position, heading, linear velocity, angular
velocity), the PNG header for the pixel size (figure inches x 150 dpi), the
contract's Euler convention through hvo_graph.geometry.rotation.euler_to_rotation,
hand-computed means for the benchmark's per-frame statistics, and the
installed package versions from importlib.metadata.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from script_helpers import load_script, png_size

from hvo_graph.errors import InputError
from hvo_graph.geometry.rotation import euler_to_rotation
from hvo_graph.sim.scenario import paper_scenario, simulate

paper_figures = load_script("paper_figures")
benchmark = load_script("benchmark")
factor_graph_figure = load_script("factor_graph_figure")


# -- paper_figures.py --------------------------------------------------------------------------

PAPER_FIGURES = [
    "fig03_position_noise_free",
    "fig04_orientation_noise_free",
    "fig05_linear_velocity_noise_free",
    "fig06_angular_velocity_noise_free",
    "fig07_position_noisy",
    "fig08_orientation_noisy",
    "fig09_linear_velocity_noisy",
    "fig10_angular_velocity_noisy",
]


def test_paper_figures_end_to_end_writes_every_figure_at_its_size(tmp_path, capsys):
    out = tmp_path / "figures"
    assert paper_figures.main(["--out", str(out), "--duration", "2", "--seed", "3"]) == 0
    printed = capsys.readouterr().out.split()
    expected = {f"{name}.{ext}" for name in [*PAPER_FIGURES, "overview"] for ext in ("png", "svg")}
    assert {p.name for p in out.iterdir()} == expected  # no temporary files left behind
    assert sorted(Path(p).name for p in printed) == sorted(expected)
    import matplotlib.image

    for name in [*PAPER_FIGURES, "overview"]:
        png = out / f"{name}.png"
        # 9 x 7.5 in (overview 11 x 6.5 in) at 150 dpi
        assert png_size(png) == ((1650, 975) if name == "overview" else (1350, 1125))
        pixels = matplotlib.image.imread(png)
        assert pixels.shape[:2] == png_size(png)[::-1]
        assert pixels[..., :3].std() > 0.05, f"{name}.png looks blank"
        root = ET.parse(out / f"{name}.svg").getroot()
        assert root.tag.endswith("svg")
        assert len(root.findall(".//{http://www.w3.org/2000/svg}path")) > 50


def test_figure_numbers_follow_the_paper():
    names = [
        paper_figures.figure_name(q.key, run)
        for run in paper_figures.RUNS
        for q in paper_figures.QUANTITIES
    ]
    assert names == PAPER_FIGURES


def test_plotted_series_use_the_contract_euler_angles_and_mid_interval_velocities():
    result = paper_figures.run_case("noisy", seed=2, duration=1.0)
    truth = result.scenario.groundtruth
    t, angles = paper_figures.trajectory_series(truth, "orientation")
    assert np.array_equal(t, truth.t)
    for k in (0, 10, len(t) - 1):
        roll, pitch, yaw = np.radians(angles[k])
        np.testing.assert_allclose(
            euler_to_rotation(roll, pitch, yaw), truth.rotations[k], atol=1e-12
        )
    t_v, v = paper_figures.measurement_series(result.frames, "linear_velocity")
    np.testing.assert_allclose(t_v, 0.5 * (truth.t[1:] + truth.t[:-1]), atol=1e-12)
    np.testing.assert_array_equal(v[0], result.frames[1].velocity.twist[3:])
    t_p, p = paper_figures.measurement_series(result.frames, "position")
    np.testing.assert_array_equal(t_p, truth.t)
    # the smoother's estimates are close to the truth: the curves drawn are the right ones
    _, smoothed = paper_figures.trajectory_series(result.estimates["smoother"], "position")
    assert np.max(np.abs(smoothed - truth.positions)) < 0.05
    assert np.max(np.abs(p - truth.positions)) < 0.1


def test_paper_figures_bad_input():
    with pytest.raises(InputError, match="run: expected one of noise_free, noisy, got 'loud'"):
        paper_figures.run_case("loud")


def test_paper_figures_bad_duration_is_a_one_line_error(tmp_path, capsys):
    assert paper_figures.main(["--out", str(tmp_path), "--duration", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("paper_figures: error: ScenarioConfig.duration")


# -- benchmark.py ------------------------------------------------------------------------------


def table_rows(markdown: str) -> list[list[str]]:
    """Cells of the performance table (the one whose header starts with 'component')."""
    lines = markdown.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| component "))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows


def number(cell: str) -> float:
    return float(cell.replace(",", ""))


def test_benchmark_quick_writes_the_table_machine_and_profile(tmp_path, capsys):
    out = tmp_path / "performance.md"
    assert benchmark.main(["--quick", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    page = out.read_text()
    assert "| component " in printed and "Top 15 functions by self time" in printed
    rows = table_rows(page)
    titles = [
        "front end (H_d pose + H_c velocity)",
        "Kalman filter (paper)",
        "smoother: ISAM2",
        "smoother: fixed-lag (1 s)",
        "smoother: batch LM",
        "tight (pixels on plane landmarks): ISAM2",
    ]
    assert [(r[0], r[1]) for r in rows] == [(t, n) for n in ("300", "1,000") for t in titles]
    for r in rows:
        frames, total, cpu, fps, first, last, ratio = map(number, r[1:8])
        assert total > 0 and cpu > 0 and first > 0 and last > 0
        assert fps == pytest.approx(frames / total, rel=0.01, abs=1.0)  # 3 digits of total
        # first / last are printed to 0.001 ms and the ratio to 0.01: it must lie within
        # what those roundings allow (a Kalman update takes ~0.02 ms, so 2 % and more)
        low, high = (last - 5e-4) / (first + 5e-4), (last + 5e-4) / max(first - 5e-4, 1e-9)
        assert low - 0.005 <= ratio <= high + 0.005
        assert number(r[9]) >= 0  # resident-set growth, MiB
        assert (r[8] == "-") == (r[0] == titles[0])  # only estimators have trajectory()
    isam2 = {r[1]: r for r in rows if r[0] == "smoother: ISAM2"}
    assert number(isam2["1,000"][9]) > 0  # 1,000 frames of GTSAM variables take memory
    assert "python experiments/benchmark.py --quick --out" in page
    assert f"gtsam {importlib.metadata.version('gtsam')}" in page
    assert f"numpy {np.__version__}" in page
    assert re.search(r"CPU: .+, \d+ logical cores", page)
    assert "## Where the time goes (smoother: ISAM2)" in page
    assert "cProfile of smoother: ISAM2 on 300 frames" in page
    assert "update" in page.split("## Where the time goes")[1]
    assert not list(tmp_path.glob(".*tmp*"))
    # Each stage beside its reference, and hvo-graph estimate end to end (300 frames).
    pairs = section_rows(page, "## Each stage beside its reference")
    assert [r[0] for r in pairs] == [
        "front end, 4 points",
        "front end, 20 points",
        "Kalman filter (paper)",
        "smoother: fixed-lag (1 s), updates",
    ]
    for r in pairs:
        assert number(r[1]) == 300 and number(r[2]) > 0 and number(r[4]) > 0
        assert number(r[5]) == pytest.approx(number(r[4]) / number(r[2]), rel=0.1, abs=0.06)
    cli = section_rows(page, "## End to end")
    # Every method on 300 frames, then the two smoothers' memory on a longer sequence.
    runs = [(m, 300) for m in ("smoother", "fixed-lag", "kalman")]
    runs += [(m, 1000) for m in ("smoother", "fixed-lag")]
    assert [r[0] for r in cli] == [f"`hvo-graph estimate --method {m}`" for m, _ in runs]
    for r, (_, frames) in zip(cli, runs, strict=True):  # a failed run: "failed (exit code)"
        assert number(r[1]) == frames and number(r[2]) > 0 and number(r[5]) > 0
    # The images path on 60 rendered frames, beside the bare OpenCV loop.
    images = section_rows(page, "## Images, 640 x 480")
    assert [r[0] for r in images] == [
        "bare OpenCV loop (decode, detect, KLT)",
        "tracking (`tracks_from_images`)",
        "`hvo-graph estimate --images --method measurements`",
        "`hvo-graph estimate --images --method smoother`",
    ]
    bare = number(images[0][2])
    for r in images:
        assert number(r[1]) == 60 and number(r[2]) > 0
        assert number(r[4]) == pytest.approx(60 / number(r[2]), rel=0.05, abs=1.0)
        assert number(r[5]) == pytest.approx(number(r[2]) / bare, rel=0.05, abs=0.01)


def section_rows(markdown: str, heading: str) -> list[list[str]]:
    """Cells of the first table after ``heading``."""
    lines = markdown.split(heading, 1)[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows


def test_benchmark_skips_batch_above_its_limit_and_says_so(tmp_path):
    out = tmp_path / "perf.md"
    argv = ["--sizes", "300", "200", "--components", "batch", "kalman", "--batch-max-frames"]
    argv += ["250", "--no-memory", "--profile-frames", "0", "--out", str(out)]
    argv += ["--reference-frames", "0", "--cli-frames", "0", "--chain-poses", "0"]
    argv += ["--image-frames", "0"]
    assert benchmark.main(argv) == 0
    page = out.read_text()
    rows = table_rows(page)
    assert [(r[0], r[1], r[2] == "skipped") for r in rows] == [
        ("Kalman filter (paper)", "200", False),
        ("smoother: batch LM", "200", False),
        ("Kalman filter (paper)", "300", False),
        ("smoother: batch LM", "300", True),
    ]
    assert all(r[9] == "-" for r in rows)  # --no-memory
    assert "skipped above 250 frames" in page
    assert "Where the time goes" not in page


def test_benchmark_rejects_sequences_too_short_for_the_first_and_last_100(tmp_path, capsys):
    assert benchmark.main(["--sizes", "150", "--out", str(tmp_path / "p.md")]) == 2
    assert capsys.readouterr().err.strip() == (
        "benchmark: error: --sizes: expected lengths >= 200 frames (first and last 100 are "
        "compared), got 150"
    )
    assert not (tmp_path / "p.md").exists()


def test_timing_statistics_by_hand():
    per_frame = np.concatenate([np.full(100, 0.001), np.full(50, 0.005), np.full(100, 0.003)])
    t = benchmark.Timing("isam2", 250, per_frame, finish=0.15)
    assert t.total == pytest.approx(0.1 + 0.25 + 0.3 + 0.15)
    assert t.fps == pytest.approx(250 / 0.8)
    assert t.first_ms == pytest.approx(1.0)
    assert t.last_ms == pytest.approx(3.0)
    assert t.growth == pytest.approx(3.0)


def test_simulated_lengths_are_exact():
    for n in (200, 1234):
        assert len(benchmark.simulate_frames(n).observations) == n
    # the same scenario as the paper's noisy run, only longer
    short = simulate(paper_scenario(noisy=True, seed=0, duration=199 / 30))
    np.testing.assert_array_equal(
        benchmark.simulate_frames(200).observations[-1].uv, short.observations[-1].uv
    )


# -- factor_graph_figure.py ---------------------------------------------------------------------


def test_factor_graph_figure_draws_every_factor_kind(tmp_path, capsys):
    assert factor_graph_figure.main(["--out", str(tmp_path)]) == 0
    png, svg = tmp_path / "factor_graph.png", tmp_path / "factor_graph.svg"
    assert png_size(png) == (1500, 960)  # 10 x 6.4 in at 150 dpi
    text = svg.read_text()
    ET.fromstring(text)
    for label, _ in factor_graph_figure.FACTORS.values():
        assert label.split(" (")[0].split(":")[0] in text
    for name in ("X(0)", "X(4)", "V(0)", "V(4)"):
        assert name in text
    # the tightly coupled graph: its own factor kinds, a landmark per track, no H_d / H_c
    png, svg = tmp_path / "factor_graph_tight.png", tmp_path / "factor_graph_tight.svg"
    assert png_size(png) == (1500, 960)
    text = svg.read_text()
    ET.fromstring(text)
    for label, _ in factor_graph_figure.TIGHT_FACTORS.values():
        assert label.split(" (")[0].split(":")[0] in text
    for j in range(len(factor_graph_figure.TIGHT_TRACKS)):
        assert f"L({j})" in text
    assert "H_d" not in text and "H_c" not in text
