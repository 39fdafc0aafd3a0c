"""Absolute and relative pose errors (APE, RPE) with evo's definitions.

For associated (and aligned) poses P_k = T_est,k and Q_k = T_gt,k (4x4, T_wc):

- APE: E_k = P_k^-1 Q_k;
- RPE over a pair (i, j): E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j).

Each E is reduced three ways (evo's pose relations):

- ``trans``: the translation error in metres (for APE ||p_est - p_gt||, for
  RPE ||t(E_ij)||);
- ``rot``: the rotation angle of E in degrees;
- ``full``: ||E - I_4||_F (unitless, evo's "full transformation").

RPE pairs follow ``evo_rpe --delta D --delta_unit U``, chosen on the estimate:

- ``f`` (frames): consecutive pairs (0, D), (D, 2D), ...; with ``all_pairs``
  every (i, i + D);
- ``m`` (metres travelled by the estimate): each pair ends at the first pose
  whose path length since the pair's start reaches D; with ``all_pairs`` every
  start i whose nearest path length to D is within 10 % of D;
- ``s`` (seconds, not in evo): as ``m`` with elapsed time in place of path length.

Statistics are evo's: rmse, mean, median, std (population), min, max, sse.
"""

from __future__ import annotations

import math

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.types import Trajectory

#: Pose relations, their key suffix in JSON/CSV, and their unit.
RELATIONS = (("trans", "m"), ("rot", "deg"), ("full", ""))
#: RPE delta units: frames, seconds, metres.
DELTA_UNITS = ("f", "s", "m")
#: Relative tolerance of an ``all_pairs`` delta in metres or seconds (evo's rel_delta_tol).
REL_DELTA_TOL = 0.1
#: Statistics of :func:`statistics`, in order.
STATISTICS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def relation_key(relation: str, unit: str) -> str:
    """ "trans_m", "rot_deg", "full": the key of a relation's statistics."""
    return f"{relation}_{unit}" if unit else relation


