"""experiments/compare.py and experiments/sweep.py end to end on tiny configurations,
and the library pieces they stand on (hvo_graph.montecarlo, hvo_graph.report)."""

from __future__ import annotations

import contextlib
import csv
import io
import math
import re
from pathlib import Path

import numpy as np
import pytest
from script_helpers import load_script, png_size

from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_LABELS, METHOD_TITLES
from hvo_graph.eval.bounds import BOUND, BOUND_TITLE, posterior_bound
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.montecarlo import run_seed, run_seeds
from hvo_graph.pipeline import estimate
from hvo_graph.report.plotting import FIGURE_DPI, METHOD_STYLE
from hvo_graph.report.progress import ProgressBar
from hvo_graph.report.tables import markdown_table
from hvo_graph.sim.scenario import paper_scenario, simulate

TINY = ["--seeds", "2", "--duration", "1.5", "--workers", "1", "--no-progress"]
T_975_DF1 = 12.706  # textbook t_{0.975, 1}: the CI of a mean of two seeds


compare = load_script("compare")
sweep = load_script("sweep")


def assert_figure(base: Path, figsize: tuple[float, float]) -> None:
    png, svg = base.with_suffix(".png"), base.with_suffix(".svg")
    assert png_size(png) == (round(figsize[0] * FIGURE_DPI), round(figsize[1] * FIGURE_DPI))
    assert png.stat().st_size > 20_000  # drawn, not blank
    text = svg.read_text()
    assert text.lstrip().startswith("<?xml") and "</svg>" in text
    assert not list(base.parent.glob(".*tmp*")), "temporary files left behind"


def table_rows(markdown: str, heading: str) -> list[list[str]]:
    """Cells of the table under ``heading`` (header row excluded)."""
    block = markdown.split(heading, 1)[1].split("###", 1)[0]
    lines = [ln for ln in block.splitlines() if ln.startswith("|")]
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]


def estimate_smoother(scenario):
    """The default smoother run on a scenario, as the experiments run it."""
    from hvo_graph.estimators.smoother import FactorGraphSmoother
    from hvo_graph.pipeline import measure

    smoother = FactorGraphSmoother()
    smoother.run(measure(scenario.observations, scenario, method="smoother"))
    return smoother


def mean_and_half(values: list[float]) -> tuple[float, float]:
    """Hand computation for two seeds: mean and t_{0.975,1} s / sqrt(2)."""
    a, b = values
    s = abs(a - b) / math.sqrt(2.0)  # sample std of two values
    return (a + b) / 2.0, T_975_DF1 * s / math.sqrt(2.0)


@pytest.fixture(scope="module")
def compare_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert compare.main([*TINY, "--out-dir", str(out)]) == 0
    return out, stdout.getvalue()


def test_compare_writes_tables_csv_and_figures(compare_run) -> None:
    out, stdout = compare_run
    page = (out / "results.md").read_text()
    assert "- Command: `python experiments/compare.py --seeds 2 --duration 1.5" in page
    assert "- Seeds: 0-1 (2 seeds)" in page
    rmse_rows = table_rows(page, "### RMSE: mean over 2 seeds")
    assert [r[0] for r in rmse_rows] == [
        *(f"{METHOD_TITLES[m]} (`{m}`)" for m in METHOD_LABELS),
        BOUND_TITLE,
    ]
    assert rmse_rows[-1][3:] == ["-", "-"]  # the bound is of the pose alone
    ratio_rows = table_rows(page, "### RMSE ratios")
    assert [r[0] for r in ratio_rows] == [
        f"{METHOD_TITLES[a]} / {METHOD_TITLES[b]}" for a, b in compare.RATIOS
    ]
    assert "target" not in page.lower() and "issue" not in page.lower()  # no internal plans
    # the tables printed are the ones written
    assert stdout.split("### RMSE: mean", 1)[1] in page

    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * (len(METHOD_LABELS) + 1)
    assert [(int(r["seed"]), r["method"]) for r in rows] == [
        (s, m) for s in (0, 1) for m in (*METHOD_LABELS, BOUND)
    ]
    by = {(int(r["seed"]), r["method"]): r for r in rows}
    # 1.5 s at 30 fps = 46 frames; errors over t >= 1 s: frames 30..45
    assert {int(r["frames"]) for r in rows} == {16}

    # The Markdown cells are the mean and CI of the CSV's per-seed values (hand computation).
    for i, m in enumerate(METHOD_LABELS):
        cell = rmse_rows[i][1]  # position [m]
        mean_text, half_text = cell.split(" ± ")
        want_mean, want_half = mean_and_half([float(by[(s, m)]["position_rmse_m"]) for s in (0, 1)])
        # both printed to the same decimal place: off by at most half its unit
        unit = 10.0 ** -len(mean_text.split(".")[1])
        assert abs(float(mean_text) - want_mean) <= 0.5 * unit * (1 + 1e-9)
        assert abs(float(half_text) - want_half) <= 0.5 * unit + 5e-4 * want_half
    # the smoothed / paper-Kalman ratio is the mean of the per-seed ratios
    cell = ratio_rows[0][4]  # angular velocity
    ratios = [
        float(by[(s, "smoother")]["angular_velocity_rmse_radps"])
        / float(by[(s, "kalman")]["angular_velocity_rmse_radps"])
        for s in (0, 1)
    ]
    shown = cell.split(" ± ")[0]
    assert abs(float(shown) - np.mean(ratios)) <= 0.5 * 10.0 ** -len(shown.split(".")[1])
    # each seed's bound is the posterior bound computed here, with the process noise the
    # smoother chose on that seed, over the same frames
    for s in (0, 1):
        scenario = simulate(paper_scenario(seed=s, duration=1.5))
        smoother = estimate_smoother(scenario)
        bound = posterior_bound(scenario, smoother.acceleration_sigma)
        keep = bound.t >= 1.0
        want = np.sqrt(np.mean(bound.position[keep] ** 2))
        assert float(by[(s, BOUND)]["position_rmse_m"]) == pytest.approx(want, rel=1e-9)
    bound_rows = table_rows(page, "### RMSE / posterior")
    assert [r[0] for r in bound_rows] == [f"{METHOD_TITLES[m]} (`{m}`)" for m in METHOD_LABELS]
    shown = bound_rows[METHOD_LABELS.index("smoother")][1].split(" ± ")[0]
    ratios = [
        float(by[(s, "smoother")]["position_rmse_m"]) / float(by[(s, BOUND)]["position_rmse_m"])
        for s in (0, 1)
    ]
    assert abs(float(shown) - np.mean(ratios)) <= 0.5 * 10.0 ** -len(shown.split(".")[1])

    assert_figure(out / "figures" / "compare_error_over_time", compare.ERROR_FIGSIZE)
    assert_figure(out / "figures" / "compare_error_distribution", compare.DISTRIBUTION_FIGSIZE)


