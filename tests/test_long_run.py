"""Long runs: smoother, fixed-lag and tight graph in bounded memory, at a flat cost per frame.

Shorter than the 100,000 frames of docs/performance.md (experiments/benchmark.py)
but long enough for anything kept per frame to show. Measured without clocks:

- what the solver holds online (ISAM2's variables and factors) is the same in
  the second half of the run as in the first: the cost of an update does not
  grow with the length of the sequence;
- the memory Python allocates per 1,000 frames (``tracemalloc``: every
  Python object and numpy array) is the same in both halves and small, and
  the process's resident set (GTSAM's C++ included) grows by no more than a
  bound per 1,000 frames;
- the default smoother's final solve, in overlapping chunks, equals the batch
  optimum (independent reference: ``BatchSmoother``, one Levenberg-Marquardt
  solve of the whole graph) and is close to the ground truth.
"""

from __future__ import annotations

import gc
import math
import tracemalloc

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import V, X

from hvo_graph.errors import InputError
from hvo_graph.estimators import factor_store
from hvo_graph.estimators.smoother import BatchSmoother, FactorGraphSmoother, FixedLagSmoother
from hvo_graph.estimators.solvers import MARGINALIZATION_BLOCKS, ONLINE_WINDOW
from hvo_graph.sim.scenario import body_twist, integrate_poses, paper_scenario
from hvo_graph.types import FrameMeasurement, PoseMeasurement, VelocityMeasurement

FPS = 30.0
FRAMES = 5000
#: Fixed process noise: no maximum-likelihood fit (not what is measured here).
SIGMA = (0.5, 0.5)
POSE_SIGMAS = np.array([0.01, 0.01, 0.003, 0.01, 0.01, 0.003])
TWIST_SIGMAS = np.array([0.1, 0.1, 0.03, 0.2, 0.2, 0.05])


def noisy_frames(n: int, seed: int = 3) -> tuple[list[FrameMeasurement], np.ndarray]:
    """The paper scenario's motion, n frames at 30 fps, measured with Gaussian noise
    (diagonal covariances); and the true positions (n, 3)."""
    config = paper_scenario(noisy=False, duration=(n - 1) / FPS)
    t = np.arange(n) / FPS
    R, p = integrate_poses(config, t)
    mid = body_twist(config, t - 0.5 / FPS)
    rng = np.random.default_rng(seed)
    pose_noise = rng.normal(size=(n, 6)) * POSE_SIGMAS
    twist_noise = rng.normal(size=(n, 6)) * TWIST_SIGMAS
    pose_cov, twist_cov = np.diag(POSE_SIGMAS**2), np.diag(TWIST_SIGMAS**2)
    frames = []
    for k in range(n):
        T = gtsam.Pose3(gtsam.Rot3(R[k]), p[k])
        if k > 0:
            T = T.retract(pose_noise[k])
        pose = PoseMeasurement(T.rotation().matrix(), T.translation(), pose_cov, 0)
        velocity = None
        if k > 0:
            velocity = VelocityMeasurement(
                mid[k] + twist_noise[k], twist_cov, t[k] - 0.5 / FPS, 1 / FPS
            )
        frames.append(FrameMeasurement(k, float(t[k]), pose, velocity, num_points=4))
    return frames, p


def _rss_kib() -> int:
    with open("/proc/self/status", encoding="ascii") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))


def held(smoother: FactorGraphSmoother) -> tuple[int, int]:
    """(variables, factors) the online solver holds now."""
    isam = smoother.backend.isam
    return isam.getLinearizationPoint().size(), isam.getFactorsUnsafe().nrFactors()


