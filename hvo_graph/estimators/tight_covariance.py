"""The tight graph's smoothed covariances: the pose's marginal, the twist's errors.

GTSAM's marginal (the inverse information) is the error covariance only when the
motion really is the model's white-noise acceleration. Real motions are smooth: for
the twist, which the tight graph knows only through the motion factors between
well-measured poses, the marginal counts a random twist wander the motion never
makes, and was 2-8x too large (twist NEES per dof 0.13-0.54 on every scenario
family). The homography smoother had the same problem and computes the covariance
of its errors instead (:mod:`~hvo_graph.estimators.error_covariance`: over the
measurement noise, P M P plus the shared noise, plus the motion model's lag).

Here the tight graph is cast as that chain: per frame the [pose; twist] state,
the motion factors between frames, each frame's projection factors as a measurement
of its pose with the landmarks at their estimates (information A_x^T A_x), and the
landmarks' errors as noise sources every frame that sees them shares (response
A_x^T A_l R, R R^T the landmarks' joint marginal covariance). The landmarks' errors
come from the same pixels as the frames', which this leaves out: on the paper's
scenario the twist variance is 0.97-1.03x the whole graph's P M P (computed
densely) after the first second, 0.88-1.55x within it, and O(K), not O(K^3).

The pose keeps its marginal (with the held scale's share,
:mod:`~hvo_graph.estimators.plane_gauge`): the pixels pin it and the marginal
matched its errors (pose NEES 0.75-1.44 per family), while the chain's error
covariance of the pose was overconfident on some (up to 2). The marginal comes from
the same chain: the frames' covariance given the landmarks plus the landmarks'
joint marginal through the frames' sensitivity to them (the law of total
covariance, :func:`~hvo_graph.estimators.error_covariance.marginal_covariances`),
equal to GTSAM's per-frame joint marginals and 25x cheaper with 50 landmarks.
The cross blocks keep the chain's correlation, rescaled to the marginal pose
block: with C the chain's error covariance and Pm the marginal pose block,
R = C_xx^-1/2 C_xv C_vv^-1/2 (singular values <= 1) and the cross block
Pm^1/2 R C_vv^1/2, so every frame's 12x12 matrix stays positive semi-definite.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from hvo_graph.estimators.error_covariance import (
    ChainSystem,
    error_covariances,
    marginal_covariances,
)
from hvo_graph.estimators.solvers import Backend, BatchBackend

__all__ = [
    "JOINT_LANDMARKS",
    "backend_error_covariances",
    "combine_pose_and_twist",
    "landmark_roots",
    "tight_chain",
    "tight_error_covariances",
]

_STATE = 12

#: Landmarks whose errors are taken jointly (their joint marginal); groups of this
#: many, in the order they were made, are taken as independent of one another.
JOINT_LANDMARKS: int = 100


def backend_error_covariances(
    backend: Backend, indices: Sequence[int], times: Sequence[float]
) -> np.ndarray:
    """:func:`tight_error_covariances` of a batch or windowed-ISAM2 back end's optimum."""
    graph = backend.graph if isinstance(backend, BatchBackend) else backend.store.whole_graph()  # type: ignore[attr-defined]
    return tight_error_covariances(graph, backend.values(), indices, times)  # type: ignore[attr-defined]


def tight_error_covariances(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    indices: Sequence[int],
    times: Sequence[float],
) -> np.ndarray:
    """(K, 12, 12) covariance of every frame's [pose tangent; twist] error: marginal
    pose block, error-covariance twist and cross blocks (module docstring).

    Args:
        graph: the tight graph (projection factors, motion factors, priors).
        values: its optimum.
        indices: the K frames, in order (X(k), V(k) in ``values``).
        times: (K,) their times, seconds.
    """
    isam = gtsam.ISAM2()
    # the linearization point held: the custom factors are not handed copies
    theta = isam.getLinearizationPoint()
    isam.update(graph, values)
    chain = tight_chain(graph, values, indices, times, landmark_roots(isam, values))
    del theta
    return combine_pose_and_twist(marginal_covariances(chain), error_covariances(chain))


def landmark_roots(
    isam: gtsam.ISAM2, values: gtsam.Values, *, group: int = JOINT_LANDMARKS
) -> list[tuple[list[int], np.ndarray]]:
    """The landmarks' joint marginal covariance as roots R (R R^T = the covariance), per
    group of up to ``group`` landmarks in the order they were made (keys): [(keys,
    R (3n, 3n))]. The landmarks' errors are correlated (a shift, turn or scale of the
    whole map): counted apart, the twist variance of the first frames was 3.7x the
    whole graph's; with the joint covariance at most 1.55x, and 0.97-1.03x beyond 1 s."""
    keys = sorted(int(k) for k in values.keys() if gtsam.Symbol(k).chr() == ord("l"))
    roots = []
    for start in range(0, len(keys), group):
        chunk = keys[start : start + group]
        c = isam.jointMarginalCovariance(chunk).fullMatrix()
        w, v = np.linalg.eigh(0.5 * (c + c.T))  # singular along n* (the plane): no Cholesky
        roots.append((chunk, v * np.sqrt(np.clip(w, 0.0, None))))
    return roots


