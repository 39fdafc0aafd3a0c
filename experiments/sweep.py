"""Accuracy against pixel noise, frame rate and number of points: smoother vs Kalman vs IPPE.

Three sweeps over the paper's scenario (hvo_graph.sim.scenario.paper_scenario),
each changing one setting and keeping the others at the paper's noisy values
(pixel noise variance 0.05 px^2, 30 fps, 4 points, 10 s):

- ``noise``: pixel noise standard deviation sigma from 0 to 2 px;
- ``fps``: frame rate from 10 to 120 frames per second;
- ``points``: number of plane points from 4 to 100.

At every value the same seeds run every method (hvo_graph.montecarlo.run_seed);
the figures show the mean over seeds of each RMSE (after the first ``--skip``
seconds) with its Student-t 95 % confidence band. The default methods are the
ISAM2 smoother (smoothed), the paper's Kalman filter (paper noisy-run R_k, also
at other noise levels, as a user of the paper would run it) and per-frame IPPE.

Writes ``<out-dir>/sweep.csv`` (one row per sweep, value and method),
``<out-dir>/sweep.md`` (the tables) and ``<out-dir>/figures/sweep_<name>.png|svg``;
prints the tables.

Usage::

    python experiments/sweep.py                      # 10 seeds per value -> out/sweep/
    python experiments/sweep.py --only noise --seeds 5 --workers 2
    python experiments/sweep.py --quick              # 2 seeds of 4 s -> out/sweep-quick/
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hvo_graph.arguments import add_monte_carlo_options, finite_float, int_at_least, names
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_LABELS, METHOD_TITLES
from hvo_graph.eval.bounds import BOUND, BOUND_TITLE
from hvo_graph.eval.metrics import QUANTITIES
from hvo_graph.eval.stats import MeanCI
from hvo_graph.montecarlo import SeedResult, method_statistics, run_seeds
from hvo_graph.report.tables import (
    csv_text,
    describe_seeds,
    format_value,
    markdown_table,
    write_text_atomic,
)
from hvo_graph.sim.scenario import PAPER_NOISE_VAR, ScenarioConfig, paper_scenario

DEFAULT_SEEDS = 10
DEFAULT_DURATION = 10.0
#: The repository (outputs go under it, wherever the script is run from).
ROOT = Path(__file__).resolve().parents[1]
#: Outputs default to out/sweep/: the repository's docs/ is written only when asked
#: (``--out-dir docs``, as ``make figures`` does).
DEFAULT_OUT_DIR = ROOT / "out" / "sweep"
DEFAULT_METHODS = ("smoother", "kalman", "ippe")
QUICK_SEEDS = 2
QUICK_DURATION = 4.0
QUICK_OUT_DIR = ROOT / "out" / "sweep-quick"
FIGSIZE = (11.0, 7.5)  # inches; PNG 1650 x 1125 px at 150 dpi


@dataclass(frozen=True)
class Sweep:
    """One swept setting.

    Attributes:
        name: ``--only`` name and file stem (``sweep_<name>``).
        title: axis label of the swept variable, with unit.
        values: the values, increasing.
        log_x: logarithmic x axis (a value 0 is then left out of the figure, not the tables).
    """

    name: str
    title: str
    values: tuple[float, ...]
    log_x: bool

    def config(self, value: float, *, seed: int, duration: float) -> ScenarioConfig:
        """The paper's noisy scenario with this setting at ``value``."""
        settings: dict[str, object] = {"seed": seed, "duration": duration}
        if self.name == "noise":
            settings["noise_var"] = float(value) ** 2
        elif self.name == "fps":
            settings["fps"] = float(value)
        elif self.name == "points":
            settings["num_points"] = int(value)
        else:
            raise InputError(f"sweep: unknown setting {self.name!r}")
        return paper_scenario(**settings)


SWEEPS: dict[str, Sweep] = {
    "noise": Sweep(
        "noise",
        "pixel noise sigma [px]",
        (0.0, 0.05, 0.1, math.sqrt(PAPER_NOISE_VAR), 0.5, 1.0, 2.0),
        log_x=True,
    ),
    "fps": Sweep("fps", "frame rate [frames/s]", (10.0, 15.0, 30.0, 60.0, 120.0), log_x=True),
    "points": Sweep("points", "number of plane points", (4, 6, 10, 20, 50, 100), log_x=True),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sweep.py",
        description="RMSE against pixel noise, frame rate and number of points.",
    )
    parser.add_argument(
        "--seeds", type=int_at_least(1), help=f"seeds 0..N-1 per value (default {DEFAULT_SEEDS})"
    )
    parser.add_argument(
        "--only",
        type=names(tuple(SWEEPS), "sweep"),
        default=list(SWEEPS),
        help=f"comma-separated subset of {','.join(SWEEPS)}",
    )
    parser.add_argument(
        "--methods",
        type=names(METHOD_LABELS, "method"),
        default=list(DEFAULT_METHODS),
        help=f"comma-separated subset of {','.join(METHOD_LABELS)} "
        f"(default {','.join(DEFAULT_METHODS)})",
    )
    parser.add_argument(
        "--duration",
        type=finite_float(0.0, strict=True),
        help=f"seconds (default {DEFAULT_DURATION:g})",
    )
    add_monte_carlo_options(
        parser,
        quick_help=f"short run: {QUICK_SEEDS} seeds of {QUICK_DURATION:g} s unless given",
        quick_out="out/sweep-quick/",
        default_out="out/sweep/; make figures passes --out-dir docs",
    )
    return parser


