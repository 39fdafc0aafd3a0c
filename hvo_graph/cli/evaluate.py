"""``hvo-graph evaluate``: errors of an estimate against ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hvo_graph.arguments import finite_float


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``evaluate`` on the subcommand parsers."""
    ev = sub.add_parser(
        "evaluate",
        help="errors of an estimate against ground truth",
        description="Position (m), orientation (deg), linear (m/s) and angular (rad/s) velocity "
        "errors, RMSE and max, matched by timestamp.",
    )
    ev.add_argument("--estimate", required=True, metavar="DIR", help="an estimate output folder")
    ev.add_argument("--groundtruth", required=True, metavar="DIR", help="a simulate-style folder")
    ev.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    ev.add_argument(
        "--skip",
        type=finite_float(0.0, strict=False),
        default=None,
        metavar="SECONDS",
        help="ignore frames in the first SECONDS after the ground truth's first timestamp",
    )
    ev.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hvo_graph.eval.metrics import error_series, format_table, summarize
    from hvo_graph.io.trajectory import read_estimate_dir, read_groundtruth_dir

    estimate = read_estimate_dir(args.estimate)
    groundtruth = read_groundtruth_dir(args.groundtruth)
    series = error_series(estimate, groundtruth)
    t_start = None if args.skip is None else float(groundtruth.t[0]) + args.skip
    summary = summarize(series, t_start=t_start)
    if args.json:
        print(json.dumps(summary.as_dict()))
    else:
        name = Path(args.estimate).resolve().name or str(args.estimate)
        print(format_table({name: summary}))
    return 0
