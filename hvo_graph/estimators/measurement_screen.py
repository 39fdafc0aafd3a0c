"""The smoother's input checks of a block of frames at once (numpy calls over the block).

:func:`screen_frames` runs the numeric checks of
:func:`~hvo_graph.estimators.measurement_checks.checked_frame` (rotations valid, vectors
finite, covariances symmetric and positive definite, a reference's share a positive
semi-definite part of its pose's covariance) for many frames with one call per test; a
frame that does not pass by a margin is left to the per-frame checks, so every decision
and message stays theirs. :func:`screen_pose_numbers` and :func:`screen_twist_numbers`
are those tests on arrays (a measurement table's columns, no records).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Iterator, Sequence

import numpy as np

from hvo_graph.types import FrameMeasurement, PoseMeasurement

#: A frame's numbers checked by :func:`screen_frames`: (pose factor covariance, the
#: reference's shared covariance, twist z, twist covariance); None where the frame has
#: no such part (a shared covariance: none, or no split).
Screened = tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None, np.ndarray | None]

#: A batched test passes a frame only by this margin (relative to the matrix's largest
#: entry): rounding in a batched call can then not flip a decision of the frame's own
#: test, and an eigenvalue this far above zero guarantees the Cholesky factorization.
SCREEN_MARGIN: float = 1e-10

#: Frames :func:`screened` checks at once.
SCREEN_BLOCK: int = 128

_I3 = np.eye(3)


def _is_array(value: object, shape: tuple[int, ...]) -> bool:
    return type(value) is np.ndarray and value.dtype == np.float64 and value.shape == shape  # type: ignore[union-attr]


def plain_frame(frame: FrameMeasurement, split: bool) -> bool:
    """Whether the frame's numbers have the usual form (float64 arrays of their shapes)."""
    pose, velocity = frame.pose, frame.velocity
    if pose is not None and not (
        _is_array(pose.rotation, (3, 3))
        and _is_array(pose.position, (3,))
        and _is_array(pose.covariance, (6, 6))
        and (
            not split
            or pose.reference_covariance is None
            or _is_array(pose.reference_covariance, (6, 6))
        )
    ):
        return False
    return velocity is None or (
        _is_array(velocity.twist, (6,)) and _is_array(velocity.covariance, (6, 6))
    )


def _symmetric_ok(c: np.ndarray) -> np.ndarray:
    """(n,) the symmetry test of :func:`~hvo_graph.errors.as_covariance` per matrix (exact)."""
    return np.abs(c - np.swapaxes(c, 1, 2)).max(axis=(1, 2)) <= 1e-9 * np.abs(c).max(axis=(1, 2))