#: Results of one sweep: per value, per method, per quantity, the RMSE mean and CI.
SweepStats = dict[float, dict[str, dict[str, MeanCI | None]]]


def sweep_statistics(
    sweep: Sweep, results: Sequence[SeedResult], methods: Sequence[str], seeds: int
) -> SweepStats:
    """Group ``results`` (values in order, ``seeds`` consecutive runs per value)."""
    out: SweepStats = {}
    for i, value in enumerate(sweep.values):
        chunk = results[i * seeds : (i + 1) * seeds]
        out[value] = {m: method_statistics(chunk, m, "rmse") for m in methods}
    return out


def _value_text(value: float) -> str:
    return f"{value:.3g}"


#: Short quantity names for the wide sweep tables.
_SHORT = {
    "position": "pos",
    "orientation": "orient",
    "linear_velocity": "v",
    "angular_velocity": "w",
}


def sweep_table(sweep: Sweep, stats: SweepStats, methods: Sequence[str]) -> str:
    """Markdown table: one row per value, the mean RMSE of every method and quantity
    (a column none of whose values is known, e.g. the bound's velocities, is left out).

    (The confidence half-widths are in the CSV and drawn as bands in the figures.)
    """
    columns = [
        (q, unit, m)
        for q, _, unit in QUANTITIES
        for m in methods
        if any(stats[value][m][q] is not None for value in sweep.values)
    ]
    header = [sweep.title, *[f"{_SHORT[q]} [{unit}] {m}" for q, unit, m in columns]]
    rows = []
    for value in sweep.values:
        cells = [_value_text(value)]
        for q, _, m in columns:
            ci = stats[value][m][q]
            cells.append(format_value(None if ci is None else ci.mean))
        rows.append(cells)
    return markdown_table(header, rows)


def sweep_csv(
    sweeps: Sequence[Sweep], all_stats: dict[str, SweepStats], methods: Sequence[str]
) -> str:
    """One row per (sweep, value, method): seeds, and per quantity RMSE mean, CI half-width."""
    header = ["sweep", "value", "method", "seeds"]
    for q in QUANTITIES:
        header += [f"{q.name}_rmse_{q.slug}_mean", f"{q.name}_rmse_{q.slug}_ci95"]
    rows = []
    for sweep in sweeps:
        for value in sweep.values:
            for m in methods:
                cells = stats_cells(all_stats[sweep.name][value][m])
                n = next((ci.n for ci in all_stats[sweep.name][value][m].values() if ci), 0)
                rows.append([sweep.name, float(value), m, n, *cells])
    return csv_text(header, rows)


def stats_cells(stats: dict[str, MeanCI | None]) -> list[float | None]:
    """[mean, half-width] per quantity (None when unknown)."""
    cells: list[float | None] = []
    for q, _, _ in QUANTITIES:
        ci = stats[q]
        cells += [None, None] if ci is None else [ci.mean, ci.half_width]
    return cells


