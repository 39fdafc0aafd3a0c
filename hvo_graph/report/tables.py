"""Tables and text files of the generated result pages: numbers, CIs, Markdown, CSV.

No domain logic: cells in, text out.
"""

from __future__ import annotations

import csv
import io
import math
import platform
from collections.abc import Iterable, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.eval.metrics import QUANTITIES, ErrorSummary
from hvo_graph.eval.stats import MeanCI
from hvo_graph.io._common import atomic_write_text


def format_value(value: float | None, digits: int = 3) -> str:
    """``value`` to ``digits`` significant digits, plain notation when readable; '-' for None."""
    if value is None or not math.isfinite(value):
        return "-"
    if value == 0:
        return "0"
    exponent = math.floor(math.log10(abs(value)))
    if -4 <= exponent < 5:
        return f"{value:.{max(0, digits - 1 - exponent)}f}"
    return f"{value:.{digits - 1}e}"


def format_ci(ci: MeanCI | None) -> str:
    """'mean ± half-width': the half-width to 2 significant digits, the mean to the same place.

    With no half-width (one seed) only the mean, to 3 significant digits; '-' for None.
    """
    if ci is None:
        return "-"
    if not math.isfinite(ci.half_width) or ci.half_width <= 0:
        return format_value(ci.mean)
    exponent = math.floor(math.log10(ci.half_width))
    if exponent < -5 or exponent > 4:
        return f"{ci.mean:.2e} ± {ci.half_width:.1e}"
    decimals = max(0, 1 - exponent)
    return f"{ci.mean:.{decimals}f} ± {ci.half_width:.{decimals}f}"


def markdown_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], align: str | None = None
) -> str:
    """A Markdown (GitHub) table with padded columns, readable as plain text too.

    Args:
        header: column titles.
        rows: cells, one string per column.
        align: one letter per column, "l" (left) or "r" (right); default: the
            first column left, the others right.
    """
    table = [list(header), *[list(r) for r in rows]]
    if any(len(r) != len(header) for r in table):
        raise InputError("markdown_table: every row needs one cell per header column")
    align = align or "l" + "r" * (len(header) - 1)
    if len(align) != len(header) or set(align) - {"l", "r"}:
        raise InputError(f"align: expected one of 'l'/'r' per column, got {align!r}")
    widths = [max(3, *(len(r[c]) for r in table)) for c in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        padded = [
            cell.ljust(w) if a == "l" else cell.rjust(w)
            for cell, w, a in zip(cells, widths, align, strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rule = "|".join(
        "-" * (w + 2) if a == "l" else "-" * (w + 1) + ":"
        for w, a in zip(widths, align, strict=True)
    )
    return "\n".join([line(table[0]), f"|{rule}|", *(line(r) for r in table[1:])])


def software_versions() -> str:
    """'Python X, numpy X, gtsam X, opencv-python-headless X, matplotlib X' (installed ones)."""
    found = []
    for package in ("numpy", "gtsam", "opencv-python-headless", "matplotlib"):
        try:
            found.append(f"{package} {version(package)}")
        except PackageNotFoundError:
            continue
    return f"Python {platform.python_version()}, " + ", ".join(found)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (no half-written file), creating its folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    return path


def csv_text(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """CSV text (Unix newlines); floats written with ``repr`` (round-trip exact), None empty."""

    def cell(v: object) -> object:
        if v is None:
            return ""
        if isinstance(v, float | np.floating):
            return repr(float(v))
        return v

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow([cell(v) for v in row])
    return buffer.getvalue()


def summary_columns() -> list[str]:
    """CSV column names of an :class:`ErrorSummary`: ``<quantity>_<rmse|max>_<unit>``, frames."""
    cols = [f"{q.name}_{stat}_{q.slug}" for q in QUANTITIES for stat in ("rmse", "max")]
    return [*cols, "frames"]


def summary_row(summary: ErrorSummary) -> list[object]:
    """The values of :func:`summary_columns` for one summary."""
    row: list[object] = [
        getattr(summary, f"{q.name}_{stat}") for q in QUANTITIES for stat in ("rmse", "max")
    ]
    return [*row, summary.frames]


def describe_seeds(seeds: Sequence[int]) -> str:
    """Seeds compactly: '0-49', or '0-3, 7, 9'."""
    values = sorted(set(int(s) for s in seeds))
    parts: list[str] = []
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and values[j + 1] == values[j] + 1:
            j += 1
        parts.append(str(values[i]) if i == j else f"{values[i]}-{values[j]}")
        i = j + 1
    return ", ".join(parts)
