"""The measured-R Kalman filter's error covariance across keyframes (not the paper).

A pose measured against keyframe r becomes a world pose T_wc = T_wr T_rc through
the filter's own estimate of T_wr (the paper's filter has no state for it), so its
error is the keyframe's error moved by the relative pose, plus the relative pose's
own. The filter takes T_wr as exact, and its P then leaves every keyframe's error
out (pose NEES per dof ~34 on a simulated traverse).

The filter's estimates and gains stay as they are; what it reports is the
covariance of its errors, tracked beside P with the keyframes' errors as clones in
the state (stochastic cloning): when poses start to come against frame r (the
frame just filtered), the error covariance of its pose rows c = x[0:6] is copied
in, with the cross terms, and the motion model leaves it unchanged; the latest
:data:`MAX_KEYFRAMES` are kept, for a camera that comes back. A keyframe pose
measures x_pose = g(c, T_rc) (g: the composition in state coordinates, the plane
re-placed at c), so with the filter's gain K on the measured rows,

    e_x <- (I - K S) e_x + K G e_c + K e_z,   S: the rows' selection, G = dg/dc,
    E_a <- (I - K_a H_a) E_a (I - K_a H_a)^T + K_a R K_a^T,   H_a = [S, -G], K_a = [K; 0],

the Joseph form, valid for any gain. Until the first keyframe E = P.

The measured-R filter leaves each reference's shared pixel noise (one offset for
every pose against it) out of R and adds it to the reported covariance; when a
keyframe takes over, that offset is part of the error the state carries on, so it
enters E's pose block before the clone is taken.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from hvo_graph.estimators.base import keyframe_world_pose
from hvo_graph.estimators.factors import keyframe_between_residual
from hvo_graph.estimators.kalman_model import (
    _euler_angles,
    _euler_rates,
    _euler_rates_inverse,
    _rotation,
)
from hvo_graph.types import PoseMeasurement

#: Keyframes whose errors are kept (the front end comes back to its last 15 references).
MAX_KEYFRAMES: int = 16


@dataclass
class KeyframeErrors:
    """The filter's error covariance with the errors of its latest keyframes cloned in.

    Attributes:
        frames: the keyframes' indices, oldest first.
        poses: (6,) [x, y, z, p, w, r] the filter's estimate of each.
        covariance: (12 + 6m, 12 + 6m) Cov([e_x; e_c1; ...; e_cm]).
    """

    frames: list[int]
    poses: list[np.ndarray]
    covariance: np.ndarray

    @property
    def state(self) -> np.ndarray:
        """(12, 12) the error covariance of the filter's state."""
        return self.covariance[:12, :12]

    def add(self, frame: int, pose: np.ndarray, offset_in_state: np.ndarray) -> None:
        """Clone the state's pose rows as keyframe ``frame`` (estimate ``pose`` (6,)), after
        adding ``offset_in_state`` (6, 6), the shared reference noise the poses so far
        carried, to the state's pose block; the oldest clone goes beyond
        :data:`MAX_KEYFRAMES`."""
        E = self.covariance
        E[:6, :6] += offset_in_state
        if len(self.frames) == MAX_KEYFRAMES:
            keep = np.r_[0:12, 18 : E.shape[0]]
            E = E[np.ix_(keep, keep)]
            del self.frames[0], self.poses[0]
        row = E[:6]
        E = np.block([[E, row.T], [row, row[:, :6]]])
        self.frames.append(frame)
        self.poses.append(np.array(pose[:6], dtype=float))
        self.covariance = E

    def find(self, frame: int) -> int | None:
        """The clone slot of keyframe ``frame`` (None: not kept)."""
        return self.frames.index(frame) if frame in self.frames else None

    def predict(self, F: np.ndarray, Q: np.ndarray) -> None:
        """e_x <- F e_x + q; the keyframes' errors stay."""
        E = self.covariance
        E[:12, :12] = F @ E[:12, :12] @ F.T + Q
        E[:12, 12:] = F @ E[:12, 12:]
        E[12:, :12] = E[:12, 12:].T

    def correct(
        self,
        K: np.ndarray,
        rows: np.ndarray,
        R_diag: np.ndarray,
        against: tuple[int, np.ndarray] | None,
    ) -> None:
        """The update with the filter's gain K (12, len(rows)) on ``rows``, noise variances
        ``R_diag``; ``against`` (clone slot, G = dg/dc (6, 6)) when the pose rows are a pose
        measured against a kept keyframe."""
        n, size = len(rows), self.covariance.shape[0]
        H = np.zeros((n, size))
        H[np.arange(n), rows] = 1.0
        if against is not None:
            slot, G = against
            pose = rows < 6
            H[pose, 12 + 6 * slot : 18 + 6 * slot] = -G[rows[pose]]
        K_a = np.zeros((size, n))
        K_a[:12] = K
        I_KH = np.eye(size) - K_a @ H
        E = I_KH @ self.covariance @ I_KH.T + (K_a * R_diag) @ K_a.T
        self.covariance = 0.5 * (E + E.T)


