"""Monte Carlo experiments: one simulated seed through every estimator, and many in parallel.

The library side of ``experiments/compare.py`` and ``experiments/sweep.py``.
One seed of one scenario (:class:`~hvo_graph.sim.scenario.ScenarioConfig`) is
simulated once and measured once per front-end kind: the homography front end
(H_d poses, H_c twists) feeds every method except "ippe", which gets OpenCV's
per-frame ``solvePnP(SOLVEPNP_IPPE)`` poses. Every random source is seeded from
the config's seed (pixel noise, layout of extra points, the Kalman filter's
random initial state), so the same seed gives the same numbers.

Methods (:data:`METHOD_LABELS`):

- ``measurements``: the raw per-frame H_d pose and H_c twist, no fusion;
- ``kalman``: the paper's 12-state filter with the paper's noisy-run R_k;
- ``kalman-measured``: the same filter given what the smoother is given: R_k the
  diagonal of the front end's covariances (``r_preset="measured"``), process
  noise equal to the smoother's white-noise acceleration (see
  :func:`~hvo_graph.estimators.process_noise.kalman_process_noise`), and the measured body velocity
  rotated into the world frame before integration (``world_frame_velocity``,
  the correct kinematics; the paper's form integrates body v as world v);
- ``smoother``: ISAM2, the final (smoothed) trajectory;
- ``smoother-online``: the same ISAM2 run, each frame's estimate right after its
  own update (``Estimator.online_trajectory``), no second run;
- ``batch``: Levenberg-Marquardt over the whole graph;
- ``fixed-lag``: GTSAM's incremental fixed-lag smoother (1 s window), final values;
- ``ippe``: per-frame IPPE poses, twists from differencing consecutive poses.
"""

from __future__ import annotations

import csv
import io
import math
import multiprocessing
import os
import platform
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from hvo_graph.errors import InputError, as_integer, as_number
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.process_noise import DEFAULT_ACCELERATION_SIGMA, kalman_process_noise
from hvo_graph.eval.metrics import (
    QUANTITIES,
    ErrorSeries,
    ErrorSummary,
    error_series,
    summarize,
)
from hvo_graph.eval.stats import MeanCI, mean_ci
from hvo_graph.io._common import atomic_write_text
from hvo_graph.sim.scenario import ScenarioConfig, simulate
from hvo_graph.types import Trajectory

#: Every method an experiment can run, in table order.
METHOD_LABELS: tuple[str, ...] = (
    "measurements",
    "kalman",
    "kalman-measured",
    "smoother",
    "smoother-online",
    "batch",
    "fixed-lag",
    "ippe",
)

#: Human-readable name of each method (tables, legends).
METHOD_TITLES: dict[str, str] = {
    "measurements": "raw measurements (H_d, H_c)",
    "kalman": "Kalman (paper, noisy R)",
    "kalman-measured": "Kalman (measured R)",
    "smoother": "ISAM2 smoothed",
    "smoother-online": "ISAM2 online",
    "batch": "batch LM",
    "fixed-lag": "fixed-lag (1 s)",
    "ippe": "IPPE per frame",
}

#: Window of the fixed-lag smoother, seconds.
FIXED_LAG_SECONDS = 1.0

#: Environment of the worker processes of :func:`run_seeds`: one BLAS / OpenMP thread
#: each. The parallelism is across processes; threaded BLAS in every worker
#: oversubscribes the cores, and the front end's small SVDs then ran ~10x slower on a
#: loaded 2-core machine.
WORKER_ENVIRONMENT: dict[str, str] = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


def check_methods(methods: Iterable[str]) -> tuple[str, ...]:
    """The methods as a tuple, in the order given.

    Raises:
        InputError: empty, unknown or repeated labels.
    """
    if isinstance(methods, str):
        methods = [methods]
    chosen = tuple(methods)
    if not chosen:
        raise InputError(f"methods: expected at least one of {', '.join(METHOD_LABELS)}")
    for label in chosen:
        if label not in METHOD_LABELS:
            raise InputError(
                f"methods: unknown method {label!r}, expected one of {', '.join(METHOD_LABELS)}"
            )
    if len(set(chosen)) != len(chosen):
        dup = next(m for m in chosen if chosen.count(m) > 1)
        raise InputError(f"methods: {dup!r} is listed twice")
    return chosen


