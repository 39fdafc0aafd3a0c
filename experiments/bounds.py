"""How close the estimators come to what the pixels allow: Cramér-Rao bounds per seed.

For each seed of a simulated scenario (the paper's noisy run by default): the
posterior Cramér-Rao bound of the pose (pixel Fisher information of every frame
plus the white-noise-acceleration motion prior over the whole sequence, with the
process noise the estimators fit by maximum likelihood on that seed's H_d poses),
the memoryless bound (frame 0 and frame k alone, no motion model), and the RMSE
of the tight smoother, the homography smoother and the raw H_d measurements on
the same data (:mod:`hvo_graph.eval.bounds`). RMSEs are after ``--skip``
seconds, pooled over seeds as sqrt(mean of squared per-seed RMSE).

Writes ``<out-dir>/bounds.md`` (the table and the command) and ``bounds.csv``
(per frame: the mean over seeds of both bounds); prints the table.

Usage::

    python experiments/bounds.py                   # 20 seeds -> out/bounds/
    python experiments/bounds.py --seeds 5 --num-points 8
    python experiments/bounds.py --quick           # 3 seeds of 4 s
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hvo_graph.arguments import finite_float, int_at_least
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import METHOD_TITLES, build_estimator
from hvo_graph.eval.bounds import memoryless_bound, posterior_bound
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.frontend import FrontEndConfig, measure_sequence
from hvo_graph.report.tables import markdown_table, software_versions, write_text_atomic
from hvo_graph.sim.scenario import PAPER_NOISE_VAR, paper_scenario, simulate

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT_DIR = ROOT / "out" / "bounds"
#: Methods compared with the bounds, in table order.
METHODS: tuple[str, ...] = ("tight", "smoother", "measurements")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bounds.py", description="Pose RMSE of the estimators against Cramér-Rao bounds."
    )
    parser.add_argument("--seeds", type=int_at_least(1), default=20, help="seeds 0..N-1")
    parser.add_argument("--duration", type=finite_float(0.0, strict=True), default=10.0)
    parser.add_argument("--num-points", type=int_at_least(4), default=4, help="plane points")
    parser.add_argument(
        "--noise-var",
        type=finite_float(0.0, strict=True),
        default=PAPER_NOISE_VAR,
        help=f"pixel noise variance, px^2 (default {PAPER_NOISE_VAR})",
    )
    parser.add_argument(
        "--skip", type=finite_float(0.0, strict=False), default=1.0, help="seconds left out"
    )
    parser.add_argument("--quick", action="store_true", help="3 seeds of 4 s")
    parser.add_argument("--out-dir", type=Path, default=None, help="default out/bounds/")
    return parser


def run_seed(seed: int, args: argparse.Namespace) -> dict[str, tuple[float, float]]:
    """{row: (position RMSE m, orientation RMSE deg)} of one seed; the bounds' per-frame
    values under "posterior-frames" / "memoryless-frames" (arrays)."""
    config = paper_scenario(
        seed=seed, duration=args.duration, num_points=args.num_points, noise_var=args.noise_var
    )
    scenario = simulate(config)
    front = FrontEndConfig(pixel_sigma=scenario.pixel_sigma)
    frames = measure_sequence(scenario.observations, scenario.camera, scenario.plane, front)
    rows: dict[str, object] = {}
    sigma = None
    for label in METHODS:
        estimator = build_estimator(label)
        trajectory = estimator.run(frames)
        summary = summarize(error_series(trajectory, scenario.groundtruth), t_start=args.skip)
        rows[label] = (summary.position_rmse, summary.orientation_rmse)
        sigma = getattr(estimator, "acceleration_sigma", sigma)
    posterior = posterior_bound(scenario, sigma)
    memoryless = memoryless_bound(scenario)
    rows["posterior bound"] = posterior.rmse(args.skip)
    rows["memoryless bound"] = memoryless.rmse(args.skip)
    rows["frames"] = (posterior, memoryless)
    return rows  # type: ignore[return-value]


def pooled(results: list[dict], row: str) -> tuple[float, float]:
    values = np.array([r[row] for r in results])
    return tuple(np.sqrt(np.mean(values**2, axis=0)))  # type: ignore[return-value]


def table(results: list[dict]) -> str:
    bound = pooled(results, "posterior bound")
    smoother = pooled(results, "smoother")
    header = [
        "",
        "position RMSE (m)",
        "orientation RMSE (deg)",
        "/ posterior bound (pos, ori)",
        "/ smoother (pos, ori)",
    ]
    rows = []
    for row in ("posterior bound", "memoryless bound", *METHODS):
        pos, ori = pooled(results, row)
        title = METHOD_TITLES.get(row, row)
        rows.append(
            [
                title,
                f"{pos:.4f}",
                f"{ori:.3f}",
                f"{pos / bound[0]:.2f}, {ori / bound[1]:.2f}",
                f"{pos / smoother[0]:.2f}, {ori / smoother[1]:.2f}",
            ]
        )
    return markdown_table(header, rows)


def frames_csv(results: list[dict]) -> str:
    posterior = [r["frames"][0] for r in results]
    memoryless = [r["frames"][1] for r in results]
    t = posterior[0].t
    lines = [
        "t,posterior_position_m,posterior_orientation_deg,memoryless_position_m,"
        "memoryless_orientation_deg"
    ]
    for k in range(len(t)):
        values = [
            np.sqrt(np.mean([b.position[k] ** 2 for b in posterior])),
            np.sqrt(np.mean([b.orientation[k] ** 2 for b in posterior])),
            np.sqrt(np.mean([b.position[k] ** 2 for b in memoryless])),
            np.sqrt(np.mean([b.orientation[k] ** 2 for b in memoryless])),
        ]
        lines.append(f"{t[k]:.6f}," + ",".join(f"{v:.6g}" for v in values))
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.seeds, args.duration = 3, 4.0
    if args.skip >= args.duration:
        print(f"bounds.py: error: --skip {args.skip} leaves no frame", file=sys.stderr)
        return 2
    out_dir = args.out_dir or DEFAULT_OUT_DIR
    try:
        results = []
        for seed in range(args.seeds):
            results.append(run_seed(seed, args))
            print(f"seed {seed} done", file=sys.stderr)
    except InputError as exc:
        print(f"bounds.py: error: {exc}", file=sys.stderr)
        return 2
    text = table(results)
    command = "python experiments/bounds.py " + shlex.join(list(argv or sys.argv[1:]))
    page = (
        "# Pose RMSE against the Cramér-Rao bounds\n\n"
        f"{args.seeds} seeds, {args.duration:g} s, {args.num_points} points, pixel noise "
        f"variance {args.noise_var:g} px^2; errors after {args.skip:g} s.\n\n"
        f"{text}\n\n- Command: `{command.strip()}`\n- Software: {software_versions()}\n"
    )
    write_text_atomic(out_dir / "bounds.md", page)
    write_text_atomic(out_dir / "bounds.csv", frames_csv(results))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
