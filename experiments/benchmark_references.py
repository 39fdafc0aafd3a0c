"""References for experiments/benchmark.py: each stage beside what its libraries allow.

- **front end**: hvo_graph's ``MeasurementFrontEnd`` against a bare numpy loop over the
  same observations doing the same mathematics per frame (pixels to normalized
  coordinates, with 6 points or more OpenCV's RANSAC homography where the front end
  calls it (where the points beyond the threshold from the DLT of the others do not
  settle the inliers: the library's own test), normalized DLT by SVD on its inliers,
  the known-normal pose,
  three Gauss-Newton steps on the transfer error, its covariance, and the H_c velocity
  by linear least squares) with none of the library's checks, bookkeeping, gates or
  records; at 4 points (the paper's scenario) and at 20 points.
- **Kalman filter**: ``KalmanBaseline.run`` against a plain numpy 12-state loop
  (x = F x, P = F P F^T + Q; S = P + R, K = P S^-1, x += K (z - x),
  P = (I - K) P) over the same measurements as plain arrays.
- **fixed-lag smoother**: the smoother against a bare GTSAM
  ``IncrementalFixedLagSmoother`` (the same window) over a chain of ``Pose3`` priors
  and between factors, one update per frame: GTSAM's own per-update cost.
- **end to end**: ``hvo-graph estimate`` as a user runs it, in a fresh process on a
  tracks CSV written by ``hvo-graph simulate``: reading, front end, estimator and
  every output file.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import gtsam
import numpy as np

from hvo_graph.frontend import FrontEndConfig, MeasurementFrontEnd
from hvo_graph.geometry._consensus import consensus_inliers
from hvo_graph.pipeline import make_estimator
from hvo_graph.report.tables import markdown_table
from hvo_graph.sim.scenario import Scenario, paper_scenario, simulate, write_scenario
from hvo_graph.types import FrameMeasurement

FPS = 30.0
#: Methods run end to end through the command line.
CLI_METHODS: tuple[str, ...] = ("smoother", "fixed-lag", "kalman")


@dataclass
class Pair:
    """One stage beside its reference: frames per second of each (CPU and wall)."""

    stage: str
    frames: int
    fps: float
    reference: str
    reference_fps: float


@dataclass
class CliRun:
    """One ``hvo-graph estimate`` run: wall and CPU seconds, the process's peak resident set
    (``ru_maxrss``, MiB, the whole process: interpreter and libraries included)."""

    method: str
    frames: int
    wall_s: float
    cpu_s: float
    peak_mib: float
    returncode: int


def _wall(run: object) -> float:
    start = time.perf_counter()
    run()  # type: ignore[operator]
    return time.perf_counter() - start


def _best(run: object, repeat: int) -> float:
    return min(_wall(run) for _ in range(repeat))


# -- front end ---------------------------------------------------------------------------------


def bare_frontend(scenario: Scenario) -> list[tuple[np.ndarray, np.ndarray]]:
    """The front end's mathematics per frame in a bare numpy loop (see the module
    docstring): (R_wc, p_wc) pose and [w; v] twist per frame, nothing else."""
    camera, plane = scenario.camera, scenario.plane
    n, d = plane.normal, plane.distance
    f = np.array([camera.fx, camera.fy])
    c = np.array([camera.cx, camera.cy])
    sigma2 = (scenario.pixel_sigma / camera.mean_focal) ** 2
    first = scenario.observations[0]
    m_ref = np.column_stack(((first.uv - c) / f, np.ones(len(first.uv))))
    X_star = d * m_ref / (m_ref @ n)[:, None]
    basis = np.linalg.svd(n[None, :])[2][1:]
    N = len(m_ref)
    A = np.zeros((2 * N, 9))
    A[0::2, 3:6] = -m_ref
    A[1::2, 0:3] = m_ref
    # The front end's RANSAC from 6 points: 5 pixel sigmas (at least 0.5 px) in
    # normalized units, OpenCV's default iterations and confidence, on the frames the
    # left-out fits do not decide.
    ransac = N >= 6
    threshold = max(5.0 * scenario.pixel_sigma, 0.5) / camera.mean_focal
    out = []
    previous = m_ref
    dt = 1.0 / FPS
    for obs in scenario.observations:
        m = np.column_stack(((obs.uv - c) / f, np.ones(N)))
        A[0::2, 6:9] = m[:, 1:2] * m_ref
        A[1::2, 6:9] = -m[:, 0:1] * m_ref
        rows = A
        if ransac:
            inliers, decided = consensus_inliers(m_ref, m[None], threshold)
            mask = inliers[0]
            if not decided[0]:
                mask = cv2.findHomography(m_ref[:, :2], m[:, :2], cv2.RANSAC, threshold)[1]
                mask = mask.ravel().astype(bool)
            if not mask.all():
                rows = A[np.repeat(mask, 2)]
        H = np.linalg.svd(rows)[2][-1].reshape(3, 3)
        s = np.linalg.svd(H, compute_uv=False)
        H = H / (s[1] if np.sum(m * (m_ref @ H.T)) > 0 else -s[1])
        U, _, Vt = np.linalg.svd((H @ basis.T) @ basis)
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        T = d * (H @ n - R @ n)
        for _ in range(3):  # Gauss-Newton on the transfer error, image Jacobian in closed form
            X = X_star @ R.T + T
            iz = 1.0 / X[:, 2]
            u, v = X[:, 0] * iz, X[:, 1] * iz
            J = np.empty((N, 2, 6))
            J[:, 0, :] = np.column_stack((u * v, -(1 + u * u), v, -iz, 0 * iz, u * iz))
            J[:, 1, :] = np.column_stack((1 + v * v, -u * v, -u, 0 * iz, -iz, v * iz))
            J = J.reshape(-1, 6)
            r = (m[:, :2] - np.column_stack((u, v))).ravel()
            delta = np.linalg.solve(J.T @ J, J.T @ r)
            pose = gtsam.Pose3(gtsam.Rot3(R.T), -R.T @ T).retract(delta)
            R = pose.rotation().matrix().T
            T = -R @ pose.translation()
        covariance = sigma2 * np.linalg.inv(J.T @ J)
        mid = 0.5 * (m + previous)
        flow = ((m - previous) / dt)[:, :2].ravel()
        x, y = mid[:, 0], mid[:, 1]
        depth = mid @ (R @ n)
        B = np.zeros((2 * N, 6))
        B[0::2, :3] = np.column_stack((x * y, -(1 + x * x), y))
        B[1::2, :3] = np.column_stack((1 + y * y, -x * y, -x))
        B[0::2, 3:] = depth[:, None] * np.column_stack((np.ones(N), 0 * x, -x))
        B[1::2, 3:] = depth[:, None] * np.column_stack((0 * x, np.ones(N), -y))
        twist = np.linalg.lstsq(B, flow, rcond=None)[0]
        twist_covariance = 2 * sigma2 / dt**2 * np.linalg.inv(B.T @ B)
        out.append((R.T, covariance, twist, twist_covariance))
        previous = m
    return out


def frontend_pair(points: int, frames: int, seed: int, repeat: int) -> Pair:
    """The front end and the bare loop on the paper's scenario with ``points`` points."""
    scenario = simulate(
        paper_scenario(noisy=True, seed=seed, duration=(frames - 1) / FPS, num_points=points)
    )

    def ours() -> None:
        front = MeasurementFrontEnd(
            scenario.camera, scenario.plane, FrontEndConfig(pixel_sigma=scenario.pixel_sigma)
        )
        front.process_all(scenario.observations)  # as the command line measures

    n = len(scenario.observations)
    return Pair(
        f"front end, {points} points",
        n,
        n / _best(ours, repeat),
        "bare numpy loop, same mathematics"
        + (" (RANSAC where the left-out fits do not decide)" if points >= 6 else ""),
        n / _best(lambda: bare_frontend(scenario), repeat),
    )


