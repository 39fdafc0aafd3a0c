"""What every ``hvo-graph`` subcommand shares: the program name, progress notes, the version."""

from __future__ import annotations

import sys

PROG = "hvo-graph"


def progress(message: str) -> None:
    """Progress notes go to stderr, and only when a person is watching it."""
    if sys.stderr.isatty():
        print(f"{PROG}: {message}", file=sys.stderr, flush=True)


def package_version() -> str:
    """The installed hvo-graph version ("unknown" when run from a source tree)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hvo-graph")
    except PackageNotFoundError:
        return "unknown"
