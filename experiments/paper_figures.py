"""The paper's Figures 3-10, redrawn for the Kalman baseline and the factor-graph smoother.

Tick, Shen and Gans show, for a noise-free run (Figs. 3-6) and a run with
0.05 px^2 pixel noise (Figs. 7-10), the estimated camera position, orientation
(heading), linear velocity and angular velocity against the truth over time
(paper Section IV; paper/NOTES.md section 6). This script simulates the same
two runs (hvo_graph.sim.scenario.paper_scenario), measures them with the
homography front end, and draws, per quantity and run, one figure with three
stacked panels (x, y, z; or roll, pitch, yaw) sharing the time axis:

- truth (dashed);
- the paper's Kalman filter with the paper's R_k for that run ("paper-noise-free"
  or "paper-noisy"), from a random initial state, as in the paper;
- the ISAM2 smoother's online estimate (each frame right after its own update:
  causal, comparable with the filter) and its smoothed estimate (the final one);
- the raw per-frame measurements from H_d and H_c as faint dots (velocities at
  their mid-interval times).

Legends give each estimate's RMSE after the first second (hvo_graph.eval.metrics:
norm of the position / velocity error, rotation angle for orientation).
Orientation is shown as the paper's Euler angles, roll r, pitch p, yaw w with
R_wc = R_y(w) R_x(p) R_z(r) (contract), in degrees; velocities are body-frame
(contract sign). Writes PNG and SVG per figure (``fig03_position_noise_free`` ..
``fig10_angular_velocity_noisy``) and ``overview`` (noisy run, position and
angular velocity) for the README.

Usage::

    .venv/bin/python experiments/paper_figures.py --out docs/figures [--seed 0] [--duration 10]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from hvo_graph.errors import InputError
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.geometry.rotation import rotation_to_euler
from hvo_graph.pipeline import make_estimator, measure
from hvo_graph.report.plotting import (
    TRUTH_STYLE,
    figure_style,
    method_style,
    new_figure,
    save_figure,
)
from hvo_graph.sim.scenario import Scenario, paper_scenario, simulate
from hvo_graph.types import FrameMeasurement, Trajectory

#: Size of the per-quantity figures, inches (PNG: 1350 x 1125 px at FIGURE_DPI = 150).
FIGSIZE: tuple[float, float] = (9.0, 7.5)
#: Size of the README overview figure, inches (PNG: 1650 x 975 px).
OVERVIEW_FIGSIZE: tuple[float, float] = (11.0, 6.5)

#: RMSE and the overview use the frames after this time (s): the Kalman filter's
#: random initial state has converged by then (the paper's "quickly").
SETTLE_TIME = 1.0

RUNS: tuple[str, ...] = ("noise_free", "noisy")
RUN_TITLES = {"noise_free": "noise-free run", "noisy": "noisy run (pixel noise 0.05 px²)"}


@dataclass(frozen=True)
class Quantity:
    """One of the paper's plotted quantities.

    Attributes:
        key: file-name part, also the hvo_graph.eval.metrics error behind the legend's RMSE
            (norm of the position / velocity error, rotation angle for orientation).
        title: what the paper's caption calls it.
        unit: axis unit.
        components: labels of the three panels.
    """

    key: str
    title: str
    unit: str
    components: tuple[str, str, str]


QUANTITIES: tuple[Quantity, ...] = (
    Quantity("position", "camera position", "m", ("x", "y", "z")),
    Quantity(
        "orientation",
        "camera orientation (Euler angles)",
        "deg",
        ("roll r", "pitch p", "yaw w"),
    ),
    Quantity(
        "linear_velocity",
        "camera linear velocity (body frame)",
        "m/s",
        ("$v_x$", "$v_y$", "$v_z$"),
    ),
    Quantity(
        "angular_velocity",
        "camera angular velocity (body frame)",
        "rad/s",
        (r"$\omega_x$", r"$\omega_y$", r"$\omega_z$"),
    ),
)

#: The paper's figure number for each (quantity, run): Figs. 3-6 noise-free, 7-10 noisy,
#: each in the order position, orientation, linear velocity, angular velocity.
FIGURE_NUMBERS: dict[tuple[str, str], int] = {
    (q.key, run): 3 + i + 4 * r for r, run in enumerate(RUNS) for i, q in enumerate(QUANTITIES)
}

#: The estimates drawn, in legend order: key of hvo_graph.report.plotting.METHOD_STYLE and label.
ESTIMATES: tuple[tuple[str, str], ...] = (
    ("kalman", "Kalman filter (paper R_k)"),
    ("smoother-online", "smoother, online (ISAM2)"),
    ("smoother", "smoother, smoothed"),
)

#: Per-figure tweaks of the shared style: the online estimate is drawn thinner and the
#: smoothed one thicker, so both stay visible where they overlap the truth.
_LINE = {
    "kalman": {"linewidth": 1.4, "zorder": 2},
    "smoother-online": {"linewidth": 1.1, "zorder": 3},
    "smoother": {"linewidth": 1.7, "zorder": 4},
}


def _style(key: str) -> dict[str, object]:
    """Axes.plot keywords: truth dashed, estimates solid, raw measurements faint dots."""
    if key == "truth":
        return {**TRUTH_STYLE, "linewidth": 1.4, "zorder": 5, "label": "truth"}
    if key == "measurements":
        colour = method_style("measurements")["color"]
        return {"color": colour, "linestyle": "none", "marker": ".", "markersize": 3, "alpha": 0.6}
    style = {**method_style(key), "linestyle": "-", **_LINE[key]}
    del style["label"]  # the legend labels say which R_k the filter used in this run
    return style


@dataclass
class RunResult:
    """One simulated run and everything drawn from it.

    Attributes:
        run: "noise_free" or "noisy".
        scenario: the simulation (ground truth in ``scenario.groundtruth``).
        frames: the front end's per-frame measurements.
        estimates: trajectories by key of :data:`ESTIMATES`.
    """

    run: str
    scenario: Scenario
    frames: list[FrameMeasurement]
    estimates: dict[str, Trajectory]


def run_case(run: str, *, seed: int = 0, duration: float = 10.0) -> RunResult:
    """Simulate one of the paper's runs and estimate it with the Kalman filter and the smoother.

    Args:
        run: "noise_free" (paper Figs. 3-6) or "noisy" (Figs. 7-10).
        seed: pixel-noise seed, also the Kalman filter's random initial state.
        duration: seconds simulated (30 fps).
    Raises:
        InputError: for an unknown run or a bad duration/seed.
    """
    if run not in RUNS:
        raise InputError(f"run: expected one of {', '.join(RUNS)}, got {run!r}")
    scenario = simulate(paper_scenario(noisy=run == "noisy", seed=seed, duration=duration))
    frames = measure(scenario.observations, scenario)
    kalman = make_estimator("kalman", seed=seed, kalman_r=f"paper-{run.replace('_', '-')}")
    smoother = make_estimator("smoother")
    smoothed = smoother.run(frames)
    return RunResult(
        run=run,
        scenario=scenario,
        frames=frames,
        estimates={
            "kalman": kalman.run(frames),
            "smoother-online": smoother.online_trajectory(),
            "smoother": smoothed,
        },
    )


def euler_degrees(rotations: np.ndarray) -> np.ndarray:
    """(K, 3) roll, pitch, yaw in degrees of (K, 3, 3) R_wc, unwrapped along time."""
    angles = np.array([rotation_to_euler(R) for R in rotations]).reshape(-1, 3)
    return np.degrees(np.unwrap(angles, axis=0))


def trajectory_series(trajectory: Trajectory, quantity: str) -> tuple[np.ndarray, np.ndarray]:
    """(t (K,), values (K, 3)) of one quantity of a trajectory, in the figures' units."""
    if quantity == "position":
        values = np.asarray(trajectory.positions)
    elif quantity == "orientation":
        values = euler_degrees(np.asarray(trajectory.rotations))
    elif quantity == "linear_velocity":
        values = trajectory.linear_velocity
    elif quantity == "angular_velocity":
        values = trajectory.angular_velocity
    else:
        raise InputError(f"quantity: expected one of {', '.join(q.key for q in QUANTITIES)}")
    return np.asarray(trajectory.t, dtype=float), np.asarray(values, dtype=float)


