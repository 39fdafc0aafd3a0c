"""The tracker's work-saving pieces (hvo_graph.frontend._klt) against the plain way.

Ground truth: an image shifted by a known displacement (cv2.warpAffine) for the
backward search's pyramid levels; OpenCV's full-frame warpPerspective and
calcOpticalFlowPyrLK for the re-alignment's box warp; the tracker with the full
pyramid in both directions for the forward-backward check on a moving sequence.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import hvo_graph.frontend._klt as klt
import hvo_graph.frontend.tracking as tracking
from hvo_graph.frontend._klt import align_to_first_sight, back_levels, forward_backward
from hvo_graph.frontend.tracker_config import TrackerConfig
from hvo_graph.sim.render import make_texture

CONFIG = TrackerConfig()
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, CONFIG.lk_iterations, 0.01)
WINDOW = (CONFIG.lk_window, CONFIG.lk_window)


def _texture(block: int, seed: int) -> np.ndarray:
    t = make_texture(480, block_texels=block, seed=seed)
    return np.clip(np.asarray(t, dtype=float)[:240, :320], 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return _texture(16, 5)


def _corners(image: np.ndarray, margin: int) -> np.ndarray:
    c = cv2.goodFeaturesToTrack(image, 60, 0.01, 10, blockSize=7).reshape(-1, 2)
    inside = np.all((c > margin) & (c < np.array(image.shape[::-1]) - margin), axis=1)
    return c[inside].astype(np.float32)


def _lk(source, target, points, guess=None, levels=None):
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW if guess is not None else 0
    moved, status, _ = cv2.calcOpticalFlowPyrLK(
        source, target, points.reshape(-1, 1, 2).astype(np.float32),
        None if guess is None else guess.reshape(-1, 1, 2).astype(np.float32),
        winSize=WINDOW, maxLevel=CONFIG.lk_levels if levels is None else levels,
        criteria=CRITERIA, flags=flags,
    )  # fmt: skip
    return moved.reshape(-1, 2), status.ravel() == 1


@pytest.mark.parametrize("block", [8, 16])  # fine and coarse texture, texels
@pytest.mark.parametrize("shift", [0.7, 3.0, 6.0, 9.0, 14.0, 18.0])
def test_the_backward_levels_recover_the_forward_displacement(block, shift):
    # The second image is the first moved by (shift, -shift / 2) px: going back from
    # p1 = p0 + d must land on p0, with the levels chosen from the displacement as with
    # the full pyramid.
    texture = _texture(block, seed=block)
    d = np.array([shift, -shift / 2])
    moved = cv2.warpAffine(
        texture, np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]]]), texture.shape[::-1],
        flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT,
    )  # fmt: skip
    p0 = _corners(texture, margin=int(shift) + 25)
    p1 = p0 + d.astype(np.float32)

    def found(levels: int) -> np.ndarray:
        back, ok = _lk(moved, texture, p1, levels=levels)
        return ok & (np.linalg.norm(back - p0, axis=1) < 0.1)

    levels = back_levels(p0, p1, CONFIG.lk_window, CONFIG.lk_levels)
    assert found(levels).mean() > 0.9
    assert found(levels).mean() >= found(CONFIG.lk_levels).mean()
    if shift > CONFIG.lk_window / 2:
        # Without a pyramid points are lost: the levels chosen are needed.
        assert levels > 0 and found(0).mean() < found(levels).mean()


def test_no_displacement_to_judge_keeps_the_full_pyramid():
    empty = np.empty((0, 2), dtype=np.float32)
    assert back_levels(empty, empty, 21, 3) == 3
    p = np.zeros((2, 2), dtype=np.float32)
    assert back_levels(p, p + np.array([np.nan, 0.0], dtype=np.float32), 21, 3) == 3


def test_the_box_warp_aligns_as_the_full_frame_warp(texture):
    # A plane homography close to the identity (a frame's drift of perspective).
    G = np.array([[1.02, 0.015, 3.2], [-0.01, 0.99, -2.1], [4e-5, -2e-5, 1.0]])
    current = cv2.warpPerspective(
        texture, G, texture.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    first = _corners(texture, margin=30).astype(np.float64)
    truth = cv2.perspectiveTransform(first.reshape(-1, 1, 2), G).reshape(-1, 2)
    guess = truth + np.array([0.3, -0.2])  # a frame-to-frame result off by a fraction
    aligned, ok = align_to_first_sight(texture, current, G, first, guess, CONFIG, _lk)
    # The plain way: the whole first image warped, LK from it at G(first) without a pyramid.
    warped = cv2.warpPerspective(
        texture, G, texture.shape[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    plain, plain_ok = _lk(warped, current, truth, guess=guess, levels=0)
    plain_ok &= np.linalg.norm(plain - guess, axis=1) < CONFIG.refine_max_px
    assert np.array_equal(ok, plain_ok) and ok.mean() > 0.9
    assert np.abs(aligned[ok] - plain[ok]).max() < 0.01
    assert np.median(np.linalg.norm(aligned[ok] - truth[ok], axis=1)) < 0.05


def test_the_shortened_backward_search_keeps_the_same_tracks(monkeypatch):
    # A sequence sliding by ~4 px per frame (tests/test_tracking.py): the tracker with the
    # backward levels chosen per frame and with the full pyramid both ways agree exactly.
    from hvo_graph.sim.render import render_plane_images
    from tests.test_tracking import CAMERA, PLANE, POSES, TIMES

    images = render_plane_images(CAMERA, PLANE, POSES[:30], noise_sigma=1.0, seed=3)
    chosen = []
    real = klt.back_levels

    def spy(*args):
        chosen.append(real(*args))
        return chosen[-1]

    monkeypatch.setattr(klt, "back_levels", spy)
    short = tracking.track_images(images, TIMES[:30], CAMERA)
    monkeypatch.setattr(klt, "back_levels", lambda p0, p1, window, levels: levels)
    full = tracking.track_images(images, TIMES[:30], CAMERA)
    assert min(chosen) < CONFIG.lk_levels  # the shortcut was taken
    for a, b in zip(short, full, strict=True):
        assert np.array_equal(a.ids, b.ids) and np.array_equal(a.uv, b.uv)


@pytest.mark.parametrize("error", [0.0, 15.0])
def test_a_wrong_prediction_costs_no_track(texture, error):
    # The second image is the first moved by (6, -3) px. Started at the truth (error 0)
    # without a pyramid, or 15 px off, the forward-backward search keeps what the plain
    # search keeps, where it keeps it.
    d = np.array([6.0, -3.0])
    moved = cv2.warpAffine(
        texture, np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]]]), texture.shape[::-1],
        flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT,
    )  # fmt: skip
    p0 = _corners(texture, margin=30)
    in_view = lambda uv: np.all((uv > 8) & (uv < np.array([311.5, 231.5])), axis=1)  # noqa: E731
    plain, keep_plain = forward_backward(_lk, texture, moved, p0, CONFIG, in_view)
    guess = p0 + (d + np.array([error, 0.0])).astype(np.float32)
    p1, keep = forward_backward(_lk, texture, moved, p0, CONFIG, in_view, guess, 0)
    assert np.array_equal(keep, keep_plain) and keep.mean() > 0.9
    assert np.abs(p1[keep] - plain[keep]).max() < 0.02
    assert np.abs(p1[keep] - (p0[keep] + d)).max() < 0.05


def test_the_predicted_start_keeps_the_same_tracks(monkeypatch):
    # The sequence of tests/test_tracking.py: the tracker starting each forward search at
    # the last step's plane motion and the one starting with no motion keep the same tracks
    # within a hundredth of a pixel.
    from hvo_graph.sim.render import render_plane_images
    from tests.test_tracking import CAMERA, PLANE, POSES, TIMES

    images = render_plane_images(CAMERA, PLANE, POSES[:30], noise_sigma=1.0, seed=3)
    levels = []
    real = tracking.predict

    def spy(*args):
        levels.append(real(*args)[1])
        return real(*args)

    monkeypatch.setattr(tracking, "predict", spy)
    predicted = tracking.track_images(images, TIMES[:30], CAMERA)
    monkeypatch.setattr(tracking, "predict", lambda *args: (None, None))
    plain = tracking.track_images(images, TIMES[:30], CAMERA)
    assert min(v for v in levels if v is not None) < CONFIG.lk_levels  # shortened
    for a, b in zip(predicted, plain, strict=True):
        assert np.array_equal(a.ids, b.ids) and np.abs(a.uv - b.uv).max() < 0.01