def stream(smoother: FactorGraphSmoother, frames: list[FrameMeasurement]) -> dict[str, list]:
    """Feed every frame; at 0, 1/2 and the end: what is held, Python memory, RSS."""
    marks = {0: "start", len(frames) // 2: "middle", len(frames): "end"}
    out: dict[str, list] = {"held": [], "python": [], "rss": []}
    gc.collect()
    tracemalloc.start()
    try:
        for i in range(len(frames) + 1):
            if i in marks:
                gc.collect()
                if i:
                    out["held"].append(held(smoother))
                out["python"].append(tracemalloc.get_traced_memory()[0])
                out["rss"].append(_rss_kib())
            if i < len(frames):
                smoother.update(frames[i])
    finally:
        tracemalloc.stop()
    return out


@pytest.fixture(scope="module")
def long_frames() -> tuple[list[FrameMeasurement], np.ndarray]:
    return noisy_frames(FRAMES)


@pytest.mark.parametrize("solver", ["isam2", "fixed-lag"])
def test_a_long_run_holds_a_bounded_window_in_bounded_memory(solver, long_frames):
    frames, truth = long_frames
    make = FactorGraphSmoother if solver == "isam2" else FixedLagSmoother
    smoother = make(acceleration_sigma=SIGMA)
    marks = stream(smoother, frames)
    half = FRAMES // 2

    # The online solver holds a window, not the sequence: at the middle and at the end
    # no more than its window's frames (X and V each; the window is marginalized in
    # blocks of a tenth of it) and their factors: the cost of an update stays flat.
    if solver == "isam2":
        window = ONLINE_WINDOW + ONLINE_WINDOW // MARGINALIZATION_BLOCKS
    else:
        window = math.ceil(FPS * smoother.lag * (1 + 1 / MARGINALIZATION_BLOCKS))
    for variables, factors in marks["held"]:
        assert variables <= 2 * (window + 4)
        assert factors <= 4 * (window + 4)
    # Python's memory per frame: as much in the second half as in the first, and
    # small (numbers in arrays, not objects per frame: about 0.6 kB per frame).
    python = np.diff(marks["python"]) / half
    assert python[1] <= 1.25 * python[0] + 50, python
    assert python[1] < 1500, python
    # The whole process (GTSAM's C++ too): under 3 MiB per 1,000 frames (a per-frame
    # GTSAM factor graph alone took ~3.4 kB per frame).
    rss = np.diff(marks["rss"]) * 1024 / half
    assert rss[1] < 3000, rss

    smoothed = smoother.trajectory()
    assert len(smoothed.t) == FRAMES
    assert np.abs(smoothed.positions - truth).max() < 0.05  # the noise is 1 cm


def against_keyframe(frames: list[FrameMeasurement], reference: int, start: int) -> list:
    """Frames >= start measure their pose against frame ``reference`` (T_rk from the
    measured poses, same covariance): one factor reaching from every chunk to that frame."""
    ref = frames[reference].pose
    T_wr = gtsam.Pose3(gtsam.Rot3(ref.rotation), ref.position)
    out = list(frames)
    for k in range(start, len(frames)):
        pose = frames[k].pose
        T_rk = T_wr.between(gtsam.Pose3(gtsam.Rot3(pose.rotation), pose.position))
        moved = PoseMeasurement(
            T_rk.rotation().matrix(), T_rk.translation(), pose.covariance, reference
        )
        out[k] = FrameMeasurement(k, frames[k].t, moved, frames[k].velocity, num_points=4)
    return out


@pytest.mark.parametrize("case", ["chain", "keyframe", "fallback"])
def test_the_chunked_final_solve_is_the_batch_optimum(case, long_frames, monkeypatch):
    """Chunks of 250 frames sharing 50. "keyframe": every frame from 100 on is measured
    against frame 20, which couples every chunk: sweeps settle too slowly, and the whole
    graph is solved at once; "fallback": the sweeps are cut short, the same."""
    frames = long_frames[0][:900]
    if case == "keyframe":
        frames = against_keyframe(frames, 20, 100)
    if case == "fallback":
        monkeypatch.setattr(factor_store, "MAX_SWEEPS", 1)
    smoother = FactorGraphSmoother(acceleration_sigma=SIGMA)
    for frame in frames:
        smoother.update(frame)
    batch = BatchSmoother(acceleration_sigma=SIGMA).run(frames)
    backend = smoother.backend
    values = gtsam.Values(backend.initial)
    estimate = backend.isam.calculateBestEstimate()
    for key in backend.live:
        is_pose = gtsam.Symbol(key).chr() == ord("x")
        values.update(key, estimate.atPose3(key) if is_pose else estimate.atVector(key))
    moves = factor_store.solve_in_chunks(backend.store, values, chunk=250, overlap=50)
    assert moves[0] > 1e-5  # the window's estimates were not the optimum
    if case == "chain":
        assert len(moves) >= 2 and moves[-1] <= 1e-9  # it settled
    elif case == "fallback":
        assert len(moves) == 2  # one sweep, then the whole graph
    else:
        assert 2 < len(moves) < 6  # sweeps that hardly shrink, then the whole graph
    for k in range(len(frames)):  # no shared reference noise: poses as estimated
        pose = values.atPose3(X(k))
        assert np.abs(pose.translation() - batch.positions[k]).max() < 1e-6
        relative = gtsam.Rot3(batch.rotations[k].T @ pose.rotation().matrix())
        assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(relative))) < 1e-5
        assert np.abs(values.atVector(V(k)) - batch.twists[k]).max() < 1e-6