def make_method(label: str, seed: int) -> Estimator:
    """A fresh estimator for ``label`` (except "smoother-online", which reads a "smoother" run).

    Args:
        label: one of :data:`METHOD_LABELS` other than "smoother-online".
        seed: seed of the Kalman filters' random initial state.
    """
    from hvo_graph.pipeline import make_estimator

    if label == "kalman-measured":
        from hvo_graph.estimators.kalman import KalmanBaseline

        return KalmanBaseline(
            r_preset="measured",
            process_noise=kalman_process_noise(DEFAULT_ACCELERATION_SIGMA),
            seed=seed,
            world_frame_velocity=True,
        )
    if label == "kalman":
        return make_estimator("kalman", seed=seed, kalman_r="paper-noisy")
    if label == "fixed-lag":
        return make_estimator("fixed-lag", lag=FIXED_LAG_SECONDS)
    if label in ("measurements", "smoother", "batch", "ippe"):
        return make_estimator(label)
    raise InputError(f"make_method: no estimator for {label!r}")


@dataclass
class SeedResult:
    """Errors of every method on one simulated seed.

    Attributes:
        seed: the scenario's seed.
        config: the scenario.
        summaries: per method, RMSE and max after ``skip`` seconds.
        series: per method, per-frame errors over the whole sequence (empty when
            not kept).
        skip: seconds left out at the start of the summaries.
    """

    seed: int
    config: ScenarioConfig
    summaries: dict[str, ErrorSummary]
    series: dict[str, ErrorSeries] = field(default_factory=dict)
    skip: float = 1.0


def run_seed(
    config: ScenarioConfig,
    methods: Sequence[str] = METHOD_LABELS,
    *,
    skip: float = 1.0,
    keep_series: bool = True,
) -> SeedResult:
    """Simulate ``config`` once and run every method on it.

    Args:
        config: the scenario, with its seed.
        methods: labels from :data:`METHOD_LABELS`.
        skip: errors are summarized over frames with t >= t_0 + skip (seconds),
            after the estimators' start-up transient (the Kalman filter starts
            from a random state).
        keep_series: also return the per-frame errors.
    Raises:
        InputError: bad methods or skip, or an estimator's InputError with the
            seed and method prepended.
        RuntimeError: any other failure of an estimator, naming the seed and method.
    """
    methods = check_methods(methods)
    if not isinstance(config, ScenarioConfig):
        raise InputError(f"config: expected a ScenarioConfig, got {type(config).__name__}")
    skip = as_number(skip, "skip", at_least=0.0, what="a number of seconds")
    if skip >= config.duration:
        raise InputError(
            f"skip: {skip:g} s leaves no frame of a {config.duration:g} s sequence to evaluate"
        )
    from hvo_graph.pipeline import measure

    scenario = simulate(config)
    truth = scenario.groundtruth
    t_start = float(truth.t[0]) + float(skip)
    frames = {}  # front-end kind -> measurements, each computed once
    isam: Estimator | None = None
    isam_smoothed: Trajectory | None = None
    result = SeedResult(seed=config.seed, config=config, summaries={}, skip=float(skip))
    for label in methods:
        kind = "ippe" if label == "ippe" else "homography"
        try:
            if kind not in frames:
                frames[kind] = measure(
                    scenario.observations, scenario, method="ippe" if kind == "ippe" else "smoother"
                )
            if label in ("smoother", "smoother-online"):
                if isam is None:
                    isam = make_method("smoother", config.seed)
                    isam_smoothed = isam.run(frames[kind])
                trajectory = isam_smoothed if label == "smoother" else isam.online_trajectory()
            else:
                trajectory = make_method(label, config.seed).run(frames[kind])
            series = error_series(trajectory, truth)
            result.summaries[label] = summarize(series, t_start=t_start)
        except InputError as exc:
            raise InputError(f"seed {config.seed}, method {label}: {exc}") from exc
        except Exception as exc:  # e.g. a GTSAM failure: say where, even from a worker process
            raise RuntimeError(
                f"seed {config.seed}, method {label}: {type(exc).__name__}: {exc}"
            ) from exc
        if keep_series:
            result.series[label] = series
    return result


