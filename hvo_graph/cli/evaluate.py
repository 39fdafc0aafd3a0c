"""``hvo-graph evaluate``: errors of one or more estimates against ground truth.

Association, alignment, APE and RPE follow evo's ``evo_ape`` / ``evo_rpe``
(hvo_graph.eval.evaluation); several estimates give one table, one row per
method, named by their ``run.json`` or folder.
"""

from __future__ import annotations

import argparse
import json
import math

from hvo_graph.arguments import finite_float, int_at_least
from hvo_graph.errors import InputError


def _any_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``evaluate`` on the subcommand parsers."""
    ev = sub.add_parser(
        "evaluate",
        help="errors of estimates against ground truth (APE, RPE, velocities)",
        description="Position (m), orientation (deg), linear (m/s) and angular (rad/s) velocity "
        "errors (RMSE and max), and the absolute and relative pose errors (APE, RPE) as evo "
        "computes them, after associating poses by timestamp and an optional alignment. "
        "EST and --groundtruth are estimate folders, simulate-style folders, EuRoC folders, "
        "or TUM / EuRoC files.",
    )
    ev.add_argument("estimates", nargs="*", metavar="EST", help="estimates to score")
    ev.add_argument(
        "--estimate", action="append", default=[], metavar="PATH", help="an estimate (repeatable)"
    )
    ev.add_argument("--groundtruth", required=True, metavar="PATH", help="the ground truth")
    ev.add_argument(
        "--t-max-diff",
        type=finite_float(0.0, strict=False),
        default=0.01,
        metavar="SECONDS",
        help="largest time difference of associated poses (as evo's --t_max_diff; default 0.01)",
    )
    ev.add_argument(
        "--t-offset",
        type=_any_float,
        default=0.0,
        metavar="SECONDS",
        help="added to the estimates' timestamps before association (as evo's --t_offset)",
    )
    ev.add_argument(
        "--align",
        choices=("none", "origin", "se3", "sim3"),
        default="none",
        help="alignment of each estimate onto the ground truth (Umeyama for se3/sim3; "
        "default none: both share the first camera frame)",
    )
    ev.add_argument(
        "--n-to-align",
        type=int_at_least(3),
        default=None,
        metavar="N",
        help="fit the se3/sim3 alignment to the first N associated poses",
    )
    ev.add_argument(
        "--delta",
        type=finite_float(0.0, strict=True),
        default=1.0,
        help="RPE pair distance (default 1)",
    )
    ev.add_argument(
        "--delta-unit",
        choices=("f", "s", "m"),
        default="f",
        help="unit of --delta: f frames, s seconds, m metres travelled (default f)",
    )
    ev.add_argument(
        "--all-pairs", action="store_true", help="RPE over all pairs, not consecutive ones"
    )
    ev.add_argument(
        "--skip",
        type=finite_float(0.0, strict=False),
        default=None,
        metavar="SECONDS",
        help="ignore frames in the first SECONDS after the ground truth's first timestamp",
    )
    fmt = ev.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="print JSON instead of tables")
    fmt.add_argument("--csv", action="store_true", help="print CSV, one row per estimate")
    ev.add_argument(
        "--plot",
        metavar="DIR",
        default=None,
        help="write error_over_time, top_view and error_distribution figures (PNG, SVG) to DIR",
    )
    ev.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hvo_graph.eval.evaluation import (
        EvaluationOptions,
        csv_table,
        evaluate_trajectory,
        format_pose_error_table,
        unique_names,
    )
    from hvo_graph.eval.metrics import format_table
    from hvo_graph.io.trajectory_paths import read_estimate, read_groundtruth

    if args.plot is not None:
        try:  # before any work: a missing extra is a usage error, not a late traceback
            import matplotlib  # noqa: F401
        except ImportError:
            raise InputError(
                "--plot: needs matplotlib (pip install 'hvo_graph[figures]')"
            ) from None
    paths = [*args.estimates, *args.estimate]
    if not paths:
        raise InputError("evaluate: expected at least one estimate (EST or --estimate PATH)")
    if args.delta_unit == "f" and args.delta != int(args.delta):
        raise InputError(f"--delta: expected a whole number of frames, got {args.delta:g}")
    options = EvaluationOptions(
        max_diff=args.t_max_diff,
        offset=args.t_offset,
        align=args.align,
        n_align=args.n_to_align,
        delta=args.delta,
        delta_unit=args.delta_unit,
        all_pairs=args.all_pairs,
        skip=args.skip,
    )
    groundtruth, velocity = read_groundtruth(args.groundtruth)
    estimates = [read_estimate(p) for p in paths]
    names = unique_names([name for _, name in estimates], [str(p) for p in paths])
    evaluations = [
        evaluate_trajectory(traj, groundtruth, velocity=velocity, options=options, method=name)
        for (traj, _), name in zip(estimates, names, strict=True)
    ]
    if args.plot is not None:
        from hvo_graph.report.evaluation_figures import write_evaluation_figures

        write_evaluation_figures(args.plot, groundtruth, evaluations)
    if args.json:
        dicts = [ev.as_dict() for ev in evaluations]
        print(json.dumps(dicts[0] if len(dicts) == 1 else {"estimates": dicts}))
    elif args.csv:
        print(csv_table(evaluations), end="")
    else:
        print(format_table({ev.method: ev.summary for ev in evaluations}))
        print()
        print(format_pose_error_table(evaluations))
    return 0
