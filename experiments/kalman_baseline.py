"""The paper's Kalman filter on the paper's two simulated runs: RMSE and lag.

Runs the paper's scenario (hvo_graph.sim.scenario.paper_scenario) without noise
(paper R_k "paper-noise-free") and with 0.05 px^2 pixel noise (paper R_k
"paper-noisy"), through the homography front end and the filter
(hvo_graph.estimators.kalman.KalmanBaseline, default Q_k, random initial state),
and prints:

- RMSE and max of position (m), orientation (deg), linear velocity (m/s) and
  angular velocity (rad/s) after the first second, for the filter as the paper
  runs it, for two non-paper variants (``world_frame_velocity``, R from the front
  end's covariances) and for the raw per-frame measurements fed to the filter;
- the lag of each estimate behind the truth, in frames: the shift that maximizes
  the cross-correlation of estimate and truth (after the first second, means
  removed, the three components of a quantity summed), refined to a fraction of a
  frame by a parabola through the peak. Positive = the estimate lags.
- with ``--sweep``: the noisy-run RMSE for a range of Q_k scalars s (all six equal).

Usage::

    .venv/bin/python experiments/kalman_baseline.py [--seed N] [--sweep]
"""

from __future__ import annotations

import argparse

import numpy as np

from hvo_graph.estimators.kalman import KalmanBaseline
from hvo_graph.estimators.measurements import RawMeasurements
from hvo_graph.estimators.process_noise import DEFAULT_PROCESS_NOISE
from hvo_graph.eval.metrics import error_series, format_table, summarize
from hvo_graph.frontend import measure_sequence
from hvo_graph.geometry.rotation import rotation_to_euler
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import Trajectory

MAX_LAG = 45  # frames searched either way (1.5 s; the shortest period is 100 frames)


def components(traj: Trajectory) -> dict[str, np.ndarray]:
    """(K, 3) series per quantity: position, Euler (p, w, r), body v, body w."""
    euler = np.array([rotation_to_euler(R) for R in traj.rotations])[:, [1, 2, 0]]
    return {
        "position": np.asarray(traj.positions),
        "orientation": np.unwrap(euler, axis=0),
        "linear velocity": np.asarray(traj.twists)[:, 3:],
        "angular velocity": np.asarray(traj.twists)[:, :3],
    }


def lag_frames(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Shift tau (frames) maximizing sum_k <e_k, g_{k - tau}> / norms; > 0: estimate lags."""
    e = estimate - estimate.mean(axis=0)
    g = truth - truth.mean(axis=0)
    n = len(e)
    taus = np.arange(-MAX_LAG, MAX_LAG + 1)
    corr = np.empty(len(taus))
    for i, tau in enumerate(taus):
        a = e[max(tau, 0) : n + min(tau, 0)]
        b = g[max(-tau, 0) : n - max(tau, 0)]
        corr[i] = np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b))
    i = int(np.argmax(corr))
    if 0 < i < len(taus) - 1:  # parabola through the peak and its neighbours
        c0, c1, c2 = corr[i - 1 : i + 2]
        denom = c0 - 2 * c1 + c2
        return float(taus[i] + (0.5 * (c0 - c2) / denom if denom != 0 else 0.0))
    return float(taus[i])


def lags(estimate: Trajectory, truth: Trajectory, t_start: float) -> dict[str, float]:
    keep_e, keep_g = estimate.t >= t_start - 1e-9, truth.t >= t_start - 1e-9
    ce, cg = components(estimate), components(truth)
    return {q: lag_frames(ce[q][keep_e], cg[q][keep_g]) for q in ce}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=0, help="pixel noise and initial state seed")
    parser.add_argument("--sweep", action="store_true", help="also sweep the Q_k scalar s")
    args = parser.parse_args()

    print(f"default Q_k scalars s_i = {DEFAULT_PROCESS_NOISE.tolist()}, seed {args.seed}")
    for noisy, preset in ((False, "paper-noise-free"), (True, "paper-noisy")):
        scenario = simulate(paper_scenario(noisy=noisy, seed=args.seed))
        gt, t_start = scenario.groundtruth, scenario.groundtruth.t[0] + 1.0
        # the front end's covariances need sigma > 0; only the "measured" rows use them
        sigma = scenario.pixel_sigma if noisy else 1e-3
        frames = measure_sequence(
            scenario.observations, scenario.camera, scenario.plane, pixel_sigma=sigma
        )
        runs = {
            f"kalman (paper, R {preset})": KalmanBaseline(r_preset=preset, seed=args.seed),
            f"kalman world-velocity, R {preset}": KalmanBaseline(
                r_preset=preset, seed=args.seed, world_frame_velocity=True
            ),
            "kalman R measured": KalmanBaseline(r_preset="measured", seed=args.seed),
        }
        trajectories = {name: kf.run(frames) for name, kf in runs.items()}
        raw = RawMeasurements()
        raw.run(frames)
        trajectories["raw (online: filter input)"] = raw.online_trajectory()
        title = "noisy (0.05 px^2)" if noisy else "noise-free"
        print(f"\n== paper's {title} run: {len(gt)} frames, errors after the first second ==")
        summaries = {
            name: summarize(error_series(traj, gt), t_start=t_start)
            for name, traj in trajectories.items()
        }
        print(format_table(summaries))
        print("\nlag behind the truth, frames (cross-correlation peak; 1 frame = 33.3 ms)")
        names = list(components(gt))
        width = max(len(n) for n in trajectories)
        print(" " * width + "  " + "  ".join(f"{n:>16}" for n in names))
        for name, traj in trajectories.items():
            lag = lags(traj, gt, t_start)
            print(f"{name:<{width}}  " + "  ".join(f"{lag[n]:>16.2f}" for n in names))

        if args.sweep and noisy:
            print("\nQ_k sweep, noisy run, R paper-noisy: RMSE after the first second")
            sweep = {}
            for s in (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1):
                kf = KalmanBaseline(r_preset=preset, seed=args.seed, process_noise=[s] * 6)
                sweep[f"s = {s:g}"] = summarize(error_series(kf.run(frames), gt), t_start=t_start)
            print(format_table(sweep))


if __name__ == "__main__":
    main()
