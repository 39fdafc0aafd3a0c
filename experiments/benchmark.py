"""Speed and memory of the front end, the Kalman filter and every smoother, side by side.

For each sequence length (default 1,000, 10,000 and 100,000 frames of the paper's
noisy scenario at 30 fps; the motion is periodic with a 10 s period, so a long
run is just a longer duration) this script

1. simulates the sequence and runs the measurement front end over it once as the
   command line does (``process_all``, which measures stretches of frames at once),
   timed over blocks of 100 frames (H_d pose + H_c velocity per frame);
2. feeds those same measurements to each estimator, one after the other: the
   paper's Kalman filter, the factor-graph smoother (default: ISAM2 over a
   window, then the batch solve), with the fixed-lag smoother (1 s window) and
   with batch Levenberg-Marquardt. Each runs ``run(frames)`` as the command
   line does, on consecutive blocks of 100 frames (each run continues where the
   last stopped), each frame timed as its share of its block: the Kalman filter
   filters in a loop of its own, and the smoothers add runs of frames posed
   against the world without an ``update`` each. The rest of ``run``
   (process-noise fit on the whole sequence, final ``trajectory()``: the batch
   solves happen there) is timed apart; the tight smoother's ``update`` calls
   are timed one by one;
3. runs every configuration (component x length) once, in a fresh subprocess
   that reports both its timing and its peak memory (the front end's
   subprocess passes its measurements on through a file; ``--no-memory``: all
   in this process). Peak memory is the growth of the resident set while the
   component runs: the peak resident set VmHWM of /proc/self/status (=
   ``getrusage`` ru_maxrss on Linux) is reset (``/proc/self/clear_refs``)
   after the inputs are loaded, and the figure reported is VmHWM after the
   run minus VmRSS before it. This counts GTSAM's C++ allocations too, which
   ``tracemalloc`` does not see. Where the reset is unavailable the ru_maxrss
   delta is reported (a lower bound);
4. profiles the ISAM2 smoother (``--profile-component``) with cProfile on 3,000
   frames: where the time goes;
5. runs a bare ``Pose3`` chain through ISAM2 (``--chain-poses``, nothing from
   hvo_graph): GTSAM 4.3's update cost grows with the number of poses, the
   reason the default smoother keeps a window;
6. puts each stage beside a reference on the same inputs (``--reference-frames``;
   experiments/benchmark_references.py): the front end (4 and 20 points) beside a
   bare numpy loop doing the same mathematics, the Kalman filter beside a plain
   numpy 12-state loop, the fixed-lag smoother's updates beside a bare GTSAM
   ``IncrementalFixedLagSmoother`` on a ``Pose3`` chain;
7. runs ``hvo-graph estimate`` end to end (``--cli-frames``, default 30,000 frames)
   for the default smoother, the fixed-lag smoother and the Kalman filter, each in
   a fresh process on a tracks CSV written as ``hvo-graph simulate`` writes it:
   wall and CPU time and the process's peak memory; the two smoothers also on
   ``--cli-memory-frames`` (default 100,000) frames;
8. times the images path on rendered 640 x 480 PNG files (``--image-frames``,
   default 450) beside a bare OpenCV loop (decode, detection, KLT) on the same
   files, and ``hvo-graph estimate --images`` end to end
   (experiments/benchmark_images.py).

Columns: overall frames per second = frames / (all frames + fit +
``trajectory()``); the CPU time of the run (``time.process_time``, steadier than
wall time when other processes share the machine); the mean wall time per frame of
the first and of the last 100 frames and their ratio (how the cost per frame grows
with the length of the sequence), and the cost curve: the mean time per frame in
each tenth of the longest run. Batch LM is skipped above ``--batch-max-frames``
(default 10,000: its solve re-linearizes the whole graph on every iteration;
the output says so). Wall-clock timings depend on the machine and its load: the
report records both.

Prints the table and writes it, with the machine, the command and the profile,
to ``docs/performance.md``. Progress goes to stderr.

Usage::

    .venv/bin/python experiments/benchmark.py                    # 1,000 to 100,000 frames
    .venv/bin/python experiments/benchmark.py --quick            # 300 and 1,000 frames
    .venv/bin/python experiments/benchmark.py --sizes 3000 --components kalman fixed-lag
        --no-memory --profile-frames 0 --chain-poses 0 --cli-frames 3000   # one line
    .venv/bin/python experiments/benchmark.py --sizes 3000 --components isam2 fixed-lag
    .venv/bin/python experiments/benchmark.py --sizes 3000 --components isam2 isam2-cov
        --repeat 3 --profile-component fixed-lag --no-memory --out /tmp/perf.md  # one line
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import dataclasses
import gc
import importlib.metadata
import importlib.util
import json
import os
import pickle
import platform
import pstats
import resource
import shlex
import subprocess
import sys
import tempfile
import time
import types
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.noise_estimation import ProcessNoiseSchedule
from hvo_graph.frontend import FrontEndConfig, MeasurementFrontEnd
from hvo_graph.pipeline import make_estimator
from hvo_graph.report.tables import markdown_table, write_text_atomic
from hvo_graph.sim.scenario import Scenario, paper_scenario, simulate
from hvo_graph.types import FrameMeasurement

#: Components benchmarked, in table order, with their titles.
COMPONENTS: dict[str, str] = {
    "frontend": "front end (H_d pose + H_c velocity)",
    "kalman": "Kalman filter (paper)",
    "isam2": "smoother: ISAM2",
    "fixed-lag": "smoother: fixed-lag (1 s)",
    "batch": "smoother: batch LM",
    "isam2-cov": "smoother: ISAM2 + covariance",
    "tight": "tight (pixels on plane landmarks): ISAM2",
}
#: What runs without ``--components`` ("isam2-cov" adds a marginal covariance per frame).
DEFAULT_COMPONENTS: tuple[str, ...] = (
    "frontend",
    "kalman",
    "isam2",
    "fixed-lag",
    "batch",
    "tight",
)
DEFAULT_SIZES: tuple[int, ...] = (1000, 10000, 100000)
QUICK_SIZES: tuple[int, ...] = (300, 1000)
#: Frames averaged at the start and at the end of a run for the growth of the cost.
WINDOW = 100
FPS = 30.0
DEFAULT_BATCH_MAX_FRAMES = 10000
#: Longest sequence of the tight graph by default (its final solve runs in bounded memory
#: and a few Levenberg-Marquardt iterations at any length); ``--tight-max-frames``
#: lowers it to skip tight on the longest runs.
DEFAULT_TIGHT_MAX_FRAMES = 100000
#: Parts of the longest run whose mean cost per frame makes the cost curve.
CURVE_PARTS = 10
#: Poses of the bare ISAM2 chain (reproduction of GTSAM 4.3's growing update cost).
DEFAULT_CHAIN_POSES = 20000
QUICK_CHAIN_POSES = 1000

#: A bare Pose3 chain through ISAM2, one pose per update: the cost of an update
#: grows with the number of poses in GTSAM 4.3 (each update destroys a temporary
#: Bayes tree, and the destructor visits every clique). Runs as printed in
#: docs/performance.md; ``poses`` and ``parts`` are set by the caller.
CHAIN_REPRODUCTION = """\
import time