def measurement_series(
    frames: Sequence[FrameMeasurement], quantity: str
) -> tuple[np.ndarray, np.ndarray]:
    """(t (M,), values (M, 3)) of the raw measurements of one quantity.

    Poses (H_d) at their frame times; twists (H_c) at their mid-interval times.
    """
    t: list[float] = []
    rows: list[np.ndarray] = []
    for frame in frames:
        if quantity in ("position", "orientation") and frame.pose is not None:
            t.append(frame.t)
            rows.append(
                frame.pose.position
                if quantity == "position"
                else np.asarray(rotation_to_euler(frame.pose.rotation))
            )
        elif quantity in ("linear_velocity", "angular_velocity") and frame.velocity is not None:
            t.append(frame.velocity.t)
            twist = frame.velocity.twist
            rows.append(twist[3:] if quantity == "linear_velocity" else twist[:3])
    values = np.array(rows, dtype=float).reshape(-1, 3)
    if quantity == "orientation" and len(values):
        values = np.degrees(np.unwrap(values, axis=0))
    return np.array(t, dtype=float), values


def rmse_after_settling(result: RunResult, key: str, quantity: Quantity) -> float | None:
    """RMSE of one estimate's error norm (hvo_graph.eval.metrics) after :data:`SETTLE_TIME`."""
    truth = result.scenario.groundtruth
    series = error_series(result.estimates[key], truth)
    if series.t[-1] < truth.t[0] + SETTLE_TIME:
        return None
    summary = summarize(series, t_start=truth.t[0] + SETTLE_TIME)
    return getattr(summary, f"{quantity.key}_rmse")