def plot_sweep(
    sweep: Sweep, stats: SweepStats, methods: Sequence[str], path: Path, *, seeds: int
) -> list[Path]:
    """Four panels (position, orientation, linear and angular velocity RMSE) against the
    swept value: mean over seeds, 95 % confidence band."""
    from hvo_graph.report.plotting import (
        figure_style,
        log_axis,
        method_style,
        new_figure,
        save_figure,
    )

    x = np.array(sweep.values, dtype=float)
    drawn = x > 0 if sweep.log_x else np.ones(len(x), dtype=bool)
    with figure_style():
        fig, axes = new_figure(*FIGSIZE, nrows=2, ncols=2, sharex=True)
        for ax, (q, title, unit) in zip(axes.flat, QUANTITIES, strict=True):
            for m in methods:
                cis = [stats[v][m][q] for v in sweep.values]
                mean = np.array([np.nan if c is None else c.mean for c in cis])
                half = np.array(
                    [
                        np.nan if c is None or not math.isfinite(c.half_width) else c.half_width
                        for c in cis
                    ]
                )
                style = method_style(m, marker=True)
                ok = drawn & np.isfinite(mean) & (mean > 0)
                ax.plot(x[ok], mean[ok], markersize=5, **style)
                band = ok & np.isfinite(half)
                if band.any():
                    # a band below zero has no place on a log axis: clip at a tenth of the mean
                    low = np.maximum(mean - half, 0.1 * mean)
                    ax.fill_between(
                        x[band],
                        low[band],
                        (mean + half)[band],
                        color=style["color"],
                        alpha=0.18,
                        linewidth=0,
                    )
            log_axis(ax)
            if sweep.log_x:
                log_axis(ax, "x")
                ax.set_xticks(x[drawn])
                ax.set_xticklabels([_value_text(v) for v in x[drawn]])
                ax.xaxis.set_minor_formatter("")
            ax.set_title(f"{title} RMSE")
            ax.set_ylabel(f"{title} RMSE [{unit}]")
        for ax in axes[1]:
            ax.set_xlabel(sweep.title)
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=len(methods))
        left_out = ", ".join(_value_text(v) for v in x[~drawn])
        fig.suptitle(
            f"RMSE against {sweep.title.split(' [')[0]}: mean of {seeds} seeds with 95 % "
            "confidence band (others at the paper's noisy scenario)"
            + (f"\n{sweep.title.split(' [')[0]} = {left_out}: see sweep.csv" if left_out else "")
        )
        return save_figure(fig, path)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the sweeps; returns the exit code (argparse exits 2 on bad options)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    seeds = args.seeds or (QUICK_SEEDS if args.quick else DEFAULT_SEEDS)
    duration = args.duration or (QUICK_DURATION if args.quick else DEFAULT_DURATION)
    out_dir = args.out_dir or (QUICK_OUT_DIR if args.quick else DEFAULT_OUT_DIR)
    sweeps = [SWEEPS[name] for name in args.only]
    try:
        if args.skip >= duration:
            raise InputError(f"--skip: {args.skip:g} s leaves nothing of a {duration:g} s sequence")
        configs = [
            sweep.config(value, seed=seed, duration=duration)
            for sweep in sweeps
            for value in sweep.values
            for seed in range(seeds)
        ]
        results = run_seeds(
            configs,
            args.methods,
            skip=args.skip,
            keep_series=False,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=not args.no_progress,
            label="sweep runs",
            bound=True,
        )
    except InputError as exc:
        parser.error(str(exc))
    # the pose's posterior bound, a row beside the methods
    methods = [*args.methods, BOUND]
    all_stats: dict[str, SweepStats] = {}
    start = 0
    for sweep in sweeps:
        count = len(sweep.values) * seeds
        all_stats[sweep.name] = sweep_statistics(
            sweep, results[start : start + count], methods, seeds
        )
        start += count
    tables = []
    for sweep in sweeps:
        tables += [
            f"### Mean RMSE over {seeds} seeds against {sweep.title}",
            "",
            sweep_table(sweep, all_stats[sweep.name], methods),
            "",
        ]
    figures = []
    if not args.no_figures:
        for sweep in sweeps:
            plot_sweep(
                sweep,
                all_stats[sweep.name],
                methods,
                out_dir / "figures" / f"sweep_{sweep.name}",
                seeds=seeds,
            )
            figures.append(f"figures/sweep_{sweep.name}.png")
    command = shlex.join(["python", "experiments/sweep.py", *argv])
    page = [
        "# Accuracy sweeps: pixel noise, frame rate, number of points",
        "",
        "Generated by `experiments/sweep.py`; do not edit by hand.",
        "",
        f"- Command: `{command}`",
        f"- Scenario: the paper's noisy scenario (0.05 px^2, 30 fps, 4 points), {duration:g} s, "
        "with one setting changed per sweep; errors after the first "
        f"{args.skip:g} s; seeds {describe_seeds(range(seeds))} at every value.",
        f"- Methods: {', '.join(f'{METHOD_TITLES[m]} (`{m}`)' for m in args.methods)}; and "
        f"the {BOUND_TITLE} of the pose (`{BOUND}`: from every pixel and the white-noise-"
        "acceleration motion model with the process noise the smoother fitted on each seed; "
        "on average over seeds no estimator knowing that model is below it).",
        "",
        *tables,
        *[f"![{Path(f).stem.replace('_', ' ')}]({f})" for f in figures],
    ]
    write_text_atomic(out_dir / "sweep.md", "\n".join(page).rstrip("\n") + "\n")
    write_text_atomic(out_dir / "sweep.csv", sweep_csv(sweeps, all_stats, methods))
    print(f"written to {out_dir}/sweep.md and {out_dir}/sweep.csv\n")
    print("\n".join(tables), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
