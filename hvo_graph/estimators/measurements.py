"""The raw per-frame estimates, no fusion (``--method measurements`` and ``ippe``).

Pose: the frame's own pose measurement, composed, when its reference is a
keyframe, with the front end's placement of that keyframe (its own world chain,
corrected where it fitted the keyframe's tilt; without one, with this
estimator's estimate of the keyframe); a frame without one keeps the previous
pose. Twist: the mid-interval velocity measurements straddle the
frame times, so the final trajectory reports at frame k the mean of the
twists at k-1/2 and k+1/2 (a central difference); the online estimate, which
cannot see frame k+1, reports the one at k-1/2.

With ``velocity_from="poses"`` the twists come from differencing consecutive
poses instead of the continuous homography: what a user of per-frame PnP
(OpenCV IPPE) would do.
"""

from __future__ import annotations

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.base import Estimator, placed_world_pose
from hvo_graph.types import FrameMeasurement, PoseMeasurement, StateEstimate, Trajectory

VELOCITY_SOURCES = ("flow", "poses")


class RawMeasurements(Estimator):
    """Pass the front end's measurements through, frame by frame."""

    name = "measurements"

    def __init__(self, velocity_from: str = "flow") -> None:
        super().__init__()
        if velocity_from not in VELOCITY_SOURCES:
            choices = ", ".join(VELOCITY_SOURCES)
            raise InputError(f"velocity_from: expected one of {choices}, got {velocity_from!r}")
        self.velocity_from = velocity_from
        self._poses: list[gtsam.Pose3] = []
        self._interval_twists: list[np.ndarray | None] = []  # twist over (k-1, k], None if unknown

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        pose = self._poses[-1] if self._poses else gtsam.Pose3()
        if frame.pose is not None:
            world = self.pose_in_world(frame.pose)
            pose = gtsam.Pose3(gtsam.Rot3(world.rotation), world.position)
        twist: np.ndarray | None
        if self.velocity_from == "flow":
            twist = (
                None if frame.velocity is None else np.asarray(frame.velocity.twist, dtype=float)
            )
        elif self._poses and frame.pose is not None and self._online:
            dt = frame.t - self._online[-1].t
            twist = gtsam.Pose3.Logmap(self._poses[-1].between(pose)) / dt
        else:
            twist = None
        self._poses.append(pose)
        self._interval_twists.append(twist)
        online_twist = next(
            (w for w in reversed(self._interval_twists) if w is not None), np.zeros(6)
        )
        return StateEstimate(
            frame.index, frame.t, pose.rotation().matrix(), pose.translation(), online_twist
        )

    def pose_in_world(self, pose: PoseMeasurement) -> PoseMeasurement:
        """T_wc = T_wr T_rc with T_wr the front end's placement of the keyframe, the one its
        plane was placed with (``reference_rotation``, ``reference_position``).

        Chaining this estimator's own keyframe estimates instead compounds every
        keyframe's error, tilt included, with nothing to correct it: on a simulated
        traverse with about 16 points in view that chain ran 100 degrees away where the
        front end's stayed within 11 (smoothed / raw position on the traverse family
        0.54 with it, 0.62 now: the raw baseline was that much worse than what the front
        end knew)."""
        placed = None if pose.reference == 0 else placed_world_pose(pose)
        return super().pose_in_world(pose) if placed is None else placed

    def trajectory(self) -> Trajectory:
        traj = self.online_trajectory()
        if len(traj) == 0:
            return traj
        twists = np.array(traj.twists)
        intervals = [*self._interval_twists, None]
        for k in range(len(traj)):
            around = [w for w in (intervals[k], intervals[k + 1]) if w is not None]
            if around:
                twists[k] = np.mean(around, axis=0)
        traj.twists = twists
        return traj
