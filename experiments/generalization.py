"""Beyond the paper's scenario: every method with default options on randomised families.

Each family of :mod:`hvo_graph.sim.families` (plane tilt 0-60 deg, 4-50 points,
10-120 fps, motion from near-hover to ~2 Hz / 1 m/s / 1 rad/s, pixel noise
0.01-2 px^2, off-plane tracks and dropped frames) is drawn with seeds 0..N-1;
every draw runs the raw measurements, the paper's Kalman filter, the Kalman
filter with measured R and the three factor-graph solvers, all with their
default options, and the tightly coupled smoother (hvo_graph.montecarlo.run_family_seed).
Per family, the tables give the mean over seeds of the per-seed RMSE ratios
(smoothed / raw, smoothed / paper Kalman, smoothed / measured-R Kalman, tight /
smoothed) for position, orientation, linear and angular velocity, the pose RMSE
of the smoother and of the tight smoother over each draw's posterior Cramér-Rao
bound (hvo_graph.eval.bounds, with the process noise the smoother fitted), and
the mean NEES per degree of freedom of pose and twist, each with its Student-t
95 % confidence interval.

Writes ``<out-dir>/generalization.md`` and ``<out-dir>/generalization.csv`` and
prints the tables.

Usage::

    python experiments/generalization.py          # 16 seeds per family -> out/generalization/
    python experiments/generalization.py --families agile,hover --seeds 4
    python experiments/generalization.py --quick            # 2 seeds of 4 s -> out/
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hvo_graph.arguments import add_monte_carlo_options, finite_float, int_at_least, names
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_TITLES
from hvo_graph.eval.bounds import BOUND, BOUND_TITLE
from hvo_graph.eval.metrics import QUANTITIES
from hvo_graph.eval.stats import MeanCI, mean_ci
from hvo_graph.montecarlo import (
    BOUND_MAX_POINTS,
    FamilySeed,
    SeedResult,
    ratio_statistics,
    run_seeds,
)
from hvo_graph.report.tables import (
    csv_text,
    describe_seeds,
    format_ci,
    markdown_table,
    software_versions,
    write_text_atomic,
)
from hvo_graph.sim.families import FAMILIES, describe

DEFAULT_SEEDS = 16
QUICK_SEEDS = 2
QUICK_DURATION = 4.0
ROOT = Path(__file__).resolve().parents[1]
#: Outputs default to out/generalization/: the repository's docs/ is written only when asked
#: (``--out-dir docs``, as ``make figures`` does).
DEFAULT_OUT_DIR = ROOT / "out" / "generalization"
QUICK_OUT_DIR = ROOT / "out" / "generalization-quick"

#: The smoothed estimate the ratios are taken of, and what it is compared with.
SMOOTHED = "smoother"
REFERENCES = ("measurements", "kalman", "kalman-measured")
#: RMSE ratios reported (numerator, reference): the smoother against each reference, and
#: the tightly coupled smoother against the smoother.
COMPARISONS: tuple[tuple[str, str], ...] = (
    *((SMOOTHED, reference) for reference in REFERENCES),
    ("tight", SMOOTHED),
    (SMOOTHED, BOUND),
    ("tight", BOUND),
)
#: Methods whose covariances are checked (NEES).
CONSISTENCY = ("smoother", "batch", "fixed-lag", "kalman-measured", "tight")
METHODS = ("measurements", "kalman", "kalman-measured", "smoother", "batch", "fixed-lag", "tight")

_SHORT = {"position": "pos", "orientation": "ori", "linear_velocity": "v", "angular_velocity": "w"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="generalization.py",
        description="Every method, default options, on randomised scenario families.",
    )
    parser.add_argument(
        "--seeds", type=int_at_least(1), help=f"seeds 0..N-1 per family (default {DEFAULT_SEEDS})"
    )
    parser.add_argument(
        "--families",
        type=names(tuple(FAMILIES), "family"),
        default=list(FAMILIES),
        help=f"comma-separated subset of {','.join(FAMILIES)}",
    )
    parser.add_argument(
        "--duration",
        type=finite_float(0.0, strict=True),
        help="seconds per sequence (default: each family's own, 6-10 s)",
    )
    add_monte_carlo_options(
        parser,
        quick_help=f"short run: {QUICK_SEEDS} seeds of {QUICK_DURATION:g} s unless given",
        quick_out="out/generalization-quick/",
        figures_option=False,
        default_out="out/generalization/; make figures passes --out-dir docs",
    )
    return parser


def nees_statistics(results: Sequence[SeedResult], method: str) -> tuple[MeanCI, MeanCI]:
    """Mean over seeds of the pose and twist NEES per degree of freedom, 95 % CIs."""
    values = np.array([r.nees[method] for r in results], dtype=float)
    return mean_ci(values[:, 0]), mean_ci(values[:, 1])


def geometric_mean(values: Sequence[float]) -> float:
    """exp(mean(log x)) over the finite values: the summary of ratios over families (a
    family without a value, such as the traverse's bound, is left out)."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return math.exp(float(np.mean(np.log(finite)))) if finite.size else math.nan


def family_tables(
    by_family: dict[str, list[SeedResult]],
) -> tuple[list[str], list[list[object]]]:
    """The page's markdown tables and the CSV rows (family, comparison, quantity, mean, CI)."""
    tables: list[str] = []
    csv_rows: list[list[object]] = []
    for numerator, reference in COMPARISONS:
        # the bound is of the pose alone
        quantities = QUANTITIES[:2] if reference == BOUND else QUANTITIES
        header = ["family", *[f"{_SHORT[q.name]} ratio" for q in quantities]]
        rows, means = [], []
        for family, results in by_family.items():
            stats = ratio_statistics(results, numerator, reference)
            rows.append([family, *[format_ci(stats[q.name]) for q in quantities]])
            means.append([stats[q.name].mean if stats[q.name] else math.nan for q in quantities])
            for q in quantities:
                ci = stats[q.name]
                csv_rows.append(
                    [family, f"{numerator}/{reference}", q.name, *_ci_cells(ci), len(results)]
                )
        finite = np.array(means, dtype=float)
        rows.append(
            [
                "geometric mean",
                *[f"{geometric_mean(finite[:, j]):.3f}" for j in range(len(quantities))],
            ]
        )
        title = BOUND_TITLE if reference == BOUND else METHOD_TITLES[reference]
        tables += [
            f"### {METHOD_TITLES[numerator]} / {title}: RMSE ratio",
            "",
            markdown_table(header, rows),
            "",
        ]
    header = ["family"]
    for m in CONSISTENCY:
        header += [f"{m} pose", f"{m} twist"]
    rows = []
    for family, results in by_family.items():
        cells: list[str] = [family]
        for m in CONSISTENCY:
            pose, twist = nees_statistics(results, m)
            cells += [format_ci(pose), format_ci(twist)]
            csv_rows.append([family, f"NEES {m}", "pose", *_ci_cells(pose), len(results)])
            csv_rows.append([family, f"NEES {m}", "twist", *_ci_cells(twist), len(results)])
        rows.append(cells)
    tables += [
        "### Mean NEES per degree of freedom (1 = honest covariance; above 1 overconfident)",
        "",
        markdown_table(header, rows),
        "",
    ]
    return tables, csv_rows


def _ci_cells(ci: MeanCI | None) -> list[float | None]:
    return [None, None] if ci is None else [ci.mean, ci.half_width]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the families; returns the exit code (argparse exits 2 on bad options)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    seeds = args.seeds or (QUICK_SEEDS if args.quick else DEFAULT_SEEDS)
    duration = args.duration or (QUICK_DURATION if args.quick else None)
    out_dir = args.out_dir or (QUICK_OUT_DIR if args.quick else DEFAULT_OUT_DIR)
    jobs = [FamilySeed(f, s, duration) for f in args.families for s in range(seeds)]
    try:
        if duration is not None and args.skip >= duration:
            raise InputError(f"--skip: {args.skip:g} s leaves nothing of a {duration:g} s sequence")
        results = run_seeds(
            jobs,
            METHODS,
            skip=args.skip,
            keep_series=False,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=not args.no_progress,
            label="sequences",
            bound=True,
        )
    except InputError as exc:
        parser.error(str(exc))
    by_family = {f: [r for r in results if r.family == f] for f in args.families}
    tables, csv_rows = family_tables(by_family)
    command = shlex.join(["python", "experiments/generalization.py", *argv])
    families = [f"- `{f}`: {describe(f)}" for f in args.families]
    page = [
        "# Beyond the paper's scenario: randomised scenario families",
        "",
        "Generated by `experiments/generalization.py`; do not edit by hand.",
        "",
        f"- Command: `{command}`",
        f"- Seeds {describe_seeds(range(seeds))} per family; errors after the first "
        f"{args.skip:g} s; every method with its default options (nothing tuned per family).",
        "- Ratios: per seed RMSE(method) / RMSE(reference), then the mean over seeds "
        "with its 95 % confidence interval; below 1 the first method is better.",
        f"- {BOUND_TITLE}: of the pose, from every pixel of the draw (plane points only; "
        "none of the dropped frames) and the white-noise-acceleration motion model with "
        "the process noise the smoother fitted on that draw; on average over seeds no "
        "estimator knowing that model is below 1. Not computed (-) for draws of more than "
        f"{BOUND_MAX_POINTS} plane points (the traverse: minutes per draw).",
        "- NEES: pose delta = Log(T_est^-1 T_true) against the 6x6 pose block, twist error "
        "against the twist block, divided by 6 and averaged over frames, then over seeds. "
        "A sequence's pose errors share one reference-frame offset, so one seed's pose NEES "
        "scatters like chi^2_6 / 6 (standard deviation 0.58): the intervals need many seeds.",
        f"- {software_versions()}",
        "",
        "## Families",
        "",
        *families,
        "",
        "## Results",
        "",
        *tables,
    ]
    write_text_atomic(out_dir / "generalization.md", "\n".join(page).rstrip("\n") + "\n")
    header = ["family", "comparison", "quantity", "mean", "ci95", "seeds"]
    write_text_atomic(out_dir / "generalization.csv", csv_text(header, csv_rows))
    print(f"written to {out_dir}/generalization.md and {out_dir}/generalization.csv\n")
    print("\n".join(tables), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