import gtsam
import numpy as np

noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01] * 3 + [0.1] * 3))
step = gtsam.Pose3(gtsam.Rot3.Yaw(0.01), np.array([1.0, 0.0, 0.0]))
isam = gtsam.ISAM2()
graph = gtsam.NonlinearFactorGraph()
graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), noise))
values = gtsam.Values()
values.insert(0, gtsam.Pose3())
isam.update(graph, values)
pose, per_update, start = gtsam.Pose3(), [], time.perf_counter()
for k in range(1, poses + 1):
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose3(k - 1, k, step, noise))
    pose = pose.compose(step)
    values = gtsam.Values()
    values.insert(k, pose)
    isam.update(graph, values)
    if k % (poses // parts) == 0:  # mean ms per update over the last poses / parts
        per_update.append(1e3 * (time.perf_counter() - start) / (poses // parts))
        print(f"{k:6d} poses: {per_update[-1]:.3f} ms per update")
        start = time.perf_counter()
"""
DEFAULT_PROFILE_FRAMES = 3000
PROFILE_TOP = 15


def make_component(name: str) -> Estimator:
    """The estimator behind a component name (not "frontend")."""
    if name == "kalman":
        return make_estimator("kalman", kalman_r="paper-noisy")
    if name in ("isam2", "isam2-cov"):
        return make_estimator("smoother", covariance=name == "isam2-cov")
    if name == "fixed-lag":
        return make_estimator("fixed-lag", lag=1.0)
    if name == "batch":
        return make_estimator("batch")
    if name == "tight":
        return make_estimator("tight")
    raise InputError(f"component: expected one of {', '.join(COMPONENTS)}, got {name!r}")


@dataclass
class Timing:
    """Wall-clock times of one component on one sequence.

    Attributes:
        component: key of :data:`COMPONENTS`.
        frames: sequence length.
        per_frame: (frames,) seconds of each ``update`` call (front end: its share of
            its block's ``process_all``; :data:`BLOCK_RUN_COMPONENTS`: of its block's
            ``run``).
        finish: seconds of the final ``trajectory()`` call (0 for the front end).
        cpu: CPU seconds of the process over the whole run (``time.process_time``; all
            threads), less sensitive than wall time to other load on the machine.
        memory_mib: peak resident-set growth while running, MiB (None: not measured).
        cpu_per_frame: (frames,) CPU seconds of each call (``time.process_time``): the
            cost curve, which wall time blurs when other processes share the cores.
    """

    component: str
    frames: int
    per_frame: np.ndarray
    finish: float = 0.0
    cpu: float = float("nan")
    memory_mib: float | None = None
    cpu_per_frame: np.ndarray | None = None

    @property
    def total(self) -> float:
        """All updates plus the final ``trajectory()``, seconds."""
        return float(np.sum(self.per_frame)) + self.finish

    @property
    def fps(self) -> float:
        """Overall frames per second."""
        return self.frames / self.total

    @property
    def first_ms(self) -> float:
        """Mean milliseconds per update over the first :data:`WINDOW` frames."""
        return 1e3 * float(np.mean(self.per_frame[:WINDOW]))

    @property
    def last_ms(self) -> float:
        """Mean milliseconds per update over the last :data:`WINDOW` frames."""
        return 1e3 * float(np.mean(self.per_frame[-WINDOW:]))

    @property
    def cpu_growth(self) -> float:
        """Mean CPU time per call, last :data:`WINDOW` calls over the first (nan: none)."""
        if self.cpu_per_frame is None:
            return float("nan")
        return float(np.mean(self.cpu_per_frame[-WINDOW:]) / np.mean(self.cpu_per_frame[:WINDOW]))

    @property
    def growth(self) -> float:
        """last_ms / first_ms: 1 for a constant cost per frame."""
        return self.last_ms / self.first_ms


def simulate_frames(frames: int, seed: int = 0, num_points: int = 4) -> Scenario:
    """The paper's noisy scenario with exactly ``frames`` frames at 30 fps."""
    duration = (frames - 1) / FPS
    scenario = simulate(
        paper_scenario(noisy=True, seed=seed, duration=duration, num_points=num_points)
    )
    if len(scenario.observations) != frames:  # floor() of the frame count must not slip
        raise RuntimeError(f"simulated {len(scenario.observations)} frames, wanted {frames}")
    return scenario


#: The front end is timed over consecutive blocks of this many frames (its time per frame
#: is the block's mean): it measures a known sequence in stretches of frames at once.
FRONTEND_BLOCK = 100


def run_frontend(scenario: Scenario) -> tuple[list[FrameMeasurement], Timing]:
    """Measure every frame as the command line does (``MeasurementFrontEnd.process_all``,
    hvo_graph.pipeline); return the records and each frame's share of the time of its
    block of ``FRONTEND_BLOCK`` frames (``process_all`` on one block after the other,
    the front end's state carried on)."""
    front = MeasurementFrontEnd(
        scenario.camera, scenario.plane, FrontEndConfig(pixel_sigma=scenario.pixel_sigma)
    )
    clock, cpu_clock = time.perf_counter, time.process_time
    observations = list(scenario.observations)
    times = np.empty(len(observations))
    cpu_times = np.empty(len(observations))
    frames: list[FrameMeasurement] = []
    cpu = time.process_time()
    for i in range(0, len(observations), FRONTEND_BLOCK):
        block = observations[i : i + FRONTEND_BLOCK]
        start, cpu_start = clock(), cpu_clock()
        frames += front.process_all(block)
        times[i : i + len(block)] = (clock() - start) / len(block)
        cpu_times[i : i + len(block)] = (cpu_clock() - cpu_start) / len(block)
    cpu = time.process_time() - cpu
    return frames, Timing("frontend", len(frames), times, cpu=cpu, cpu_per_frame=cpu_times)


def run_estimator(name: str, frames: Sequence[FrameMeasurement]) -> Timing:
    """Time a fresh estimator's ``run(frames)`` as the command line runs it: every
    ``update`` call, and the rest of ``run`` (the final ``trajectory()`` and, for the
    smoothers, the process-noise fit on the whole sequence before the first update)."""
    estimator = make_component(name)
    if name in BLOCK_RUN_COMPONENTS:
        return _run_in_blocks(name, estimator, frames)
    clock, cpu_clock = time.perf_counter, time.process_time
    times: list[float] = []
    cpu_times: list[float] = []
    update = estimator.update

    def timed_update(frame: FrameMeasurement) -> object:
        start, cpu_start = clock(), cpu_clock()
        result = update(frame)
        times.append(clock() - start)
        cpu_times.append(cpu_clock() - cpu_start)
        return result

    estimator.update = timed_update  # type: ignore[method-assign]
    cpu = time.process_time()
    start = clock()
    estimator.run(frames)
    elapsed = clock() - start
    per_frame = np.array(times)
    finish = elapsed - float(per_frame.sum())
    cpu = time.process_time() - cpu
    return Timing(name, len(frames), per_frame, finish, cpu=cpu, cpu_per_frame=np.array(cpu_times))


#: Estimators whose ``run`` does not call ``update`` for every frame (the Kalman filter: its
#: own loop over the whole sequence; the factor-graph smoothers: runs of frames posed
#: against the world, estimators/_world_runs.py); timed block by block instead.
BLOCK_RUN_COMPONENTS = ("kalman", "isam2", "isam2-cov", "fixed-lag", "batch")


def _run_in_blocks(name: str, estimator: Estimator, frames: Sequence[FrameMeasurement]) -> Timing:
    """Time ``run`` on consecutive blocks of ``FRONTEND_BLOCK`` frames (each run continues
    where the last stopped: the same estimates as one run), every frame its share of its
    block; the final ``trajectory()`` once at the end (the blocks' own are skipped). A
    smoother's process-noise fit reads the whole sequence first, as its ``run`` does (the
    blocks' runs do not fit again), and counts with the final ``trajectory()``."""
    clock, cpu_clock = time.perf_counter, time.process_time
    n = len(frames)
    times, cpu_times = np.empty(n), np.empty(n)
    trajectory = estimator.trajectory
    estimator.trajectory = lambda: None  # type: ignore[method-assign,assignment,return-value]
    cpu = cpu_clock()
    fit = 0.0
    schedule = getattr(estimator, "process_noise", None)
    if isinstance(schedule, ProcessNoiseSchedule):  # a smoother's (the filter's is an array)
        start = clock()
        schedule.fit_all(frames)
        fit = clock() - start
        schedule.fit_all = lambda frames: None  # each block's run would refit on its block
    for i in range(0, n, FRONTEND_BLOCK):
        block = frames[i : i + FRONTEND_BLOCK]
        start, cpu_start = clock(), cpu_clock()
        estimator.run(block)
        times[i : i + len(block)] = (clock() - start) / len(block)
        cpu_times[i : i + len(block)] = (cpu_clock() - cpu_start) / len(block)
    estimator.trajectory = trajectory  # type: ignore[method-assign]
    start = clock()
    trajectory()
    finish = clock() - start + fit
    cpu = cpu_clock() - cpu
    return Timing(name, n, times, finish, cpu=cpu, cpu_per_frame=cpu_times)


# -- memory, in a fresh subprocess per configuration ------------------------------------------


def _status_kib(field: str) -> int | None:
    """A "kB" field of /proc/self/status (VmRSS, VmHWM), or None off Linux."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _reset_peak() -> bool:
    """Reset VmHWM to the current resident set (Linux >= 4.0); False when unavailable."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
            f.write("5")
    except OSError:
        return False
    return _status_kib("VmHWM") is not None


def _max_rss_kib() -> int:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss // 1024 if sys.platform == "darwin" else rss  # bytes on macOS, KiB elsewhere


def component_worker(
    component: str, inputs: Path, frames_out: Path | None = None
) -> dict[str, object]:
    """Run one configuration once in this (fresh) process: its timing and its peak
    resident-set growth (KiB), as a JSON-able dict; the front end also pickles its
    measurements to ``frames_out`` (the estimators' input), so nothing runs twice.

    A throwaway instance first runs on a few frames, so that lazy imports and one-off
    library initialization (not the component's own cost) happen before the baseline.
    """
    with open(inputs, "rb") as f:
        data = pickle.load(f)
    if component == "frontend":
        warm = dataclasses.replace(data, observations=data.observations[:3])
        run_frontend(warm)
    else:
        run_estimator(component, data[:3])
    gc.collect()
    if _reset_peak():
        method = "VmHWM after - VmRSS before (peak reset)"
        before = _status_kib("VmRSS")
    else:
        method = "ru_maxrss after - ru_maxrss before"
        before = _max_rss_kib()
    if component == "frontend":
        frames, timing = run_frontend(data)
    else:
        timing = run_estimator(component, data)
    after = _status_kib("VmHWM") if method.startswith("VmHWM") else _max_rss_kib()
    assert before is not None and after is not None
    if frames_out is not None:
        frames_out.write_bytes(pickle.dumps(frames))
    return {
        "growth_kib": after - before,
        "method": method,
        "per_frame": timing.per_frame.tolist(),
        "cpu_per_frame": None if timing.cpu_per_frame is None else timing.cpu_per_frame.tolist(),
        "finish": timing.finish,
        "cpu": timing.cpu,
    }


def timed_in_subprocess(
    component: str, inputs: Path, frames_out: Path | None = None
) -> Timing | None:
    """:func:`component_worker` in a fresh interpreter: the Timing with its peak memory
    (MiB), or None when the subprocess failed (the reason goes to stderr)."""
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", component]
    command += [str(inputs)] + ([str(frames_out)] if frames_out is not None else [])
    result = subprocess.run(command, capture_output=True, text=True, check=False, timeout=3600)
    if result.returncode != 0:
        tail = result.stderr.strip().splitlines()[-1:] or ["no output"]
        print(f"[benchmark] {component} (subprocess) failed: {tail[0]}", file=sys.stderr)
        return None
    report = json.loads(result.stdout.strip().splitlines()[-1])
    per_frame = np.asarray(report["per_frame"], dtype=float)
    timing = Timing(component, len(per_frame), per_frame, report["finish"], cpu=report["cpu"])
    if report["cpu_per_frame"] is not None:
        timing.cpu_per_frame = np.asarray(report["cpu_per_frame"], dtype=float)
    timing.memory_mib = float(report["growth_kib"]) / 1024.0
    return timing


# -- profile ----------------------------------------------------------------------------------


@dataclass
class ProfileEntry:
    """One function of a cProfile run: where, how often, self and cumulative seconds."""

    function: str
    calls: int
    self_s: float
    cumulative_s: float


def _function_name(key: tuple[str, int, str]) -> str:
    filename, line, name = key
    if filename == "~":
        return name  # a built-in, e.g. "<built-in method gtsam.gtsam.update>" (ISAM2.update)
    path = Path(filename)
    parts = path.parts
    for anchor in ("hvo_graph", "site-packages"):
        if anchor in parts:
            parts = parts[parts.index(anchor) + (anchor == "site-packages") :]
            break
    else:
        parts = parts[-2:]
    return f"{'/'.join(parts)}:{line}({name})"


def _category(key: tuple[str, int, str]) -> str:
    filename, _, name = key
    if "factors.py" in filename:
        return "custom factor callbacks (hvo_graph/estimators/factors.py)"
    if "smoother.py" in filename:
        return "smoother bookkeeping (hvo_graph/estimators/smoother.py)"
    if filename == "~" and "gtsam" in name:
        return "GTSAM C++ calls (self time, without the Python callbacks)"
    if "numpy" in filename or "numpy" in name:
        return "numpy"
    return "other Python (interpreter, base classes, profiler)"


@dataclass
class Profile:
    """cProfile summary of one estimator (key of :data:`COMPONENTS`) on one sequence."""

    component: str
    frames: int
    total_s: float
    top: list[ProfileEntry]
    categories: dict[str, float]


def profile_component(
    frames: Sequence[FrameMeasurement], component: str = "isam2", top: int = PROFILE_TOP
) -> Profile:
    """Profile ``update`` over every frame and the final ``trajectory()`` of one estimator."""
    profiler = cProfile.Profile()
    profiler.enable()
    run_estimator(component, frames)
    profiler.disable()
    stats = pstats.Stats(profiler)
    raw = stats.stats  # type: ignore[attr-defined]  # {key: (cc, nc, tt, ct, callers)}
    total = float(sum(v[2] for v in raw.values()))
    entries = sorted(raw.items(), key=lambda kv: kv[1][2], reverse=True)
    categories: dict[str, float] = {}
    for key, (_, _, self_s, _, _) in raw.items():
        categories[_category(key)] = categories.get(_category(key), 0.0) + self_s
    return Profile(
        component=component,
        frames=len(frames),
        total_s=total,
        top=[
            ProfileEntry(_function_name(key), int(nc), float(tt), float(ct))
            for key, (_, nc, tt, ct, _) in entries[:top]
        ],
        categories=dict(sorted(categories.items(), key=lambda kv: kv[1], reverse=True)),
    )


# -- report -----------------------------------------------------------------------------------

TABLE_HEADER: tuple[str, ...] = (
    "component",
    "frames",
    "total [s]",
    "CPU [s]",
    "frames/s",
    f"first {WINDOW} [ms/frame]",
    f"last {WINDOW} [ms/frame]",
    "last/first",
    "fit + trajectory() [s]",
    "peak memory [MiB]",
    f"last/first {WINDOW}, CPU",
)


def cost_curve(timing: Timing, parts: int = CURVE_PARTS) -> list[float]:
    """Mean ms per ``update`` in each of ``parts`` equal parts of the run, in order: CPU
    time where measured (wall time otherwise)."""
    per_frame = timing.per_frame if timing.cpu_per_frame is None else timing.cpu_per_frame
    return [1e3 * float(np.mean(chunk)) for chunk in np.array_split(per_frame, parts)]


def curve_section(timings: Sequence[Timing]) -> str:
    """Markdown: the cost curve of every estimator on the longest sequence it ran."""
    longest: dict[str, Timing] = {}
    for t in timings:
        if t.component != "frontend" and t.frames >= longest.get(t.component, t).frames:
            longest[t.component] = t
    rows = []
    for name in (c for c in COMPONENTS if c in longest):
        t = longest[name]
        curve = cost_curve(t)
        rows.append(
            [
                COMPONENTS[name],
                f"{t.frames:,}",
                *(f"{c:.3f}" for c in curve),
                f"{curve[-1] / curve[0]:.2f}",
            ]
        )
    header = ["component", "frames"] + [f"part {i + 1}" for i in range(CURVE_PARTS)]
    return markdown_table([*header, "last/first"], rows)


def chain_growth(poses: int, parts: int = 10) -> list[float]:
    """Run :data:`CHAIN_REPRODUCTION`: mean ms per update in each tenth of the chain."""
    namespace: dict[str, object] = {"poses": poses, "parts": parts}
    with contextlib.redirect_stdout(sys.stderr):  # its progress lines are not the report
        exec(compile(CHAIN_REPRODUCTION, "<chain reproduction>", "exec"), namespace)
    return list(namespace["per_update"])  # type: ignore[call-overload]


def chain_section(poses: int, per_update: Sequence[float]) -> str:
    """Markdown: the bare-chain reproduction, its code and what it measured here."""
    parts = len(per_update)
    rows = [[f"{(i + 1) * (poses // parts):,}", f"{ms:.3f}"] for i, ms in enumerate(per_update)]
    return "\n\n".join(
        [
            "One ISAM2 holding a whole sequence pays, on every update, for a walk over the "
            "whole Bayes tree: `ISAM2::recalculateIncremental` builds and destroys a temporary "
            "tree per update, and in GTSAM 4.3 the `BayesTree` destructor visits every clique "
            "breadth-first (it did not in 4.2). No ISAM2 parameter avoids it. A bare `Pose3` "
            "chain shows it, with nothing from hvo_graph:",
            "```python\n# not run (poses, parts: set by experiments/benchmark.py)\n"
            + CHAIN_REPRODUCTION
            + "```",
            f"Measured here ({poses:,} poses, mean over each {poses // parts:,}):",
            markdown_table(["poses so far", "ms per update"], rows),
            f"Last/first: {per_update[-1] / per_update[0]:.1f}. The default smoother therefore "
            "keeps only a window of frames in ISAM2 (older frames are marginalized into a "
            "linear prior, so the online estimate of each new frame is unchanged) and gets its "
            "final trajectory from the batch optimum of the whole graph, solved in chunks from "
            "the window's estimates (next section): the same result as the batch solver, at a "
            "cost per frame that does not grow with the length of the sequence.",
        ]
    )


#: How the default smoother keeps long runs in bounded memory (docs/performance.md).
MEMORY_SECTION = """\
The default smoother's final trajectory is the batch optimum of every factor of the \
sequence, so it keeps them all; what it keeps per frame decides its memory on long runs \
(`tracemalloc` for Python's share, VmRSS / VmHWM for GTSAM's C++):

- **factors as numbers**: the motion factor and the H_d pose factor of each frame are \
56 floats in growing numpy arrays \
(`hvo_graph.estimators.factor_store.FactorStore`), rebuilt as GTSAM factors when solved. \
As GTSAM objects they take ~2.2 kB per frame (each with its own noise model: the motion \
factor's 12 x 12, the pose's 6 x 6). Other factors (the anchor, keyframe between factors, \
H_c twist factors where poses leave a gap) are kept as they are: few on most sequences;
- **online estimates as numbers**: 19 floats per frame \
(`hvo_graph.estimators.state_log.StateLog`) instead of a `StateEstimate` with three \
arrays (~0.7 kB per frame); no per-frame dict entries;
- **the final solve in chunks**: one Levenberg-Marquardt solve of the whole graph held \
~9 kB per frame at its peak (linearized system, elimination tree, iterates). \
`solve_in_chunks` solves 2,000 frames at a time with the frames just outside them held \
(block Gauss-Seidel), consecutive chunks sharing 200 frames, then the seams between \
chunks again until no value moves by more than 1e-9: a stationary point of the whole \
problem, i.e. the batch optimum (tests check it against the batch solver to 1e-6 m and \
1e-5 deg). The graph is a chain, so what a held edge leaves out fades within tens of \
frames: on the paper's scenario the seams move by ~1e-10 on their second pass. The final \
pass costs ~1.5 times one solve of the whole graph (the factors are rebuilt from their \
numbers, the seams solved twice), and its memory is one chunk's. Should a factor reach \
far across chunks (a keyframe in use for thousands of frames) and the sweeps settle \
slowly, the whole graph is solved at once: the batch optimum always.

What remains per frame is ~1.4 kB: those arrays (with their growth headroom), each \
frame's estimate as GTSAM `Values` for the final solve, the frame indices and times. The \
peak memory above does not count the input: the benchmark loads the measurement records \
first, and as `FrameMeasurement` objects (covariances, reference-noise Jacobians) they \
weigh ~8 kB per frame, more than the smoother's own state.

The tight graph (`--method tight`) keeps its factors the same way: per frame the motion \
pair and one projection factor per observed point as 6 numbers (frame, landmark, \
normalized image point, sigma, robust or not), each landmark's plane prior as it is. Its \
landmarks are seen by frames far apart (on the paper's scenario every frame sees every \
point), so a chunk of frames cannot be solved with the rest held: moving every landmark and frame \
together costs almost nothing, and such sweeps would crawl. Its final solve \
(`hvo_graph.estimators.chunked_lm`) is Levenberg-Marquardt on the whole graph with each \
linear system solved 2,000 frames at a time: a forward pass linearizes each chunk and \
eliminates its frames (and the landmarks no later frame sees) in time order, carrying a \
dense factor on the chunk's last frame and the landmarks still observed to the next \
chunk; a backward pass back-substitutes chunk by chunk (the factors and conditionals of \
the first chunks are kept (10,000 frames of 4 points), later chunks are linearized and \
eliminated again). The \
optimum is that of one solve of the whole graph (tests: within 1e-6 m and 1e-5 deg of \
the `tight-batch` solver, marginals within 1e-5 of its), the memory is one chunk's plus \
the carried factors, and an iteration costs about 1.5 eliminations of the whole graph. \
Only the first frame's pixels fix where the rest of the sequence lies along the plane \
and its scale (a similarity that keeps the plane changes no later projection), against \
the motion model, whose cost falls with the square of the scale; they take a Gaussian \
loss. With a Huber loss like the other pixels' (reweighted at every linearization), the \
iterates crept along that similarity (30,000 frames: each step 0.63 times the \
previous), and at 100,000 frames the optimum shrank the trajectory by over a quarter; \
with a Gaussian one the solve from the window's estimates converges in a few \
iterations. When two consecutive steps are aligned and shrinking, the next is also tried \
extrapolated to the sum of the steps to come, and taken when its error is the lower.\
"""


def _seconds(value: float) -> str:
    """At least three significant digits, no exponent."""
    return f"{value:.0f}" if value >= 100 else f"{value:#.3g}"


def _memory_text(value: float | None, measured: bool) -> str:
    if not measured:
        return "-"
    return "failed" if value is None else f"{value:.1f}"


def results_table(
    timings: Sequence[Timing], skipped: Sequence[tuple[str, int]], memory: bool
) -> str:
    """The Markdown table: one row per (length, component), skipped ones marked."""
    order = list(COMPONENTS)
    rows: list[tuple[int, int, list[str]]] = []
    for t in timings:
        cells = [
            COMPONENTS[t.component],
            f"{t.frames:,}",
            _seconds(t.total),
            _seconds(t.cpu),
            f"{t.fps:,.0f}",
            f"{t.first_ms:.3f}",
            f"{t.last_ms:.3f}",
            f"{t.growth:.2f}",
            "-" if t.component == "frontend" else f"{t.finish:.3f}",
            _memory_text(t.memory_mib, memory),
            f"{t.cpu_growth:.2f}",
        ]
        rows.append((t.frames, order.index(t.component), cells))
    for component, frames in skipped:
        cells = [COMPONENTS[component], f"{frames:,}", "skipped", *["-"] * 8]
        rows.append((frames, order.index(component), cells))
    return markdown_table(TABLE_HEADER, [cells for *_, cells in sorted(rows, key=lambda r: r[:2])])


def profile_section(profile: Profile) -> str:
    """Markdown: time per category and the top functions by self time."""
    share = [
        [name, f"{seconds:.2f}", f"{100.0 * seconds / profile.total_s:.0f} %"]
        for name, seconds in profile.categories.items()
    ]
    top = [
        [
            f"`{e.function}`",
            f"{e.calls:,}",
            f"{e.self_s:.3f}",
            f"{100.0 * e.self_s / profile.total_s:.1f} %",
            f"{e.cumulative_s:.3f}",
        ]
        for e in profile.top
    ]
    return "\n\n".join(
        [
            f"cProfile of {COMPONENTS[profile.component]} on {profile.frames:,} frames (every "
            "`update` and the "
            f"final `trajectory()`): {profile.total_s:.2f} s of profiled self time (cProfile "
            "slows Python code more than C++ code, so Python's share is overstated).",
            "Self time by where it is spent:",
            markdown_table(["where", "self [s]", "share"], share),
            f"Top {len(profile.top)} functions by self time (`<built-in method gtsam.gtsam.X>` "
            "is a C++ method of GTSAM: `update` is ISAM2.update or "
            "IncrementalFixedLagSmoother.update, i.e. relinearization, elimination and "
            "back-substitution; the Python factor callbacks it triggers are listed separately):",
            markdown_table(["function", "calls", "self [s]", "share", "cumulative [s]"], top),
        ]
    )


def machine_description() -> list[str]:
    """Bullet lines: CPU, cores, memory, OS, load, versions."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    cores = os.cpu_count()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores
    memory = ""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            kib = int(f.readline().split()[1])
        memory = f", {kib / 1024**2:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"

    def version(package: str) -> str:
        try:
            return importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            return "not installed"

    return [
        f"- CPU: {cpu}, {cores} logical cores ({usable} usable by this process){memory}",
        f"- OS: {platform.platform()}",
        f"- load average (1, 5, 15 min) at the start: {load}",
        f"- Python {platform.python_version()} ({platform.python_implementation()}), "
        f"gtsam {version('gtsam')}, numpy {version('numpy')}, "
        f"opencv-python-headless {version('opencv-python-headless')}",
    ]


def performance_markdown(
    timings: Sequence[Timing],
    skipped: Sequence[tuple[str, int]],
    *,
    command: str,
    machine: Sequence[str],
    memory: bool,
    batch_max: int,
    profile: Profile | None,
    elapsed: float,
    chain: tuple[int, Sequence[float]] | None = None,
    sections: Sequence[tuple[str, str]] = (),
) -> str:
    """The whole docs/performance.md (``sections``: (title, Markdown) appended)."""
    parts = [
        "# Performance",
        "",
        f"Generated by `{command}` in {elapsed:.0f} s (experiments/benchmark.py; its module "
        "docstring describes every measurement).",
        "",
        "## Machine",
        "",
        *machine,
        "",
        "## Speed and memory",
        "",
        "The paper's noisy scenario (4 points, 0.05 px² pixel noise, 30 fps; periodic, so long "
        "sequences are longer durations). The front end runs once per length; its measurements "
        "are fed to every estimator, one after the other.",
        "",
        "Every estimator runs as the command line runs it, `run(frames)`, on consecutive "
        "blocks of 100 frames (each run goes on where the last stopped: the same estimates "
        "as one run), each frame timed as its share of its block; the tight smoother's "
        "`update` calls one by one.",
        "",
        f"- **frames/s**: frames / the whole `run` (every frame, the final "
        "`trajectory()`, and the smoothers' process-noise fit before the first frame), wall time; "
        "**CPU**: CPU seconds of the whole run (`time.process_time`, all threads; steadier "
        "than wall time when other processes load the machine); "
        f"**first / last {WINDOW}**: mean wall time of the first and the last {WINDOW} "
        "frames, and their ratio "
        "(1 = constant cost per frame); "
        f"**last/first {WINDOW}, CPU**: the same ratio in CPU time per call.",
        "- **fit + trajectory()**: the time `run` spends outside its frames: the smoothers' "
        "maximum-likelihood fit of the process noise on the whole sequence, and the final call "
        "that returns the smoothed trajectory. The batch solver, the default smoother and "
        "the tight graph solve the whole graph there (batch: one Levenberg-Marquardt solve "
        "from the raw measurements; the default smoother and tight: in chunks from their "
        "window's estimates, below); their frames only add factors (and, for the "
        "default smoother and tight, update the window).",
    ]
    if memory:
        parts.append(
            "- **peak memory**: growth of the resident set while the component runs; every row "
            "runs once, in a fresh subprocess that measures both its time and this: VmHWM "
            "(/proc/self/status, = `getrusage` ru_maxrss on Linux) "
            "after the run minus VmRSS before it, with the peak reset (/proc/self/clear_refs) "
            "once the inputs are loaded. Includes GTSAM's C++ allocations (tracemalloc sees only "
            "Python's) and the interpreter's own growth."
        )
    if any(component == "batch" for component, _ in skipped):
        parts.append(
            f"- **batch LM** is skipped above {batch_max:,} frames (`--batch-max-frames`): each "
            "Levenberg-Marquardt iteration re-linearizes every factor (Python callbacks for the "
            "custom factors) and factorizes the whole graph."
        )
    if any(component == "tight" for component, _ in skipped):
        limit = max(n for component, n in skipped if component == "tight")
        parts.append(f"- **tight** is skipped at {limit:,} frames (above `--tight-max-frames`).")
    parts += ["", results_table(timings, skipped, memory)]
    if any(t.component != "frontend" for t in timings):
        parts += [
            "",
            "## Cost per frame along the sequence",
            "",
            f"Mean CPU time per frame [ms] (`time.process_time` around each block or call: "
            "other processes on the machine change the wall time of a call, not its CPU time) in "
            f"each of {CURVE_PARTS} equal parts of the longest run of every estimator (the final "
            "`trajectory()` not included; it is in the table above). A flat row is a cost per "
            "frame that does not grow with the length of the sequence.",
            "",
            curve_section(timings),
        ]
    for title, text in sections:
        parts += ["", f"## {title}", "", text]
    if chain is not None:
        parts += ["", "## Why the default smoother keeps a window", "", chain_section(*chain)]
    if any(t.component.startswith("isam2") for t in timings):
        parts += ["", "## How the default smoother keeps long runs in bounded memory", ""]
        parts += [MEMORY_SECTION]
    if profile is not None:
        title = COMPONENTS[profile.component]
        parts += ["", f"## Where the time goes ({title})", "", profile_section(profile)]
    return "\n".join(parts) + "\n"


# -- command line -----------------------------------------------------------------------------


def _progress(message: str) -> None:
    print(f"[benchmark] {message}", file=sys.stderr, flush=True)


def _positive_sizes(sizes: Sequence[int]) -> list[int]:
    for n in sizes:
        if n < 2 * WINDOW:
            raise InputError(
                f"--sizes: expected lengths >= {2 * WINDOW} frames (first and last {WINDOW} are "
                f"compared), got {n}"
            )
    return sorted(set(sizes))


def _fastest(name: str, frames: Sequence[FrameMeasurement], repeat: int) -> Timing:
    """The fastest of ``repeat`` timed runs in this process (the one least disturbed by
    other load)."""
    best = None
    for _ in range(repeat):
        gc.collect()
        timing = run_estimator(name, frames)
        if best is None or timing.total < best.total:
            best = timing
    assert best is not None
    return best


def _fastest_subprocess(
    name: str, inputs: Path, repeat: int, frames_out: Path | None = None
) -> Timing | None:
    """The fastest of ``repeat`` runs, each in a fresh process with its peak memory."""
    best = None
    for _ in range(repeat):
        timing = timed_in_subprocess(name, inputs, frames_out)
        if timing is not None and (best is None or timing.total < best.total):
            best = timing
    return best


def _measure_in_process(
    scenario: Scenario, components: Sequence[str], repeat: int
) -> tuple[list[FrameMeasurement], Timing | None]:
    """The front end in this process: its measurements, and its fastest timing when
    it is benchmarked."""
    frames, timing = run_frontend(scenario)
    if "frontend" not in components:
        return frames, None
    for _ in range(repeat - 1):
        again = run_frontend(scenario)[1]
        timing = again if again.total < timing.total else timing
    return frames, timing


def run_sizes(
    sizes: Sequence[int],
    components: Sequence[str],
    args: argparse.Namespace,
    *,
    memory: bool,
    profile_frames: int,
) -> tuple[list[Timing], list[tuple[str, int]], list[FrameMeasurement] | None]:
    """Time every component at every size: (timings, skipped (component, size), the
    measurements of the profile's size when it is one of the sizes).

    With ``memory``, every run (the front end's too) happens once, in a fresh
    subprocess that reports both its timing and its peak memory; the front end's
    subprocess hands its measurements to the estimators' through a file.
    """
    timings: list[Timing] = []
    skipped: list[tuple[str, int]] = []
    profile_input: list[FrameMeasurement] | None = None
    with tempfile.TemporaryDirectory(prefix="hvo_benchmark_") as tmp:
        for n in sizes:
            _progress(f"{n:,} frames: simulating")
            scenario = simulate_frames(n, seed=args.seed, num_points=args.num_points)
            measurements = Path(tmp) / f"measurements_{n}.pickle"
            front: Timing | None = None
            if memory:
                observations = Path(tmp) / f"observations_{n}.pickle"
                observations.write_bytes(pickle.dumps(scenario))
                front = _fastest_subprocess("frontend", observations, args.repeat, measurements)
            if front is None:  # no memory figures, or the subprocess failed
                frames, front = _measure_in_process(scenario, components, args.repeat)
                measurements.write_bytes(pickle.dumps(frames))
                del frames
            results: list[Timing] = []
            if "frontend" in components and front is not None:
                results.append(front)
                _progress(
                    f"{n:,} frames: frontend: {front.total:.2f} s ({front.fps:,.0f} frames/s)"
                )
            del scenario  # 100,000 frames of records are not small
            for name in components:
                if name == "frontend":
                    continue
                if name == "batch" and n > args.batch_max_frames:
                    skipped.append((name, n))
                    _progress(f"{n:,} frames: batch skipped (> --batch-max-frames)")
                    continue
                if name == "tight" and n > args.tight_max_frames:
                    skipped.append((name, n))
                    _progress(f"{n:,} frames: tight skipped (> --tight-max-frames)")
                    continue
                timing = _fastest_subprocess(name, measurements, args.repeat) if memory else None
                if timing is None:
                    frames = pickle.loads(measurements.read_bytes())
                    timing = _fastest(name, frames, args.repeat)
                    del frames
                results.append(timing)
                _progress(
                    f"{n:,} frames: {name}: {timing.total:.2f} s ({timing.fps:,.0f} frames/s)"
                )
            timings += results
            if n == profile_frames:
                profile_input = pickle.loads(measurements.read_bytes())
            measurements.unlink()

    return timings, skipped, profile_input


def _sibling(name: str) -> types.ModuleType:
    """experiments/<name>.py as a module (this folder is not a package)."""
    path = Path(__file__).resolve().parent / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def reference_sections(args: argparse.Namespace) -> list[tuple[str, str]]:
    """Each stage beside its reference, and the end-to-end command-line runs
    (experiments/benchmark_references.py), as (title, Markdown) sections."""
    refs = _sibling("benchmark_references")
    sections = []
    frames = args.reference_frames
    frames = (300 if args.quick else 3000) if frames is None else frames
    if frames:
        _progress(f"references: {frames:,} frames")
        measured = run_frontend(simulate_frames(frames, seed=args.seed))[0]
        pairs = [
            refs.frontend_pair(4, frames, args.seed, args.repeat),
            refs.frontend_pair(20, frames, args.seed, args.repeat),
            refs.kalman_pair(measured, args.repeat),
            refs.fixed_lag_pair(measured, args.repeat),
        ]
        text = "\n\n".join(
            [
                "Each stage on the same inputs as a bare loop doing the same work with only "
                "numpy or GTSAM (experiments/benchmark_references.py describes each); wall "
                "time, the fastest of `--repeat` runs.",
                refs.pairs_section(pairs),
                "What bounds each stage: the front end measures stretches of frames that see "
                "the same tracks with one numpy call per step over all of them (DLT, "
                "Gauss-Newton steps, gate, pose noise, H_c solve), so LAPACK's small SVDs "
                "and solves and, with 6 points or more, OpenCV's RANSAC (one call per "
                "frame the left-out fits do not decide) set its speed; the bare "
                "loop measures one frame at a time and pays "
                "the interpreter's cost per numpy call. The Kalman filter's per-frame work is a "
                "dozen 12 x 12 products and one solve, the same as the plain loop's (Joseph "
                "form and angle wrapping included); its measurements are converted before "
                "the loop and its estimates to the contract's form after it, for all frames "
                "at once. The fixed-lag "
                "smoother pays GTSAM's `IncrementalFixedLagSmoother.update` (relinearization, "
                "re-elimination of the window, marginalization of the frames leaving it) with "
                "twice the variables of the bare chain (a pose and a twist per frame, joined "
                "by GTSAM's 12-dimensional motion factor), and in Python each frame's input "
                "checks (`update` checks one frame alone; `run` checks blocks of frames at "
                "once), factors and estimate.",
            ]
        )
        sections.append(("Each stage beside its reference", text))
    cli = args.cli_frames
    cli = (300 if args.quick else 30000) if cli is None else cli
    long = args.cli_memory_frames
    long = (1000 if args.quick else 100000) if long is None else long
    if cli or long:
        _progress(f"end to end: hvo-graph estimate on {cli:,} and {long:,} frames")
        runs = refs.cli_runs(cli, args.seed) if cli else []
        if long:  # the smoothers' memory on a long sequence
            runs += refs.cli_runs(long, args.seed, ("smoother", "fixed-lag"))
        text = "\n\n".join(
            [
                f"`hvo-graph estimate` on a {cli:,}-frame tracks CSV of the paper's scenario "
                "(written as `hvo-graph simulate` writes it), one fresh process per method, as "
                "a user runs it: reading the CSV, the front end, the estimator and every "
                f"output file; the smoother and the fixed-lag smoother also on {long:,} frames "
                "(their peak memory over a long sequence). Without `--online` the default "
                "smoother runs no online window: its final solve starts from the measurements "
                "(`FactorGraphSmoother.run(frames, online=False)`, the same optimum), and its "
                "frames posed against the world go to the factor store in runs read from the "
                "measurement table's arrays; the fixed-lag smoother still updates once "
                "per frame, but such frames skip the per-frame checks (their numbers are "
                "screened a block at a time). The per-update rows above time both "
                "with every frame through `update`, as a streaming user runs them.",
                refs.cli_section(runs),
            ]
        )
        sections.append(("End to end", text))
    images = args.image_frames
    images = (60 if args.quick else 450) if images is None else images
    if images:
        _progress(f"images: {images:,} rendered 640 x 480 frames")
        stages = _sibling("benchmark_images")
        text = "\n\n".join(
            [
                f"{images:,} rendered 640 x 480 frames of the paper's plane and motion, as PNG "
                "files in a folder (experiments/benchmark_images.py): a bare OpenCV loop "
                "(decode, `goodFeaturesToTrack` with 200 corners, one `calcOpticalFlowPyrLK` "
                "per frame, nothing else), hvo_graph's tracking of the same files (the same "
                "calls plus the forward-backward check, gates, re-identification and keyframe "
                "re-alignment), and `hvo-graph estimate --images` end to end in a fresh "
                "process (its start-up, the imports of numpy, OpenCV and GTSAM, included).",
                stages.images_section(stages.image_stages(images, args.seed)),
            ]
        )
        sections.append(("Images, 640 x 480", text))
    return sections


def build_parser() -> argparse.ArgumentParser:
    """The command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", help="sequence lengths, frames")
    parser.add_argument("--quick", action="store_true", help="300 and 1,000 frames, short profile")
    parser.add_argument(
        "--components",
        nargs="+",
        choices=list(COMPONENTS),
        default=list(DEFAULT_COMPONENTS),
        help="what to benchmark (isam2-cov: ISAM2 with a marginal covariance per frame)",
    )
    parser.add_argument("--batch-max-frames", type=int, default=DEFAULT_BATCH_MAX_FRAMES)
    parser.add_argument("--tight-max-frames", type=int, default=DEFAULT_TIGHT_MAX_FRAMES)
    parser.add_argument(
        "--profile-frames",
        type=int,
        help=f"frames of the profile (default {DEFAULT_PROFILE_FRAMES}, --quick 300, 0 none)",
    )
    parser.add_argument(
        "--profile-component",
        choices=[c for c in COMPONENTS if c != "frontend"],
        default="isam2",
        help="estimator to profile (default isam2)",
    )
    parser.add_argument("--no-memory", action="store_true", help="skip the memory subprocesses")
    parser.add_argument(
        "--chain-poses",
        type=int,
        help=f"poses of the bare ISAM2 chain (default {DEFAULT_CHAIN_POSES:,}, --quick "
        f"{QUICK_CHAIN_POSES:,}, 0 none)",
    )
    parser.add_argument(
        "--reference-frames",
        type=int,
        help="frames of each stage beside its reference (default 3,000, --quick 300, 0 none)",
    )
    parser.add_argument(
        "--cli-frames",
        type=int,
        help="frames of the end-to-end hvo-graph estimate runs (default 30,000, --quick "
        "300, 0 none)",
    )
    parser.add_argument(
        "--cli-memory-frames",
        type=int,
        help="frames of the end-to-end runs of the smoother and the fixed-lag smoother on a "
        "long sequence (default 100,000, --quick 1,000, 0 none)",
    )
    parser.add_argument(
        "--image-frames",
        type=int,
        help="rendered 640 x 480 frames of the images path (default 450, --quick 60, 0 none)",
    )
    parser.add_argument("--repeat", type=int, default=1, help="keep the fastest of N timed runs")
    parser.add_argument("--seed", type=int, default=0, help="pixel-noise seed")
    parser.add_argument("--num-points", type=int, default=4, help="plane points (default 4)")
    parser.add_argument("--out", type=Path, default=Path("docs/performance.md"))
    parser.add_argument(
        "--worker", nargs="+", metavar="COMPONENT INPUTS [FRAMES_OUT]", help=argparse.SUPPRESS
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Command line; see the module docstring. Returns the exit code."""
    args = build_parser().parse_args(argv)

    if args.worker is not None:
        component, inputs, *frames_out = args.worker
        out = Path(frames_out[0]) if frames_out else None
        print(json.dumps(component_worker(component, Path(inputs), out)))
        return 0

    started = time.perf_counter()
    command = "python experiments/benchmark.py" + (
        " " + shlex.join(sys.argv[1:] if argv is None else list(argv))
        if (sys.argv[1:] if argv is None else argv)
        else ""
    )
    try:
        sizes = _positive_sizes(args.sizes or (QUICK_SIZES if args.quick else DEFAULT_SIZES))
        if args.repeat < 1:
            raise InputError(f"--repeat: expected an integer >= 1, got {args.repeat}")
        profile_frames = args.profile_frames
        if profile_frames is None:
            profile_frames = 300 if args.quick else DEFAULT_PROFILE_FRAMES
        if profile_frames < 0:
            raise InputError(f"--profile-frames: expected >= 0, got {profile_frames}")
        chain_poses = args.chain_poses
        if chain_poses is None:
            chain_poses = QUICK_CHAIN_POSES if args.quick else DEFAULT_CHAIN_POSES
        if chain_poses != 0 and chain_poses < 10:
            raise InputError(f"--chain-poses: expected 0 or >= 10, got {chain_poses}")
    except InputError as error:
        print(f"benchmark: error: {error}", file=sys.stderr)
        return 2
    components = [c for c in COMPONENTS if c in args.components]
    memory = not args.no_memory
    machine = machine_description()

    timings, skipped, profile_input = run_sizes(
        sizes, components, args, memory=memory, profile_frames=profile_frames
    )

    profile = None
    if profile_frames:
        if profile_input is None:
            _progress(f"profile: measuring {profile_frames:,} frames")
            profile_input = run_frontend(
                simulate_frames(profile_frames, seed=args.seed, num_points=args.num_points)
            )[0]
        _progress(f"profile: {args.profile_component} on {profile_frames:,} frames")
        profile = profile_component(profile_input, args.profile_component)

    chain = None
    if chain_poses:
        _progress(f"bare ISAM2 chain: {chain_poses:,} poses")
        chain = (chain_poses, chain_growth(chain_poses))

    sections = reference_sections(args)
    table = results_table(timings, skipped, memory)
    print(table)
    if any(t.component != "frontend" for t in timings):
        print()
        print(curve_section(timings))
    if profile is not None:
        print()
        print(profile_section(profile))
    text = performance_markdown(
        timings,
        skipped,
        command=command,
        machine=machine,
        memory=memory,
        batch_max=args.batch_max_frames,
        profile=profile,
        elapsed=time.perf_counter() - started,
        chain=chain,
        sections=sections,
    )
    write_text_atomic(args.out, text)
    _progress(f"wrote {args.out} in {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