def world_pose(pose: PoseMeasurement, keyframe: np.ndarray) -> np.ndarray:
    """(6,) g(c, T_rc): the world pose [x, y, z, p, w, r] of a keyframe-relative pose with
    the keyframe at ``keyframe`` (6,) [x, y, z, p, w, r] (the plane re-placed there)."""
    p, w, r = keyframe[3:6]
    world = keyframe_world_pose(pose, _rotation(r, p, w), keyframe[:3])
    roll, pitch, yaw = _euler_angles(np.asarray(world.rotation))
    return np.concatenate((world.position, (pitch, yaw, roll)))


def world_pose_jacobian(pose: PoseMeasurement, keyframe: np.ndarray) -> np.ndarray:
    """(6, 6) G = dg/dc at ``keyframe``: in tangents, T_wc = T_wr Z(T_wr) moves by
    Ad(Z^-1) + d(plane re-placement) per right perturbation of T_wr (the keyframe
    factor's own Jacobian, :func:`~hvo_graph.estimators.factors.keyframe_between_residual`,
    at a zero residual), mapped from and to the state's Euler-angle coordinates."""
    p, w, r = keyframe[3:6]
    R_wr = _rotation(r, p, w)
    world = keyframe_world_pose(pose, R_wr, keyframe[:3])
    T_wr = gtsam.Pose3(gtsam.Rot3(R_wr), np.asarray(keyframe[:3], dtype=float))
    Z = gtsam.Pose3(gtsam.Rot3(np.asarray(pose.rotation)), np.asarray(pose.position, dtype=float))
    if pose.plane_jacobian is not None and pose.reference_rotation is not None:
        T_wc = gtsam.Pose3(gtsam.Rot3(np.asarray(world.rotation)), np.asarray(world.position))
        A = gtsam.Pose3(gtsam.Rot3(pose.reference_rotation), pose.reference_position)
        _, (d_keyframe, _) = keyframe_between_residual(
            T_wr, T_wc, Z, A, np.asarray(pose.plane_jacobian), jacobians=True
        )
        tangent = -d_keyframe
    else:
        tangent = Z.inverse().AdjointMap()
    return tangent_to_pose_state(world_pose(pose, keyframe)) @ tangent @ _to_tangent(keyframe)


def tangent_to_pose_state(pose: np.ndarray) -> np.ndarray:
    """(6, 6) d[x, y, z, p, w, r] / d[rot; trans] of a right perturbation at ``pose`` (6,)
    [x, y, z, p, w, r]: position moves by R_wc trans, the angles by E rot (E: the Euler
    rate matrix, :func:`~hvo_graph.estimators.kalman_model.euler_rate_matrix`)."""
    p, w, r = (float(a) for a in pose[3:6])
    out = np.zeros((6, 6))
    out[0:3, 3:6] = _rotation(r, p, w)
    out[3:6, 0:3] = _euler_rates(r, p, "keyframe pose")
    return out


def _to_tangent(pose: np.ndarray) -> np.ndarray:
    """The inverse of :func:`tangent_to_pose_state` (the pose block of
    :func:`~hvo_graph.estimators.kalman_model.state_to_tangent_jacobian`)."""
    p, w, r = (float(a) for a in pose[3:6])
    out = np.zeros((6, 6))
    out[0:3, 3:6] = _euler_rates_inverse(r, p, "keyframe pose")
    out[3:6, 0:3] = _rotation(r, p, w).T
    return out
