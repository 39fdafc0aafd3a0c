"""A text progress bar for long runs (no dependency)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

from hvo_graph.errors import as_integer


def _clock_text(seconds: float) -> str:
    seconds = max(0, round(seconds))
    minutes, s = divmod(seconds, 60)
    hours, m = divmod(minutes, 60)
    return f"{hours}:{m:02d}:{s:02d}" if hours else f"{m}:{s:02d}"


class ProgressBar:
    """A text progress bar with counts, elapsed time and ETA (no dependency).

    On a terminal the bar is redrawn in place (carriage return); otherwise (a
    log file, a test) one line is written per 10 % of progress, and at the end.

    Args:
        total: number of steps (> 0).
        label: what is counted, e.g. "seeds".
        stream: where to write; default ``sys.stderr``.
        width: characters of the bar.
        enabled: False writes nothing.
        clock: seconds, monotonic (injectable for tests).
        rate_unit: when given, the line also shows the rate, e.g. "12.5 frames/s"
            for "frames".
    """

    def __init__(
        self,
        total: int,
        *,
        label: str = "",
        stream: TextIO | None = None,
        width: int = 30,
        enabled: bool = True,
        clock: Callable[[], float] = time.monotonic,
        rate_unit: str | None = None,
    ) -> None:
        self.total = as_integer(total, "total", 1)
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.enabled = enabled
        self.clock = clock
        self.rate_unit = rate_unit
        self.done = 0
        self._start = clock()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_decile = -1
        self._closed = False
        if enabled and self._tty:
            self._draw()

    def text(self) -> str:
        """The bar as a line: ``label [#####.....] done/total  pct%  elapsed m:ss  ETA m:ss``,
        then ``  R unit/s`` when ``rate_unit`` is set."""
        fraction = self.done / self.total
        filled = round(fraction * self.width)
        elapsed = self.clock() - self._start
        eta = "?" if self.done == 0 else _clock_text(elapsed * (self.total - self.done) / self.done)
        bar = "#" * filled + "." * (self.width - filled)
        head = f"{self.label} " if self.label else ""
        line = (
            f"{head}[{bar}] {self.done}/{self.total} {100 * fraction:3.0f}%  "
            f"elapsed {_clock_text(elapsed)}  ETA {eta}"
        )
        if self.rate_unit is not None:
            rate = f"{self.done / elapsed:.1f}" if elapsed > 0 and self.done else "?"
            line += f"  {rate} {self.rate_unit}/s"
        return line

    def _draw(self) -> None:
        if self._tty:
            self.stream.write("\r" + self.text())
        else:
            self.stream.write(self.text() + "\n")
        self.stream.flush()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more finished steps."""
        self.done = min(self.total, self.done + n)
        if not self.enabled:
            return
        decile = (10 * self.done) // self.total
        if self._tty or decile > self._last_decile:
            self._last_decile = decile
            self._draw()

    def close(self) -> None:
        """End the bar's line (terminal)."""
        if self.enabled and self._tty and not self._closed:
            self.stream.write("\n")
            self.stream.flush()
        self._closed = True

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
