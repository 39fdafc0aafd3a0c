"""Sensitivity of the smoother to its white-noise-acceleration strength (docs/smoother.md).

Runs the ISAM2 smoother on the paper's noisy scenario (0.05 px^2) for a grid of
``acceleration_sigma = (s_w, s_v)`` and prints the RMSE (after the first
second) of the smoothed and of the online estimates, pooled over seeds
(sqrt of the mean squared per-seed RMSE). The default was chosen by a rule
(q = a_max^2 dt, docs/smoother.md), not by this grid; the grid shows how far
it is from the best values, on seeds 0-9 and on held-out seeds 10-19.

Usage::

    .venv/bin/python experiments/smoother_tuning.py               # grid, seeds 0-9
    .venv/bin/python experiments/smoother_tuning.py --seeds 10 20 --default-only
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from hvo_graph.estimators.process_noise import DEFAULT_ACCELERATION_SIGMA
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.frontend import measure_sequence
from hvo_graph.sim.scenario import paper_scenario, simulate

GRID = (0.02, 0.03, 0.05, 0.1, 0.2, 0.4)


def rmse_row(trajectory, groundtruth) -> list[float]:
    s = summarize(error_series(trajectory, groundtruth), t_start=1.0)
    return [s.position_rmse, s.orientation_rmse, s.linear_velocity_rmse, s.angular_velocity_rmse]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs=2, default=[0, 10], metavar=("FIRST", "STOP"))
    parser.add_argument(
        "--default-only", action="store_true", help="only the default and 4 neighbours"
    )
    args = parser.parse_args()

    data = []
    for seed in range(*args.seeds):
        scenario = simulate(paper_scenario(noisy=True, seed=seed))
        frames = measure_sequence(
            scenario.observations, scenario.camera, scenario.plane, pixel_sigma=scenario.pixel_sigma
        )
        data.append((frames, scenario.groundtruth))

    s_w, s_v = DEFAULT_ACCELERATION_SIGMA
    if args.default_only:
        configs = [(s_w, s_v), (s_w / 2, s_v), (2 * s_w, s_v), (s_w, s_v / 2), (s_w, 2 * s_v)]
    else:
        configs = [(s_w, s_v), *itertools.product(GRID, GRID)]
    print(f"seeds {args.seeds[0]}..{args.seeds[1] - 1}; RMSE after 1 s, pooled over seeds")
    print(
        f"{'s_w':>6} {'s_v':>6} | smoothed: {'pos m':>7} {'deg':>6} {'v m/s':>7} {'w rad/s':>7}"
        f" | online: {'pos m':>7} {'deg':>6} {'v m/s':>7} {'w rad/s':>7}"
    )
    for sigma in configs:
        smoothed, online = [], []
        for frames, groundtruth in data:
            smoother = FactorGraphSmoother(acceleration_sigma=sigma)
            smoothed.append(rmse_row(smoother.run(frames), groundtruth))
            online.append(rmse_row(smoother.online_trajectory(), groundtruth))
        a = np.sqrt(np.mean(np.square(smoothed), axis=0))
        b = np.sqrt(np.mean(np.square(online), axis=0))
        mark = "  (default)" if sigma == (s_w, s_v) else ""
        print(
            f"{sigma[0]:6.3f} {sigma[1]:6.3f} |           {a[0]:7.4f} {a[1]:6.3f} {a[2]:7.4f} "
            f"{a[3]:7.4f} |         {b[0]:7.4f} {b[1]:6.3f} {b[2]:7.4f} {b[3]:7.4f}{mark}",
            flush=True,
        )


if __name__ == "__main__":
    main()
