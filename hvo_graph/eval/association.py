"""Association of two trajectories by timestamp, with evo's semantics.

An estimate and a ground truth rarely share timestamps (a motion-capture system
samples at its own rate and clock). Poses are paired as ``evo_ape`` /
``evo_rpe`` pair them (``--t_max_diff``, ``--t_offset``): the estimate's times
are shifted by ``offset`` (t_est + offset is compared with t_gt); the trajectory
with fewer poses is walked in order and each of its poses takes the nearest
pose of the other within ``max_diff`` seconds (ties go to the earlier one);
poses without a partner within ``max_diff`` are dropped. A pose of the longer
trajectory may serve two poses of the shorter one.

Velocities are associated the same way: each estimate frame takes the nearest
ground-truth velocity row within ``max_diff`` (rows of ``nan``, unknown
velocities, are skipped first), so the velocity file's rows need not match the
pose file's.
"""

from __future__ import annotations

import numpy as np

from hvo_graph.errors import InputError

#: evo's default ``--t_max_diff`` (seconds).
DEFAULT_MAX_DIFF = 0.01


def nearest_within(
    stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float, offset_2: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """For each time of ``stamps_1``, the nearest of ``stamps_2 + offset_2`` within ``max_diff``.

    Args:
        stamps_1: (N,) increasing times.
        stamps_2: (M,) increasing times, M >= 1.
        max_diff: largest accepted |t_1 - (t_2 + offset_2)|, seconds.
        offset_2: added to ``stamps_2`` before comparing, seconds.
    Returns:
        (i_1, i_2): int index arrays of the matched pairs, in the order of ``stamps_1``.
    """
    s1 = np.asarray(stamps_1, dtype=float)
    s2 = np.asarray(stamps_2, dtype=float) + offset_2
    if s1.size == 0 or s2.size == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    in_range = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
    upper = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    diff_ub = s2[upper] - s1
    diff_lb = np.where(upper > 0, s1 - s2[np.maximum(upper - 1, 0)], np.inf)
    take_upper = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lower = ~take_upper & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = in_range & (take_upper | take_lower)
    j = np.where(take_upper, upper, upper - 1)
    return np.flatnonzero(ok), j[ok].astype(int)


def associate(
    t_gt: np.ndarray,
    t_est: np.ndarray,
    *,
    max_diff: float = DEFAULT_MAX_DIFF,
    offset: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i_gt, i_est) of ground-truth and estimate poses, as ``evo_ape`` forms them.

    Args:
        t_gt: (N,) increasing ground-truth times, seconds.
        t_est: (M,) increasing estimate times, seconds.
        max_diff: largest accepted |t_gt - (t_est + offset)|, seconds (evo's ``--t_max_diff``).
        offset: added to the estimate's times (evo's ``--t_offset``), seconds.
    Returns:
        Two int arrays of equal length, increasing.
    Raises:
        InputError: when ``max_diff`` is negative or no pair is found.
    """
    if not max_diff >= 0.0:
        raise InputError(f"--t-max-diff: expected a number >= 0, got {max_diff!r}")
    t_gt, t_est = np.asarray(t_gt, dtype=float), np.asarray(t_est, dtype=float)
    if len(t_est) > len(t_gt):
        i_gt, i_est = nearest_within(t_gt, t_est, max_diff, offset)
    else:
        i_est, i_gt = nearest_within(t_est, t_gt, max_diff, -offset)
    if len(i_gt) == 0:
        raise InputError(
            f"no estimate timestamp is within {max_diff:g} s of a ground-truth timestamp "
            f"after a time offset of {offset:g} s (estimate {t_est[0]:.6f}..{t_est[-1]:.6f} s, "
            f"ground truth {t_gt[0]:.6f}..{t_gt[-1]:.6f} s)"
        )
    return i_gt, i_est


def associate_velocity(
    t_est: np.ndarray,
    t_vel: np.ndarray,
    twists: np.ndarray,
    *,
    max_diff: float = DEFAULT_MAX_DIFF,
    offset: float = 0.0,
) -> np.ndarray:
    """Ground-truth twists at the estimate's times: (M, 6), NaN where no row is within reach.

    Args:
        t_est: (M,) estimate times, seconds.
        t_vel: (L,) ground-truth velocity times, seconds.
        twists: (L, 6) ground-truth body twists [w; v]; rows of NaN are skipped.
        max_diff: largest accepted |t_vel - (t_est + offset)|, seconds.
        offset: added to the estimate's times, seconds.
    """
    twists = np.asarray(twists, dtype=float)
    known = np.isfinite(twists).all(axis=1)
    t_known, tw_known = np.asarray(t_vel, dtype=float)[known], twists[known]
    out = np.full((len(t_est), 6), np.nan)
    i_est, i_vel = nearest_within(np.asarray(t_est, dtype=float) + offset, t_known, max_diff)
    out[i_est] = tw_known[i_vel]
    return out
