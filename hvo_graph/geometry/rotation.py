"""Rotations: skew matrices, SO(3) projection, and the paper's Euler angles.

Euler convention (paper eqs. 3-5, NOTES section 4, contract): roll r, pitch p,
yaw w with

    R_wc = R_y(w) R_x(p) R_z(r)

so yaw turns about the camera's y axis (down), pitch about x (right), roll
about the optical axis z. Body rates (wx, wy, wz) are in the camera frame.
"""

from __future__ import annotations

import numpy as np

from hvo_graph.errors import InputError, as_matrix, as_vector

#: |cos p| below this is treated as the singularity of eqs. 3-5 (p = +-90 deg).
GIMBAL_LOCK_COS = 1e-6


def skew(w: np.ndarray) -> np.ndarray:
    """(3, 3) matrix w^ with w^ x = w × x."""
    wx, wy, wz = as_vector(w, "w", 3)
    return np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to ``M`` in Frobenius norm (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(as_matrix(M, "M", (3, 3)))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R_wc = R_y(yaw) R_x(pitch) R_z(roll)."""
    return rot_y(yaw) @ rot_x(pitch) @ rot_z(roll)


def rotation_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_to_rotation`: (roll r, pitch p, yaw w), p in [-pi/2, pi/2].

    From R = R_y(w) R_x(p) R_z(r): R[1,2] = -sin p, R[0,2] = cos p sin w,
    R[2,2] = cos p cos w, R[1,0] = cos p sin r, R[1,1] = cos p cos r.

    Raises:
        InputError: at gimbal lock (|cos p| < GIMBAL_LOCK_COS), where r and w
            are not separable.
    """
    R = as_matrix(R, "R", (3, 3))
    pitch = float(np.arcsin(np.clip(-R[1, 2], -1.0, 1.0)))
    if np.hypot(R[1, 0], R[1, 1]) < GIMBAL_LOCK_COS:
        raise InputError("rotation: pitch is +-90 deg (gimbal lock); roll and yaw are undefined")
    yaw = float(np.arctan2(R[0, 2], R[2, 2]))
    roll = float(np.arctan2(R[1, 0], R[1, 1]))
    return roll, pitch, yaw


def euler_rates(roll: float, pitch: float, w_body: np.ndarray) -> np.ndarray:
    """Paper eqs. 3-5: (rdot, pdot, wdot) from body rates (wx, wy, wz).

        rdot = (wx sin r + wy cos r) tan p + wz
        pdot =  wx cos r - wy sin r
        wdot = (wx sin r + wy cos r) sec p

    Raises:
        InputError: near p = +-90 deg, where the equations are singular.
    """
    cp = np.cos(pitch)
    if abs(cp) < GIMBAL_LOCK_COS:
        raise InputError(
            "pitch is +-90 deg: the Euler rate equations (paper eqs. 3-5) are singular"
        )
    wx, wy, wz = as_vector(w_body, "w_body", 3)
    a = wx * np.sin(roll) + wy * np.cos(roll)
    return np.array([a * np.tan(pitch) + wz, wx * np.cos(roll) - wy * np.sin(roll), a / cp])


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2.0 * np.pi)
