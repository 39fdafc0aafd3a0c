"""Monte Carlo comparison of every estimator on the paper's (noisy) scenario.

Each seed simulates the scenario once (pixel noise, and the Kalman filters'
random initial state, drawn from the seed), measures it once per front end and
runs every method on the same measurements (hvo_graph.montecarlo.run_seed).
RMSE and max of position (m), orientation (deg), linear velocity (m/s) and
angular velocity (rad/s) are computed after the first ``--skip`` seconds; the
tables give their mean over seeds with a Student-t 95 % confidence interval,
and the mean over seeds of per-seed RMSE ratios (paired: both methods saw the
same data). Same seeds, same tables.

Writes ``<out-dir>/results.md`` (tables, seeds, the command), ``<out-dir>/results.csv``
(one row per seed and method) and ``<out-dir>/figures/compare_error_over_time``
and ``compare_error_distribution`` (.png and .svg); prints the tables.

Usage::

    python experiments/compare.py                 # 50 seeds, paper noisy scenario -> out/compare/
    python experiments/compare.py --out-dir docs  # what `make figures` runs: the docs' tables
    python experiments/compare.py --seeds 20 --workers 2
    python experiments/compare.py --quick         # 5 seeds of 4 s -> out/compare-quick/
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hvo_graph.arguments import add_monte_carlo_options, finite_float, int_at_least, names
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_LABELS, METHOD_TITLES
from hvo_graph.eval.bounds import BOUND, BOUND_TITLE
from hvo_graph.eval.metrics import QUANTITIES
from hvo_graph.montecarlo import (
    SeedResult,
    mean_error_over_time,
    method_statistics,
    metric_values,
    ratio_statistics,
    run_seeds,
)
from hvo_graph.report.tables import (
    csv_text,
    describe_seeds,
    format_ci,
    format_value,
    markdown_table,
    software_versions,
    summary_columns,
    summary_row,
    write_text_atomic,
)
from hvo_graph.sim.scenario import PAPER_NOISE_VAR, ScenarioConfig, paper_scenario

DEFAULT_SEEDS = 50
#: The repository (outputs go under it, wherever the script is run from).
ROOT = Path(__file__).resolve().parents[1]
#: Outputs default to out/compare/: the repository's docs/ is written only when asked
#: (``--out-dir docs``, as ``make figures`` does).
DEFAULT_OUT_DIR = ROOT / "out" / "compare"
#: ``--quick``: what ``make demo`` runs (seconds, not minutes).
QUICK_SEEDS = 5
QUICK_DURATION = 4.0
QUICK_OUT_DIR = ROOT / "out" / "compare-quick"

#: RMSE ratios reported, (numerator, denominator): < 1 means the numerator is better.
RATIOS: tuple[tuple[str, str], ...] = (
    ("smoother", "kalman"),
    ("smoother", "measurements"),
    ("smoother", "ippe"),
    ("smoother", "kalman-measured"),
    ("smoother-online", "kalman"),
    ("tight", "smoother"),
)

ERROR_FIGSIZE = (11.0, 7.5)  # inches; PNG 1650 x 1125 px at 150 dpi
DISTRIBUTION_FIGSIZE = (11.0, 8.0)  # PNG 1650 x 1200 px

METHOD_NOTES: dict[str, str] = {
    "measurements": "the front end's per-frame pose (discrete homography H_d) and twist "
    "(continuous homography H_c), no fusion",
    "kalman": "the paper's 12-state Kalman filter with the paper's noisy-run R_k "
    "(docs/kalman.md), random initial state from the seed",
    "kalman-measured": "the same filter given the smoother's information: R_k = diagonal of "
    "the front end's covariances, process noise equal to the smoother's white-noise "
    "acceleration, body velocity rotated into the world frame",
    "smoother": "GTSAM factor graph solved by ISAM2, final (smoothed) trajectory",
    "smoother-online": "the same ISAM2 run, each frame's estimate right after its own update "
    "(causal)",
    "batch": "the same factor graph, Levenberg-Marquardt over the whole sequence",
    "fixed-lag": "the same factor graph, GTSAM incremental fixed-lag smoother (1 s window)",
    "tight": "tightly coupled GTSAM graph: one projection factor per pixel on plane landmarks, "
    "the smoother's motion model, ISAM2 online then the batch optimum (final trajectory)",
    "tight-online": "the same tight ISAM2 run, each frame's estimate right after its own update",
    "tight-batch": "the same tight graph, Levenberg-Marquardt over the whole sequence",
    "tight-fixed-lag": "the same tight graph, GTSAM incremental fixed-lag smoother (1 s window)",
    "ippe": "per-frame OpenCV solvePnP (SOLVEPNP_IPPE) on the plane points, twist from "
    "differencing consecutive poses",
}


def _seed_list(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers >= 0, got {text!r}"
        ) from None
    if not seeds or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers >= 0, got {text!r}")
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"seed listed twice in {text!r}")
    return seeds


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="compare.py",
        description="Monte Carlo comparison of the estimators (RMSE, max, 95 % CI over seeds).",
    )
    seeds = parser.add_mutually_exclusive_group()
    seeds.add_argument(
        "--seeds", type=int_at_least(1), help=f"use seeds 0..N-1 (default {DEFAULT_SEEDS})"
    )
    seeds.add_argument("--seed-list", type=_seed_list, help="explicit seeds, e.g. 3,5,8")
    parser.add_argument(
        "--noise-var",
        type=finite_float(0.0, strict=False),
        default=PAPER_NOISE_VAR,
        help=f"pixel noise variance, px^2 (default {PAPER_NOISE_VAR}, the paper's noisy run)",
    )
    parser.add_argument(
        "--duration", type=finite_float(0.0, strict=True), help="seconds (default 10)"
    )
    parser.add_argument(
        "--fps", type=finite_float(0.0, strict=True), default=30.0, help="frames per second"
    )
    parser.add_argument("--num-points", type=int_at_least(4), default=4, help="plane points (>= 4)")
    parser.add_argument(
        "--methods",
        type=names(METHOD_LABELS, "method"),
        default=list(METHOD_LABELS),
        help=f"comma-separated subset of {','.join(METHOD_LABELS)}",
    )
    add_monte_carlo_options(
        parser,
        quick_help=f"short demo: {QUICK_SEEDS} seeds of {QUICK_DURATION:g} s unless given",
        quick_out="out/compare-quick/",
        default_out="out/compare/; make figures passes --out-dir docs",
    )
    return parser


def build_configs(args: argparse.Namespace) -> list[ScenarioConfig]:
    """One ScenarioConfig per seed (raises InputError for a bad scenario)."""
    return [
        paper_scenario(
            noise_var=args.noise_var,
            duration=args.duration,
            fps=args.fps,
            num_points=args.num_points,
            seed=seed,
        )
        for seed in args.seed_values
    ]


def _pretty_number(x: float) -> str:
    return f"{x:g}"


def scenario_text(config: ScenarioConfig, skip: float) -> str:
    """One sentence naming the scenario's settings."""
    paper = (
        "the paper's noisy scenario"
        if config.noise_var == PAPER_NOISE_VAR
        else "the paper's scenario"
    )
    return (
        f"{paper} (hvo_graph.simulation.paper_scenario): pixel noise variance "
        f"{_pretty_number(config.noise_var)} px^2 (sigma {config.pixel_sigma:.4g} px), "
        f"{_pretty_number(config.fps)} fps, {_pretty_number(config.duration)} s "
        f"({config.num_frames} frames), {config.num_points} plane points; errors over "
        f"t >= {_pretty_number(skip)} s"
    )