def test_compare_csv_matches_the_pipeline_run_directly(compare_run) -> None:
    """Seed 1 through hvo_graph.pipeline.estimate gives the numbers of the CSV."""
    out, _ = compare_run
    with open(out / "results.csv", newline="") as f:
        by = {(int(r["seed"]), r["method"]): r for r in csv.DictReader(f)}
    scenario = simulate(paper_scenario(seed=1, duration=1.5))
    for method, online in (
        ("measurements", False),
        ("kalman", False),
        ("smoother", True),
        ("ippe", False),
    ):
        label = "smoother-online" if online else method
        # seed 1 also seeds the Kalman filter's random initial state
        seeded = {"seed": 1} if method == "kalman" else {}
        options = {"online": True} if online else {}
        trajectory = estimate(scenario.observations, scenario, method, **seeded, **options)
        s = summarize(error_series(trajectory, scenario.groundtruth), t_start=1.0)
        assert float(by[(1, label)]["position_rmse_m"]) == pytest.approx(s.position_rmse, rel=1e-9)
        assert float(by[(1, label)]["angular_velocity_max_radps"]) == pytest.approx(
            s.angular_velocity_max, rel=1e-9
        )


def test_compare_is_deterministic(compare_run, tmp_path, capsys) -> None:
    out, stdout = compare_run
    assert compare.main([*TINY, "--out-dir", str(tmp_path), "--no-figures"]) == 0
    again = capsys.readouterr().out
    assert again.split("### RMSE: mean", 1)[1] == stdout.split("### RMSE: mean", 1)[1]
    assert (tmp_path / "results.csv").read_bytes() == (out / "results.csv").read_bytes()


def test_compare_rejects_bad_options(capsys) -> None:
    with pytest.raises(SystemExit) as info:
        compare.main(["--methods", "smoother,telepathy"])
    assert info.value.code == 2
    assert "unknown method 'telepathy'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        compare.main([*TINY, "--skip", "2", "--out-dir", "unused"])
    assert info.value.code == 2
    assert "--skip: 2 s leaves nothing of a 1.5 s sequence" in capsys.readouterr().err


