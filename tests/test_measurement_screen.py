"""The smoother's block-wise input checks (measurement_screen.screen_frames).

Reference: the per-frame checks (checked_frame without a screened entry), which
every frame passed to ``update`` still goes through: a block's frames must come
out with the same numbers, and a bad frame in ``run`` must fail with the same
message as when streamed.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from measurement_records import pose_record, velocity_record

from hvo_graph.errors import InputError
from hvo_graph.estimators.measurement_checks import checked_frame
from hvo_graph.estimators.measurement_screen import screen_frames
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.types import FrameMeasurement, PoseMeasurement

FPS = 30.0


def _checked(frame, previous, *, split, screened=None):
    return checked_frame(
        frame,
        [previous.t],
        [previous.index],
        lambda _: True,
        1.0,
        known={0, previous.index},
        split_reference=split,
        screened=screened,
    )


def _same(a, b) -> None:
    """Two checked frames with identical numbers (poses by their matrices)."""
    assert a[:2] == b[:2]
    for x, y in zip(a[2:], b[2:], strict=True):
        assert (x is None) == (y is None)
        if x is None:
            continue
        assert len(x) == len(y)
        for u, v in zip(x, y, strict=True):
            if hasattr(u, "matrix"):
                u, v = u.matrix(), v.matrix()
            np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


@pytest.mark.parametrize("split", [True, False])
def test_a_screened_block_gives_the_numbers_of_the_per_frame_checks(noisy_run, split):
    frames = noisy_run[1][:120]
    screened = screen_frames(frames, split_reference=split)
    assert all(entry is not None for entry in screened)
    assert frames[5].pose.reference_covariance is not None  # the split is exercised
    for previous, frame, entry in zip(frames, frames[1:], screened[1:], strict=False):
        own = _checked(frame, previous, split=split)
        _same(_checked(frame, previous, split=split, screened=entry), own)


_pose, _velocity = pose_record, velocity_record


def _turn(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_SHARED = np.diag([2e-5] * 6)
#: Frames the per-frame checks refuse, some only just (a test within rounding of its bound).
BAD = [
    _pose(covariance=np.diag([1, 1, 1, 1, 1, -1.0])),
    _pose(covariance=np.diag([1, 1, 1, 1, 1, 0.0])),
    _pose(covariance=np.eye(6) + np.eye(6, k=1)),
    _pose(covariance=np.eye(6) + 2e-9 * np.eye(6, k=1)),
    _pose(covariance=np.eye(5)),
    _pose(covariance=np.where(np.eye(6) > 0, np.inf, 0.0)),
    _pose(rotation=2 * np.eye(3)),
    _pose(rotation=(1 + 0.50005e-6) * np.eye(3)),  # R^T R - I just over 1e-6
    _pose(rotation=-np.eye(3)),
    _pose(rotation=[[2, 0, 0], [0, 2, 0], [0, 0, 2]]),  # a list: checked alone
    _pose(position=np.array([0.0, np.nan, 0.0])),
    _pose(reference=5),
    _pose(reference=2),  # earlier, but not a frame of the sequence
    _pose(reference_covariance=np.eye(6) * 2e-4),  # more than the whole covariance
    _pose(reference_covariance=np.diag([1e-4, 0, 0, 0, 0, 0.0])),  # own part singular
    _pose(reference_covariance=np.diag([-1e-8, 0, 0, 0, 0, 0.0])),  # not semi-definite
    _pose(reference_covariance=np.full((6, 6), np.nan)),
    _velocity(covariance=np.zeros((6, 6))),
    _velocity(covariance=np.diag([1, 1, 1, 1, 1, -1e-30])),
    _velocity(twist=np.zeros(3)),
    _velocity(twist=np.array([0, 0, 0, 0, 0, np.inf])),
    _velocity(dt=-1.0),
    _velocity(t=float("nan")),
    _velocity(t=1.0),
]


def _shared(part) -> bool:
    """Whether ``part`` is bad only in its reference covariance (read with the split)."""
    return isinstance(part, PoseMeasurement) and part.reference_covariance is not None


def _bad_frame(part) -> FrameMeasurement:
    if isinstance(part, PoseMeasurement):
        return FrameMeasurement(3, 3 / FPS, part, _velocity(t=2.5 / FPS), 4)
    return FrameMeasurement(3, 3 / FPS, _pose(rotation=_turn(0.1)), part, 4)


def _start() -> list[FrameMeasurement]:
    first = FrameMeasurement(0, 0.0, _pose(reference_covariance=_SHARED), None, 4)
    return [first, FrameMeasurement(1, 1 / FPS, _pose(), _velocity(), 4)]


def _message(run) -> str:
    with pytest.raises(InputError) as error:
        run()
    return str(error.value)


@pytest.mark.parametrize(
    ("part", "split"),
    [(part, split) for split in (True, False) for part in BAD if split or not _shared(part)],
)
def test_a_bad_frame_in_a_block_fails_as_when_streamed(part, split):
    frames = [*_start(), _bad_frame(part)]
    options = dict(shared_reference_noise=split, acceleration_sigma=0.1)

    def streamed():
        smoother = FactorGraphSmoother(**options)
        for frame in frames:
            smoother.update(frame)

    expected = _message(streamed)
    assert expected.startswith("frame 3: ")
    assert _message(lambda: FactorGraphSmoother(**options).run(frames)) == expected


def test_frames_near_a_bound_are_left_to_their_own_checks():
    near = [
        _pose(rotation=(1 + 0.49995e-6) * np.eye(3)),  # R^T R - I just inside 1e-6
        _pose(covariance=np.diag([1, 1, 1, 1, 1, 1e-17])),  # definite, barely
        # Smallest eigenvalue -0.95e-9 of the largest: within the allowed -1e-9.
        _pose(reference_covariance=1e-6 * np.diag([1, 1, 1, 1, 1, -0.95e-9])),
    ]
    frames = [_bad_frame(p) for p in near]
    assert screen_frames(frames, split_reference=True) == [None] * 3
    previous = _start()[1]
    for frame in frames:  # accepted, by the per-frame checks
        assert _checked(frame, previous, split=True)[2] is not None


def test_a_screen_checks_only_what_the_options_use():
    # Without the split the reference covariance is not read: not a reason to refuse.
    frame = _bad_frame(_pose(reference_covariance=np.full((6, 6), np.nan)))
    assert screen_frames([frame], split_reference=False)[0] is not None
    assert screen_frames([frame], split_reference=True)[0] is None
    kept = dataclasses.replace(frame, velocity=None)
    factor, shared, z, covariance = screen_frames([kept], split_reference=False)[0]
    np.testing.assert_array_equal(factor, kept.pose.covariance)
    assert shared is None and z is None and covariance is None
