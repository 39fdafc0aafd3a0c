"""The images path after a loss: re-identification, re-acquisition, and a run that says
when the pose was lost.

A rendered sequence (the image experiment's motion, 320 x 240) with a motion-blur
passage, or with the camera looking at a blank wall for a while: every track is
lost there. When the plane comes back into view the tracker finds its lost tracks
again (re-identification: same ids, so poses are measured against frame 0 again);
with that turned off it re-detects, and the front end must pick the pose up against
a new reference (re-acquisition) instead of coasting on the motion model for the
rest of the sequence. Ground truth is the rendering's.
"""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from hvo_graph.eval.metrics import error_series
from hvo_graph.frontend import measure_sequence
from hvo_graph.frontend.health import MAX_FRACTION_WITHOUT_POSE, front_end_health
from hvo_graph.frontend.tracking import TrackerConfig, track_images
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.image_runs import ImageRunConfig
from hvo_graph.io.config import SceneConfig
from hvo_graph.pipeline import run_estimate
from hvo_graph.sim.images import ground_truth, plane_texture, render_stream
from hvo_graph.types import FrameMeasurement, PoseMeasurement

CAMERA = CameraModel(400.0, 400.0, 160.0, 120.0, 320, 240)
BLURRED = range(45, 52)


def motion_blur(image: np.ndarray) -> np.ndarray:
    """A 41-pixel horizontal motion streak over a defocus: no corner survives it."""
    kernel = np.full((1, 41), 1.0 / 41, dtype=np.float32)
    return cv2.filter2D(cv2.GaussianBlur(image, (0, 0), 6), -1, kernel)


def rendered_run(edit, tracker: TrackerConfig | None = None):
    """The image experiment's motion (seed 1, 4 s), rendered, ``edit``-ed in place, tracked
    and estimated by the smoother: (truth, tracks, EstimateRun)."""
    config = ImageRunConfig(seed=1, duration=4.0, camera=CAMERA)
    motion = config.motion()
    truth = ground_truth(motion)
    texture = plane_texture(CAMERA, 1)
    images = list(render_stream(CAMERA, motion.plane, truth, texture, noise_sigma=2.0, seed=1))
    edit(images)
    tracks = track_images(images, truth.t, CAMERA, tracker)
    scene = SceneConfig(CAMERA, motion.plane, 0.1)
    return truth, tracks, run_estimate(tracks, scene, "smoother", ransac_threshold_px=2.0)


def blur(images):
    for k in BLURRED:
        images[k] = motion_blur(images[k])


def blank(images):
    """The camera looks at a blank wall: no texture at all."""
    for k in BLURRED:
        images[k] = np.full_like(images[k], 128)


@pytest.fixture(scope="module")
def blurred_run():
    """Re-identification off: what happens when the old points are not found again."""
    return rendered_run(blur, TrackerConfig(reidentify_frames=0))


@pytest.mark.parametrize("edit", [blur, blank], ids=["motion-blur", "blank-view"])
def test_lost_tracks_are_reidentified_and_the_pose_returns_to_frame_0(edit):
    truth, tracks, run = rendered_run(edit)
    end = BLURRED[-1] + 1
    before = set(tracks[BLURRED[0] - 1].ids.tolist())
    assert not before & set(tracks[BLURRED[0]].ids.tolist())  # all lost in the passage
    assert len(before & set(tracks[end].ids.tolist())) >= 0.8 * len(before)  # found again
    # The points seen again are frame 0's: every pose after the passage is measured
    # against frame 0 itself, not against a new reference tied to it through the gap.
    assert all(f.pose is not None and f.pose.reference == 0 for f in run.frames[end:])
    errors = error_series(run.trajectory, truth)
    assert errors.position[end:].max() < 0.005 and errors.orientation[end:].max() < 0.1
    assert front_end_health(run.frames).warnings() == []


def test_a_sudden_lighting_change_keeps_the_pose():
    """From frame 45 on the scene is much darker (gain 0.45): KLT's brightness constancy
    breaks for a frame; the tracker re-detects and the pose goes on."""

    def darken(images):
        for k in range(45, len(images)):
            images[k] = cv2.convertScaleAbs(images[k], alpha=0.45, beta=10)

    truth, _, run = rendered_run(darken)
    assert all(f.pose is not None for f in run.frames[1:])
    errors = error_series(run.trajectory, truth)
    assert errors.position.max() < 0.01 and errors.orientation.max() < 0.3


def test_the_blur_loses_every_track_and_the_tracker_redetects(blurred_run):
    _, tracks, _ = blurred_run
    before = set(tracks[BLURRED[0] - 1].ids.tolist())
    after = set(tracks[BLURRED[-1] + 1].ids.tolist())
    assert not before & after  # nothing tracked across the passage
    assert len(after) >= 100


