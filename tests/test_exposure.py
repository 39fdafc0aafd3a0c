"""Exposure compensation: tracks through auto exposure (gain and offset changing).

Ground truth: the rendered plane's projection (``track_error``, the RMS error of
every track against where its first sighting's plane point projects); the same
sequence tracked without compensation shows what the change costs.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.eval.consistency import track_error
from hvo_graph.frontend.exposure import ExposureCompensation, scaled_image
from hvo_graph.frontend.tracker_config import TrackerConfig
from hvo_graph.frontend.tracking import track_images
from hvo_graph.image_runs import ImageRunConfig
from hvo_graph.sim.images import ground_truth, plane_texture, render_stream


def _image(seed: int, mean: float = 90.0, std: float = 15.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(mean, std, (120, 160)), 0, 255).astype(np.uint8)


def test_scaling_rounds_and_clips_like_numpy() -> None:
    image = _image(0, std=40.0)
    for factor in (0.37, 1.0, 1.9):
        expected = np.clip(np.rint(image * factor), 0, 255)
        assert np.abs(scaled_image(image, factor).astype(int) - expected).max() <= 1


def test_a_gain_change_is_undone() -> None:
    first = _image(1)
    darker = np.rint(0.6 * first.astype(float)).astype(np.uint8)
    compensate = ExposureCompensation()
    np.testing.assert_array_equal(compensate(first), first)  # the first image is the reference
    diff = compensate(darker).astype(int) - first.astype(int)
    # Up to rounding: the darker image's 0.5 gray level over the gain 0.6, and the output's.
    assert np.abs(diff).max() <= 1
    assert abs(diff.mean()) < 0.1


def test_images_within_tolerance_of_the_first_are_left_as_they_are() -> None:
    compensate = ExposureCompensation()
    first = _image(2)
    compensate(first)
    slightly = np.clip(first.astype(int) + 1, 0, 255).astype(np.uint8)  # 1 of 90: content
    np.testing.assert_array_equal(compensate(slightly), slightly)


def test_a_blur_is_not_taken_for_an_exposure_change() -> None:
    # Same mean, a quarter of the contrast: stretching it back would make corners up.
    compensate = ExposureCompensation()
    first = _image(3, std=40.0)
    compensate(first)
    blurred = cv2.GaussianBlur(first, (0, 0), 3)
    assert blurred.std() < first.std() / 3
    np.testing.assert_array_equal(compensate(blurred), blurred)


def test_black_images_are_left_as_they_are_and_set_no_reference() -> None:
    compensate = ExposureCompensation()
    black = np.zeros((40, 60), dtype=np.uint8)
    np.testing.assert_array_equal(compensate(black), black)
    assert compensate.reference_mean is None
    textured = _image(4)
    np.testing.assert_array_equal(compensate(textured), textured)
    assert compensate.reference_mean == pytest.approx(textured.mean())


def test_the_setting_must_be_a_boolean() -> None:
    with pytest.raises(InputError, match=r"^compensate_exposure: expected true or false, got 1$"):
        TrackerConfig(compensate_exposure=1)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def auto_exposure():
    """Two seconds of the image experiment's motion under auto exposure: the gain swings
    0.7-1.3 at 1 Hz and steps by 1.4x every half second."""
    config = ImageRunConfig(seed=4, duration=2.0, skip=0.0)
    motion = config.motion()
    truth = ground_truth(motion)
    texture = plane_texture(config.camera, config.seed)
    rendered = render_stream(
        config.camera, motion.plane, truth, texture, noise_sigma=config.image_noise, seed=4
    )
    images = []
    for t, image in zip(truth.t, rendered, strict=True):
        gain = (1.0 + 0.3 * np.sin(2.0 * np.pi * t)) * (1.4 if int(2.0 * t) % 2 else 1.0)
        images.append(np.clip(np.rint(gain * image), 0, 255).astype(np.uint8))
    return config.camera, motion.plane, truth, images


def test_tracks_follow_the_plane_through_auto_exposure(auto_exposure) -> None:
    camera, plane, truth, images = auto_exposure
    tracks = track_images(images, truth.t, camera, TrackerConfig(compensate_exposure=True))
    assert min(len(o.ids) for o in tracks) >= 50
    assert track_error(tracks, truth, camera, plane) < 0.05  # constant exposure: ~0.015 px


def test_without_compensation_auto_exposure_moves_the_tracks(auto_exposure) -> None:
    camera, plane, truth, images = auto_exposure
    tracks = track_images(images, truth.t, camera)  # the default: no compensation
    assert track_error(tracks, truth, camera, plane) > 0.1