def _draw_quantity(
    axes: Sequence[Axes], result: RunResult, quantity: Quantity, *, show_measurements: bool
) -> list[str]:
    """Draw truth, measurements and estimates of one quantity into three panels.

    Returns what leaves the axes somewhere: keys of :data:`ESTIMATES` (only possible
    in the first :data:`SETTLE_TIME` seconds, e.g. the Kalman filter's random start)
    and/or "measurements".
    """
    t_true, truth = trajectory_series(result.scenario.groundtruth, quantity.key)
    t_meas, meas = measurement_series(result.frames, quantity.key)
    curves = {key: trajectory_series(result.estimates[key], quantity.key) for key, _ in ESTIMATES}
    settle = t_true[0] + SETTLE_TIME
    # y range per panel: truth and estimates after settling, so that neither the Kalman
    # filter's random start nor the (much noisier) raw velocity measurements flatten the
    # curves; at least a quarter of the widest panel's range, so that a component that is
    # zero in truth (w_x) is not magnified down to numerical noise.
    ranges = []
    for c in range(3):
        shown = np.concatenate([truth[:, c]] + [v[t >= settle, c] for t, v in curves.values()])
        ranges.append((float(np.min(shown)), float(np.max(shown))))
    widest = max(high - low for low, high in ranges)
    notes: set[str] = set()
    for c, ax in enumerate(axes):
        if show_measurements and len(t_meas):
            ax.plot(t_meas, meas[:, c], **_style("measurements"))  # type: ignore[arg-type]
        for key, _ in ESTIMATES:
            t, values = curves[key]
            ax.plot(t, values[:, c], **_style(key))  # type: ignore[arg-type]
        ax.plot(t_true, truth[:, c], **_style("truth"))  # type: ignore[arg-type]
        low, high = ranges[c]
        centre, half = 0.5 * (low + high), 0.5 * max(high - low, 0.25 * widest, 1e-9)
        ylim = (centre - 1.12 * half, centre + 1.12 * half)
        ax.set_ylim(*ylim)
        for what, values in [(key, v[:, c]) for key, (_, v) in curves.items()] + (
            [("measurements", meas[:, c])] if show_measurements else []
        ):
            if values.size and (np.min(values) < ylim[0] or np.max(values) > ylim[1]):
                notes.add(what)
        ax.set_ylabel(f"{quantity.components[c]} [{quantity.unit}]")
        ax.grid(True, color="0.88", linewidth=0.6)
        ax.margins(x=0)
    axes[-1].set_xlabel("time t [s]")
    return sorted(notes)


def _proxy(key: str) -> Line2D:
    """A legend entry drawn like the curves of ``key`` (markers enlarged to be visible)."""
    style = _style(key)
    if style.get("marker"):
        style.update(markersize=8, alpha=0.8)
    return Line2D([], [], **style)  # type: ignore[arg-type]


def _estimate_label(result: RunResult, key: str) -> str:
    """Legend text of an estimate; the Kalman filter's names the run's R_k preset."""
    label = dict(ESTIMATES)[key]
    return (
        label.replace("R_k", f"R_k, {result.run.replace('_', '-')}") if key == "kalman" else label
    )


def _legend_labels(result: RunResult, quantity: Quantity) -> list[str]:
    labels = []
    for key, _ in ESTIMATES:
        label = _estimate_label(result, key)
        rmse = rmse_after_settling(result, key, quantity)
        labels.append(label if rmse is None else f"{label}: RMSE {rmse:.3g} {quantity.unit}")
    return labels


