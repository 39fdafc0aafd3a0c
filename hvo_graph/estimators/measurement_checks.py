"""Checks of the measurement records a factor-graph smoother is given.

Each returns the values the graph needs, or raises InputError naming the frame
and the field; the smoother calls them all before it changes any state.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Sequence

import gtsam
import numpy as np

from hvo_graph.errors import (
    InputError,
    as_covariance,
    as_integer,
    as_matrix,
    as_rotation,
    as_vector,
)
from hvo_graph.estimators.factors import interval_weights
from hvo_graph.estimators.measurement_screen import Screened
from hvo_graph.geometry._fit import plane_basis
from hvo_graph.types import (
    FrameMeasurement,
    PoseMeasurement,
    TiltMeasurement,
    VelocityMeasurement,
)


def checked_covariance(matrix: object, name: str) -> np.ndarray:
    """A (6, 6) symmetric positive definite covariance, symmetrized, or InputError."""
    c = as_covariance(matrix, name, 6)
    return 0.5 * (c + c.T)


def checked_pose(
    pose: PoseMeasurement, k: int, *, definite: bool = True
) -> tuple[gtsam.Pose3, np.ndarray, int]:
    """(measured pose, covariance, reference index) of frame k's H_d pose, or InputError.

    ``definite=False`` leaves the covariance's positive definiteness to the caller
    (:func:`checked_reference_covariance` with ``covariance`` tests it with the split).
    """
    name = f"frame {k}: pose"
    R = as_rotation(pose.rotation, f"{name}.rotation")
    p = np.asarray(pose.position, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"{name}.position: expected a finite (3,) vector, got shape {p.shape}")
    if definite:
        cov = checked_covariance(pose.covariance, f"{name}.covariance")
    else:
        cov = _symmetric_covariance(pose.covariance, f"{name}.covariance")
    return gtsam.Pose3(gtsam.Rot3(R), p), cov, _checked_reference_index(pose, k)


def _checked_reference_index(pose: PoseMeasurement, k: int) -> int:
    name = f"frame {k}: pose.reference"
    ref = as_integer(pose.reference, name, 0, what="a frame index")
    if ref != 0 and ref >= k:
        raise InputError(f"{name}: expected an earlier frame than {k}, got {ref}")
    return int(ref)


def _symmetric_covariance(matrix: object, name: str) -> np.ndarray:
    """A finite, symmetric (6, 6) matrix, symmetrized (as_covariance without the factorization)."""
    c = as_matrix(matrix, name, (6, 6))
    if np.abs(c - c.T).max() > 1e-9 * np.abs(c).max():
        raise InputError(f"{name}: expected a symmetric matrix")
    return 0.5 * (c + c.T)


def checked_velocity(velocity: VelocityMeasurement, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(twist, covariance) of frame k's H_c twist, or InputError."""
    name = f"frame {k}: velocity"
    z = np.asarray(velocity.twist, dtype=float)
    if z.shape != (6,) or not np.all(np.isfinite(z)):
        raise InputError(f"{name}.twist: expected a finite (6,) vector, got shape {z.shape}")
    cov = checked_covariance(velocity.covariance, f"{name}.covariance")
    _check_interval(velocity, name)
    return z, cov


def checked_tilt(
    tilt: TiltMeasurement | None, k: int, known: Container[int]
) -> TiltMeasurement | None:
    """Frame k's keyframe tilt (unit normals, a covariance positive definite across n_r,
    an earlier frame), as float arrays, or InputError; None stays None."""
    if tilt is None:
        return None
    name = f"frame {k}: keyframe_tilt"
    r = as_integer(tilt.frame, f"{name}.frame", 0, what="a frame index")
    if r not in known:
        raise InputError(f"{name}.frame: {r} is not an earlier frame of this sequence")
    normals = []
    for field in ("normal", "world_normal"):
        n = as_vector(getattr(tilt, field), f"{name}.{field}", 3)
        if abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise InputError(f"{name}.{field}: expected a unit vector, norm {np.linalg.norm(n)}")
        normals.append(n)
    C = as_matrix(tilt.covariance, f"{name}.covariance", (3, 3))
    basis = plane_basis(normals[0])
    as_covariance(basis @ (0.5 * (C + C.T)) @ basis.T, f"{name}.covariance (across normal)", 2)
    return TiltMeasurement(r, normals[0], normals[1], 0.5 * (C + C.T))


def _check_interval(velocity: VelocityMeasurement, name: str) -> None:
    if not math.isfinite(velocity.t):
        raise InputError(f"{name}.t: expected a finite time, got {velocity.t}")
    if not (math.isfinite(velocity.dt) and velocity.dt >= 0):
        raise InputError(f"{name}.dt: expected a finite interval >= 0, got {velocity.dt}")