# -- Kalman filter -----------------------------------------------------------------------------


def bare_kalman(t: np.ndarray, z: np.ndarray, R_diag: np.ndarray, q: np.ndarray) -> np.ndarray:
    """A plain numpy 12-state Kalman filter, every state measured: (K, 12) estimates."""
    x, P, eye = np.zeros(12), np.eye(12), np.eye(12)
    R = np.diag(R_diag)
    out = np.empty((len(t), 12))
    for k in range(len(t)):
        if k:
            dt = t[k] - t[k - 1]
            F = np.eye(12)
            F[:6, 6:] = dt * eye[:6, :6]
            Q = np.diag(np.concatenate((q * dt**3 / 3, q * dt)))
            x, P = F @ x, F @ P @ F.T + Q
        K = np.linalg.solve(P + R, P).T
        x = x + K @ (z[k] - x)
        P = (eye - K) @ P
        out[k] = x
    return out


def kalman_pair(frames: list[FrameMeasurement], repeat: int) -> Pair:
    """``KalmanBaseline.run`` and :func:`bare_kalman` on the same measurements."""
    from hvo_graph.estimators.kalman_model import PAPER_R_NOISY

    t = np.array([f.t for f in frames])
    z = np.zeros((len(frames), 12))
    for i, f in enumerate(frames):
        if f.pose is not None:
            z[i, :3] = f.pose.position
        if f.velocity is not None:
            z[i, 6:] = np.concatenate((f.velocity.twist[3:], f.velocity.twist[:3]))
    q = np.full(6, 0.1)
    ours = _best(lambda: make_estimator("kalman", kalman_r="paper-noisy").run(frames), repeat)
    bare = _best(lambda: bare_kalman(t, z, np.asarray(PAPER_R_NOISY), q), repeat)
    n = len(frames)
    return Pair("Kalman filter (paper)", n, n / ours, "plain numpy 12-state loop", n / bare)


