"""The smoother's factors, kept by role so that its error covariance can be computed.

:mod:`hvo_graph.estimators.error_covariance` needs the linearized system split
by where each factor's information comes from: the motion model, priors
without random error, and measurements (with the shared reference-frame noise
each pose measurement carries). The back ends (ISAM2, fixed-lag) do not keep
every factor, so the smoother records them here as it adds them, and
:meth:`FactorRecord.system` linearizes them at the final estimate.

A keyframe's between factors reach back to the keyframe, further than a
neighbour. So that the chain stays block tridiagonal, every frame from r + 1 to
the last one measured against keyframe r carries a copy of X_r in its state
([pose; twist; copies]), tied to the previous frame's copy (and the first one
to X_r itself) by a stiff equality: every pose measured against r then shares
r's error, as it does in the graph. A keyframe the front end comes back to
(points seen again after a loss) keeps its copy open until then, in a slot of
its own while a later keyframe's copy runs beside it; treating it as known
instead was a loop closure to an exact pose, and made every covariance before
it 1.5-3x too small. Other factors on frames further apart than neighbours (a
twist factor across a dropped frame) enter as if the earlier frame were known.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from hvo_graph.estimators.error_covariance import ChainSystem, SharedResponse, error_covariances


@dataclass
class _Shared:
    """A pose factor's response to the reference points' noise (unit variance)."""

    factor: gtsam.NonlinearFactor
    whitening: np.ndarray  # (6, 6) R with R^T R = the factor's information
    jacobian: np.ndarray  # (6, 2N) d eta / d rho
    ids: np.ndarray  # (N,) reference point ids
    reference: int = 0  # the frame whose pixels they are (0: the world frame's)


@dataclass
class FactorRecord:
    """Every factor of a smoother run, by role (see the module docstring)."""

    motion: list[gtsam.NonlinearFactor] = field(default_factory=list)
    fixed: list[gtsam.NonlinearFactor] = field(default_factory=list)
    measurement: list[gtsam.NonlinearFactor] = field(default_factory=list)
    shared: list[_Shared] = field(default_factory=list)
    #: Per frame in order: the keyframe its latest pose is against (0: the world frame).
    keyframes: list[int] = field(default_factory=list)
    #: The frames whose reference pixel noise the shared factors carry.
    shared_references: set[int] = field(default_factory=set)

    @property
    def rates(self) -> bool:
        """Whether the frames carry a twist rate A(k) (white-noise jerk: 18 states)."""
        keys = self.motion[0].keys() if self.motion else []
        return any(gtsam.Symbol(key).chr() == ord("a") for key in keys)

    def add_frame(self, keyframe: int | None) -> None:
        """The next frame: the keyframe of its pose (None: no pose, the last one's)."""
        last = self.keyframes[-1] if self.keyframes else 0
        self.keyframes.append(last if keyframe is None else keyframe)

    def add_shared(
        self,
        factor: gtsam.NonlinearFactor,
        covariance: np.ndarray,
        jacobian: np.ndarray,
        ids: np.ndarray,
        reference: int = 0,
    ) -> None:
        """A pose measurement factor (noise ``covariance``, own pixels) whose error also
        moves by ``jacobian`` (6, 2N) per unit of the noise of the points ``ids`` in frame
        ``reference`` (0: the world frame; a keyframe: the same draw for every pose
        measured against it)."""
        # GTSAM's own whitening R (R^T R = covariance^-1), the one in the linearized A.
        whitening = gtsam.noiseModel.Gaussian.Covariance(covariance).R()
        self.shared.append(_Shared(factor, whitening, np.asarray(jacobian), ids, reference))
        self.shared_references.add(reference)

    def system(
        self,
        values: gtsam.Values,
        indices: Sequence[int],
        times: Sequence[float],
        keyframes: Sequence[int] | None = None,
    ) -> ChainSystem:
        """The linearized chain at ``values`` over the frames ``indices`` (in order);
        per frame [pose tangent; twist] (and the twist rate with :attr:`rates`), and the
        keyframe copy when ``keyframes`` (per frame, the keyframe its latest pose is
        against; 0: the world frame) names one (module docstring)."""
        K = len(indices)
        base = 18 if self.rates else 12
        slot = {}
        for n, k in enumerate(indices):
            slot[X(k)] = (n, 0)
            slot[V(k)] = (n, 6)
            if self.rates:
                slot[gtsam.symbol_shorthand.A(k)] = (n, 12)
        copies = _keyframe_copies(indices, keyframes)
        state = base + 6 * max((len(c) for c in copies), default=0)
        columns = _shared_columns(self.shared)
        out = {
            "motion_diagonal": np.zeros((K, state, state)),
            "motion_upper": np.zeros((max(K - 1, 0), state, state)),
            "measurement_upper": np.zeros((max(K - 1, 0), state, state)),
            "fixed": np.zeros((K, state, state)),
            "measurement": np.zeros((K, state, state)),
            "gradient": np.zeros((K, state)),
        }
        for factor in self.motion:
            _accumulate(factor, values, slot, out["motion_diagonal"], out["motion_upper"])
        for factor in self.fixed:
            _accumulate(factor, values, slot, out["fixed"], None)
        jacobians = {}  # linearized once: the information, the gradient, the shared pull
        for factor in self.measurement + [s.factor for s in self.shared]:
            linear, places = _accumulate(
                factor,
                values,
                _with_copy(factor, slot, copies, base),
                out["measurement"],
                out["measurement_upper"],
            )
            A, b = linear.jacobian()
            jacobians[id(factor)] = (A, places)
            for n, offset, column in places:
                out["gradient"][n, offset : offset + 6] += A[:, column : column + 6].T @ b
        entries = []
        for item in self.shared:
            A, places = jacobians[id(item.factor)]
            response = A.T @ (item.whitening @ item.jacobian)  # (6 per key, 2N)
            c = np.array([columns[item.reference, int(i)] for i in item.ids], dtype=int)
            cols = np.ravel(np.column_stack((2 * c, 2 * c + 1)))
            entries += [(n, offset, cols, response[col : col + 6]) for n, offset, col in places]
        if state > base:
            _tie_copies(out, copies, base)
        shared = SharedResponse(K, state, 2 * len(columns), entries)
        return ChainSystem(times=np.asarray(times, dtype=float), shared=shared, **out)

    def covariances(
        self,
        finals: Sequence[tuple[gtsam.Pose3, np.ndarray]],
        indices: Sequence[int],
        times: Sequence[float],
        *,
        anchored: bool,
        keyframes: Sequence[int] | None = None,
    ) -> np.ndarray:
        """(K, 12, 12) covariance of the smoothed errors at the final (pose, twist) of each
        frame; ``anchored``: the poses are reported relative to the first one's;
        ``keyframes``: as :meth:`system` (None: those of :meth:`add_frame`)."""
        values = gtsam.Values()
        for k, (pose, twist) in zip(indices, finals, strict=True):
            values.insert(X(k), pose)
            values.insert(V(k), np.asarray(twist, dtype=float))
            if self.rates:  # every factor is linear in A: its value changes no information
                values.insert(gtsam.symbol_shorthand.A(k), np.zeros(6))
        adjoint = None
        if anchored:
            anchor = finals[0][0]
            adjoint = np.array([pose.between(anchor).AdjointMap() for pose, _ in finals])
        if keyframes is None and len(self.keyframes) == len(indices):
            keyframes = self.keyframes
        system = self.system(values, indices, times, keyframes)
        base = 18 if self.rates else 12
        covariance = error_covariances(system, anchor_adjoint=adjoint, bias_states=base)
        return covariance[:, :12, :12]


#: Information of the equality that ties a keyframe copy to the next frame's, relative to
#: the largest measurement information of the chain: stiff, yet far from rounding.
COPY_STIFFNESS: float = 1e6


def _keyframe_copies(
    indices: Sequence[int], keyframes: Sequence[int] | None
) -> list[dict[int, int]]:
    """Per frame, the keyframes whose copies it carries and their slots: keyframe r from
    frame r + 1 to the last frame measured against it; a slot is free again after its
    keyframe's last frame (few overlap: a keyframe the front end comes back to)."""
    copies: list[dict[int, int]] = [{} for _ in indices]
    if keyframes is None:
        return copies
    position = {k: n for n, k in enumerate(indices)}
    last: dict[int, int] = {}
    for n, r in enumerate(keyframes):
        if r and r in position and position[r] < n:
            last[r] = n
    free_from: list[int] = []  # per slot, the first frame it is free again
    for r in sorted(last, key=position.__getitem__):
        start, end = position[r] + 1, last[r]
        slot = next((s for s, f in enumerate(free_from) if f <= start), len(free_from))
        if slot == len(free_from):
            free_from.append(0)
        free_from[slot] = end + 1
        for n in range(start, end + 1):
            copies[n][r] = slot
    return copies


def _with_copy(
    factor: gtsam.NonlinearFactor,
    slot: dict[int, tuple[int, int]],
    copies: list[dict[int, int]],
    base: int,
) -> dict[int, tuple[int, int]]:
    """``slot``, with each keyframe a factor reaches back to mapped to its copy in the
    factor's newest frame's state."""
    keys = factor.keys()
    latest = max(slot[key][0] for key in keys)
    carried = copies[latest]
    moved = {
        X(r): (latest, base + 6 * s)
        for r, s in carried.items()
        if X(r) in keys and slot[X(r)][0] < latest
    }
    return {**slot, **moved} if moved else slot


def _tie_copies(out: dict[str, np.ndarray], copies: list[dict[int, int]], base: int) -> None:
    """The stiff equalities copy_n = copy_n-1 (or = X_r at the keyframe's own frame) as
    priors without random error (``fixed``, and the upper blocks of Lambda), and a unit
    prior on the slots a frame leaves empty (they stay out of everything else)."""
    pose = out["measurement"][:, :6, :6]
    stiffness = COPY_STIFFNESS * max(float(np.abs(pose).max()), 1.0)
    E = stiffness * np.eye(6)
    slots = (out["fixed"].shape[1] - base) // 6
    for n, carried in enumerate(copies):
        for s in range(slots):
            c = slice(base + 6 * s, base + 6 * s + 6)
            r = next((r for r, used in carried.items() if used == s), None)
            if r is None:
                out["fixed"][n, c, c] += np.eye(6)
                continue
            kept = copies[n - 1].get(r)
            before = slice(0, 6) if kept is None else slice(base + 6 * kept, base + 6 * kept + 6)
            out["fixed"][n - 1, before, before] += E
            out["fixed"][n, c, c] += E
            out["measurement_upper"][n - 1, before, c] -= E


def _shared_columns(shared: Sequence[_Shared]) -> dict[tuple[int, int], int]:
    """A column pair per (reference frame, point id): each frame's pixels are their own draw."""
    keys = sorted({(item.reference, int(i)) for item in shared for i in item.ids})
    return {key: c for c, key in enumerate(keys)}


def _accumulate(
    factor: gtsam.NonlinearFactor,
    values: gtsam.Values,
    slot: dict[int, tuple[int, int]],
    diagonal: np.ndarray,
    upper: np.ndarray | None,
) -> tuple[gtsam.GaussianFactor, list[tuple[int, int, int]]]:
    """Add the factor's information to the chain's blocks; the linearized factor and its
    (frame, offset, column) places (blocks on frames before the latest one's neighbour
    are left out)."""
    linear = factor.linearize(values)
    H = linear.information()
    places = [(*slot[key], 6 * i) for i, key in enumerate(linear.keys())]
    latest = max(n for n, _, _ in places)
    places = [p for p in places if p[0] >= latest - 1]
    for n1, o1, c1 in places:
        for n2, o2, c2 in places:
            block = H[c1 : c1 + 6, c2 : c2 + 6]
            if n1 == n2:
                diagonal[n1, o1 : o1 + 6, o2 : o2 + 6] += block
            elif n2 == n1 + 1 and upper is not None:
                upper[n1, o1 : o1 + 6, o2 : o2 + 6] += block
    return linear, places
