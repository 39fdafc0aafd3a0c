"""``hvo-graph batch``: ``estimate`` (and ``evaluate``) over many sequence folders."""

from __future__ import annotations

import argparse
import sys

from hvo_graph.arguments import finite_float, int_at_least
from hvo_graph.cli._common import PROG
from hvo_graph.cli.estimate import IMAGE_RANSAC_PX, METHODS


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``batch`` on the subcommand parsers."""
    batch = sub.add_parser(
        "batch",
        help="estimate (and evaluate) many sequences, locally or on a Dask cluster",
        description="Each SEQUENCE_DIR is a folder with camera.yaml and tracks.csv or images/ "
        "(groundtruth.txt too: the estimate is evaluated), or a folder of such folders. "
        "Writes DIR/<sequence>/ (the estimate files, evaluation.json, run.json) and "
        "DIR/batch.json. A failed sequence is reported and the others go on; a rerun skips "
        "the sequences already written. Exit status 1 when a sequence failed.",
    )
    batch.add_argument("sequences", nargs="+", metavar="SEQUENCE_DIR", help="sequence folders")
    batch.add_argument("--method", choices=METHODS, default=METHODS[0], help="default: smoother")
    batch.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    batch.add_argument(
        "--config",
        metavar="FILE",
        default=None,
        help="YAML mapping of estimate options (names without --), for every sequence",
    )
    batch.add_argument(
        "--covariance", action="store_true", help="also write covariance.csv for each sequence"
    )
    batch.add_argument(
        "--skip",
        type=finite_float(0.0, strict=False),
        default=None,
        metavar="SECONDS",
        help="evaluation ignores the first SECONDS of ground truth",
    )
    where = batch.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=int_at_least(1),
        default=None,
        metavar="N",
        help="local worker processes (default: one per core)",
    )
    where.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        default=None,
        help="run on the workers of this Dask scheduler (needs dask[distributed])",
    )
    batch.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    batch.set_defaults(handler=run)


def _options(args: argparse.Namespace) -> dict[str, object]:
    """The library options of ``--config`` and ``--covariance``, parsed and checked exactly
    as ``estimate`` parses them."""
    from hvo_graph.cli import estimate
    from hvo_graph.estimators.registry import check_applicable
    from hvo_graph.pipeline import FRONT_END_OPTIONS

    parser = argparse.ArgumentParser(prog=PROG)
    estimate.add_parser(parser.add_subparsers())
    argv = ["estimate", "--camera", "-", "--tracks", "-", "--out", "-", "--method", args.method]
    est = parser.parse_args([*argv, *(["--covariance"] if args.covariance else [])])
    if args.config is not None:
        estimate._apply_config(est, args.config)
    options = estimate._estimate_options(est)
    check_applicable(
        args.method,
        [k for k in options if k not in FRONT_END_OPTIONS],
        spell=lambda name: estimate._FLAGS.get(name, "--" + name.replace("_", "-")),
    )
    return options


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from hvo_graph.batch import find_sequences, run_batch
    from hvo_graph.report.tables import write_text_atomic

    jobs = find_sequences(args.sequences)
    outcomes = run_batch(
        jobs,
        args.out,
        args.method,
        _options(args),
        image_options={"ransac_threshold_px": IMAGE_RANSAC_PX},
        skip=args.skip,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.no_progress and sys.stderr.isatty(),
    )
    import json

    report = [
        {"sequence": o.name, "status": o.status, "message": o.message, **o.evaluation}
        for o in outcomes
    ]
    write_text_atomic(Path(args.out) / "batch.json", json.dumps(report, indent=2) + "\n")
    failed = [o for o in outcomes if o.status == "failed"]
    for o in failed:
        print(f"{PROG} batch: {o.name}: failed: {o.message}", file=sys.stderr)
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    print(
        f"{PROG} batch: {len(outcomes)} sequences ({args.method}): {counts['done']} done, "
        f"{counts['skipped']} skipped (already in {args.out}), {counts['failed']} failed"
    )
    return 1 if failed else 0