# -- fixed-lag smoother ------------------------------------------------------------------------


def bare_fixed_lag(frames: int, lag: float = 1.0) -> None:
    """GTSAM's IncrementalFixedLagSmoother over a Pose3 chain at 30 fps: a prior (the
    measured pose) and a between factor (the motion) per frame, one update each."""
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.001), np.array([0.001, 0.0, 0.0]))
    smoother = gtsam.IncrementalFixedLagSmoother(lag, gtsam.ISAM2Params())
    pose = gtsam.Pose3()
    for k in range(frames):
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(k, pose, noise))
        if k:
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, step, noise))
        values = gtsam.Values()
        values.insert(k, pose)
        smoother.update(graph, values, {k: k / FPS})
        pose = pose.compose(step)


def fixed_lag_pair(frames: list[FrameMeasurement], repeat: int) -> Pair:
    """The fixed-lag smoother's updates (process noise given, no fit) and the bare chain."""

    def ours() -> None:
        smoother = make_estimator("fixed-lag", lag=1.0, acceleration_sigma=(0.05, 0.05))
        for frame in frames:
            smoother.update(frame)

    n = len(frames)
    return Pair(
        "smoother: fixed-lag (1 s), updates",
        n,
        n / _best(ours, repeat),
        "bare GTSAM IncrementalFixedLagSmoother, Pose3 chain",
        n / _best(lambda: bare_fixed_lag(n), repeat),
    )


def pairs_section(pairs: list[Pair]) -> str:
    """Markdown: each stage beside its reference."""
    rows = [
        [
            p.stage,
            f"{p.frames:,}",
            f"{p.fps:,.0f}",
            p.reference,
            f"{p.reference_fps:,.0f}",
            f"{p.reference_fps / p.fps:.1f}",
        ]
        for p in pairs
    ]
    header = ["stage", "frames", "frames/s", "reference", "reference frames/s", "reference / stage"]
    return markdown_table(header, rows)


# -- end to end --------------------------------------------------------------------------------


def cli_runs(frames: int, seed: int, methods: tuple[str, ...] = CLI_METHODS) -> list[CliRun]:
    """``hvo-graph estimate`` on a ``frames``-frame tracks file, one fresh process each."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="hvo_cli_") as tmp:
        folder = Path(tmp) / "sequence"
        scenario = simulate(paper_scenario(noisy=True, seed=seed, duration=(frames - 1) / FPS))
        write_scenario(folder, scenario)
        for method in methods:
            command = [sys.executable, "-m", "hvo_graph", "estimate"]
            command += ["--camera", str(folder / "camera.yaml")]
            command += ["--tracks", str(folder / "tracks.csv"), "--method", method]
            command += ["--out", str(Path(tmp) / method)]
            log = Path(tmp) / f"{method}.log"
            usage_file = Path(tmp) / f"{method}.rusage"
            with open(log, "w", encoding="utf-8") as output:
                start = time.perf_counter()
                code = subprocess.call(
                    [sys.executable, "-c", _LAUNCHER, str(usage_file), *command],
                    stdout=output,
                    stderr=subprocess.STDOUT,
                )
                wall = time.perf_counter() - start
            if code != 0:
                print(log.read_text(encoding="utf-8")[-500:], file=sys.stderr)
            cpu, peak_kib = (float(v) for v in usage_file.read_text().split())
            runs.append(CliRun(method, frames, wall, cpu, peak_kib / 1024.0, code))
    return runs


# A process forked from this one starts with this one's peak resident set on Linux (exec
# keeps the old address space's high-water mark in ru_maxrss), and this process holds
# the simulated sequence: a small launcher forks the command instead, and writes the
# command's own CPU seconds and peak resident set (KiB) from wait4.
_LAUNCHER = """
import os, subprocess, sys
process = subprocess.Popen(sys.argv[2:])
_, status, usage = os.wait4(process.pid, 0)
with open(sys.argv[1], "w") as out:
    out.write(f"{usage.ru_utime + usage.ru_stime} {usage.ru_maxrss}")
sys.exit(os.waitstatus_to_exitcode(status))
"""


def cli_section(runs: list[CliRun]) -> str:
    """Markdown: the end-to-end command-line runs."""
    rows = [
        [
            f"`hvo-graph estimate --method {r.method}`",
            f"{r.frames:,}",
            f"{r.wall_s:.1f}" if r.returncode == 0 else f"failed ({r.returncode})",
            f"{r.cpu_s:.1f}",
            f"{r.frames / r.wall_s:,.0f}",
            f"{r.peak_mib:.0f}",
        ]
        for r in runs
    ]
    header = ["command", "frames", "wall [s]", "CPU [s]", "frames/s", "peak memory [MiB]"]
    return markdown_table(header, rows)