def _titled(label: str) -> str:
    return BOUND_TITLE if label == BOUND else f"{METHOD_TITLES[label]} (`{label}`)"


def _rows(results: Sequence[SeedResult], methods: Sequence[str]) -> list[str]:
    """The methods' rows, then the bound's where the results have it."""
    return [*methods, BOUND] if results and BOUND in results[0].summaries else list(methods)


def bound_table(results: Sequence[SeedResult], methods: Sequence[str]) -> str:
    """Markdown: each method's pose RMSE over the posterior bound's (per seed, then mean)."""
    rows = []
    for m in methods:
        stats = ratio_statistics(results, m, BOUND)
        rows.append([_titled(m), format_ci(stats["position"]), format_ci(stats["orientation"])])
    return markdown_table(["method", "position / bound", "orientation / bound"], rows)


def tables_markdown(results: Sequence[SeedResult], methods: Sequence[str]) -> str:
    """The result tables (Markdown): RMSE with CI, mean max, RMSE ratios and their bounds."""
    header = ["method"] + [f"{title} [{unit}]" for _, title, unit in QUANTITIES]
    rmse_rows, max_rows = [], []
    for m in _rows(results, methods):
        rmse = method_statistics(results, m, "rmse")
        peak = method_statistics(results, m, "max")
        rmse_rows.append([_titled(m)] + [format_ci(rmse[q]) for q, _, _ in QUANTITIES])
        max_rows.append(
            [_titled(m)]
            + [format_value(None if peak[q] is None else peak[q].mean) for q, _, _ in QUANTITIES]
        )
    n = len(results)
    parts = [
        f"### RMSE: mean over {n} seeds ± 95 % confidence half-width",
        "",
        markdown_table(header, rmse_rows),
        "",
        f"### Max error: mean over {n} seeds of each seed's largest error",
        "",
        markdown_table(header, max_rows),
    ]
    ratios = [(a, b) for a, b in RATIOS if a in methods and b in methods]
    if ratios:
        ratio_rows = []
        stats = {pair: ratio_statistics(results, *pair) for pair in ratios}
        for a, b in ratios:
            ratio_rows.append(
                [f"{METHOD_TITLES[a]} / {METHOD_TITLES[b]}"]
                + [format_ci(stats[(a, b)][q]) for q, _, _ in QUANTITIES]
            )
        parts += [
            "",
            "### RMSE ratios: mean over seeds of the per-seed ratio ± 95 % confidence half-width",
            "",
            "Each seed's RMSE of the first method divided by the second's on the same data, then "
            "averaged (the mean of per-seed ratios, not the ratio of mean RMSEs); below 1 the "
            "first method is more accurate.",
            "",
            markdown_table(["ratio"] + [title for _, title, _ in QUANTITIES], ratio_rows),
        ]
    if _rows(results, methods)[-1] == BOUND:
        parts += [
            "",
            f"### RMSE / {BOUND_TITLE} of the pose: mean over seeds of the per-seed ratio",
            "",
            "The bound: no estimator that knows the motion model (the white-noise acceleration "
            "the smoother fits on each seed's H_d poses) can have a smaller pose error "
            "covariance, given every pixel of the sequence (hvo_graph.eval.bounds). On "
            "average over seeds no method can be below 1 (one seed can).",
            "",
            bound_table(results, methods),
        ]
    return "\n".join(parts) + "\n"


