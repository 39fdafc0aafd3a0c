"""Speed of the factor-graph smoother (issue 4 benchmark; not a test).

Measures frames per second of ``FactorGraphSmoother`` with the ISAM2 and the
fixed-lag (1 s) solvers on long synthetic sequences, the mean time of the
first and last 100 updates, and (``--profile``) where the time goes.

The measurements are synthetic but at the paper's scale: ground truth from the
paper scenario's motion (hvo_graph.simulation, periodic, so any length stays
realistic), plus Gaussian noise drawn with the full covariances the front end
reports on the paper's noisy run (frame 150: pose sigma ~1.6 cm / 0.45 deg,
twist sigma ~0.5 m/s / 0.24 rad/s in the worst axes). Measurement generation
is outside the timing.

Usage::

    .venv/bin/python experiments/smoother_speed.py                 # 3,000 and 30,000 frames
    .venv/bin/python experiments/smoother_speed.py --frames 3000 --profile isam2
    .venv/bin/python experiments/smoother_speed.py --repeat 3      # best of 3 runs
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time

import gtsam
import numpy as np

from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.frontend import measure_sequence
from hvo_graph.simulation import body_twist, integrate_poses, paper_scenario, simulate
from hvo_graph.types import FrameMeasurement, PoseMeasurement, VelocityMeasurement


def paper_covariances() -> tuple[np.ndarray, np.ndarray]:
    """The front end's pose and twist covariances at frame 150 of the paper's noisy run."""
    scenario = simulate(paper_scenario(noisy=True, seed=0, duration=5.0))
    frame = measure_sequence(
        scenario.observations, scenario.camera, scenario.plane, pixel_sigma=scenario.pixel_sigma
    )[150]
    assert frame.pose is not None and frame.velocity is not None
    return frame.pose.covariance, frame.velocity.covariance


def synthetic_frames(n: int, seed: int = 0) -> list[FrameMeasurement]:
    """n frames at 30 fps: ground truth + noise with the paper-scale covariances."""
    config = paper_scenario(noisy=True, duration=(n - 1) / 30.0)
    t = np.arange(n) / config.fps
    rotations, positions = integrate_poses(config, t)
    pose_cov, twist_cov = paper_covariances()
    rng = np.random.default_rng(seed)
    pose_noise = rng.multivariate_normal(np.zeros(6), pose_cov, size=n)
    twist_noise = rng.multivariate_normal(np.zeros(6), twist_cov, size=n)
    mid_twists = body_twist(config, t - 0.5 / config.fps)
    frames = []
    for k in range(n):
        truth = gtsam.Pose3(gtsam.Rot3(rotations[k]), positions[k])
        noisy = truth.retract(pose_noise[k]) if k > 0 else truth
        pose = PoseMeasurement(noisy.rotation().matrix(), noisy.translation(), pose_cov, 0)
        velocity = None
        if k > 0:
            velocity = VelocityMeasurement(
                mid_twists[k] + twist_noise[k], twist_cov, t[k] - 0.5 / config.fps, 1.0 / config.fps
            )
        frames.append(FrameMeasurement(k, float(t[k]), pose, velocity, num_points=4))
    return frames


def tree_nnz_time(frames: list[FrameMeasurement]) -> float:
    """Seconds of one ``ISAM2.treeNnz()`` after ISAM2 has taken every frame.

    GTSAM 4.3's ISAM2::update calls treeNnz() (a walk over the whole Bayes tree,
    for its adaptive-reordering bookkeeping) unconditionally at the end of every
    update: the part of an ISAM2 update that grows with the sequence length.
    """
    estimator = FactorGraphSmoother(solver="isam2")
    for frame in frames:
        estimator.update(frame)
    isam = estimator._isam
    assert isam is not None
    start = time.perf_counter()
    for _ in range(20):
        isam.treeNnz()
    return (time.perf_counter() - start) / 20


def run(frames: list[FrameMeasurement], solver: str, **options: object) -> np.ndarray:
    """(K, 2) per-update wall and CPU times (seconds) of one pass over ``frames``.

    CPU time (this process only) is reported beside wall time because the
    machine is shared: other processes inflate wall time, not CPU time.
    """
    estimator = FactorGraphSmoother(solver=solver, **options)  # type: ignore[arg-type]
    times = np.empty((len(frames), 2))
    wall, cpu = time.perf_counter, time.process_time
    for i, frame in enumerate(frames):
        w0, c0 = wall(), cpu()
        estimator.update(frame)
        times[i] = wall() - w0, cpu() - c0
    return times


def report(label: str, times: np.ndarray) -> None:
    """One line: frames/s, mean time of the first and last 100 updates (wall; CPU)."""
    parts = []
    for j, clock in enumerate(("wall", "cpu")):
        t = times[:, j]
        first, last = t[:100].mean(), t[-100:].mean()
        parts.append(
            f"{clock} {len(t) / t.sum():6.0f} frames/s, first/last 100 "
            f"{1e3 * first:.3f}/{1e3 * last:.3f} ms (x{last / first:.2f})"
        )
    print(f"{label:28s} " + " | ".join(parts), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="*", default=[3000, 30000])
    parser.add_argument("--repeat", type=int, default=1, help="keep the fastest of N runs")
    parser.add_argument("--profile", choices=["isam2", "fixed-lag"], default=None)
    parser.add_argument("--covariance", action="store_true", help="compute_covariance=True too")
    args = parser.parse_args()

    for n in args.frames:
        frames = synthetic_frames(n)
        for solver in ("isam2", "fixed-lag"):
            runs = [run(frames, solver) for _ in range(args.repeat)]
            report(f"{solver} {n} frames", min(runs, key=lambda r: r[:, 0].sum()))
            if solver == "isam2":
                nnz_ms = 1e3 * tree_nnz_time(frames)
                print(f"{'':28s} ISAM2.treeNnz() after {n} frames: {nnz_ms:.3f} ms")
            if args.covariance:
                runs = [run(frames, solver, compute_covariance=True) for _ in range(args.repeat)]
                report(f"{solver} {n} frames + covariance", min(runs, key=lambda r: r[:, 0].sum()))

    if args.profile is not None:
        frames = synthetic_frames(args.frames[0])
        profiler = cProfile.Profile()
        profiler.enable()
        run(frames, args.profile)
        profiler.disable()
        out = io.StringIO()
        pstats.Stats(profiler, stream=out).sort_stats("tottime").print_stats(18)
        print(out.getvalue())


if __name__ == "__main__":
    main()
