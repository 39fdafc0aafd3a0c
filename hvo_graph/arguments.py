"""Command-line argument types and options shared by ``hvo-graph`` and experiments/.

Each type raises ``argparse.ArgumentTypeError`` with what was expected, so
argparse prints one line naming the option and exits with status 2.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from pathlib import Path


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def finite_float(minimum: float, *, strict: bool) -> Callable[[str], float]:
    """An argparse type: a finite number > ``minimum`` (``strict``) or >= ``minimum``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        ok = value > minimum if strict else value >= minimum
        if not (ok and math.isfinite(value)):
            op = ">" if strict else ">="
            raise argparse.ArgumentTypeError(
                f"expected a finite number {op} {minimum:g}, got {text}"
            )
        return value

    return parse


def acceleration_sigma_value(text: str) -> str | float | tuple[float, float]:
    """``--acceleration-sigma``: "auto", one number (both), or "angular,linear" (each > 0)."""
    if text.strip() == "auto":
        return "auto"
    parse = finite_float(0.0, strict=True)
    parts = [parse(p) for p in text.split(",")]
    if len(parts) == 1:
        return parts[0]
    if len(parts) == 2:
        return (parts[0], parts[1])
    raise argparse.ArgumentTypeError(f"expected 'auto', a number or 'angular,linear', got {text!r}")


def names(choices: Sequence[str], what: str) -> Callable[[str], list[str]]:
    """An argparse type: a comma- or space-separated list of distinct ``choices``."""

    def parse(text: str) -> list[str]:
        picked = [n for n in text.replace(",", " ").split() if n]
        for n in picked:
            if n not in choices:
                raise argparse.ArgumentTypeError(
                    f"unknown {what} {n!r}; expected some of {', '.join(choices)}"
                )
        if not picked or len(set(picked)) != len(picked):
            raise argparse.ArgumentTypeError(f"expected distinct {what}s, got {text!r}")
        return picked

    return parse


def add_monte_carlo_options(
    parser: argparse.ArgumentParser,
    *,
    quick_help: str,
    quick_out: str,
    workers: bool = True,
    figures_option: bool = True,
    default_out: str = "the repository's docs/",
) -> None:
    """The options every Monte Carlo script under experiments/ takes.

    --skip, --out-dir, --no-progress and --quick; --workers, --scheduler and
    --no-figures unless the script has no use for them (``workers``, ``figures_option``).
    """
    parser.add_argument(
        "--skip",
        type=finite_float(0.0, strict=False),
        default=1.0,
        help="seconds at the start left out of the errors (default 1.0)",
    )
    if workers:
        parser.add_argument(
            "--workers",
            type=int_at_least(1),
            help="worker processes (default: os.cpu_count())",
        )
        parser.add_argument(
            "--scheduler",
            metavar="tcp://HOST:PORT",
            help="run the seeds on the workers of this Dask scheduler (docs/batch.md)",
        )
    parser.add_argument(
        "--out-dir",
        type=Path,
        help=f"output folder (default: {default_out}; {quick_out} with --quick)",
    )
    if figures_option:
        parser.add_argument("--no-figures", action="store_true", help="skip the figures")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--quick", action="store_true", help=quick_help)
