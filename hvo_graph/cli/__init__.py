"""The ``hvo-graph`` command: ``simulate``, ``estimate``, ``evaluate``, ``plane`` and
``batch`` (docs/conventions.md, docs/batch.md).

A thin layer over the library: it parses arguments, reads the contract's files,
calls :func:`hvo_graph.sim.scenario.simulate`, :func:`hvo_graph.pipeline.estimate`
or :mod:`hvo_graph.eval.metrics`, and writes the contract's files. Bad input
(an :class:`~hvo_graph.errors.InputError`, or a file that cannot be read or
written) prints one line ``hvo-graph: error: ...`` on stderr and exits with
status 2, like argparse's own usage errors; never a traceback.

Examples::

    hvo-graph simulate --out run/                       # the paper's noisy scenario
    hvo-graph estimate --camera run/camera.yaml --tracks run/tracks.csv \\
        --method smoother --out run/smoother
    hvo-graph evaluate --estimate run/smoother --groundtruth run/
    hvo-graph batch runs/ --method smoother --out results/ [--scheduler tcp://HOST:8786]
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence

from hvo_graph.cli import batch, estimate, evaluate, plane, simulate
from hvo_graph.cli._common import PROG, package_version
from hvo_graph.cli.estimate import IMAGE_RANSAC_PX, KALMAN_R, METHODS, ROBUST
from hvo_graph.errors import InputError

__all__ = ["IMAGE_RANSAC_PX", "KALMAN_R", "METHODS", "PROG", "ROBUST", "build_parser", "main"]

#: The subcommands, in the order ``--help`` lists them; each module registers its parser.
SUBCOMMANDS = (simulate, estimate, evaluate, plane, batch)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (one subcommand per module of this package)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Homography-based visual odometry fused in a GTSAM factor graph.",
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in SUBCOMMANDS:
        command.add_parser(sub)
    return parser


def _os_error_message(exc: OSError) -> str:
    """'cannot read|write PATH: reason', naming the path the OS complained about."""
    reason = exc.strerror or str(exc)
    if exc.filename is None:
        return reason
    return f"{exc.filename}: {reason}"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 usage or input error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code or 0)
    try:
        status = args.handler(args)
        if argv is None and threading.current_thread() is threading.main_thread():
            # The program itself, its output complete: a Ctrl-C from here on would only
            # kill the exiting interpreter (status -2, a traceback-free but wrong code).
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        return status
    except InputError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
    except OSError as exc:
        print(f"{PROG}: error: {_os_error_message(exc)}", file=sys.stderr)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
