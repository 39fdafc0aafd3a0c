"""How well the front end kept up: what a run reports next to its trajectory.

A trajectory is only as good as its measurements. Where the front end had no
pose (H_d) measurement (the tracks were lost to motion blur, the plane left
the view, too few points were shared with the reference) the estimators
predict through the motion model, and the error grows with the length of the
gap. :func:`front_end_health` summarizes the front end's output so that a run
can say so: frames with a pose, the longest stretch without one, tracks per
frame, rejected track points, and reference changes (keyframes, and
re-acquisitions: a new reference taken after the old one's points were lost).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from itertools import pairwise

import numpy as np

from hvo_graph.measurement_table import frame_columns
from hvo_graph.types import FrameMeasurement

#: Warn when more than this fraction of the frames had no pose measurement.
MAX_FRACTION_WITHOUT_POSE = 0.10


@dataclass(frozen=True)
class FrontEndHealth:
    """The front end's output at a glance (plain values, for ``run.json``).

    Attributes:
        frames: frames processed.
        frames_with_pose: frames with a pose (H_d) measurement.
        frames_with_velocity: frames with a velocity (H_c) measurement.
        longest_gap: most consecutive frames without a pose measurement.
        longest_gap_start: frame index where that stretch starts (None: no gap).
        tracks_min, tracks_median, tracks_max: tracked points per frame.
        rejected_points: track points rejected as outliers, over all frames.
        reference_changes: times the pose reference moved to another frame.
        reacquisitions: of those, moves to a frame without a pose of its own (the
            reference's points were lost and the pose was picked up again).
        gaps: (first, last) frame indices of every stretch without a pose measurement.
    """

    frames: int
    frames_with_pose: int
    frames_with_velocity: int
    longest_gap: int
    longest_gap_start: int | None
    tracks_min: int
    tracks_median: float
    tracks_max: int
    rejected_points: int
    reference_changes: int
    reacquisitions: int
    gaps: tuple[tuple[int, int], ...] = ()

    @property
    def fraction_without_pose(self) -> float:
        """Fraction of the frames without a pose measurement (0 for no frames)."""
        return 1.0 - self.frames_with_pose / self.frames if self.frames else 0.0

    def as_dict(self) -> dict[str, object]:
        """The fields and ``fraction_without_pose``, as plain values."""
        return asdict(self) | {"fraction_without_pose": round(self.fraction_without_pose, 4)}

    def summary(self) -> str:
        """One line for a person, e.g. ``"300 frames, 290 with a pose (96.7%), ..."``."""
        return (
            f"{self.frames} frames, {self.frames_with_pose} with a pose "
            f"({100 * (1 - self.fraction_without_pose):.1f}%), "
            f"{self.tracks_min}-{self.tracks_max} tracks per frame "
            f"(median {self.tracks_median:g}), {self.rejected_points} track points rejected, "
            f"{self.reference_changes} reference changes ({self.reacquisitions} after a loss)"
        )

    def warnings(self) -> list[str]:
        """Sentences for a person when the front end lost the pose too often (else [])."""
        if self.fraction_without_pose <= MAX_FRACTION_WITHOUT_POSE:
            return []
        missing = self.frames - self.frames_with_pose
        return [
            f"{missing} of {self.frames} frames ({100 * self.fraction_without_pose:.1f}%) had "
            f"no pose measurement (longest gap: {self.longest_gap} frames from frame "
            f"{self.longest_gap_start}); there the trajectory rests on the motion model alone"
        ]


def front_end_health(frames: Sequence[FrameMeasurement]) -> FrontEndHealth:
    """Summarize the front end's measurements of a run.

    Args:
        frames: the front end's output, one :class:`FrameMeasurement` per frame in order.
    Returns:
        The counts of :class:`FrontEndHealth`.
    """
    columns = frame_columns(frames)  # a MeasurementTable's without making its records
    has_pose, index = columns.has_pose.tolist(), columns.index.tolist()
    gaps, run_start = [], 0
    for k, ok in enumerate([*has_pose, True]):
        if not ok:
            continue
        if k > run_start:
            gaps.append((index[run_start], index[k - 1], k - run_start))
        run_start = k + 1
    longest = max(gaps, key=lambda g: g[2], default=(None, None, 0))
    tracks = columns.num_points.astype(int)
    references = columns.references[columns.has_pose].tolist()
    changes = [b for a, b in pairwise([0, *references]) if b != a]  # from W (frame 0) on
    without_pose = {i for i, ok in zip(index, has_pose, strict=True) if not ok}
    return FrontEndHealth(
        frames=len(frames),
        frames_with_pose=int(sum(has_pose)),
        frames_with_velocity=int(columns.has_velocity.sum()),
        longest_gap=longest[2],
        longest_gap_start=longest[0],
        tracks_min=int(tracks.min()) if len(tracks) else 0,
        tracks_median=float(np.median(tracks)) if len(tracks) else 0.0,
        tracks_max=int(tracks.max()) if len(tracks) else 0,
        rejected_points=int(columns.num_rejected.sum()),
        reference_changes=len(changes),
        reacquisitions=sum(r in without_pose for r in changes),
        gaps=tuple((first, last) for first, last, _ in gaps),
    )
