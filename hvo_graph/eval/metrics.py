"""Trajectory errors against ground truth, matched by timestamp.

Per matched frame k (estimate ^, ground truth gt):

- position error      ||p^_k - p_gt,k||                          (m)
- orientation error   angle of R_gt,k^T R^_k, in degrees         (deg)
- linear velocity     ||v^_k - v_gt,k||  (body frame)            (m/s)
- angular velocity    ||w^_k - w_gt,k||  (body frame)            (rad/s)

Poses are compared directly in the world frame W = F* (both trajectories
start from the same reference frame, so no alignment is applied); position and
orientation errors are the translation and rotation-angle APE of
:mod:`hvo_graph.eval.ape_rpe`, the code ``hvo-graph evaluate`` reports. Summaries
give the RMSE sqrt(mean e_k^2) and the maximum over the frames kept.
Velocity rows that are NaN (unknown velocity) are left out of the velocity
statistics; a trajectory without twists gives no velocity statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.eval.ape_rpe import ape_errors
from hvo_graph.types import Trajectory

#: Fewer matched timestamps than this fraction of the estimate's frames is an error.
MIN_MATCHED_FRACTION = 0.5

#: Units as they appear in JSON keys and CSV column names.
_UNIT_SLUGS = {"m": "m", "deg": "deg", "m/s": "mps", "rad/s": "radps"}
#: Short names of the quantities in :func:`format_table`.
_SHORT = {
    "position": "pos",
    "orientation": "orient",
    "linear_velocity": "lin vel",
    "angular_velocity": "ang vel",
}


class Quantity(NamedTuple):
    """One error quantity: the :class:`ErrorSeries` attribute, a title and the unit."""

    name: str
    title: str
    unit: str

    @property
    def slug(self) -> str:
        """The unit in keys and column names: m, deg, mps, radps."""
        return _UNIT_SLUGS[self.unit]

    @property
    def key(self) -> str:
        """``<name>_<slug>``, e.g. "linear_velocity_mps", a key of :meth:`ErrorSummary.as_dict`."""
        return f"{self.name}_{self.slug}"


#: The four errors, in table order.
QUANTITIES: tuple[Quantity, ...] = (
    Quantity("position", "position", "m"),
    Quantity("orientation", "orientation", "deg"),
    Quantity("linear_velocity", "linear velocity", "m/s"),
    Quantity("angular_velocity", "angular velocity", "rad/s"),
)


@dataclass
class ErrorSeries:
    """Per-frame errors at the matched timestamps.

    Attributes:
        t: (K,) ground-truth times of the matched frames, seconds.
        position: (K,) ||p_est - p_gt||, metres.
        orientation: (K,) angle of R_gt^T R_est, degrees.
        linear_velocity: (K,) ||v_est - v_gt||, m/s (NaN where unknown), or None.
        angular_velocity: (K,) ||w_est - w_gt||, rad/s (NaN where unknown), or None.
    """

    t: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    linear_velocity: np.ndarray | None = None
    angular_velocity: np.ndarray | None = None


@dataclass
class ErrorSummary:
    """RMSE and maximum of each error over the frames kept.

    Velocity entries are None when no velocity could be compared.
    """

    position_rmse: float
    position_max: float
    orientation_rmse: float
    orientation_max: float
    linear_velocity_rmse: float | None
    linear_velocity_max: float | None
    angular_velocity_rmse: float | None
    angular_velocity_max: float | None
    frames: int

    def as_dict(self) -> dict[str, object]:
        """{"position_m": {"rmse", "max"}, "orientation_deg": ..., "linear_velocity_mps": ...,
        "angular_velocity_radps": ..., "frames": K}; velocity entries None when unknown."""
        out: dict[str, object] = {}
        for q in QUANTITIES:
            rmse, peak = getattr(self, f"{q.name}_rmse"), getattr(self, f"{q.name}_max")
            out[q.key] = None if rmse is None else {"rmse": rmse, "max": peak}
        out["frames"] = self.frames
        return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """(K,) rotation angles (radians) of (K, 3, 3) rotation matrices.

    angle = atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2), accurate near 0 and pi
    (unlike arccos of the trace).
    """
    R = np.asarray(R, dtype=float)
    axis = np.stack(
        (R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]), axis=-1
    )
    cos = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    return np.arctan2(0.5 * np.linalg.norm(axis, axis=-1), cos)


def match_timestamps(
    t_est: np.ndarray, t_gt: np.ndarray, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_est, i_gt) of estimate times within ``tolerance`` of a ground-truth time."""
    t_est, t_gt = np.asarray(t_est, dtype=float), np.asarray(t_gt, dtype=float)
    if len(t_gt) == 1:
        j = np.zeros(len(t_est), dtype=int)
    else:
        # t_gt is increasing: the nearest time is one of the two around t_est.
        right = np.clip(np.searchsorted(t_gt, t_est), 1, len(t_gt) - 1)
        left = right - 1
        j = np.where(np.abs(t_gt[left] - t_est) <= np.abs(t_gt[right] - t_est), left, right)
    ok = np.abs(t_gt[j] - t_est) <= tolerance
    return np.flatnonzero(ok), j[ok]


