"""Shared plumbing of the readers and writers: atomic writes and numeric tables.

Every writer goes through :func:`atomic_write_text`: the text is written to a
temporary file in the destination directory, then moved over the destination
with ``os.replace`` (atomic on POSIX and Windows), so a crash or a full disk
never leaves a half-written output.

Readers report problems as ``InputError("<file>:<line>: <what was expected>")``
with 1-based line numbers.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from hvo_graph.errors import InputError

PathLike = str | os.PathLike


def atomic_write_text(path: PathLike, text: str | Iterable[str]) -> None:
    """Write ``text`` (UTF-8, ``\\n`` line ends; a string or its pieces in order) to
    ``path`` atomically.

    The temporary file is created with mode 0o666 minus the umask (what a
    plain ``open(path, "w")`` would give), then fsynced and renamed.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.writelines([text] if isinstance(text, str) else text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def staged_output(
    directory: PathLike, owned: Sequence[str], last: Sequence[str] = ("run.json",)
) -> Iterator[Path]:
    """Write a set of files into ``directory`` all or nothing.

    Yields a staging folder (hidden, inside ``directory``, so on the same file
    system); what the block writes there is moved into ``directory`` only when the
    block ends without an exception (each file by ``os.replace``, the ``last`` names
    after the others, so a complete ``run.json`` marks a complete output). Names of
    ``owned`` that the block did not write are removed from ``directory`` (a stale
    ``covariance.csv`` must not sit next to new poses). On an error or Ctrl-C the
    staging folder is removed and ``directory`` keeps what it had; other files in
    ``directory`` are never touched.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=directory))
    try:
        yield stage
        written = sorted(p.name for p in stage.iterdir())
        for name in written:
            if name not in last:
                os.replace(stage / name, directory / name)
        for name in owned:
            if name not in written:
                (directory / name).unlink(missing_ok=True)
        for name in last:
            if name in written:
                os.replace(stage / name, directory / name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def read_text(path: PathLike) -> str:
    """The file's text; OSError propagates (callers name the path), bad encoding is InputError."""
    data = Path(path).read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{path}: expected a UTF-8 text file ({exc.reason} at byte {exc.start})"
        ) from None


def fmt(x: float) -> str:
    """Shortest text that reads back as exactly the same float (Python's repr); no '-0.0'."""
    return repr(float(x) + 0.0)


def _parses(lines: Sequence[str], delimiter: str | None, ncols: int) -> bool:
    try:
        a = np.loadtxt(lines, delimiter=delimiter, comments=None, ndmin=2, dtype=float)
    except ValueError:
        return False
    return a.shape[1] == ncols


def _explain_line(line: str, delimiter: str | None, names: Sequence[str]) -> str:
    """Why one line is not ``len(names)`` numbers separated by ``delimiter``."""
    fields = line.split(delimiter)
    sep = "comma-separated" if delimiter == "," else "space-separated"
    if len(fields) != len(names):
        return f"expected {len(names)} {sep} values ({' '.join(names)}), got {len(fields)}"
    for name, value in zip(names, fields, strict=True):
        if not value.strip() or not _parses([value], None, 1):
            return f"column '{name}': expected a number, got {value.strip()!r}"
    return f"expected {len(names)} {sep} numbers ({' '.join(names)})"


def parse_table(
    path: PathLike,
    lines: Sequence[str],
    linenos: np.ndarray,
    names: Sequence[str],
    delimiter: str | None,
) -> np.ndarray:
    """Parse numeric rows fast (numpy), or name the first bad line.

    Args:
        path: file name for messages.
        lines: the data lines (no header, no comments, no blank lines).
        linenos: (len(lines),) 1-based line number of each entry of ``lines``.
        names: column names, one per expected value.
        delimiter: "," for CSV, None for whitespace.
    Returns:
        (len(lines), len(names)) float array (may contain NaN/inf: callers check).
    Raises:
        InputError: "<path>:<line>: ..." for the first line that is not a row of numbers.
    """
    ncols = len(names)
    if not lines:
        return np.zeros((0, ncols))
    try:
        table = np.loadtxt(lines, delimiter=delimiter, comments=None, ndmin=2, dtype=float)
        if table.shape[1] == ncols:
            return table
    except ValueError:
        pass
    # Bisect for the first offending line: a block parses iff all its lines do,
    # so this costs about two full parses and needs no second parser.
    lo, hi = 0, len(lines)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _parses(lines[lo:mid], delimiter, ncols):
            lo = mid
        else:
            hi = mid
    raise InputError(f"{path}:{linenos[lo]}: {_explain_line(lines[lo], delimiter, names)}")