def _reduce(R: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
    """The three errors of poses E = (R (K, 3, 3), p (K, 3))."""
    cos = np.clip(0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    axis = np.stack((R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]), -1)
    angle = np.arctan2(0.5 * np.linalg.norm(axis, axis=-1), cos)
    full = np.sqrt(np.sum((R - np.eye(3)) ** 2, axis=(1, 2)) + np.sum(p**2, axis=1))
    return {
        "trans_m": np.linalg.norm(p, axis=1),
        "rot_deg": np.degrees(angle),
        "full": full,
    }


def ape_errors(estimate: Trajectory, groundtruth: Trajectory) -> dict[str, np.ndarray]:
    """APE per associated pose: {"trans_m", "rot_deg", "full"}, each (K,).

    Args:
        estimate, groundtruth: associated (pose k with pose k), aligned as wanted.
    """
    R_est, p_est = np.asarray(estimate.rotations), np.asarray(estimate.positions)
    R_gt, p_gt = np.asarray(groundtruth.rotations), np.asarray(groundtruth.positions)
    # E = P^-1 Q: rotation R_est^T R_gt, translation R_est^T (p_gt - p_est).
    R = np.einsum("kji,kjl->kil", R_est, R_gt)
    p = np.einsum("kji,kj->ki", R_est, p_gt - p_est)
    return _reduce(R, p)


def _chain(progress: np.ndarray, delta: float) -> list[int]:
    """Consecutive pair ends: the first index whose progress since the last end reaches delta."""
    ids, start = [0], progress[0]
    for i in range(1, len(progress)):
        if progress[i] - start >= delta:
            ids.append(i)
            start = progress[i]
    return ids


def _all_pairs(progress: np.ndarray, delta: float) -> np.ndarray:
    pairs = []
    for i in range(len(progress) - 1):
        ahead = progress[i + 1 :] - progress[i]
        c = int(np.argmin(np.abs(ahead - delta)))
        if abs(ahead[c] - delta) <= delta * REL_DELTA_TOL:
            pairs.append((i, c + i + 1))
    return np.array(pairs, dtype=int).reshape(-1, 2)


def rpe_pairs(
    estimate: Trajectory, delta: float, unit: str = "f", *, all_pairs: bool = False
) -> np.ndarray:
    """(P, 2) index pairs (i, j) of the RPE for ``delta`` in ``unit`` (see the module doc).

    Raises:
        InputError: for a bad delta or unit, or when no pair is found.
    """
    if unit not in DELTA_UNITS:
        raise InputError(f"--delta-unit: expected one of {', '.join(DELTA_UNITS)}, got {unit!r}")
    if not (delta > 0 and math.isfinite(delta)):
        raise InputError(f"--delta: expected a number > 0, got {delta!r}")
    k = len(estimate)
    if unit == "f":
        if delta != int(delta):
            raise InputError(f"--delta: expected a whole number of frames, got {delta:g}")
        d = int(delta)
        starts = np.arange(0, k - d) if all_pairs else np.arange(0, k, d)[:-1]
        pairs = np.column_stack((starts, starts + d)).astype(int).reshape(-1, 2)
        pairs = pairs[pairs[:, 1] < k]
    else:
        if unit == "m":
            steps = np.linalg.norm(np.diff(np.asarray(estimate.positions), axis=0), axis=1)
            progress = np.concatenate(([0.0], np.cumsum(steps)))
        else:
            progress = np.asarray(estimate.t, dtype=float)
        if all_pairs:
            pairs = _all_pairs(progress, delta)
        else:
            if unit == "m":
                ids = _chain_path(np.asarray(estimate.positions), delta)
            else:
                ids = _chain(progress, delta)
            pairs = np.column_stack((ids[:-1], ids[1:])).astype(int).reshape(-1, 2)
    if len(pairs) == 0:
        raise InputError(
            f"--delta {delta:g} {unit}: no pose pair of the estimate ({k} associated poses) is "
            "that far apart; use a smaller --delta"
        )
    return pairs


def _chain_path(positions: np.ndarray, delta: float) -> list[int]:
    # The path restarts from 0 at each pair end, summed step by step like evo, so the
    # same poses are chosen down to the last rounding.
    ids, path = [0], 0.0
    for i in range(1, len(positions)):
        path += float(np.linalg.norm(positions[i] - positions[i - 1]))
        if path >= delta:
            ids.append(i)
            path = 0.0
    return ids


def rpe_errors(
    estimate: Trajectory, groundtruth: Trajectory, pairs: np.ndarray
) -> dict[str, np.ndarray]:
    """RPE per pair: {"trans_m", "rot_deg", "full"}, each (P,).

    Args:
        estimate, groundtruth: associated (pose k with pose k), aligned as wanted.
        pairs: (P, 2) indices from :func:`rpe_pairs`.
    """
    i, j = pairs[:, 0], pairs[:, 1]

    def relative(traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
        R, p = np.asarray(traj.rotations), np.asarray(traj.positions)
        R_rel = np.einsum("kji,kjl->kil", R[i], R[j])
        p_rel = np.einsum("kji,kj->ki", R[i], p[j] - p[i])
        return R_rel, p_rel

    (R_q, p_q), (R_p, p_p) = relative(groundtruth), relative(estimate)
    # E = Q_rel^-1 P_rel: rotation R_q^T R_p, translation R_q^T (p_p - p_q).
    R = np.einsum("kji,kjl->kil", R_q, R_p)
    p = np.einsum("kji,kj->ki", R_q, p_p - p_q)
    return _reduce(R, p)


def statistics(errors: np.ndarray) -> dict[str, float]:
    """evo's statistics of (K,) errors: rmse, mean, median, std, min, max, sse.

    Raises:
        InputError: when ``errors`` is empty.
    """
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        raise InputError("statistics: no errors to summarise")
    return {
        "rmse": math.sqrt(float(np.mean(e**2))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.dot(e, e)),
    }