def _run_seed_job(job: tuple[ScenarioConfig, tuple[str, ...], float, bool]) -> SeedResult:
    config, methods, skip, keep_series = job
    return run_seed(config, methods, skip=skip, keep_series=keep_series)


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
    ) -> None:
        self.total = as_integer(total, "total", 1)
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.enabled = enabled
        self.clock = clock
        self.done = 0
        self._start = clock()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_decile = -1
        self._closed = False
        if enabled and self._tty:
            self._draw()

    def text(self) -> str:
        """The bar as a line: ``label [#####.....] done/total  pct%  elapsed m:ss  ETA m:ss``."""
        fraction = self.done / self.total
        filled = round(fraction * self.width)
        elapsed = self.clock() - self._start
        eta = "?" if self.done == 0 else _clock_text(elapsed * (self.total - self.done) / self.done)
        bar = "#" * filled + "." * (self.width - filled)
        head = f"{self.label} " if self.label else ""
        return (
            f"{head}[{bar}] {self.done}/{self.total} {100 * fraction:3.0f}%  "
            f"elapsed {_clock_text(elapsed)}  ETA {eta}"
        )

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


def resolve_workers(workers: int | None) -> int:
    """Worker processes: ``workers`` (>= 1), or ``os.cpu_count()`` when None."""
    if workers is None:
        return max(1, os.cpu_count() or 1)
    return as_integer(workers, "workers", 1)


