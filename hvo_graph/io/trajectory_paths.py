"""Trajectories named by a path: files or folders, TUM or EuRoC, and the method behind them.

``hvo-graph evaluate`` accepts, for an estimate or the ground truth:

- an ``estimate`` output folder (``trajectory.txt``, ``velocity.csv``, ``run.json``);
- a ``simulate``-style folder (``groundtruth.txt``, ``groundtruth_velocity.csv``);
- a EuRoC folder holding ``state_groundtruth_estimate0/data.csv`` (directly or
  under ``mav0/``);
- a TUM file (``timestamp tx ty tz qx qy qz qw``, what ``evo_ape tum`` reads);
- a EuRoC ground-truth CSV (``#timestamp, p_RS_R_x [m], ..., q_RS_w [], q_RS_x [],
  q_RS_y [], q_RS_z [], ...``: times in nanoseconds, quaternion w first; what
  ``evo_ape euroc`` reads). Its velocities are in the world frame, not the body
  frame of the contract, and are not read. EuRoC poses are the body (IMU) frame
  in its world: compare them with a camera trajectory only after alignment.

Ground-truth velocities are returned as their own series (t, twists): their rows
need not match the poses' rows; the evaluation associates them by time.
"""

from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.io._common import (
    PathLike,
    check_finite,
    check_increasing,
    first_line,
    parse_table,
    read_text,
)
from hvo_graph.io.trajectory import (
    ESTIMATE_FILES,
    GROUNDTRUTH_FILES,
    read_estimate_dir,
    read_tum,
    read_velocity,
)
from hvo_graph.types import Trajectory

#: Where a EuRoC sequence keeps its ground truth, relative to the sequence folder.
EUROC_GROUNDTRUTH = (
    Path("state_groundtruth_estimate0/data.csv"),
    Path("mav0/state_groundtruth_estimate0/data.csv"),
)
_EUROC_NAMES = ("timestamp", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z")

Velocity = tuple[np.ndarray, np.ndarray]


def read_euroc_groundtruth(path: PathLike) -> Trajectory:
    """Read a EuRoC ground-truth CSV: t = timestamp / 1e9 s, p (3,), q (w, x, y, z).

    Columns after the eighth (velocities, biases) are ignored.
    Raises:
        InputError: "<file>:<line>: ..." for a short or non-numeric row, a bad
            quaternion, non-increasing timestamps, or no rows.
    """
    lines, linenos = [], []
    for i, line in enumerate(read_text(path).splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            lines.append(s)
            linenos.append(i)
    if not lines:
        raise InputError(f"{path}: expected EuRoC rows 'timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,...'")
    ln = np.array(linenos)
    ncols = len(lines[0].split(","))
    if ncols < len(_EUROC_NAMES):
        raise InputError(
            f"{path}:{ln[0]}: expected at least 8 comma-separated columns "
            f"(timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z), got {ncols}"
        )
    names = _EUROC_NAMES + tuple(f"column {c + 1}" for c in range(len(_EUROC_NAMES), ncols))
    table = parse_table(path, lines, ln, names, ",")[:, : len(_EUROC_NAMES)]
    check_finite(path, table, ln, _EUROC_NAMES)
    t = table[:, 0] / 1e9
    check_increasing(path, t, ln, "timestamp")
    q = table[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    row = first_line(np.abs(norm - 1.0) > 1e-3, ln)
    if row is not None:
        raise InputError(f"{path}:{row}: expected a unit quaternion q_w q_x q_y q_z")
    q = q / norm[:, None]
    R = np.array([gtsam.Rot3.Quaternion(w, x, y, z).matrix() for w, x, y, z in q])
    return Trajectory(t=t, rotations=R, positions=table[:, 1:4].copy())


def read_trajectory_file(path: PathLike) -> Trajectory:
    """Read a TUM file, or a EuRoC CSV (told apart by commas in the first data line)."""
    for line in read_text(path).splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            return read_euroc_groundtruth(path) if "," in s else read_tum(path)
    raise InputError(f"{path}: expected a TUM or EuRoC trajectory, found no data line")


def method_name(path: PathLike) -> str:
    """The method of an estimate: ``run.json``'s "method", else the folder's (file's) name.

    Raises:
        InputError: when a ``run.json`` exists but is not a JSON object.
    """
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    record = folder / "run.json"
    if record.is_file():
        try:
            data = json.loads(read_text(record))
        except json.JSONDecodeError as exc:
            raise InputError(f"{record}:{exc.lineno}: expected JSON ({exc.msg})") from None
        if not isinstance(data, dict):
            raise InputError(f"{record}: expected a JSON object")
        if isinstance(data.get("method"), str) and data["method"]:
            return str(data["method"])
    if p.is_dir() or p.name == ESTIMATE_FILES[0]:
        return folder.resolve().name or str(folder)
    return p.stem


def _missing(path: Path, what: str) -> InputError:
    if not path.exists():
        return InputError(f"{path}: expected a directory or a trajectory file, found nothing")
    return InputError(f"{path}: expected {what}")


def read_estimate(path: PathLike) -> tuple[Trajectory, str]:
    """An estimate from an output folder or a trajectory file, and its method name.

    A file named ``trajectory.txt`` is read with its folder (velocities included).
    """
    p = Path(path)
    if p.is_file() and p.name == ESTIMATE_FILES[0]:
        p = p.parent
    if p.is_dir():
        if not (p / ESTIMATE_FILES[0]).exists() and (p / GROUNDTRUTH_FILES[0]).is_file():
            return _groundtruth_folder(p)[0], method_name(p)
        return read_estimate_dir(p), method_name(p)
    if p.is_file():
        return read_trajectory_file(p), method_name(p)
    raise _missing(p, "an estimate folder or a trajectory file")


def _groundtruth_folder(folder: Path) -> tuple[Trajectory, Velocity | None]:
    poses = folder / GROUNDTRUTH_FILES[0]
    velocity = folder / GROUNDTRUTH_FILES[1]
    traj = read_tum(poses)
    return traj, (read_velocity(velocity) if velocity.exists() else None)


def read_groundtruth(path: PathLike) -> tuple[Trajectory, Velocity | None]:
    """Ground-truth poses and, when there is a velocity file, its (t (L,), twists (L, 6)).

    Accepts a ``simulate``-style folder, an estimate folder, a EuRoC sequence
    folder, or a TUM / EuRoC file (a file named ``groundtruth.txt`` brings the
    ``groundtruth_velocity.csv`` beside it).
    """
    p = Path(path)
    if p.is_dir():
        if (p / GROUNDTRUTH_FILES[0]).exists():
            return _groundtruth_folder(p)
        if (p / ESTIMATE_FILES[0]).exists():
            traj = read_estimate_dir(p)
            return traj, None if traj.twists is None else (traj.t, traj.twists)
        for rel in EUROC_GROUNDTRUTH:
            if (p / rel).is_file():
                return read_euroc_groundtruth(p / rel), None
        raise InputError(
            f"{p}: expected {GROUNDTRUTH_FILES[0]}, {ESTIMATE_FILES[0]} or "
            f"{EUROC_GROUNDTRUTH[0]} in this folder"
        )
    if p.is_file():
        if p.name == GROUNDTRUTH_FILES[0]:
            return _groundtruth_folder(p.parent)
        return read_trajectory_file(p), None
    raise _missing(p, "a ground-truth folder or file")
