"""Exposure compensation: tracks through auto exposure (gain and offset changing).

Ground truth: the rendered plane's projection (``track_error``, the RMS error of
every track against where its first sighting's plane point projects); the same
sequence tracked without compensation shows what the change costs.
"""

from __future__ import annotations

import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.eval.consistency import track_error
from hvo_graph.frontend.exposure import (
    ExposureCompensation,
    image_statistics,
    matched_exposure,
)
from hvo_graph.frontend.tracker_config import TrackerConfig
from hvo_graph.frontend.tracking import track_images
from hvo_graph.image_runs import ImageRunConfig
from hvo_graph.sim.images import ground_truth, plane_texture, render_stream


def _image(seed: int, mean: float = 90.0, std: float = 15.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(mean, std, (120, 160)), 0, 255).astype(np.uint8)


def test_the_statistics_are_numpys_mean_and_std() -> None:
    image = _image(0)
    assert image_statistics(image) == pytest.approx((image.mean(), image.std()), rel=1e-9)


def test_the_matched_image_has_the_target_mean_and_contrast() -> None:
    image = _image(0)
    out = matched_exposure(image, image_statistics(image), (128.0, 40.0))
    assert out.dtype == np.uint8 and out.shape == image.shape
    assert out.mean() == pytest.approx(128.0, abs=0.5)
    assert out.std() == pytest.approx(40.0, abs=0.5)


def test_a_gain_and_offset_change_is_undone() -> None:
    first = _image(1)
    brighter = np.clip(np.rint(1.5 * first.astype(float) + 12.0), 0, 255).astype(np.uint8)
    assert brighter.max() < 255  # no clipping: the change is exactly affine (up to rounding)
    compensate = ExposureCompensation()
    np.testing.assert_array_equal(compensate(first), first)  # the first image sets the target
    diff = compensate(brighter).astype(int) - first.astype(int)
    # Up to rounding: the brighter image's 0.5 gray level, over the gain 1.5, and the output's.
    assert np.abs(diff).max() <= 1
    assert np.abs(diff).mean() < 0.5


def test_images_within_tolerance_of_the_first_are_left_as_they_are() -> None:
    compensate = ExposureCompensation()
    first = _image(2)
    compensate(first)
    slightly = np.clip(first.astype(int) + 1, 0, 255).astype(np.uint8)  # a gray level: content
    np.testing.assert_array_equal(compensate(slightly), slightly)


def test_uniform_images_are_left_as_they_are_and_set_no_target() -> None:
    compensate = ExposureCompensation()
    black = np.zeros((40, 60), dtype=np.uint8)
    np.testing.assert_array_equal(compensate(black), black)
    assert compensate.target is None
    textured = _image(3)
    np.testing.assert_array_equal(compensate(textured), textured)
    assert compensate.target == pytest.approx(image_statistics(textured))


def test_the_setting_must_be_a_boolean() -> None:
    with pytest.raises(InputError, match=r"^compensate_exposure: expected true or false, got 1$"):
        TrackerConfig(compensate_exposure=1)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def auto_exposure():
    """Two seconds of the image experiment's motion, the gain swinging 0.7-1.3 at 1 Hz
    and the offset stepping by 25 gray levels every half second."""
    config = ImageRunConfig(seed=4, duration=2.0, skip=0.0)
    motion = config.motion()
    truth = ground_truth(motion)
    texture = plane_texture(config.camera, config.seed)
    rendered = render_stream(
        config.camera, motion.plane, truth, texture, noise_sigma=config.image_noise, seed=4
    )
    images = []
    for t, image in zip(truth.t, rendered, strict=True):
        gain = 1.0 + 0.3 * np.sin(2.0 * np.pi * t)
        offset = 25.0 * (int(2.0 * t) % 2)
        images.append(np.clip(np.rint(gain * image + offset), 0, 255).astype(np.uint8))
    return config.camera, motion.plane, truth, images


def test_tracks_follow_the_plane_through_auto_exposure(auto_exposure) -> None:
    camera, plane, truth, images = auto_exposure
    tracks = track_images(images, truth.t, camera)
    assert min(len(o.ids) for o in tracks) >= 50
    assert track_error(tracks, truth, camera, plane) < 0.05  # constant exposure: ~0.015 px


def test_without_compensation_auto_exposure_moves_the_tracks(auto_exposure) -> None:
    camera, plane, truth, images = auto_exposure
    tracks = track_images(images, truth.t, camera, TrackerConfig(compensate_exposure=False))
    assert track_error(tracks, truth, camera, plane) > 0.1