def results_markdown(
    results: Sequence[SeedResult],
    methods: Sequence[str],
    *,
    command: str,
    skip: float,
    figures: Sequence[str] = (),
) -> str:
    """The whole ``results.md`` page."""
    config = results[0].config
    seeds = [r.seed for r in results]
    lines = [
        "# Results: Monte Carlo comparison of the estimators",
        "",
        "Generated by `experiments/compare.py`; do not edit by hand (`make figures` "
        "regenerates it, and the same seeds give the same numbers).",
        "",
        f"- Command: `{command}`",
        f"- Scenario: {scenario_text(config, skip)}.",
        f"- Seeds: {describe_seeds(seeds)} ({len(seeds)} seeds); each seed draws the pixel noise "
        "and the Kalman filters' random initial state. Per-seed numbers: `results.csv`.",
        f"- Software: {software_versions()}.",
        "- Errors: position ||p - p_gt|| (m), orientation angle of R_gt^T R (deg), body linear "
        "velocity ||v - v_gt|| (m/s), body angular velocity ||w - w_gt|| (rad/s); RMSE and max "
        "over the frames of each seed, then the mean over seeds with a Student-t 95 % "
        "confidence interval.",
        "",
        tables_markdown(results, methods).rstrip("\n"),
        "",
        "### Methods",
        "",
    ]
    lines += [f"- {_titled(m)}: {METHOD_NOTES[m]}." for m in methods]
    if figures:
        lines += ["", "### Figures", ""]
        lines += [f"![{Path(f).stem.replace('_', ' ')}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def results_csv(results: Sequence[SeedResult], methods: Sequence[str]) -> str:
    """One row per (seed, method): every RMSE and max, and the frames evaluated."""
    rows = [
        [r.seed, m, *summary_row(r.summaries[m])] for r in results for m in _rows(results, methods)
    ]
    return csv_text(["seed", "method", *summary_columns()], rows)


def plot_error_over_time(
    results: Sequence[SeedResult], methods: Sequence[str], path: Path, *, skip: float
) -> list[Path]:
    """Four panels: mean over seeds of each method's per-frame error against time (log y)."""
    from hvo_graph.report.plotting import (
        figure_style,
        log_axis,
        method_style,
        new_figure,
        save_figure,
    )

    with figure_style():
        fig, axes = new_figure(*ERROR_FIGSIZE, nrows=2, ncols=2, sharex=True)
        curves = {m: mean_error_over_time(results, m) for m in methods}
        for ax, (q, title, unit) in zip(axes.flat, QUANTITIES, strict=True):
            evaluated, everything = [], []
            for m in methods:
                t, y = curves[m][0], curves[m][1][q]
                ok = np.isfinite(y) & (y > 0)
                ax.plot(t[ok], y[ok], **method_style(m))
                everything.append(y[ok])
                evaluated.append(y[ok & (t >= t[0] + skip - 1e-9)])
            ax.axvspan(t[0], t[0] + skip, color="#000000", alpha=0.06, linewidth=0)
            log_axis(ax)
            # The first frames are exact by construction (the world frame is the first
            # camera frame): the lower limit comes from the evaluated frames only.
            low, high = np.concatenate(evaluated), np.concatenate(everything)
            if low.size:
                ax.set_ylim(0.5 * low.min(), 1.5 * high.max())
            ax.set_title(f"{title} error")
            ax.set_ylabel(f"{title} error [{unit}]")
        for ax in axes[1]:
            ax.set_xlabel("time [s]")
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=4)
        config = results[0].config
        fig.suptitle(
            f"Error over time, mean of {len(results)} seeds (sigma {config.pixel_sigma:.3g} px, "
            f"{config.fps:g} fps, {config.num_points} points); shaded: the first {skip:g} s, "
            "left out of the statistics"
        )
        return save_figure(fig, path)