def test_the_pose_is_reacquired_after_the_blur(blurred_run):
    truth, _, run = blurred_run
    end = BLURRED[-1] + 1
    # The first sharp frame re-detects (it becomes the new reference); every later frame
    # has a pose again.
    assert all(f.pose is not None for f in run.frames[end + 1 :])
    references = {f.pose.reference for f in run.frames[end + 1 :]}
    assert min(references) >= BLURRED[0]  # a new reference, not the lost frame 0
    health = front_end_health(run.frames)
    assert health.reacquisitions >= 1 and health.reference_changes >= health.reacquisitions
    assert health.warnings() == []
    # The new reference is tied to the old one through the graph: the trajectory after
    # the passage stays within millimetres of the truth (d* = 2 m).
    errors = error_series(run.trajectory, truth)
    assert errors.position[end:].max() < 0.01
    assert errors.orientation[end:].max() < 0.3


def test_without_reacquisition_the_health_report_warns(blurred_run):
    # Keyframes off: the front end stays on frame 0, whose points are gone after the blur
    # (not re-identified here).
    _, tracks, _ = blurred_run
    plane = ImageRunConfig(seed=1, duration=4.0, camera=CAMERA).motion().plane
    frames = measure_sequence(
        tracks, CAMERA, plane, keyframe_min_points=None, ransac_threshold_px=2.0, pixel_sigma=0.1
    )
    health = front_end_health(frames)
    missing = len(frames) - BLURRED[0]
    assert health.frames_with_pose == BLURRED[0] and health.reacquisitions == 0
    assert health.longest_gap == missing and health.longest_gap_start == BLURRED[0]
    assert health.fraction_without_pose > MAX_FRACTION_WITHOUT_POSE
    (warning,) = health.warnings()
    assert f"{missing} of {len(frames)} frames" in warning
    assert f"longest gap: {missing} frames from frame {BLURRED[0]}" in warning


def test_health_counts_on_a_hand_made_sequence():
    pose = PoseMeasurement(np.eye(3), np.zeros(3), np.eye(6))
    frames = [
        FrameMeasurement(0, 0.0, None, None, 10, 0),
        FrameMeasurement(1, 0.1, pose, None, 12, 2),
        FrameMeasurement(2, 0.2, None, None, 3, 0),
        FrameMeasurement(3, 0.3, None, None, 40, 0),
        FrameMeasurement(4, 0.4, PoseMeasurement(np.eye(3), np.zeros(3), np.eye(6), 3), None, 38),
        FrameMeasurement(5, 0.5, PoseMeasurement(np.eye(3), np.zeros(3), np.eye(6), 4), None, 36),
    ]
    health = front_end_health(frames)
    assert (health.frames, health.frames_with_pose, health.frames_with_velocity) == (6, 3, 0)
    assert (health.longest_gap, health.longest_gap_start) == (2, 2)
    assert health.gaps == ((0, 0), (2, 3))
    assert (health.tracks_min, health.tracks_median, health.tracks_max) == (3, 24.0, 40)
    assert health.rejected_points == 2
    # 0 -> 3 (frame 3 had no pose: after a loss) -> 4 (a keyframe with its own pose)
    assert (health.reference_changes, health.reacquisitions) == (2, 1)
    assert health.as_dict()["fraction_without_pose"] == 0.5


def test_estimate_command_reports_a_lost_pose(tmp_path):
    """End to end: a third of the run with 3 points (too few for a pose); the command says so."""
    sim = tmp_path / "sim"
    cmd = [sys.executable, "-m", "hvo_graph"]
    subprocess.run([*cmd, "simulate", "--out", str(sim), "--duration", "3"], check=True)
    lines = (sim / "tracks.csv").read_text().splitlines()
    first_id = lines[1].split(",")[2]
    kept = [lines[0]] + [
        row
        for row in lines[1:]
        if not (30 <= int(row.split(",")[0]) < 60 and row.split(",")[2] == first_id)
    ]
    (sim / "tracks.csv").write_text("\n".join(kept) + "\n")
    out = tmp_path / "est"
    result = subprocess.run(
        [*cmd, "estimate", "--camera", str(sim / "camera.yaml"),
         "--tracks", str(sim / "tracks.csv"), "--method", "kalman", "--out", str(out)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "hvo-graph estimate: front end: 91 frames, 61 with a pose (67.0%)" in result.stderr
    assert (
        "hvo-graph estimate: warning: 30 of 91 frames (33.0%) had no pose measurement "
        "(longest gap: 30 frames from frame 30)" in result.stderr
    )
    health = json.loads((out / "run.json").read_text())["front_end_health"]
    assert health["frames_with_pose"] == 61 and health["longest_gap"] == 30
    assert health["gaps"] == [[30, 59]]
    assert health["fraction_without_pose"] == round(30 / 91, 4)
