"""One estimate against ground truth, the field's way: associate, align, APE, RPE, velocities.

:func:`evaluate_trajectory` is what ``hvo-graph evaluate`` runs for each
estimate. Its steps and their evo counterparts:

1. drop estimate frames in the first ``skip`` seconds of the ground truth;
2. associate poses by time (:func:`~hvo_graph.eval.association.associate`,
   evo's ``--t_max_diff`` / ``--t_offset``);
3. align the estimate (:func:`~hvo_graph.eval.alignment.align`: none, origin,
   SE(3) or Sim(3), evo's ``--align_origin`` / ``-a`` / ``-as`` / ``--n_to_align``);
4. APE and RPE (:mod:`~hvo_graph.eval.ape_rpe`, evo's pose relations);
5. the contract's error summary (:class:`~hvo_graph.eval.metrics.ErrorSummary`:
   position, orientation, linear and angular velocity, RMSE and max) at the
   associated frames, with the ground-truth velocity associated by time.

Position and orientation errors of step 5 are the APE's ``trans_m`` and
``rot_deg``; the experiments' tables use the same :mod:`~hvo_graph.eval.metrics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.eval.alignment import Alignment, align
from hvo_graph.eval.ape_rpe import STATISTICS, ape_errors, rpe_errors, rpe_pairs, statistics
from hvo_graph.eval.association import DEFAULT_MAX_DIFF, associate, associate_velocity
from hvo_graph.eval.metrics import MIN_MATCHED_FRACTION, ErrorSeries, ErrorSummary, summarize
from hvo_graph.types import Trajectory


@dataclass(frozen=True)
class EvaluationOptions:
    """How an estimate is scored (defaults: evo's association, no alignment, RPE per frame).

    Attributes:
        max_diff: association tolerance, seconds (evo ``--t_max_diff``).
        offset: added to the estimate's times, seconds (evo ``--t_offset``).
        align: "none", "origin", "se3" or "sim3".
        n_align: fit se3/sim3 to the first n associated poses (None: all).
        delta: RPE pair distance, in ``delta_unit``.
        delta_unit: "f" frames, "s" seconds, "m" metres travelled.
        all_pairs: RPE over all pairs at ``delta`` instead of consecutive ones.
        skip: leave out estimate frames before ground-truth t0 + skip (None: keep all).
    """

    max_diff: float = DEFAULT_MAX_DIFF
    offset: float = 0.0
    align: str = "none"
    n_align: int | None = None
    delta: float = 1.0
    delta_unit: str = "f"
    all_pairs: bool = False
    skip: float | None = None

    def as_dict(self) -> dict[str, object]:
        """The options as plain values (for JSON)."""
        return {
            "t_max_diff_s": self.max_diff,
            "t_offset_s": self.offset,
            "align": self.align,
            "n_to_align": self.n_align,
            "delta": self.delta,
            "delta_unit": self.delta_unit,
            "all_pairs": self.all_pairs,
            "skip_s": self.skip,
        }


@dataclass
class Evaluation:
    """The scores of one estimate.

    Attributes:
        method: the estimate's name in tables.
        estimate: (K,) associated estimate poses, aligned.
        groundtruth: (K,) the ground-truth poses they were paired with.
        alignment: the transform applied to the estimate.
        ape: {"trans_m", "rot_deg", "full"}: (K,) errors per associated pose.
        rpe: {"trans_m", "rot_deg", "full"}: (P,) errors per RPE pair.
        rpe_pairs: (P, 2) indices into the associated poses.
        series: the contract's per-frame errors (velocities associated by time).
        summary: their RMSE and max.
        estimate_frames: frames of the estimate before association.
        options: how it was scored.
    """

    method: str
    estimate: Trajectory
    groundtruth: Trajectory
    alignment: Alignment
    ape: dict[str, np.ndarray]
    rpe: dict[str, np.ndarray]
    rpe_pairs: np.ndarray
    series: ErrorSeries
    summary: ErrorSummary
    estimate_frames: int
    options: EvaluationOptions

    def as_dict(self) -> dict[str, object]:
        """The contract's keys (position_m, ..., frames) plus method, ape, rpe, alignment,
        association and options. APE/RPE entries hold evo's statistics."""
        out = self.summary.as_dict()
        out["method"] = self.method
        out["ape"] = {k: statistics(e) for k, e in self.ape.items()}
        out["rpe"] = {k: statistics(e) for k, e in self.rpe.items()}
        out["rpe"]["pairs"] = len(self.rpe_pairs)  # type: ignore[index]
        out["alignment"] = self.alignment.as_dict()
        out["association"] = {"matched": len(self.estimate), "estimate": self.estimate_frames}
        out["options"] = self.options.as_dict()
        return out


def _subset(traj: Trajectory, index: np.ndarray) -> Trajectory:
    return Trajectory(
        t=np.asarray(traj.t, dtype=float)[index],
        rotations=np.asarray(traj.rotations)[index],
        positions=np.asarray(traj.positions)[index],
        twists=None if traj.twists is None else np.asarray(traj.twists)[index],
    )


def _velocity_errors(
    estimate: Trajectory, velocity: tuple[np.ndarray, np.ndarray] | None, opts: EvaluationOptions
) -> tuple[np.ndarray | None, np.ndarray | None]:
    if estimate.twists is None or velocity is None:
        return None, None
    truth = associate_velocity(
        estimate.t, velocity[0], velocity[1], max_diff=opts.max_diff, offset=opts.offset
    )
    diff = np.asarray(estimate.twists) - truth
    return np.linalg.norm(diff[:, 3:], axis=1), np.linalg.norm(diff[:, :3], axis=1)


def evaluate_trajectory(
    estimate: Trajectory,
    groundtruth: Trajectory,
    *,
    velocity: tuple[np.ndarray, np.ndarray] | None = None,
    options: EvaluationOptions | None = None,
    method: str = "estimate",
) -> Evaluation:
    """Score ``estimate`` against ``groundtruth`` (see the module doc for the steps).

    Args:
        estimate: the estimated trajectory (twists optional).
        groundtruth: the reference poses (their twists are used when ``velocity`` is None).
        velocity: ground-truth body velocities (t (L,), twists (L, 6) [w; v]), rows
            need not match the poses' (NaN rows are skipped), or None.
        options: association, alignment and RPE settings.
        method: the name shown in tables.
    Raises:
        InputError: when nothing is associated, fewer than half of the poses that
            could be are, or the alignment or RPE cannot be formed.
    """
    opts = options or EvaluationOptions()
    if len(estimate) == 0 or len(groundtruth) == 0:
        raise InputError(f"{method}: the estimate and the ground truth must both have poses")
    if velocity is None and groundtruth.twists is not None:
        velocity = (np.asarray(groundtruth.t), np.asarray(groundtruth.twists))
    if opts.skip is not None:
        keep = np.asarray(estimate.t) + opts.offset >= groundtruth.t[0] + opts.skip - 1e-9
        if not keep.any():
            raise InputError(
                f"--skip: no estimate frame of {method} at t >= {groundtruth.t[0] + opts.skip:g} s"
            )
        estimate = _subset(estimate, np.flatnonzero(keep))
    i_gt, i_est = associate(groundtruth.t, estimate.t, max_diff=opts.max_diff, offset=opts.offset)
    possible = min(len(estimate), len(groundtruth))
    if len(i_est) < MIN_MATCHED_FRACTION * possible:
        raise InputError(
            f"{method}: only {len(i_est)} of {possible} poses are associated within "
            f"{opts.max_diff:g} s (estimate {estimate.t[0]:.6f}..{estimate.t[-1]:.6f} s, ground "
            f"truth {groundtruth.t[0]:.6f}..{groundtruth.t[-1]:.6f} s); check --t-offset"
        )
    est, gt = _subset(estimate, i_est), _subset(groundtruth, i_gt)
    alignment = align(est, gt, opts.align, n=opts.n_align)
    est = alignment.apply(est)
    ape = ape_errors(est, gt)
    pairs = rpe_pairs(est, opts.delta, opts.delta_unit, all_pairs=opts.all_pairs)
    linear, angular = _velocity_errors(est, velocity, opts)
    series = ErrorSeries(
        t=np.asarray(gt.t),
        position=ape["trans_m"],
        orientation=ape["rot_deg"],
        linear_velocity=linear,
        angular_velocity=angular,
    )
    return Evaluation(
        method=method,
        estimate=est,
        groundtruth=gt,
        alignment=alignment,
        ape=ape,
        rpe=rpe_errors(est, gt, pairs),
        rpe_pairs=pairs,
        series=series,
        summary=summarize(series),
        estimate_frames=len(estimate),
        options=opts,
    )


def unique_names(names: list[str], paths: list[str]) -> list[str]:
    """``names`` with repeats told apart by their path: "smoother (run1/smoother)"."""
    out = []
    for name, path in zip(names, paths, strict=True):
        out.append(f"{name} ({path})" if names.count(name) > 1 else name)
    return out


def _table(rows: list[list[str]]) -> str:
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    return "\n".join(
        "  ".join(
            [r[0].ljust(widths[0])] + [r[c].rjust(widths[c]) for c in range(1, len(r))]
        ).rstrip()
        for r in rows
    )


def format_pose_error_table(evaluations: list[Evaluation]) -> str:
    """Aligned table: one row per method, APE and RPE (translation m, rotation deg) RMSE,
    mean and max, the RPE pairs and the alignment."""
    header = ["method"]
    for kind in ("APE", "RPE"):
        for rel, unit in (("trans", "m"), ("rot", "deg")):
            header += [f"{kind} {rel} {s} [{unit}]" for s in ("RMSE", "mean", "max")]
    header += ["RPE pairs", "align"]
    rows = [header]
    for ev in evaluations:
        row = [ev.method]
        for errors in (ev.ape, ev.rpe):
            for key in ("trans_m", "rot_deg"):
                st = statistics(errors[key])
                row += [f"{st[s]:.4g}" for s in ("rmse", "mean", "max")]
        align = ev.alignment.method
        if ev.alignment.method == "sim3":
            align += f" s={ev.alignment.scale:.4g}"
        row += [str(len(ev.rpe_pairs)), align]
        rows.append(row)
    return _table(rows)


def csv_table(evaluations: list[Evaluation]) -> str:
    """CSV text: a header, then one row per method (the contract's RMSE/max of position,
    orientation and velocities, then evo's statistics of each APE and RPE relation)."""
    header = ["method", "frames"]
    summary_keys = [k for k in evaluations[0].summary.as_dict() if k != "frames"]
    header += [f"{k}_{s}" for k in summary_keys for s in ("rmse", "max")]
    relations = list(evaluations[0].ape)
    for kind in ("ape", "rpe"):
        header += [f"{kind}_{r}_{s}" for r in relations for s in STATISTICS]
    header += ["rpe_pairs", "align", "scale"]
    lines = [",".join(header)]
    for ev in evaluations:
        d = ev.summary.as_dict()
        cells: list[object] = [_csv_name(ev.method), d["frames"]]
        for k in summary_keys:
            entry = d[k]
            cells += ["" if entry is None else repr(entry[s]) for s in ("rmse", "max")]  # type: ignore[index]
        for errors in (ev.ape, ev.rpe):
            for r in relations:
                st = statistics(errors[r])
                cells += [repr(st[s]) for s in STATISTICS]
        cells += [len(ev.rpe_pairs), ev.alignment.method, repr(ev.alignment.scale)]
        lines.append(",".join(str(c) for c in cells))
    return "\n".join(lines) + "\n"


def _csv_name(name: str) -> str:
    return '"' + name.replace('"', '""') + '"' if any(c in name for c in ',"\n') else name