def plot_error_distribution(
    results: Sequence[SeedResult], methods: Sequence[str], path: Path
) -> list[Path]:
    """Four panels: box plots of the per-seed RMSE of each method (log y)."""
    from hvo_graph.report.plotting import (
        figure_style,
        log_axis,
        method_style,
        new_figure,
        save_figure,
    )

    with figure_style():
        fig, axes = new_figure(*DISTRIBUTION_FIGSIZE, nrows=2, ncols=2, sharex=True)
        positions = np.arange(1, len(methods) + 1)
        for ax, (q, title, unit) in zip(axes.flat, QUANTITIES, strict=True):
            data = []
            for m in methods:
                v = metric_values(results, m, q)
                data.append(v[np.isfinite(v)])
            boxes = ax.boxplot(
                data,
                positions=positions,
                widths=0.6,
                patch_artist=True,
                showfliers=True,
                medianprops={"color": "#000000"},
                flierprops={"markersize": 3},
            )
            for patch, m in zip(boxes["boxes"], methods, strict=True):
                patch.set_facecolor(str(method_style(m)["color"]))
                patch.set_alpha(0.7)
            values = np.concatenate(data)
            positive = values[values > 0]
            if positive.size and positive.max() > 20.0 * positive.min():
                log_axis(ax)  # methods an order of magnitude apart
            ax.set_title(f"{title} RMSE per seed")
            ax.set_ylabel(f"{title} RMSE [{unit}]")
            ax.grid(axis="x", visible=False)
        for ax in axes[1]:
            ax.set_xticks(positions)
            ax.set_xticklabels(
                [str(method_style(m)["label"]) for m in methods], rotation=30, ha="right"
            )
        config = results[0].config
        fig.suptitle(
            f"Per-seed RMSE after the first {results[0].skip:g} s, {len(results)} seeds "
            f"(sigma {config.pixel_sigma:.3g} px, {config.fps:g} fps); boxes: quartiles, "
            "whiskers: 1.5 IQR"
        )
        return save_figure(fig, path)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the comparison; returns the exit code (argparse exits 2 on bad options)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.seed_list is not None:
        args.seed_values = args.seed_list
    else:
        count = args.seeds or (QUICK_SEEDS if args.quick else DEFAULT_SEEDS)
        args.seed_values = list(range(count))
    if args.duration is None:
        args.duration = QUICK_DURATION if args.quick else 10.0
    out_dir = args.out_dir or (QUICK_OUT_DIR if args.quick else DEFAULT_OUT_DIR)
    try:
        configs = build_configs(args)
        if args.skip >= args.duration:
            raise InputError(
                f"--skip: {args.skip:g} s leaves nothing of a {args.duration:g} s sequence"
            )
        results = run_seeds(
            configs,
            args.methods,
            skip=args.skip,
            keep_series=not args.no_figures,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=not args.no_progress,
            bound=True,
        )
    except InputError as exc:
        parser.error(str(exc))
    figures: list[str] = []
    if not args.no_figures:
        fig_dir = out_dir / "figures"
        plot_error_over_time(
            results, args.methods, fig_dir / "compare_error_over_time", skip=args.skip
        )
        plot_error_distribution(results, args.methods, fig_dir / "compare_error_distribution")
        figures = ["figures/compare_error_over_time.png", "figures/compare_error_distribution.png"]
    command = shlex.join(["python", "experiments/compare.py", *argv])
    write_text_atomic(
        out_dir / "results.md",
        results_markdown(results, args.methods, command=command, skip=args.skip, figures=figures),
    )
    write_text_atomic(out_dir / "results.csv", results_csv(results, args.methods))
    print(scenario_text(results[0].config, args.skip))
    print(f"seeds {describe_seeds(args.seed_values)}; written to {out_dir}/results.md\n")
    print(tables_markdown(results, args.methods), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