def quantity_figure(result: RunResult, quantity: Quantity) -> Figure:
    """One of the paper's Figures 3-10: three stacked panels sharing the time axis."""
    fig, grid = new_figure(*FIGSIZE, nrows=3, ncols=1, sharex=True)
    axes = grid[:, 0]
    notes = _draw_quantity(axes, result, quantity, show_measurements=True)
    number = FIGURE_NUMBERS[(quantity.key, result.run)]
    fig.suptitle(
        f"Fig. {number} (paper): {quantity.title}, {RUN_TITLES[result.run]}"
        f" (one run, seed {result.scenario.config.seed})",
        fontsize=13,
        fontweight="bold",
    )
    handles = [_proxy(key) for key, _ in ESTIMATES] + [_proxy("measurements"), _proxy("truth")]
    raw = "raw measurement (H_d / H_c)"
    if "measurements" in notes:
        raw += ", some beyond the axes"
    labels = [*_legend_labels(result, quantity), raw, "truth"]
    subtitle = f"RMSE after the first {SETTLE_TIME:g} s (error norm)"
    if "kalman" in notes:
        subtitle += (
            "; the Kalman filter starts from a random state: its first frames leave the axes"
        )
    elif set(notes) - {"measurements"}:
        subtitle += "; some estimates leave the axes in the first second"
    fig.legend(
        handles,
        labels,
        loc="outside lower center",
        ncol=2,
        fontsize=9,
        frameon=False,
        title=subtitle,
        title_fontsize=8.5,
    )
    return fig


def overview_figure(result: RunResult) -> Figure:
    """README figure: position and angular velocity of one run, truth vs Kalman vs smoother."""
    fig, axes = new_figure(*OVERVIEW_FIGSIZE, nrows=3, ncols=2, sharex=True)
    by_key = {q.key: q for q in QUANTITIES}
    labels: list[str] = []
    for column, key in enumerate(("position", "angular_velocity")):
        quantity = by_key[key]
        _draw_quantity(axes[:, column], result, quantity, show_measurements=False)
        axes[0, column].set_title(
            f"{quantity.title} (paper Fig. {FIGURE_NUMBERS[(key, result.run)]})", fontsize=10.5
        )
        labels.append(
            ", ".join(
                f"{short} {rmse:.2g} {quantity.unit}"
                for short, rmse in (
                    ("Kalman", rmse_after_settling(result, "kalman", quantity)),
                    ("smoother", rmse_after_settling(result, "smoother", quantity)),
                )
                if rmse is not None
            )
        )
    fig.suptitle(
        f"hvo_graph on the paper's {RUN_TITLES[result.run]}: smoother vs Kalman filter\n"
        f"one run, seed {result.scenario.config.seed}; means over seeds in docs/results.md",
        fontsize=13,
        fontweight="bold",
    )
    names = [_estimate_label(result, key) for key, _ in ESTIMATES]
    handles = [_proxy(key) for key, _ in ESTIMATES] + [_proxy("truth")]
    rmse = "; ".join(
        f"{q}: {text}" for q, text in zip(("position", "ang. vel."), labels, strict=True)
    )
    fig.legend(
        handles,
        [*names, "truth"],
        loc="outside lower center",
        ncol=4,
        fontsize=9.5,
        frameon=False,
        title=f"RMSE after {SETTLE_TIME:g} s: {rmse}" if all(labels) else None,
        title_fontsize=9,
    )
    return fig


def figure_name(quantity: str, run: str) -> str:
    """File name (without extension) of a paper figure, e.g. ``fig03_position_noise_free``."""
    return f"fig{FIGURE_NUMBERS[(quantity, run)]:02d}_{quantity}_{run}"


def make_figures(
    out: Path, *, seed: int = 0, duration: float = 10.0, overview: bool = True
) -> list[Path]:
    """Run both of the paper's runs and write Figures 3-10 (and the overview) into ``out``.

    Returns:
        The files written (PNG and SVG of each figure).
    """
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for run in RUNS:
        start = time.perf_counter()
        result = run_case(run, seed=seed, duration=duration)
        print(
            f"[paper_figures] {run}: {len(result.frames)} frames simulated and estimated "
            f"in {time.perf_counter() - start:.1f} s",
            file=sys.stderr,
        )
        with figure_style():
            for quantity in QUANTITIES:
                written += save_figure(
                    quantity_figure(result, quantity), out / figure_name(quantity.key, run)
                )
            if overview and run == "noisy":
                written += save_figure(overview_figure(result), out / "overview")
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``paper_figures.py [--out DIR] [--seed N] [--duration S] [--no-overview]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/figures"), help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="pixel noise and Kalman initial state")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds simulated (30 fps)")
    parser.add_argument("--no-overview", action="store_true", help="skip overview.png")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    try:
        written = make_figures(
            args.out, seed=args.seed, duration=args.duration, overview=not args.no_overview
        )
    except InputError as error:
        print(f"paper_figures: error: {error}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    print(
        f"[paper_figures] {len(written)} files in {time.perf_counter() - start:.1f} s",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