def test_sweep_writes_csv_tables_and_figures(tmp_path, monkeypatch, capsys) -> None:
    small = {
        "noise": sweep.Sweep("noise", "pixel noise sigma [px]", (0.0, 0.5), log_x=True),
        "fps": sweep.Sweep("fps", "frame rate [frames/s]", (15.0, 30.0), log_x=True),
        "points": sweep.Sweep("points", "number of plane points", (4, 8), log_x=True),
    }
    monkeypatch.setattr(sweep, "SWEEPS", small)
    assert sweep.main([*TINY, "--out-dir", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    with open(tmp_path / "sweep.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    methods = [*sweep.DEFAULT_METHODS, BOUND]
    assert [(r["sweep"], float(r["value"]), r["method"]) for r in rows] == [
        (name, float(v), m) for name, s in small.items() for v in s.values for m in methods
    ]
    assert {r["seeds"] for r in rows} == {"2"}
    # Noise-free input: the smoother and IPPE recover the pose; with 0.5 px they do not.
    noise = {(float(r["value"]), r["method"]): r for r in rows if r["sweep"] == "noise"}
    for m in ("smoother", "ippe"):
        assert float(noise[(0.0, m)]["position_rmse_m_mean"]) < 1e-4
        assert float(noise[(0.5, m)]["position_rmse_m_mean"]) > 1e-3
    # the bound grows with the pixel noise and has no velocity
    assert float(noise[(0.5, BOUND)]["position_rmse_m_mean"]) > 100 * float(
        noise[(0.0, BOUND)]["position_rmse_m_mean"]
    )
    assert noise[(0.5, BOUND)]["linear_velocity_rmse_mps_mean"] == ""
    # The fps sweep really changes the frame rate: the same seed at 30 fps equals compare's run.
    direct = run_seed(paper_scenario(seed=0, duration=1.5, fps=30.0), ["kalman"], keep_series=False)
    other = run_seed(paper_scenario(seed=1, duration=1.5, fps=30.0), ["kalman"], keep_series=False)
    fps30 = next(
        r for r in rows if r["sweep"] == "fps" and r["value"] == "30.0" and r["method"] == "kalman"
    )
    want = (direct.summaries["kalman"].position_rmse + other.summaries["kalman"].position_rmse) / 2
    assert float(fps30["position_rmse_m_mean"]) == pytest.approx(want, rel=1e-12)

    page = (tmp_path / "sweep.md").read_text()
    for s in small.values():
        rows_md = table_rows(page, f"against {s.title}")
        assert [r[0] for r in rows_md] == [f"{v:.3g}" for v in s.values]
        assert f"against {s.title}" in printed
        assert_figure(tmp_path / "figures" / f"sweep_{s.name}", sweep.FIGSIZE)


def test_run_seeds_in_processes_equals_in_process() -> None:
    configs = [paper_scenario(seed=s, duration=1.5) for s in (4, 5)]
    methods = ["kalman", "smoother", "smoother-online"]
    serial = run_seeds(configs, methods, workers=1, progress=False, keep_series=False)
    parallel = run_seeds(configs, methods, workers=2, progress=False, keep_series=False)
    assert [r.seed for r in parallel] == [4, 5]
    for a, b in zip(serial, parallel, strict=True):
        assert a.summaries == b.summaries
    # the online ISAM2 estimate is causal, hence (here) worse than the smoothed one
    assert all(
        r.summaries["smoother-online"].linear_velocity_rmse
        > r.summaries["smoother"].linear_velocity_rmse
        for r in serial
    )


def test_run_seed_rejects_bad_methods_and_skip() -> None:
    config = paper_scenario(duration=1.5)
    with pytest.raises(InputError, match=r"methods: unknown method 'kalmann'"):
        run_seed(config, ["kalmann"])
    with pytest.raises(InputError, match=r"methods: 'ippe' is listed twice"):
        run_seed(config, ["ippe", "ippe"])
    with pytest.raises(InputError, match=r"skip: 1.5 s leaves no frame of a 1.5 s sequence"):
        run_seed(config, ["ippe"], skip=1.5)


def test_progress_bar_counts_and_estimates_time() -> None:
    stream = io.StringIO()
    now = [100.0]
    bar = ProgressBar(4, label="seeds", stream=stream, width=8, clock=lambda: now[0])
    now[0] = 110.0
    bar.update()
    # one of four done in 10 s: 30 s to go
    assert stream.getvalue().splitlines()[-1] == (
        "seeds [##......] 1/4  25%  elapsed 0:10  ETA 0:30"
    )
    now[0] = 140.0
    bar.update(3)
    bar.close()
    assert stream.getvalue().splitlines()[-1] == (
        "seeds [########] 4/4 100%  elapsed 0:40  ETA 0:00"
    )


def test_markdown_table_and_method_styles() -> None:
    text = markdown_table(["a", "bb"], [["x", "1"], ["long", "22"]])
    assert text.splitlines() == [
        "| a    |  bb |",
        "|------|----:|",
        "| x    |   1 |",
        "| long |  22 |",
    ]
    with pytest.raises(InputError, match="every row needs one cell per header column"):
        markdown_table(["a", "b"], [["x"]])
    # one distinct colour-and-line-style per method, a legend text for each
    assert set(METHOD_STYLE) == {*METHOD_LABELS, BOUND}  # and the bound's row
    looks = {(s["color"], s["linestyle"]) for s in METHOD_STYLE.values()}
    assert len(looks) == len(METHOD_LABELS) + 1
    assert all(re.fullmatch(r"#[0-9A-F]{6}", str(s["color"])) for s in METHOD_STYLE.values())