@contextmanager
def _environment(values: Mapping[str, str]) -> Iterator[None]:
    """Set environment variables for the duration of the block (restored after)."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def run_seeds(
    configs: Sequence[ScenarioConfig],
    methods: Sequence[str] = METHOD_LABELS,
    *,
    skip: float = 1.0,
    keep_series: bool = True,
    workers: int | None = None,
    progress: bool = True,
    label: str = "seeds",
) -> list[SeedResult]:
    """:func:`run_seed` for every config, over ``workers`` processes; results in input order.

    Args:
        configs: one scenario per run (typically the same scenario, different seeds).
        methods: labels from :data:`METHOD_LABELS`.
        skip: seconds left out at the start of every summary.
        keep_series: keep the per-frame errors.
        workers: processes (``concurrent.futures.ProcessPoolExecutor``, started with
            "spawn" and :data:`WORKER_ENVIRONMENT`); 1 runs in this process; None =
            ``os.cpu_count()``.
        progress: draw a :class:`ProgressBar` on stderr.
        label: what the progress bar counts.
    """
    methods = check_methods(methods)
    workers = resolve_workers(workers)
    configs = list(configs)
    if not configs:
        raise InputError("configs: expected at least one scenario")
    jobs = [(config, methods, skip, keep_series) for config in configs]
    results: list[SeedResult | None] = [None] * len(jobs)
    with ProgressBar(len(jobs), label=label, enabled=progress) as bar:
        if workers == 1 or len(jobs) == 1:
            for i, job in enumerate(jobs):
                results[i] = _run_seed_job(job)
                bar.update()
        else:
            # Longest runs first (front-end cost ~ frames x points), so that no
            # worker is left with a long run at the end; results keep the input order.
            order = sorted(
                range(len(jobs)), key=lambda i: -configs[i].num_frames * configs[i].num_points
            )
            # Fresh interpreters ("spawn") read WORKER_ENVIRONMENT before importing numpy;
            # forked workers would inherit this process's BLAS threads.
            with (
                _environment(WORKER_ENVIRONMENT),
                ProcessPoolExecutor(
                    max_workers=min(workers, len(jobs)),
                    mp_context=multiprocessing.get_context("spawn"),
                ) as pool,
            ):
                pending = {pool.submit(_run_seed_job, jobs[i]): i for i in order}
                while pending:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in finished:
                        i = pending.pop(future)
                        error = future.exception()
                        if error is not None:
                            for other in pending:
                                other.cancel()
                            raise error
                        results[i] = future.result()
                        bar.update()
    return [r for r in results if r is not None]


# -- aggregation over seeds --------------------------------------------------------------


def metric_values(
    results: Sequence[SeedResult], method: str, quantity: str, stat: str = "rmse"
) -> np.ndarray:
    """(S,) the ``stat`` ("rmse" or "max") of ``quantity`` for ``method``, one per seed.

    NaN where a seed gave no value (velocity unknown).
    """
    if stat not in ("rmse", "max"):
        raise InputError(f"stat: expected 'rmse' or 'max', got {stat!r}")
    if quantity not in {q for q, _, _ in QUANTITIES}:
        names = ", ".join(q for q, _, _ in QUANTITIES)
        raise InputError(f"quantity: expected one of {names}, got {quantity!r}")
    out = np.empty(len(results))
    for i, r in enumerate(results):
        if method not in r.summaries:
            raise InputError(f"seed {r.seed}: no result for method {method!r}")
        value = getattr(r.summaries[method], f"{quantity}_{stat}")
        out[i] = np.nan if value is None else value
    return out


def _finite_ci(values: np.ndarray) -> MeanCI | None:
    finite = values[np.isfinite(values)]
    return mean_ci(finite) if finite.size else None


def method_statistics(
    results: Sequence[SeedResult], method: str, stat: str = "rmse"
) -> dict[str, MeanCI | None]:
    """Per quantity, the mean over seeds of ``stat`` with its 95 % CI (None: no values)."""
    return {q: _finite_ci(metric_values(results, method, q, stat)) for q, _, _ in QUANTITIES}


def ratio_statistics(
    results: Sequence[SeedResult], numerator: str, denominator: str
) -> dict[str, MeanCI | None]:
    """Per quantity, the mean over seeds of RMSE(numerator) / RMSE(denominator), 95 % CI.

    The ratio is taken per seed first (a paired comparison on identical data),
    then averaged: the mean of per-seed ratios, not the ratio of mean RMSEs.
    """
    out: dict[str, MeanCI | None] = {}
    for q, _, _ in QUANTITIES:
        num = metric_values(results, numerator, q)
        den = metric_values(results, denominator, q)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[q] = _finite_ci(num / den)
    return out


def mean_error_over_time(
    results: Sequence[SeedResult], method: str
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Per-frame error of ``method`` averaged over seeds.

    Returns:
        t (K,) seconds and, per quantity, (K,) mean error (NaN where no seed has a value).
    Raises:
        InputError: series not kept, or seeds with different frame times.
    """
    if not results or any(method not in r.series for r in results):
        raise InputError(f"mean_error_over_time: per-frame errors of {method!r} were not kept")
    t = results[0].series[method].t
    curves: dict[str, np.ndarray] = {}
    for q, _, _ in QUANTITIES:
        rows = []
        for r in results:
            s = r.series[method]
            if len(s.t) != len(t) or not np.allclose(s.t, t):
                raise InputError(f"seed {r.seed}: frame times differ from seed {results[0].seed}")
            e = getattr(s, q)
            rows.append(np.full(len(t), np.nan) if e is None else np.asarray(e, dtype=float))
        stack = np.array(rows)
        count = np.isfinite(stack).sum(axis=0)
        total = np.where(np.isfinite(stack), stack, 0.0).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            curves[q] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return np.asarray(t, dtype=float), curves


# -- formatting and files ----------------------------------------------------------------


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
    from importlib.metadata import PackageNotFoundError, version

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
        getattr(summary, f"{q}_{stat}") for q, _, _ in QUANTITIES for stat in ("rmse", "max")
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