def first_line(mask: np.ndarray, linenos: np.ndarray) -> int | None:
    """1-based line number of the first True entry of ``mask``, or None."""
    bad = np.flatnonzero(mask)
    return int(linenos[bad[0]]) if bad.size else None


def check_finite(
    path: PathLike, table: np.ndarray, linenos: np.ndarray, names: Sequence[str]
) -> None:
    """Raise naming the first line and column holding NaN or inf."""
    bad = ~np.isfinite(table)
    row = first_line(bad.any(axis=1), linenos)
    if row is not None:
        i = int(np.flatnonzero(bad.any(axis=1))[0])
        col = names[int(np.flatnonzero(bad[i])[0])]
        raise InputError(f"{path}:{row}: column '{col}': expected a finite number, got {table[i]}")


def check_increasing(path: PathLike, t: np.ndarray, linenos: np.ndarray, what: str = "t") -> None:
    """Raise naming the first line whose time does not exceed the previous one."""
    row = first_line(np.concatenate(([False], np.diff(t) <= 0)), linenos)
    if row is not None:
        raise InputError(f"{path}:{row}: {what} must be strictly increasing")


def check_header(path: PathLike, lines: list[str], header: str) -> None:
    """The first line must be exactly ``header`` (surrounding whitespace ignored)."""
    if not lines:
        raise InputError(f"{path}:1: expected the header line '{header}', got an empty file")
    if lines[0].strip() != header:
        raise InputError(f"{path}:1: expected the header line '{header}', got {lines[0].strip()!r}")


#: ASCII line breaks other than "\n" (str.splitlines sees them; numpy's reader does not).
_OTHER_BREAKS = "\r\x0b\x0c\x1c\x1d\x1e"
#: A blank line between rows (csv_body names it).
_BLANK_LINE = re.compile(r"\n[ \t]*\n")


def plain_csv_table(path: PathLike, text: str, header: str, ncols: int) -> np.ndarray | None:
    """The table of a plain CSV file (``text`` its contents) read by numpy straight from
    the file, without a Python string per line; None when anything is unusual (a header
    other than ``header``, no rows, a blank line, another line break, a row numpy refuses
    or of another width), so that :func:`csv_body` and :func:`parse_table` name it.

    Returns:
        (rows, ncols) float array, row i from line i + 2, as :func:`parse_table` parses it.
    """
    start = text.find("\n")
    if start < 0 or text[:start].strip() != header or not text.isascii():
        return None
    body = text[start + 1 :].rstrip()
    if not body[: body.find("\n") % (len(body) + 1)].strip():  # no rows, or a blank first
        return None
    if any(c in text for c in _OTHER_BREAKS) or _BLANK_LINE.search(body):
        return None
    try:
        table = np.loadtxt(
            path, delimiter=",", skiprows=1, comments=None, ndmin=2, dtype=float, encoding="utf-8"
        )
    except (ValueError, OSError):
        return None
    return table if table.shape == (body.count("\n") + 1, ncols) else None


def csv_body(path: PathLike, text: str, header: str) -> tuple[list[str], np.ndarray]:
    """Check a CSV's header; return its data lines and their 1-based line numbers.

    Trailing blank lines are ignored; a blank line between rows is an error.
    """
    lines = text.splitlines()
    check_header(path, lines, header)
    body = lines[1:]
    while body and not body[-1].strip():
        body.pop()
    for i, line in enumerate(body):
        if not line.strip():
            raise InputError(f"{path}:{i + 2}: expected a row ({header}), got a blank line")
    return body, np.arange(2, len(body) + 2)
