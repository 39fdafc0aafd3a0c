"""The default smoother's solver strategy (hvo_graph.estimators.solvers.Isam2Backend).

Online estimates come from ISAM2 over a sliding window of frames, the final
ones from the batch solve of the whole graph. Independent references: the
batch Levenberg-Marquardt solver run from the raw measurements
(``BatchSmoother``), and one ISAM2 holding the whole sequence
(``IncrementalBackend``, the default smoother's back end before the window),
for the online estimates; ground truth of the paper's scenario.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from hvo_graph.estimators.smoother import (
    DEFAULT_RELINEARIZE_SKIP,
    DEFAULT_RELINEARIZE_THRESHOLD,
    BatchSmoother,
    FactorGraphSmoother,
)
from hvo_graph.estimators.solvers import ONLINE_WINDOW, IncrementalBackend, isam2_params
from hvo_graph.eval.metrics import error_series
from hvo_graph.types import FrameMeasurement


def whole_sequence_isam2() -> FactorGraphSmoother:
    """A default smoother whose back end is one ISAM2 over the whole sequence."""
    smoother = FactorGraphSmoother(compute_covariance=True)
    params = isam2_params(
        DEFAULT_RELINEARIZE_THRESHOLD, DEFAULT_RELINEARIZE_SKIP, find_unused_factor_slots=False
    )
    smoother.backend = IncrementalBackend(params, compute_covariance=True)
    return smoother


def rotation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (deg) between two stacks of rotation matrices."""
    return np.degrees(
        [np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(x.T @ y))) for x, y in zip(a, b, strict=True)]
    )


def relative_covariance_error(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / sqrt(b_ii b_jj) over every frame and entry."""
    scale = np.sqrt(np.einsum("nii,njj->nij", b, b))
    return float(np.max(np.abs(a - b) / scale))


def against_keyframe(frames: list[FrameMeasurement], reference: int, start: int) -> list:
    """The frames with the poses of frames >= start re-expressed against frame ``reference``
    (T_rk = T_wr^-1 T_wk from the measured poses, same covariance)."""
    ref = frames[reference].pose
    T_wr = gtsam.Pose3(gtsam.Rot3(ref.rotation), ref.position)
    out = list(frames)
    for k in range(start, len(frames)):
        pose = frames[k].pose
        T_rk = T_wr.between(gtsam.Pose3(gtsam.Rot3(pose.rotation), pose.position))
        changed = dataclasses.replace(
            pose,
            rotation=T_rk.rotation().matrix(),
            position=np.asarray(T_rk.translation()),
            reference=reference,
            reference_covariance=None,
        )
        out[k] = dataclasses.replace(frames[k], pose=changed)
    return out


@pytest.fixture(scope="module")
def runs(noisy_run):
    """(frames, default smoother, its smoothed trajectory, batch trajectory)."""
    frames = noisy_run[1]
    assert len(frames) > 3 * ONLINE_WINDOW  # frames do leave the window
    smoother = FactorGraphSmoother(compute_covariance=True)
    smoothed = smoother.run(frames)
    batch = BatchSmoother(compute_covariance=True).run(frames)
    return frames, smoother, smoothed, batch


def test_smoothed_trajectory_and_marginals_are_the_batch_ones(runs):
    _, _, smoothed, batch = runs
    assert np.abs(smoothed.positions - batch.positions).max() < 1e-6
    assert rotation_deg(smoothed.rotations, batch.rotations).max() < 1e-5
    assert np.abs(smoothed.twists - batch.twists).max() < 1e-6
    assert relative_covariance_error(smoothed.covariances, batch.covariances) < 1e-6


def test_online_estimates_are_those_of_one_isam2_over_the_whole_sequence(runs, noisy_run):
    frames, smoother, _, _ = runs
    reference = whole_sequence_isam2()
    reference.run(frames)
    online, expected = smoother.online_trajectory(), reference.online_trajectory()
    # The same solution: twists and marginals to rounding. Poses are reported against
    # the anchor X(k0), which a whole-sequence ISAM2 reads with its wildfire-limited
    # (slightly stale) delta: within 0.2 mm / 0.01 deg, far inside the ~1 cm noise.
    assert np.abs(online.twists - expected.twists).max() < 1e-9
    # Marginals too, but for the anchor's, which each frame's pose covariance carries:
    # the window keeps it as X(k0) left, the whole-sequence ISAM2 keeps updating it.
    w = ONLINE_WINDOW
    assert relative_covariance_error(online.covariances[:w], expected.covariances[:w]) < 1e-8
    twist = (slice(None), slice(6, 12), slice(6, 12))
    assert relative_covariance_error(online.covariances[twist], expected.covariances[twist]) < 1e-8
    assert np.abs(online.positions - expected.positions).max() < 2e-4
    assert rotation_deg(online.rotations, expected.rotations).max() < 0.01
    # and they are causal estimates of the truth, not the smoothed values
    truth = noisy_run[0].groundtruth
    assert error_series(online, truth).position.max() < 0.1
    assert np.abs(online.positions - runs[2].positions).max() > 1e-4


def test_a_keyframe_in_use_stays_in_the_window(noisy_run):
    # Every frame from 21 on is measured against frame 20: X(20) must stay a variable.
    frames = against_keyframe(noisy_run[1], 20, 21)
    smoother = FactorGraphSmoother(compute_covariance=True)
    smoother.run(frames)
    assert smoother.backend.isam.valueExists(gtsam.symbol_shorthand.X(20))
    reference = whole_sequence_isam2()
    reference.run(frames)
    online, expected = smoother.online_trajectory(), reference.online_trajectory()
    assert np.abs(online.twists - expected.twists).max() < 1e-9
    assert np.abs(online.positions - expected.positions).max() < 2e-3  # anchor read-out


def test_a_keyframe_first_used_after_it_left_the_window(noisy_run):
    # Frame 20 left the window long before frame 200 refers to it: the window gets the
    # factor conditioned on the keyframe's estimate; the final solve gets it unchanged.
    frames = against_keyframe(noisy_run[1], 20, 200)
    smoother = FactorGraphSmoother()
    smoothed = smoother.run(frames)
    assert not smoother.backend.isam.valueExists(gtsam.symbol_shorthand.X(20))
    batch = BatchSmoother().run(frames)
    assert np.abs(smoothed.positions - batch.positions).max() < 1e-6
    reference = whole_sequence_isam2()
    reference.run(frames)
    online, expected = smoother.online_trajectory(), reference.online_trajectory()
    # the same twists up to frame 200, then within the keyframe's own uncertainty
    assert np.abs(online.twists[:200] - expected.twists[:200]).max() < 1e-9
    assert np.abs(online.twists - expected.twists).max() < 0.02
    assert np.abs(online.positions - expected.positions).max() < 0.01