def keyframe_model(pose: PoseMeasurement, k: int) -> tuple[gtsam.Pose3, np.ndarray] | None:
    """(assumed keyframe pose A, plane Jacobian J) of a keyframe-relative pose, or None."""
    fields = (pose.reference_rotation, pose.reference_position, pose.plane_jacobian)
    if all(f is None for f in fields):
        return None
    name = f"frame {k}: pose"
    if any(f is None for f in fields):
        raise InputError(
            f"{name}: reference_rotation, reference_position and plane_jacobian go together"
        )
    R = as_rotation(pose.reference_rotation, f"{name}.reference_rotation")
    p = np.asarray(pose.reference_position, dtype=float)
    J = np.asarray(pose.plane_jacobian, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"{name}.reference_position: expected a finite (3,) vector")
    if J.shape != (6, 6) or not np.all(np.isfinite(J)):
        raise InputError(f"{name}.plane_jacobian: expected a finite (6, 6) matrix")
    return gtsam.Pose3(gtsam.Rot3(R), p), J


def checked_reference_covariance(
    pose: PoseMeasurement, k: int, covariance: np.ndarray | None = None
) -> np.ndarray | None:
    """The pose's reference covariance (None when absent), symmetrized and checked.

    It must be a positive semi-definite part of the pose covariance: what is
    left, the frame's own noise, must stay positive definite. ``covariance``: the
    pose covariance, checked but for its definiteness (``checked_pose(...,
    definite=False)``): tested here too, in the same batched eigenvalue call.
    """
    if pose.reference_covariance is None:
        if covariance is not None:
            checked_covariance(covariance, f"frame {k}: pose.covariance")
        return None
    name = f"frame {k}: pose.reference_covariance"
    ref = np.asarray(pose.reference_covariance, dtype=float)
    if ref.shape != (6, 6) or not np.all(np.isfinite(ref)):
        raise InputError(f"{name}: expected a finite (6, 6) matrix")
    ref = 0.5 * (ref + ref.T)
    full = np.asarray(pose.covariance, dtype=float) if covariance is None else covariance
    own = full - ref
    scale = max(1e-300, float(np.abs(ref).max()))
    if covariance is None:
        smallest = np.linalg.eigvalsh(np.stack((ref, own)))[:, 0]
    else:
        smallest = np.linalg.eigvalsh(np.stack((ref, own, covariance)))[:, 0]
        if not smallest[2] > 0:
            raise InputError(f"frame {k}: pose.covariance: expected a positive definite matrix")
    if smallest[0] < -1e-9 * scale or not smallest[1] > 0:
        raise InputError(
            f"{name}: expected a positive semi-definite part of pose.covariance "
            "(covariance - reference_covariance positive definite)"
        )
    return ref


def twist_nodes(
    k: int,
    t: float,
    meas: VelocityMeasurement,
    times: Sequence[float],
    indices: Sequence[int],
    in_graph: Callable[[int], bool],
    lag: float,
) -> tuple[list[int], list[float]]:
    """Frame indices and weights of the mean-twist factor of frame k (at time t).

    ``times`` and ``indices`` are the frames before k; ``in_graph`` tells whether a
    frame is still a variable (fixed-lag window of ``lag`` seconds).
    """
    start, end = meas.t - 0.5 * meas.dt, meas.t + 0.5 * meas.dt
    tol = 1e-9 * max(1.0, abs(t))
    if start > t + tol:
        raise InputError(
            f"frame {k}: velocity interval [{start:.6g}, {end:.6g}] s starts after the "
            f"frame time {t:.6g} s"
        )
    first_time = times[0] if times else t
    if end < first_time - tol:
        raise InputError(
            f"frame {k}: velocity interval [{start:.6g}, {end:.6g}] s ends before the "
            f"first frame ({first_time:.6g} s)"
        )
    if times and abs(start - times[-1]) <= tol and abs(end - t) <= tol:
        # the usual finite-difference interval [t_{k-1}, t_k]
        nodes, weights = [indices[-1], k], [0.5, 0.5]
    else:
        # Only the nodes that can carry weight: from the last one at or before `start`.
        first = len(times)
        while first > 0 and (first == len(times) or times[first] > start):
            first -= 1
        node_times = [*times[first:], t]
        candidates = [*indices[first:], k]
        weighted = interval_weights(node_times, start, end)
        nodes = [candidates[i] for i, _ in weighted]
        weights = [w for _, w in weighted]
    for index in nodes:
        if index != k and not in_graph(index):
            raise InputError(
                f"frame {k}: the velocity interval [{start:.6g}, {end:.6g}] s reaches frame "
                f"{index}, which already left the fixed-lag window ({lag} s); "
                "increase lag"
            )
    return nodes, weights


