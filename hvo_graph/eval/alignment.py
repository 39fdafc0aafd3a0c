"""Alignment of an estimate to ground truth: none, origin, SE(3) or Sim(3) (Umeyama).

A monocular or drifting estimate lives in its own world frame (and, without a
known plane distance d*, its own scale). Before absolute errors are taken the
estimate may be moved onto the ground truth, as ``evo_ape`` does:

- ``none``: compared as they are (both share W = F*, the contract's default);
- ``origin``: the transform that maps the estimate's first pose onto the ground
  truth's first pose, T = T_gt,0 T_est,0^-1, applied to every pose;
- ``se3`` / ``sim3``: the rotation R, translation t (and scale s) that minimise
  sum_k ||p_gt,k - (s R p_est,k + t)||^2 over the associated positions
  (Umeyama 1991, optionally the first ``n`` of them).

The aligned pose is (R R_wc, s R p_wc + t). Body velocities are unchanged by
a rigid motion of the world; a scale s multiplies the linear velocity v.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.types import Trajectory

#: Alignment names accepted by :func:`align` (and ``hvo-graph evaluate --align``).
ALIGNMENTS = ("none", "origin", "se3", "sim3")


@dataclass(frozen=True)
class Alignment:
    """A similarity transform p -> s R p + t applied to an estimate.

    Attributes:
        method: one of :data:`ALIGNMENTS`.
        rotation: (3, 3) R.
        translation: (3,) t, metres.
        scale: s (1 unless ``sim3``).
        poses: number of associated poses the transform was fitted to (0 for none).
    """

    method: str
    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0
    poses: int = 0

    def apply(self, trajectory: Trajectory) -> Trajectory:
        """The transformed copy of ``trajectory`` (twists: v scaled by s; covariances dropped)."""
        R, t, s = self.rotation, self.translation, self.scale
        twists = None
        if trajectory.twists is not None:
            twists = np.array(trajectory.twists, dtype=float)
            twists[:, 3:] *= s
        return Trajectory(
            t=np.array(trajectory.t, dtype=float),
            rotations=np.einsum("ij,kjl->kil", R, np.asarray(trajectory.rotations)),
            positions=s * np.asarray(trajectory.positions) @ R.T + t,
            twists=twists,
        )

    def as_dict(self) -> dict[str, object]:
        """Plain values for JSON: method, rotation (3x3 list), translation, scale, poses."""
        return {
            "method": self.method,
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "scale": float(self.scale),
            "poses": self.poses,
        }


def umeyama(
    source: np.ndarray, target: np.ndarray, *, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (R, t, s) with target_k ~ s R source_k + t (Umeyama 1991).

    Args:
        source: (N, 3) points, e.g. estimate positions.
        target: (N, 3) points, e.g. ground-truth positions.
        with_scale: fit s (Sim(3)); otherwise s = 1 (SE(3)).
    Returns:
        R (3, 3) with det R = +1, t (3,), s.
    Raises:
        InputError: when the points do not fix a rotation (fewer than 3, or all on a line).
    """
    x, y = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"umeyama: expected two (N, 3) arrays, got {x.shape} and {y.shape}")
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    cov = yc.T @ xc / len(x)  # eq. 38
    u, d, vt = np.linalg.svd(cov)
    if len(x) < 3 or np.count_nonzero(d > np.finfo(float).eps) < 2:
        raise InputError(
            f"alignment: the {len(x)} estimate positions used do not fix a rotation "
            "(fewer than 3, or all on one line); use --align origin or none, or more poses"
        )
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:  # a reflection otherwise, eq. 43
        sign[2] = -1.0
    R = (u * sign) @ vt
    s = float(np.sum(d * sign) / np.mean(np.sum(xc**2, axis=1))) if with_scale else 1.0
    return R, mean_y - s * R @ mean_x, s


def _pose_matrix(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def align(
    estimate: Trajectory, groundtruth: Trajectory, method: str = "none", *, n: int | None = None
) -> Alignment:
    """The alignment of ``estimate`` onto ``groundtruth`` (associated: pose k with pose k).

    Args:
        estimate, groundtruth: trajectories of equal length, already associated.
        method: one of :data:`ALIGNMENTS`.
        n: fit ``se3``/``sim3`` to the first ``n`` poses only (None: all).
    Raises:
        InputError: for an unknown method, ``n`` with none/origin, or degenerate positions.
    """
    if method not in ALIGNMENTS:
        raise InputError(f"--align: expected one of {', '.join(ALIGNMENTS)}, got {method!r}")
    if n is not None and method in ("none", "origin"):
        raise InputError(f"--n-to-align: applies to --align se3 or sim3, not {method}")
    if len(estimate) != len(groundtruth) or len(estimate) == 0:
        raise InputError("align: expected two associated trajectories of the same length")
    if method == "none":
        return Alignment("none", np.eye(3), np.zeros(3))
    if method == "origin":
        T = _pose_matrix(groundtruth.rotations[0], groundtruth.positions[0]) @ np.linalg.inv(
            _pose_matrix(estimate.rotations[0], estimate.positions[0])
        )
        return Alignment("origin", T[:3, :3], T[:3, 3], 1.0, 1)
    k = len(estimate) if n is None else min(n, len(estimate))
    R, t, s = umeyama(
        np.asarray(estimate.positions)[:k],
        np.asarray(groundtruth.positions)[:k],
        with_scale=method == "sim3",
    )
    return Alignment(method, R, t, s, k)