def _definite(c: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(n,) whether each matrix still ``ok`` (finite) has a lower triangle (what Cholesky
    reads) positive definite by :data:`SCREEN_MARGIN`."""
    out = np.zeros(len(c), dtype=bool)
    c = c[ok]
    out[ok] = _smallest_above(c, SCREEN_MARGIN * np.abs(c).max(axis=(1, 2)))
    return out


def _smallest_above(c: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(n,) whether the smallest eigenvalue of each matrix (its lower triangle) exceeds
    ``floor`` (n,): c - floor I positive definite. One batched Cholesky where every
    matrix passes (the usual case, 9x faster than the eigenvalues), else the eigenvalues."""
    try:
        np.linalg.cholesky(c - floor[:, None, None] * np.eye(c.shape[-1]))
        return np.ones(len(c), dtype=bool)
    except np.linalg.LinAlgError:
        return np.linalg.eigvalsh(c)[:, 0] > floor


def _screen_poses(poses: list[PoseMeasurement], split: bool) -> tuple[np.ndarray, list, list]:
    """(n,) pass flags, factor covariances and shared covariances (or None) of the poses."""
    has = np.array([split and p.reference_covariance is not None for p in poses])
    ok, factor, rows, ref = screen_pose_numbers(
        np.array([p.rotation for p in poses]),
        np.array([p.position for p in poses]),
        np.array([p.covariance for p in poses]),
        has,
        lambda rows: np.array([poses[i].reference_covariance for i in rows]),
        split,
    )
    shared: list = [None] * len(poses)
    for j, i in enumerate(rows.tolist()):
        shared[i] = ref[j]
    return ok, list(factor), shared


def screen_pose_numbers(
    R: np.ndarray,
    p: np.ndarray,
    C: np.ndarray,
    has: np.ndarray,
    references: Callable[[np.ndarray], np.ndarray],
    split: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The numeric checks of n poses (R (n, 3, 3), p (n, 3), covariance C (n, 6, 6); those
    ``has`` (n,) with their reference's share apart, ``references(rows)`` (m, 6, 6);
    ``split``: shares are split off): (ok (n,), factor covariances (n, 6, 6), the rows
    with a share, their shares (m, 6, 6))."""
    ok = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(C).all(axis=(1, 2))
    ok &= np.isfinite(p).all(axis=1)
    ok &= np.abs(np.swapaxes(R, 1, 2) @ R - _I3).max(axis=(1, 2)) <= 1e-6 - SCREEN_MARGIN
    ok &= np.linalg.det(np.where(ok[:, None, None], R, _I3)) > 0.5  # R^T R = I: det +-1
    ok &= _symmetric_ok(C)
    sym = 0.5 * (C + np.swapaxes(C, 1, 2))
    # No split: the covariance as given must be definite (checked_pose), else the
    # symmetrized one (checked_reference_covariance without a reference).
    ok &= has | _definite(sym if split else C, ok & ~has)
    rows = np.flatnonzero(has & ok)
    ref = np.zeros((0, 6, 6))
    if len(rows):
        ref = references(rows)
        finite = np.isfinite(ref).all(axis=(1, 2))
        ok[rows[~finite]] = False
        rows, ref = rows[finite], ref[finite]
        ref = 0.5 * (ref + np.swapaxes(ref, 1, 2))
        own = sym[rows] - ref
        scale = np.maximum(1e-300, np.abs(ref).max(axis=(1, 2)))
        # The reference's share positive semi-definite (to 1e-9 of its scale), the pose's
        # own part and the whole positive definite.
        passed = (
            _smallest_above(ref, (-1e-9 + SCREEN_MARGIN) * scale)
            & _smallest_above(own, SCREEN_MARGIN * np.abs(own).max(axis=(1, 2)))
            & _smallest_above(sym[rows], SCREEN_MARGIN * np.abs(sym[rows]).max(axis=(1, 2)))
        )
        ok[rows] &= passed
        sym[rows] = own
    return ok, sym, rows, ref


def screen_frames(
    frames: Sequence[FrameMeasurement], *, split_reference: bool
) -> list[Screened | None]:
    """The numeric checks of :func:`checked_frame` for a block of frames, vectorised.

    Per frame: its :data:`Screened` numbers, exactly those its own checks return
    (the rotation valid, vectors finite, covariances symmetric and positive definite,
    the reference's share a positive semi-definite part of the pose covariance); or
    None where the frame does not have the usual form or a test does not pass by
    :data:`SCREEN_MARGIN`: :func:`checked_frame` then checks it on its own, so every
    decision and message stays that of the per-frame checks.
    """
    with np.errstate(all="ignore"):  # NaN or inf: the frame is checked on its own
        return _screen(frames, split_reference)


def _screen(frames: Sequence[FrameMeasurement], split_reference: bool) -> list[Screened | None]:
    out: list[Screened | None] = [None] * len(frames)
    plain = [i for i, f in enumerate(frames) if plain_frame(f, split_reference)]
    posed = [i for i in plain if frames[i].pose is not None]
    moving = [i for i in plain if frames[i].velocity is not None]
    passed = dict.fromkeys(plain, True)
    pose_part: dict[int, tuple] = {}
    if posed:
        ok, factor, shared = _screen_poses([frames[i].pose for i in posed], split_reference)  # type: ignore[misc]
        for j, i in enumerate(posed):
            passed[i] = bool(ok[j])
            pose_part[i] = (factor[j], shared[j])
    twist_part: dict[int, tuple] = {}
    if moving:
        velocities = [frames[i].velocity for i in moving]
        Z = np.array([v.twist for v in velocities])  # type: ignore[union-attr]
        ok, sym = screen_twist_numbers(Z, np.array([v.covariance for v in velocities]))  # type: ignore[union-attr]
        for j, i in enumerate(moving):
            passed[i] = passed[i] and bool(ok[j])
            twist_part[i] = (Z[j], sym[j])
    for i, good in passed.items():
        if good:
            out[i] = (*pose_part.get(i, (None, None)), *twist_part.get(i, (None, None)))
    return out


def screen_twist_numbers(Z: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numeric checks of n twists z (n, 6) with covariances C (n, 6, 6): (ok (n,),
    the symmetrized covariances)."""
    ok = np.isfinite(Z).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    ok &= _symmetric_ok(C)
    ok &= _definite(C, ok)
    return ok, 0.5 * (C + np.swapaxes(C, 1, 2))


def screened(
    frames: Iterable[FrameMeasurement], split_reference: bool
) -> Iterator[tuple[list[FrameMeasurement], list[Screened | None]]]:
    """Blocks of :data:`SCREEN_BLOCK` frames with their :func:`screen_frames` entries (a
    block's records are held, not the whole sequence's)."""
    stream = iter(frames)
    while block := list(itertools.islice(stream, SCREEN_BLOCK)):
        yield block, screen_frames(block, split_reference=split_reference)