def poses_span(previous: int, previous_reference: int | None, reference: int) -> bool:
    """Whether two consecutive H_d poses already measure the interval between them.

    True when the next frame's pose is against the same reference as frame
    ``previous``'s (``previous_reference``; None: it had no pose) or against
    ``previous`` itself: the flow over that interval is made of the same pixels,
    and an H_c twist there would count them twice.
    """
    return reference == previous or previous_reference == reference


#: A checked frame: (k, t, pose, twist). pose: (measured Pose3, factor covariance,
#: reference[, the reference's shared covariance]); twist: (z, covariance, node
#: frame indices, node weights).
CheckedFrame = tuple[int, float, tuple | None, tuple | None]


def checked_frame(
    frame: FrameMeasurement,
    times: Sequence[float],
    indices: Sequence[int],
    in_graph: Callable[[int], bool],
    lag: float,
    *,
    known: Container[int],
    split_reference: bool,
    screened: Screened | None = None,
) -> CheckedFrame:
    """Every check of a frame for the smoother, before it changes anything.

    Args:
        frame: the next frame.
        times, indices: the frames so far (times, indices, in order).
        in_graph: whether an earlier frame is still a variable of the graph.
        lag: fixed-lag window (s), for the twist nodes.
        known: the frame indices so far (a set or dict: a reference must be one).
        split_reference: the pose factor carries the frame's own pixel noise only;
            the reference's share comes fourth in the pose tuple.
        screened: the frame's entry of :func:`~.measurement_screen.screen_frames` (same
            ``split_reference``): its numbers are checked already; None: every check here.
    Raises:
        InputError: naming the frame and the field.
    """
    k, t = as_integer(frame.index, "frame.index", 0), float(frame.t)
    checked_tilt(frame.keyframe_tilt, k, known)
    if not math.isfinite(t):
        raise InputError(f"frame {k}: t is not finite ({frame.t})")
    # With the split, the pose covariance's definiteness is tested with the split's
    # eigenvalues (one batched call) instead of a Cholesky factorization of its own.
    split = split_reference and frame.pose is not None
    if screened is not None:
        return _screened_frame(frame, k, t, screened, times, indices, in_graph, lag, known)
    pose_meas = None if frame.pose is None else checked_pose(frame.pose, k, definite=not split)
    velocity = None if frame.velocity is None else checked_velocity(frame.velocity, k)
    if pose_meas is not None and pose_meas[2] != 0 and pose_meas[2] not in known:
        raise InputError(
            f"frame {k}: pose.reference {pose_meas[2]} is not an earlier frame of this sequence"
        )
    twist_meas = None
    if velocity is not None:
        assert frame.velocity is not None
        nodes = twist_nodes(k, t, frame.velocity, times, indices, in_graph, lag)
        twist_meas = (*velocity, *nodes)
    if pose_meas is not None and split:
        assert frame.pose is not None
        reference = checked_reference_covariance(frame.pose, k, pose_meas[1])
        if reference is not None:
            pose_meas = (pose_meas[0], pose_meas[1] - reference, pose_meas[2], reference)
    return k, t, pose_meas, twist_meas


def _screened_frame(
    frame: FrameMeasurement,
    k: int,
    t: float,
    screened: Screened,
    times: Sequence[float],
    indices: Sequence[int],
    in_graph: Callable[[int], bool],
    lag: float,
    known: Container[int],
) -> CheckedFrame:
    """:func:`checked_frame` of a frame whose numbers
    :func:`~.measurement_screen.screen_frames` checked: the remaining checks, in order."""
    pose, velocity = frame.pose, frame.velocity
    factor, shared, z, covariance = screened
    pose_meas: tuple | None = None
    if pose is not None:
        ref = _checked_reference_index(pose, k)
        measured = gtsam.Pose3(gtsam.Rot3(pose.rotation), pose.position)
        pose_meas = (measured, factor, ref) if shared is None else (measured, factor, ref, shared)
    if velocity is not None:
        _check_interval(velocity, f"frame {k}: velocity")
    if pose_meas is not None and pose_meas[2] != 0 and pose_meas[2] not in known:
        raise InputError(
            f"frame {k}: pose.reference {pose_meas[2]} is not an earlier frame of this sequence"
        )
    twist_meas = None
    if velocity is not None:
        nodes = twist_nodes(k, t, velocity, times, indices, in_graph, lag)
        twist_meas = (z, covariance, *nodes)
    return k, t, pose_meas, twist_meas
