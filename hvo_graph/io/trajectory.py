"""Trajectory files of the contract: TUM poses, velocity CSV, covariance CSV, and their folders.

``trajectory.txt`` / ``groundtruth.txt`` (TUM, what ``evo_ape tum`` reads):
one line per frame ``timestamp tx ty tz qx qy qz qw`` (space separated), the
pose T_wc (camera to world, world = first camera frame); ``#`` lines are
comments. Quaternions are written with qw >= 0; on reading they are
normalised (a norm off 1 by more than 1e-3 is an error).

``velocity.csv`` / ``groundtruth_velocity.csv``: header ``t,vx,vy,vz,wx,wy,wz``,
the camera's body velocity in the current camera frame (d/dt T_wc = T_wc
[w; v]^). Note the column order v, w while :class:`~hvo_graph.types.Trajectory`
twists are [w; v] (GTSAM's order). A velocity that is unknown at a frame may be
written as ``nan`` (all six values); evaluation skips such frames.

``covariance.csv`` (written only when an estimate carries covariances): header
``t,c_0_0,c_0_1,...,c_0_11,c_1_1,...,c_11_11``, i.e. the time and the 78
upper-triangular entries (row-major, i <= j) of the 12x12 marginal covariance
of [pose tangent; twist] = [rot (3); trans (3); w (3); v (3)], the pose part in
GTSAM's right-perturbation convention (T_true = T_est * Exp(delta)).

All values are written at full double precision (Python's shortest round-trip
repr), so a write/read round trip is exact.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.io._common import (
    PathLike,
    atomic_write_text,
    check_finite,
    check_increasing,
    csv_body,
    first_line,
    parse_table,
    read_text,
)
from hvo_graph.types import Trajectory

VELOCITY_HEADER = "t,vx,vy,vz,wx,wy,wz"
_VELOCITY_COLUMNS = tuple(VELOCITY_HEADER.split(","))
_TUM_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
_TUM_COMMENT = "# timestamp tx ty tz qx qy qz qw  (T_wc, camera to world; metres)"
_IU = np.triu_indices(12)
COVARIANCE_HEADER = "t," + ",".join(f"c_{i}_{j}" for i, j in zip(*_IU, strict=True))
_COVARIANCE_COLUMNS = tuple(COVARIANCE_HEADER.split(","))

#: File names inside an estimate folder and a ground-truth folder.
ESTIMATE_FILES = ("trajectory.txt", "velocity.csv", "covariance.csv")
GROUNDTRUTH_FILES = ("groundtruth.txt", "groundtruth_velocity.csv")

#: Largest accepted deviation of a rotation from orthonormality, max |R^T R - I|.
_ROTATION_TOL = 1e-6
#: Largest accepted | |q| - 1 | of a quaternion read from a TUM file.
_QUATERNION_TOL = 1e-3


def _check_times(t: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1:
        raise InputError(f"{name}: expected shape (K,), got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{name}: contains NaN or inf")
    if np.any(np.diff(t) <= 0):
        raise InputError(f"{name}: timestamps must be strictly increasing")
    return t


def _check_trajectory(trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = _check_times(trajectory.t, "trajectory.t")
    k = len(t)
    R = np.asarray(trajectory.rotations, dtype=float)
    p = np.asarray(trajectory.positions, dtype=float)
    if R.shape != (k, 3, 3) or p.shape != (k, 3):
        raise InputError(
            f"trajectory: expected rotations ({k}, 3, 3) and positions ({k}, 3), "
            f"got {R.shape} and {p.shape}"
        )
    bad = ~(np.isfinite(R).all(axis=(1, 2)) & np.isfinite(p).all(axis=1))
    if bad.any():
        raise InputError(f"trajectory: pose {int(np.flatnonzero(bad)[0])} contains NaN or inf")
    err = np.abs(np.einsum("kji,kjl->kil", R, R) - np.eye(3)).max(axis=(1, 2))
    err = np.maximum(err, np.abs(np.linalg.det(R) - 1.0))
    if np.any(err > _ROTATION_TOL):
        i = int(np.argmax(err > _ROTATION_TOL))
        raise InputError(
            f"trajectory.rotations[{i}]: not a rotation matrix (orthonormality error {err[i]:.2g})"
        )
    return t, R, p


#: Rows formatted per piece of a written file (bounds the text held at once).
_ROWS_PER_PIECE = 4096


def _text(header: str, table: np.ndarray, sep: str) -> Iterator[str]:
    """The lines ``header`` and each row of ``table`` (repr of every value, ``sep``
    between), in pieces of :data:`_ROWS_PER_PIECE` rows: a long file is never one string."""
    yield header + "\n"
    for start in range(0, len(table), _ROWS_PER_PIECE):
        rows = (table[start : start + _ROWS_PER_PIECE] + 0.0).tolist()  # + 0.0: no "-0.0"
        yield "".join(sep.join(map(repr, row)) + "\n" for row in rows)


def write_tum(path: PathLike, trajectory: Trajectory) -> None:
    """Write the poses T_wc of ``trajectory`` as a TUM file (atomically).

    Args:
        path: destination file.
        trajectory: t (K,), rotations (K, 3, 3) R_wc, positions (K, 3) p_wc.
    Raises:
        InputError: on non-increasing times, NaN, or a matrix that is not a rotation.
    """
    t, R, p = _check_trajectory(trajectory)
    q = _quaternions(R)
    atomic_write_text(path, _text(_TUM_COMMENT, np.column_stack((t, p, q)), " "))


def _quaternions(R: np.ndarray) -> np.ndarray:
    """(K, 4) unit quaternions (qx, qy, qz, qw), qw >= 0, of (K, 3, 3) near-rotations.

    The arithmetic of ``gtsam.Rot3(nearest_rotation(R)).toQuaternion()`` (Eigen's
    rotation-matrix conversion, Shepperd's method), over all rows at once: each R is
    projected onto SO(3) by SVD (Rot3 needs an exactly orthonormal matrix), then the
    largest of w, x, y, z is taken from the diagonal and the others from the sums and
    differences of the off-diagonal entries.
    """
    U, _, Vt = np.linalg.svd(R)
    D = np.ones((len(R), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    M = (U * D[:, None, :]) @ Vt
    q = np.empty((len(R), 4))  # x, y, z, w
    trace = M[:, 0, 0] + (M[:, 1, 1] + M[:, 2, 2])  # Eigen's order of the sum
    positive = trace > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sqrt(trace + 1.0)
        half = 0.5 / s
        q[:, 3] = 0.5 * s
        q[:, 0] = (M[:, 2, 1] - M[:, 1, 2]) * half
        q[:, 1] = (M[:, 0, 2] - M[:, 2, 0]) * half
        q[:, 2] = (M[:, 1, 0] - M[:, 0, 1]) * half
        for i in (0, 1, 2):
            j, k = (i + 1) % 3, (i + 2) % 3
            diag = M[:, (0, 1, 2), (0, 1, 2)]
            first = np.where(diag[:, 1] > diag[:, 0], 1, 0)
            largest = np.where(diag[:, 2] > diag[np.arange(len(M)), first], 2, first)
            rows = ~positive & (largest == i)
            if not rows.any():
                continue
            m = M[rows]
            s = np.sqrt(m[:, i, i] - m[:, j, j] - m[:, k, k] + 1.0)
            half = 0.5 / s
            out = np.empty((len(m), 4))
            out[:, i] = 0.5 * s
            out[:, 3] = (m[:, k, j] - m[:, j, k]) * half
            out[:, j] = (m[:, j, i] + m[:, i, j]) * half
            out[:, k] = (m[:, k, i] + m[:, i, k]) * half
            q[rows] = out
    return np.where(q[:, 3:4] < 0, -q, q)


def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, ``#`` comments).

    Returns:
        Trajectory with t (K,), rotations (K, 3, 3) R_wc, positions (K, 3); twists None.
    Raises:
        InputError: "<file>:<line>: ..." for a line that is not 8 numbers, NaN/inf,
            a bad quaternion, non-increasing timestamps, or no poses at all.
        OSError: when the file cannot be read.
    """
    lines, linenos = [], []
    for i, line in enumerate(read_text(path).splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            lines.append(s)
            linenos.append(i)
    if not lines:
        raise InputError(f"{path}: expected at least one line 'timestamp tx ty tz qx qy qz qw'")
    ln = np.array(linenos)
    table = parse_table(path, lines, ln, _TUM_COLUMNS, None)
    check_finite(path, table, ln, _TUM_COLUMNS)
    check_increasing(path, table[:, 0], ln, "timestamp")
    q = table[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    row = first_line(np.abs(norm - 1.0) > _QUATERNION_TOL, ln)
    if row is not None:
        raise InputError(f"{path}:{row}: expected a unit quaternion qx qy qz qw")
    q = q / norm[:, None]
    R = np.array([gtsam.Rot3.Quaternion(w, x, y, z).matrix() for x, y, z, w in q])
    return Trajectory(t=table[:, 0].copy(), rotations=R, positions=table[:, 1:4].copy())


def write_velocity(path: PathLike, t: np.ndarray, twists: np.ndarray) -> None:
    """Write body velocities as ``t,vx,vy,vz,wx,wy,wz`` (atomically).

    Args:
        t: (K,) strictly increasing times.
        twists: (K, 6) body twists [w; v]; a row of NaN marks an unknown velocity.
    """
    t = _check_times(t, "t")
    twists = np.asarray(twists, dtype=float)
    if twists.shape != (len(t), 6):
        raise InputError(f"twists: expected shape ({len(t)}, 6), got {twists.shape}")
    nan = np.isnan(twists)
    bad = np.isinf(twists).any(axis=1) | (nan.any(axis=1) & ~nan.all(axis=1))
    if bad.any():
        raise InputError(
            f"twists[{int(np.flatnonzero(bad)[0])}]: expected finite values (or NaN in all six)"
        )
    table = np.column_stack((t, twists[:, 3:], twists[:, :3]))
    atomic_write_text(path, _text(VELOCITY_HEADER, table, ","))


def read_velocity(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a velocity CSV.

    Returns:
        t (K,) and twists (K, 6) [w; v] (reordered from the file's v, w columns);
        rows written as all-``nan`` (unknown velocity) come back as NaN.
    Raises:
        InputError: "<file>:<line>: ..." for a bad header or row, inf, a partly-NaN
            row, non-increasing t, or no rows.
        OSError: when the file cannot be read.
    """
    body, ln = csv_body(path, read_text(path), VELOCITY_HEADER)
    if not body:
        raise InputError(f"{path}:2: expected at least one row after the header")
    table = parse_table(path, body, ln, _VELOCITY_COLUMNS, ",")
    check_finite(path, table[:, :1], ln, _VELOCITY_COLUMNS[:1])
    nan = np.isnan(table[:, 1:])
    row = first_line(np.isinf(table[:, 1:]).any(axis=1) | (nan.any(axis=1) & ~nan.all(axis=1)), ln)
    if row is not None:
        raise InputError(f"{path}:{row}: expected finite velocities (or nan in all six columns)")
    check_increasing(path, table[:, 0], ln)
    return table[:, 0].copy(), np.column_stack((table[:, 4:7], table[:, 1:4]))


def write_covariance(path: PathLike, t: np.ndarray, covariances: np.ndarray) -> None:
    """Write (K, 12, 12) covariances as ``t`` + 78 upper-triangular entries per row."""
    t = _check_times(t, "t")
    cov = np.asarray(covariances, dtype=float)
    if cov.shape != (len(t), 12, 12):
        raise InputError(f"covariances: expected shape ({len(t)}, 12, 12), got {cov.shape}")
    if np.any(np.isinf(cov)):
        raise InputError("covariances: contains inf")
    atomic_write_text(
        path, _text(COVARIANCE_HEADER, np.column_stack((t, cov[:, _IU[0], _IU[1]])), ",")
    )


def read_covariance(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a covariance CSV; returns t (K,) and the symmetric (K, 12, 12) matrices."""
    body, ln = csv_body(path, read_text(path), COVARIANCE_HEADER)
    if not body:
        raise InputError(f"{path}:2: expected at least one row after the header")
    table = parse_table(path, body, ln, _COVARIANCE_COLUMNS, ",")
    check_finite(path, table[:, :1], ln, _COVARIANCE_COLUMNS[:1])
    row = first_line(np.isinf(table).any(axis=1), ln)
    if row is not None:
        raise InputError(f"{path}:{row}: expected finite covariance entries")
    check_increasing(path, table[:, 0], ln)
    cov = np.zeros((len(table), 12, 12))
    cov[:, _IU[0], _IU[1]] = table[:, 1:]
    cov[:, _IU[1], _IU[0]] = table[:, 1:]
    return table[:, 0].copy(), cov


def _check_same_times(t_ref: np.ndarray, t: np.ndarray, ref: Path, other: Path) -> None:
    if len(t) != len(t_ref) or np.any(np.abs(t - t_ref) > 1e-6):
        raise InputError(
            f"{other}: expected the same timestamps as {ref} ({len(t_ref)} rows), "
            f"got {len(t)} rows with different times"
        )


def _twists_at(t: np.ndarray, tv: np.ndarray, twists: np.ndarray) -> np.ndarray:
    """(K, 6) twists at times ``t``: the row of ``tv`` within 1e-6 s, NaN where there is none.

    A ground-truth velocity file need not have one row per pose (e.g. a pose file
    with fewer rows); hvo_graph.eval associates the full series with a tolerance.
    """
    out = np.full((len(t), 6), np.nan)
    j = np.clip(np.searchsorted(tv, t), 0, len(tv) - 1)
    j_left = np.clip(j - 1, 0, len(tv) - 1)
    j = np.where(np.abs(tv[j_left] - t) < np.abs(tv[j] - t), j_left, j)
    ok = np.abs(tv[j] - t) <= 1e-6
    out[ok] = twists[j[ok]]
    return out


def _write_dir(directory: PathLike, trajectory: Trajectory, names: tuple[str, ...]) -> None:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    write_tum(directory / names[0], trajectory)
    # A file this trajectory has no data for is removed, so that a stale one from
    # an earlier run in the same folder is never read back with the new poses.
    if trajectory.twists is not None:
        write_velocity(directory / names[1], trajectory.t, trajectory.twists)
    else:
        (directory / names[1]).unlink(missing_ok=True)
    if len(names) > 2:
        if trajectory.covariances is not None:
            write_covariance(directory / names[2], trajectory.t, trajectory.covariances)
        else:
            (directory / names[2]).unlink(missing_ok=True)


def _read_dir(directory: PathLike, names: tuple[str, ...]) -> Trajectory:
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"{directory}: expected a directory")
    pose_file, vel_file = directory / names[0], directory / names[1]
    trajectory = read_tum(pose_file)
    if vel_file.exists():
        tv, twists = read_velocity(vel_file)
        if names == GROUNDTRUTH_FILES:
            trajectory.twists = _twists_at(trajectory.t, tv, twists)
        else:
            _check_same_times(trajectory.t, tv, pose_file, vel_file)
            trajectory.twists = twists
    if len(names) > 2 and (directory / names[2]).exists():
        tc, cov = read_covariance(directory / names[2])
        _check_same_times(trajectory.t, tc, pose_file, directory / names[2])
        trajectory.covariances = cov
    return trajectory


def write_estimate_dir(directory: PathLike, trajectory: Trajectory) -> None:
    """Write an estimate folder: ``trajectory.txt``, ``velocity.csv`` (when twists
    are set) and ``covariance.csv`` (when covariances are set).

    Creates the folder; removes a ``velocity.csv`` / ``covariance.csv`` left
    there by an earlier run when this trajectory has no twists / covariances.
    """
    _write_dir(directory, trajectory, ESTIMATE_FILES)


def read_estimate_dir(directory: PathLike) -> Trajectory:
    """Read an estimate folder; twists/covariances are None when their file is absent.

    Raises:
        InputError: when a file is malformed or the files' timestamps differ.
        OSError: when ``trajectory.txt`` is missing or unreadable.
    """
    return _read_dir(directory, ESTIMATE_FILES)


def write_groundtruth_dir(directory: PathLike, groundtruth: Trajectory) -> None:
    """Write a ground-truth folder: ``groundtruth.txt`` and ``groundtruth_velocity.csv``.

    Raises:
        InputError: when ``groundtruth`` has no twists.
    """
    if groundtruth.twists is None:
        raise InputError("groundtruth: expected twists (groundtruth_velocity.csv is required)")
    _write_dir(directory, groundtruth, GROUNDTRUTH_FILES)


def read_groundtruth_dir(directory: PathLike) -> Trajectory:
    """Read a ground-truth folder (``groundtruth.txt`` + ``groundtruth_velocity.csv``).

    ``groundtruth_velocity.csv`` is optional: without it the twists are None
    (velocity errors are then not evaluated). Its rows need not match the poses':
    each pose takes the velocity row at its time (within 1e-6 s), NaN when there
    is none (:func:`hvo_graph.io.trajectory_paths.read_groundtruth` keeps the
    whole series for association with a tolerance).
    """
    return _read_dir(directory, GROUNDTRUTH_FILES)


def write_run_record(directory: PathLike, record: dict[str, object]) -> Path:
    """Write ``DIR/run.json``: what produced the estimate in ``directory`` (method,
    options in force, noise chosen, data rejected, inputs, versions, wall time).

    Non-finite numbers are written as null (JSON has no NaN).
    """
    path = Path(directory) / "run.json"
    atomic_write_text(path, json.dumps(_json_safe(record), indent=2, sort_keys=True) + "\n")
    return path


def _json_safe(value: object) -> object:
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
