"""The streaming interface shared by every estimator.

One :meth:`Estimator.update` per frame, in order, returns the online (causal)
estimate of that frame. :meth:`Estimator.trajectory` returns the final
estimate of every frame: the same as the online one for a filter, the
smoothed one for a smoother. :meth:`Estimator.run` does a whole sequence.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.state_log import StateLog
from hvo_graph.types import (
    FrameMeasurement,
    PoseMeasurement,
    StateEstimate,
    Trajectory,
)


class Estimator(ABC):
    """Base class: keeps the online estimates and checks frame order."""

    #: name used by the command line (``--method``).
    name: str = ""

    def __init__(self) -> None:
        self._online = StateLog()

    @abstractmethod
    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        """Fuse one frame and return its online estimate."""

    def update(self, frame: FrameMeasurement) -> StateEstimate:
        """Fuse the measurements of the next frame; return its online estimate."""
        if self._online:
            index, t = self._online.last()
            if frame.index <= index or frame.t <= t:
                raise InputError(
                    f"frame {frame.index} (t={frame.t}) does not follow frame "
                    f"{index} (t={t}): frames must arrive in increasing order"
                )
        estimate = self._update(frame)
        self._online.append(estimate)
        return estimate

    def pose_in_world(self, pose: PoseMeasurement) -> PoseMeasurement:
        """A keyframe-relative pose T_rc as a world pose T_wc = T_wr T_rc.

        T_wr is this estimator's own online estimate of the keyframe, taken as
        exact: the covariance (right perturbation of T_rc) carries over
        unchanged, since T_wr T_rc Exp(delta) = T_wc Exp(delta). Estimators
        without keyframe states (the raw measurements, the paper's filter) use
        this; the smoother adds a between factor instead.
        """
        if pose.reference == 0:
            return pose
        keyframe = self._online.find(pose.reference)
        if keyframe is None:
            raise InputError(
                f"pose measurement refers to frame {pose.reference}, which was not estimated before"
            )
        return keyframe_world_pose(pose, keyframe.rotation, keyframe.position)

    def online_trajectory(self) -> Trajectory:
        """The online estimate of every frame so far (each as it was right after its update)."""
        return self._online.trajectory()

    def trajectory(self) -> Trajectory:
        """The final estimate of every frame so far (smoothed, for smoothers)."""
        return self.online_trajectory()

    def run(self, frames: Iterable[FrameMeasurement], *, online: bool = True) -> Trajectory:
        """Update with every frame and return :meth:`trajectory`.

        ``online`` False: the caller wants the final estimates only, and a smoother may
        skip work that serves :meth:`online_trajectory` alone (the default smoother does).
        """
        for frame in frames:
            self.update(frame)
        return self.trajectory()


def placed_world_pose(pose: PoseMeasurement) -> PoseMeasurement | None:
    """T_wc = T_wr T_rc of a keyframe-relative pose through the front end's own placement of
    its keyframe (``reference_rotation``, ``reference_position``: the pose with which it
    placed the plane, so no re-placement); None when the pose does not carry one."""
    R_wr, p_wr = pose.reference_rotation, pose.reference_position
    if R_wr is None or p_wr is None:
        return None
    R_wr = np.asarray(R_wr, dtype=float)
    position = R_wr @ np.asarray(pose.position, dtype=float) + np.asarray(p_wr, dtype=float)
    return PoseMeasurement(R_wr @ pose.rotation, position, pose.covariance, reference=0)


def keyframe_world_pose(
    pose: PoseMeasurement, R_wr: np.ndarray, p_wr: np.ndarray
) -> PoseMeasurement:
    """T_wc = T_wr T_rc of a keyframe-relative pose with the keyframe at (R_wr (3, 3), p_wr
    (3,)), the plane re-placed there when the front end says how; covariance as given."""
    R_rc, p_rc = pose.rotation, np.asarray(pose.position)
    if pose.plane_jacobian is not None and pose.reference_rotation is not None:
        # The front end placed the plane with its own keyframe pose; re-place it at ours.
        import gtsam

        from hvo_graph.estimators.factors import replace_keyframe_plane

        moved = replace_keyframe_plane(
            gtsam.Pose3(gtsam.Rot3(R_rc), p_rc),
            gtsam.Pose3(gtsam.Rot3(pose.reference_rotation), pose.reference_position),
            pose.plane_jacobian,
            gtsam.Pose3(gtsam.Rot3(np.asarray(R_wr, dtype=float)), np.asarray(p_wr, dtype=float)),
        )
        R_rc, p_rc = moved.rotation().matrix(), np.asarray(moved.translation())
    return PoseMeasurement(R_wr @ R_rc, R_wr @ p_rc + p_wr, pose.covariance, reference=0)