def _poses_at(trajectory: Trajectory, index: np.ndarray) -> Trajectory:
    return Trajectory(
        t=np.asarray(trajectory.t, dtype=float)[index],
        rotations=np.asarray(trajectory.rotations)[index],
        positions=np.asarray(trajectory.positions)[index],
    )


def error_series(
    estimate: Trajectory, groundtruth: Trajectory, *, tolerance: float = 1e-6
) -> ErrorSeries:
    """Per-frame errors of ``estimate`` against ``groundtruth``, matched by timestamp.

    Args:
        estimate: the estimated trajectory (twists optional).
        groundtruth: the reference trajectory (twists optional).
        tolerance: largest |t_est - t_gt| (seconds) for two frames to match.
    Returns:
        Errors at the matched frames (velocity errors None unless both have twists).
    Raises:
        InputError: when no timestamp matches, or fewer than half of the
            estimate's timestamps do (a sign of a different time base).
    """
    if len(estimate) == 0 or len(groundtruth) == 0:
        raise InputError("error_series: estimate and ground truth must both have frames")
    i_est, i_gt = match_timestamps(estimate.t, groundtruth.t, tolerance)
    if len(i_est) == 0 or len(i_est) < MIN_MATCHED_FRACTION * len(estimate):
        raise InputError(
            f"estimate: only {len(i_est)} of its {len(estimate)} timestamps match the ground "
            f"truth within {tolerance:g} s (estimate {estimate.t[0]:.6g}..{estimate.t[-1]:.6g} s, "
            f"ground truth {groundtruth.t[0]:.6g}..{groundtruth.t[-1]:.6g} s)"
        )
    # The APE of hvo-graph evaluate (evo's translation part and rotation angle): one
    # formula for the command, the experiments and the docs' tables.
    ape = ape_errors(_poses_at(estimate, i_est), _poses_at(groundtruth, i_gt))
    series = ErrorSeries(
        t=np.asarray(groundtruth.t, dtype=float)[i_gt],
        position=ape["trans_m"],
        orientation=ape["rot_deg"],
    )
    if estimate.twists is not None and groundtruth.twists is not None:
        diff = np.asarray(estimate.twists)[i_est] - np.asarray(groundtruth.twists)[i_gt]
        series.angular_velocity = np.linalg.norm(diff[:, :3], axis=1)
        series.linear_velocity = np.linalg.norm(diff[:, 3:], axis=1)
    return series


def _stats(e: np.ndarray | None) -> tuple[float | None, float | None]:
    if e is None:
        return None, None
    e = e[np.isfinite(e)]
    if e.size == 0:
        return None, None
    return float(math.sqrt(np.mean(e**2))), float(np.max(e))


def summarize(series: ErrorSeries, *, t_start: float | None = None) -> ErrorSummary:
    """RMSE and max of each error.

    Args:
        series: per-frame errors.
        t_start: keep only frames with t >= t_start (e.g. ground-truth t0 + 1
            for "after the first second"); None keeps all.
    Raises:
        InputError: when no frame is left.
    """
    keep = np.ones(len(series.t), dtype=bool)
    if t_start is not None:
        keep = np.asarray(series.t) >= t_start - 1e-9
    if not keep.any():
        raise InputError(
            f"t_start: no matched frame at t >= {t_start:g} s "
            f"(matched frames span {series.t[0]:.6g}..{series.t[-1]:.6g} s)"
        )
    values: dict[str, float | None] = {}
    for q in QUANTITIES:
        e = getattr(series, q.name)
        values[f"{q.name}_rmse"], values[f"{q.name}_max"] = _stats(None if e is None else e[keep])
    return ErrorSummary(**values, frames=int(keep.sum()))  # type: ignore[arg-type]


def format_table(summaries: dict[str, ErrorSummary]) -> str:
    """Aligned plain-text table: one row per method, RMSE and max of each error.

    Columns: pos RMSE/max [m], orient RMSE/max [deg], lin vel RMSE/max [m/s],
    ang vel RMSE/max [rad/s], frames. Velocity cells are '-' when unknown.
    """
    header = ["method"]
    for q in QUANTITIES:
        header += [f"{_SHORT[q.name]} RMSE [{q.unit}]", f"{_SHORT[q.name]} max [{q.unit}]"]
    header.append("frames")
    rows = [header]
    for method, s in summaries.items():
        row = [str(method)]
        for q in QUANTITIES:
            for stat in ("rmse", "max"):
                value = getattr(s, f"{q.name}_{stat}")
                row.append("-" if value is None else f"{value:.4g}")
        row.append(str(s.frames))
        rows.append(row)
    widths = [max(len(r[c]) for r in rows) for c in range(len(header))]
    lines = []
    for r in rows:
        cells = [r[0].ljust(widths[0])] + [r[c].rjust(widths[c]) for c in range(1, len(r))]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines)


def position_rmse_between(series: ErrorSeries, start: float, stop: float) -> float | None:
    """RMSE of the position error over frames with start <= t < stop (None: no frame)."""
    keep = (series.t >= start - 1e-9) & (series.t < stop - 1e-9)
    e = series.position[keep]
    return float(math.sqrt(np.mean(e**2))) if e.size else None
