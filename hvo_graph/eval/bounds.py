"""Cramér-Rao bounds of the pose on a simulated scenario: what the pixels allow.

Two bounds, each the inverse of a Fisher information built as a GTSAM factor
graph linearized at the ground truth (the same factors as
:mod:`hvo_graph.estimators.tight`, without the robust loss):

- **posterior** (Bayesian, Van Trees) bound: every pixel observation of every
  frame (isotropic noise of the scene's pixel sigma, in normalized coordinates),
  the plane n*^T L = d* on the true points, X(0) = I, and the white-noise-
  acceleration motion prior (the smoothers' motion factors,
  :func:`~hvo_graph.estimators.motion_model.wna_factor`, with the given (s_w, s_v))
  over the whole sequence. Its inverse's pose blocks bound the
  error covariance of any estimator that knows this prior;
- **memoryless** bound: the pose of frame k from the pixels of frame 0 and frame k
  alone (plane, X(0) = I, no motion model): what a per-frame estimator (H_d, IPPE)
  can at best reach.

Per frame the bound is sqrt(trace) of the rotation block (reported in degrees, the
orientation error angle) and of the translation block (metres, the position error
norm: with T_true = T_est Exp(delta), p_true - p_est = R delta_t); over frames,
the RMSE bound is sqrt(mean of the traces).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from hvo_graph.errors import InputError, as_number
from hvo_graph.estimators.motion_model import wna_factor
from hvo_graph.estimators.process_noise import acceleration_sigma as check_acceleration_sigma
from hvo_graph.estimators.process_noise import twist_spectral_density
from hvo_graph.estimators.tight import DEFAULT_PLANE_SIGMA, IN_PLANE_SIGMA
from hvo_graph.sim.scenario import Scenario

__all__ = [
    "BOUND",
    "BOUND_TITLE",
    "MIN_PIXEL_SIGMA",
    "PoseBound",
    "bound_ratio",
    "memoryless_bound",
    "posterior_bound",
]

#: The row of the posterior bound in result tables (beside the methods' labels) and its
#: title there.
BOUND = "posterior-bound"
BOUND_TITLE = "posterior Cramér-Rao bound"

#: Pixel sigma (px) used for a noise-free scenario (a zero sigma has no finite bound).
MIN_PIXEL_SIGMA = 1e-3

_UNIT = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PoseBound:
    """A pose bound per frame.

    Attributes:
        t: (K,) frame times, seconds.
        position: (K,) sqrt(trace) of the translation block, metres.
        orientation: (K,) sqrt(trace) of the rotation block, degrees.
    """

    t: np.ndarray
    position: np.ndarray
    orientation: np.ndarray

    def rmse(self, t_start: float = 0.0) -> tuple[float, float]:
        """(position m, orientation deg) RMSE bound over the frames with t >= t_start."""
        keep = self.t >= t_start
        if not keep.any():
            raise InputError(f"t_start: {t_start} s leaves no frame")
        return (
            float(np.sqrt(np.mean(self.position[keep] ** 2))),
            float(np.sqrt(np.mean(self.orientation[keep] ** 2))),
        )


def _pose(scenario: Scenario, k: int) -> gtsam.Pose3:
    truth = scenario.groundtruth
    return gtsam.Pose3(gtsam.Rot3(truth.rotations[k]), truth.positions[k])


def _sigma(scenario: Scenario) -> float:
    return max(scenario.pixel_sigma, MIN_PIXEL_SIGMA) / scenario.camera.mean_focal


def _plane_noise(normal: np.ndarray) -> gtsam.noiseModel.Base:
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    R = np.vstack((normal / DEFAULT_PLANE_SIGMA, a / IN_PLANE_SIGMA, b / IN_PLANE_SIGMA))
    return gtsam.noiseModel.Gaussian.SqrtInformation(R)


def _frame_factors(
    scenario: Scenario,
    frames: Sequence[int],
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
) -> None:
    """Poses X(k) at the truth, the true points L(j) on the plane, the projection factors.

    Only frames the scenario observed have pixels (a dropped frame keeps its pose, tied
    to its neighbours by the motion prior alone), and only plane points (off-plane
    tracks added to ``observations`` are not in ``clean_observations``).
    """
    noise = gtsam.noiseModel.Isotropic.Sigma(2, _sigma(scenario))
    plane = _plane_noise(np.asarray(scenario.plane.normal, dtype=float))
    observed = {int(o.index) for o in scenario.observations}
    seen: set[int] = set()
    for k in frames:
        pose = _pose(scenario, k)
        values.insert(X(k), pose)
        if k not in observed:
            continue
        obs = scenario.clean_observations[k]
        R, p = pose.rotation().matrix(), np.asarray(pose.translation())
        for track in np.asarray(obs.ids).tolist():
            point = scenario.points_world[track]
            if track not in seen:
                seen.add(track)
                values.insert(L(track), point)
                graph.add(gtsam.PriorFactorPoint3(L(track), point, plane))
            c = R.T @ (point - p)
            m = c[:2] / c[2]  # noise-free: the linearization point is the truth
            graph.add(gtsam.GenericProjectionFactorCal3_S2(m, noise, X(k), L(track), _UNIT))
    first = frames[0]
    graph.add(
        gtsam.PriorFactorPose3(X(first), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
    )


def _bound(scenario: Scenario, covariances: list[np.ndarray]) -> PoseBound:
    C = np.array(covariances)
    return PoseBound(
        t=np.asarray(scenario.groundtruth.t, dtype=float)[: len(C)],
        position=np.sqrt(np.trace(C[:, 3:, 3:], axis1=1, axis2=2)),
        orientation=np.rad2deg(np.sqrt(np.trace(C[:, :3, :3], axis1=1, axis2=2))),
    )


def posterior_bound(scenario: Scenario, acceleration_sigma: float | Sequence[float]) -> PoseBound:
    """The posterior Cramér-Rao bound of the pose at every frame (module docstring).

    Args:
        scenario: a simulated sequence (ground truth, points, pixel sigma).
        acceleration_sigma: (s_w, s_v) of the motion prior (one number: both).
    Returns:
        The bound per frame.
    """
    sigma = check_acceleration_sigma(acceleration_sigma)
    truth = scenario.groundtruth
    if truth.twists is None:
        raise InputError("scenario: the ground truth has no twists")
    K = len(truth.t)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    _frame_factors(scenario, list(range(K)), graph, values)
    q = twist_spectral_density(sigma)
    values.insert(V(0), truth.twists[0])
    graph.add(gtsam.PriorFactorVector(V(0), np.zeros(6), gtsam.noiseModel.Isotropic.Sigma(6, 10.0)))
    for k in range(1, K):
        values.insert(V(k), truth.twists[k])
        dt = float(truth.t[k] - truth.t[k - 1])
        graph.add(wna_factor(k - 1, k, dt, q))
    # One elimination; the marginals of each pose from its Bayes tree (QR: stiff priors).
    params = gtsam.ISAM2Params()
    params.setFactorization("QR")
    isam = gtsam.ISAM2(params)
    isam.update(graph, values)
    return _bound(scenario, [isam.marginalCovariance(X(k)) for k in range(K)])


def memoryless_bound(scenario: Scenario) -> PoseBound:
    """The bound of a per-frame estimator: the pose of frame k from frames 0 and k alone
    (NaN at frames the scenario did not observe)."""
    covariances = [np.zeros((6, 6))]
    observed = {int(o.index) for o in scenario.observations}
    for k in range(1, len(scenario.groundtruth.t)):
        if k not in observed:
            covariances.append(np.full((6, 6), np.nan))
            continue
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        _frame_factors(scenario, [0, k], graph, values)
        covariances.append(gtsam.Marginals(graph, values).marginalCovariance(X(k)))
    return _bound(scenario, covariances)


def bound_ratio(rmse: float, bound: float) -> float:
    """rmse / bound (inf for a zero bound)."""
    as_number(rmse, "rmse", at_least=0.0)
    return float(rmse / bound) if bound > 0 else float("inf")