def test_the_tight_graph_holds_a_bounded_window_online():
    # Every landmark stays in view for the whole run, so without the window rebuild the
    # online ISAM2 would hold every frame's X, V (1,200 of them over 600 frames).
    from hvo_graph.estimators.tight import TightSmoother
    from hvo_graph.pipeline import measure
    from hvo_graph.sim.scenario import simulate

    scenario = simulate(paper_scenario(duration=20.0))  # 601 frames, 4 points
    tight = TightSmoother(acceleration_sigma=SIGMA)
    held_sizes = []
    for frame in measure(scenario.observations, scenario, method="tight"):
        tight.update(frame)
        held_sizes.append(tight.backend.isam.getLinearizationPoint().size())
    window = tight.backend.window
    bound = 2 * (2 * window + 1) + 4  # X, V of at most 2 windows, and the 4 landmarks
    assert max(held_sizes) <= bound
    assert max(held_sizes[300:]) == max(held_sizes[:300])
    estimate = tight.trajectory()
    error = np.linalg.norm(estimate.positions - scenario.groundtruth.positions, axis=1)
    assert np.sqrt(np.mean(error[30:] ** 2)) < 0.02


@pytest.mark.parametrize("case", ["chain", "keyframe"])
def test_a_run_without_online_estimates_reaches_the_same_optimum(case, long_frames):
    """``run(frames, online=False)`` skips the online window: the final solve starts from
    the measurements instead of the window's estimates. Two chunks and their seam
    ("chain"), or every frame from 100 on measured against frame 20 ("keyframe": the
    initial values compose each measurement with frame 20's)."""
    frames = long_frames[0][:2600]
    if case == "keyframe":
        frames = against_keyframe(frames, 20, 100)
    windowed = FactorGraphSmoother(acceleration_sigma=SIGMA, compute_covariance=True)
    expected = windowed.run(frames)
    smoother = FactorGraphSmoother(acceleration_sigma=SIGMA, compute_covariance=True)
    final = smoother.run(frames, online=False)
    assert smoother.backend.isam.getLinearizationPoint().size() == 0  # no window ran
    assert smoother.backend.moves[0] > 10 * max(windowed.backend.moves[0], 1e-6)
    assert np.abs(final.positions - expected.positions).max() < 1e-8
    turn = np.einsum("kji,kjl->kil", expected.rotations, final.rotations)
    angles = [np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R))) for R in turn]
    assert max(angles) < 1e-8
    assert np.abs(final.twists - expected.twists).max() < 1e-8
    scale = np.abs(expected.covariances).max()
    assert np.abs(final.covariances - expected.covariances).max() < 1e-6 * scale
    with pytest.raises(
        InputError,
        match=r"^online_trajectory: the run kept no online estimates \(online=False\)$",
    ):
        smoother.online_trajectory()


def test_a_robust_run_keeps_its_window_without_online_estimates(long_frames):
    # A robust loss needs the window's predictions as initial values (an outlier started
    # at its own value would be fitted first): online=False does not skip the window.
    frames = long_frames[0][:200]
    smoother = FactorGraphSmoother(acceleration_sigma=SIGMA, robust="huber")
    smoother.run(frames, online=False)
    assert smoother.backend.isam.getLinearizationPoint().size() > 0  # the window ran
    assert len(smoother.online_trajectory().t) == 200