def tight_chain(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    indices: Sequence[int],
    times: Sequence[float],
    roots: list[tuple[list[int], np.ndarray]],
) -> ChainSystem:
    """The tight graph linearized at ``values`` as the homography smoother's chain
    (module docstring); ``roots``: the landmarks' :func:`landmark_roots`."""
    K = len(indices)
    slot = {}
    for n, k in enumerate(indices):
        slot[X(k)], slot[V(k)] = (n, 0), (n, 6)
    column = {key: 3 * i for i, key in enumerate(k for keys, _ in roots for k in keys)}
    parts = {
        name: np.zeros((K, _STATE, _STATE)) for name in ("motion_diagonal", "fixed", "measurement")
    }
    upper = np.zeros((max(K - 1, 0), _STATE, _STATE))
    gradient = np.zeros((K, _STATE))
    shared = np.zeros((K, _STATE, max(3 * len(column), 1)))
    linear = graph.linearize(values)
    for i in range(graph.size()):
        factor = linear.at(i)
        if factor is None:
            continue
        keys = [int(key) for key in factor.keys()]
        A, b = factor.jacobian()
        widths = np.cumsum([0] + [6 if key in slot else 3 for key in keys])
        blocks = [A[:, lo:hi] for lo, hi in itertools.pairwise(widths)]
        framed = [
            (slot[key], block) for key, block in zip(keys, blocks, strict=True) if key in slot
        ]
        if isinstance(graph.at(i), gtsam.GenericProjectionFactorCal3_S2):
            ((n, _), A_x), landmark = framed[0], keys[1]
            parts["measurement"][n, :6, :6] += A_x.T @ A_x
            gradient[n, :6] += A_x.T @ b
            c = column[landmark]
            shared[n, :6, c : c + 3] += A_x.T @ blocks[1]
        elif len(framed) == len(keys):  # motion factors and priors (landmark ones left out)
            target = parts["fixed"] if len({n for (n, _), _ in framed}) == 1 else None
            for (n1, o1), B1 in framed:
                for (n2, o2), B2 in framed:
                    block = B1.T @ B2
                    if n1 == n2:
                        (target if target is not None else parts["motion_diagonal"])[
                            n1, o1 : o1 + 6, o2 : o2 + 6
                        ] += block
                    elif n2 == n1 + 1:
                        upper[n1, o1 : o1 + 6, o2 : o2 + 6] += block
    start = 0
    for keys, root in roots:  # per unit of each group's joint landmark noise
        group = slice(start, start + 3 * len(keys))
        shared[:, :, group] = shared[:, :, group] @ root
        start = group.stop
    return ChainSystem(
        motion_upper=upper,
        measurement_upper=np.zeros_like(upper),
        shared=shared,
        gradient=gradient,
        times=np.asarray(times, dtype=float),
        **parts,
    )


def combine_pose_and_twist(marginals: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """(K, 12, 12): the marginals' pose block, the error covariance's twist block, and
    its cross block rescaled to the marginal pose (module docstring)."""
    pose, twist = marginals[:, :6, :6], errors[:, 6:, 6:]
    R = _inverse_root(errors[:, :6, :6]) @ errors[:, :6, 6:] @ _inverse_root(twist)
    u, s, vt = np.linalg.svd(R)
    R = u @ (np.minimum(s, 1.0)[:, :, None] * vt)
    out = np.empty_like(errors)
    out[:, :6, :6], out[:, 6:, 6:] = pose, twist
    out[:, :6, 6:] = _root(pose) @ R @ _root(twist)
    out[:, 6:, :6] = np.swapaxes(out[:, :6, 6:], 1, 2)
    return out


def _root(c: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(c)
    return (v * np.sqrt(np.clip(w, 0.0, None))[:, None, :]) @ np.swapaxes(v, 1, 2)


def _inverse_root(c: np.ndarray) -> np.ndarray:
    """The pseudo-inverse square root (directions below 1e-12 of the largest: none)."""
    w, v = np.linalg.eigh(c)
    keep = w > 1e-12 * np.max(np.abs(w), axis=1, keepdims=True)
    inv = np.where(keep, 1.0 / np.sqrt(np.where(keep, w, 1.0)), 0.0)
    return (v * inv[:, None, :]) @ np.swapaxes(v, 1, 2)
