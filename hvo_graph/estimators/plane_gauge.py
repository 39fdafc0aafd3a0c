"""The scale of the tightly coupled smoother's map, held once the first frames fix it.

A similarity of the world that keeps the plane n*^T X = d* (a shift t along it, a
turn theta about n*, a scale 1 + s about a point c of it: g = (t_a, t_b, theta, s)),
applied to every pose but the first (X(k0) = I is the world) and to every landmark,
changes no later projection: only the first frame's pixels and the motion factors
next to X(k0) (the jump it makes between X(k0) and the next pose) observe it. The
scale also multiplies every later velocity, so the motion model's cost falls with the
square of the scale, summed over the whole sequence: the joint maximum a posteriori
trades that information against a pull that grows with the sequence and shrinks the
map (a MAP bias on a multiplicative mode: the joint optimum ignores the volume that
shrinking the whole trajectory removes; -0.6 % at 30,000 frames of the paper's
scenario, -2.7 % at 100,000). Shift and turn change only the factors next to X(k0):
no pull.

So the scale is estimated where its information is, at the start, and then held:
after :data:`HOLD_AFTER` frames (the pull of so few frames is negligible) the map's
scale relative to the first frame's back-projection is read from the estimate so far
with its variance, and a stiff factor holds it there for the rest of the sequence;
every other degree of freedom of the map stays free. The scale is a linear function
of the first frame's landmarks: with b_j the plane point seen at m_j from X(k0) = I
(in-plane coordinates u_j = E^T b_j, E the plane's axes), the weighted least-squares
similarity that maps the landmarks onto the b_j is

    g(L) = Sigma_g sum_j A_j^T W_j E^T (b_j - L_j),   A_j = [I_2, J (u_j - c), u_j - c],

(W_j the information of u_j from the pixel noise, Sigma_g = (sum_j A_j^T W_j A_j)^-1
its covariance from the first frame alone, J the quarter turn about n*, c the weighted
centroid), and the scale is its last component s(L) = c_s^T (L - b). Its variance at
the hold, c_s^T Sigma_L c_s from the joint marginal of those landmarks, is what the
graph no longer carries: :func:`add_scale_share` adds it back to each frame's
covariance through that frame's sensitivity to the held value (a nuisance shared by
every frame, first order: :meth:`FirstFrameGauge.sensitivities`).
Holding the shift and turn too, or the scale at the first frame's back-projection
alone, threw away the motion model's information next to X(k0): 3-4 % larger position
errors on the paper scenario's 10 s runs.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from hvo_graph.errors import InputError
from hvo_graph.estimators.solvers import Backend, BatchBackend
from hvo_graph.estimators.tight_solvers import WindowIsam2Backend
from hvo_graph.types import PointObservations

__all__ = [
    "DEFAULT_GAUGE_STIFFNESS",
    "HOLD_AFTER",
    "MIN_GAUGE_POINTS",
    "FirstFrameGauge",
    "add_scale_share",
    "first_frame_gauge",
    "hold_scale",
    "plane_axes",
    "plane_noise",
    "release_tracks",
]

#: How much stiffer than the estimate it holds the scale factor is (its standard
#: deviation is the scale's over this): the held scale keeps 1e-6 of its variance,
#: while QR stays well conditioned (the plane rows are stiffer).
DEFAULT_GAUGE_STIFFNESS: float = 1e3

#: Frames after which the map's scale is read and held (module docstring): the motion
#: model's information next to X(k0) is in by then, its pull over them is negligible.
HOLD_AFTER: int = 30

#: Fewest first-frame landmarks that hold the similarity (2 determine it exactly; 3
#: leave the fit a redundancy, so one poorly placed point does not decide it).
MIN_GAUGE_POINTS: int = 3

_QUARTER_TURN = np.array([[0.0, -1.0], [1.0, 0.0]])


def plane_axes(normal: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal axes E = [a, b] of the plane with normal n* (a, b, n* right-handed:
    n* x a = b), the same as the tight smoother's plane factor uses."""
    n = np.asarray(normal, dtype=float)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.column_stack((a, np.cross(n, a)))


_PLANE_NOISE: dict[tuple[float, ...], gtsam.noiseModel.Base] = {}


def plane_noise(normal: np.ndarray, sigma: float, in_plane_sigma: float) -> gtsam.noiseModel.Base:
    """The noise model of a landmark's plane prior: square-root information
    [n*^T / sigma; E^T / in_plane_sigma] (one stiff row along n*, :func:`plane_axes` loose),
    one object per plane and sigmas (cached)."""
    normal = np.asarray(normal, dtype=float)
    cache_key = (*np.round(normal, 12).tolist(), float(sigma), float(in_plane_sigma))
    model = _PLANE_NOISE.get(cache_key)
    if model is None:
        R = np.vstack((normal / sigma, plane_axes(normal).T / in_plane_sigma))
        model = _PLANE_NOISE[cache_key] = gtsam.noiseModel.Gaussian.SqrtInformation(R)
    return model


class FirstFrameGauge:
    """The scale of the map relative to the first frame's back-projection, held by a
    factor and added back to the covariances (module docstring).

    Args:
        keys: (N,) landmark keys L(j) observed in the first frame (X(k0) = I).
        m: (N, 2) their normalized image coordinates (x/z, y/z) there.
        sigma: standard deviation of m (pixel sigma over the mean focal length).
        normal, distance: the plane n* (3,) and d* (m) in W.
        stiffness: :data:`DEFAULT_GAUGE_STIFFNESS`.

    Attributes:
        keys: the landmark keys (list of int); points: (N, 3) the back-projections b_j;
        center: (3,) c, the point the scale and turn are about; axes: (3, 2) E;
        covariance: (4, 4) Sigma_g of g = (t_a, t_b, theta, s) from the first frame's
        pixel noise alone; coefficients: (N, 4, 3) dg/dL_j; scale, variance: the
        scale held and its variance (None until :meth:`hold`).

    Raises:
        InputError: fewer than :data:`MIN_GAUGE_POINTS` points, a ray that does not
            meet the plane in front of the camera, or points that do not fix a similarity
            (all at one place).
    """

    def __init__(
        self,
        keys: Sequence[int],
        m: np.ndarray,
        sigma: float,
        normal: np.ndarray,
        distance: float,
        *,
        stiffness: float = DEFAULT_GAUGE_STIFFNESS,
    ) -> None:
        m = np.asarray(m, dtype=float).reshape(-1, 2)
        if len(m) != len(keys) or len(m) < MIN_GAUGE_POINTS:
            raise InputError(
                f"first-frame gauge: expected at least {MIN_GAUGE_POINTS} points with one key "
                f"each, got {len(m)} points and {len(keys)} keys"
            )
        self.keys = [int(key) for key in keys]
        #: The first frame's index (set by :func:`first_frame_gauge`).
        self.first: int | None = None
        #: The scale held and its variance (:meth:`hold`); None until held.
        self.scale: float | None = None
        self.variance: float | None = None
        self._factor: gtsam.CustomFactor | None = None
        self._inputs = (m, float(sigma), np.asarray(normal, dtype=float), float(distance))
        self.stiffness = float(stiffness)
        n = self._inputs[2]
        rays = np.column_stack((m, np.ones(len(m))))
        along = rays @ n
        with np.errstate(divide="ignore"):
            depth = distance / along
        if not np.all(np.isfinite(depth) & (depth > 0)):
            raise InputError("first-frame gauge: a ray does not meet the plane in front")
        self.points = distance * rays / along[:, None]
        self.axes = E = plane_axes(n)
        u = self.points @ E
        # du/dm (N, 2, 2): b = d m~ / (n^T m~), so db/dm = d / (n^T m~) (P - m~ n_xy^T / n^T m~)
        P = np.vstack((np.eye(2), np.zeros((1, 2))))
        db = (distance / along)[:, None, None] * (
            P[None] - rays[:, :, None] * n[None, None, :2] / along[:, None, None]
        )
        du = np.einsum("ia,nib->nab", E, db)
        W = np.linalg.inv(sigma**2 * du @ np.transpose(du, (0, 2, 1)))  # (N, 2, 2)
        centroid = np.linalg.solve(W.sum(axis=0), np.einsum("nab,nb->a", W, u))
        r = u - centroid
        A = np.empty((len(m), 2, 4))
        A[:, :, :2] = np.eye(2)
        A[:, :, 2] = r @ _QUARTER_TURN.T
        A[:, :, 3] = r
        AtW = np.transpose(A, (0, 2, 1)) @ W  # (N, 4, 2)
        information = np.einsum("nab,nbc->ac", AtW, A)
        if np.linalg.cond(information) > 1e12:
            raise InputError("first-frame gauge: the points do not fix a similarity of the plane")
        self.covariance = np.linalg.inv(information)
        self.covariance = 0.5 * (self.covariance + self.covariance.T)
        self.center = E @ centroid + distance * n
        # g(L) = Sigma_g sum_j A_j^T W_j E^T (b_j - L_j): its coefficient of L_j
        self.coefficients = -np.einsum("ab,nbc,dc->nad", self.covariance, AtW, E)

    def similarity(self, landmarks: np.ndarray) -> np.ndarray:
        """g (4,) = (t_a, t_b, theta, s) of landmarks (N, 3) (rows in the order of
        :attr:`keys`): the similarity that maps them onto the first frame's back-projection."""
        offsets = self.points - np.asarray(landmarks, dtype=float).reshape(-1, 3)
        return -np.einsum("nad,nd->a", self.coefficients, offsets)

    def hold(self, landmarks: np.ndarray, covariance: np.ndarray) -> None:
        """Hold the scale of the estimate ``landmarks`` (N, 3) whose joint covariance is
        ``covariance`` (3N, 3N): :attr:`scale` = s(L), :attr:`variance` = c_s^T Sigma c_s."""
        landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 3)
        covariance = np.asarray(covariance, dtype=float)
        c = self.coefficients[:, 3, :].ravel()
        self.scale = float(self.similarity(landmarks)[3])
        self.variance = float(c @ covariance @ c)
        self._factor = None

    def factor(self, offset: float = 0.0) -> gtsam.CustomFactor:
        """The factor s(L) = :attr:`scale` (+ ``offset``), standard deviation
        sqrt(:attr:`variance`) / stiffness: linear in the landmarks (one object per hold;
        a new one for an offset)."""
        if self.scale is None or self.variance is None:
            raise ValueError("first-frame gauge: hold() it first")
        if self._factor is None or offset:
            sigma = np.sqrt(self.variance) / self.stiffness
            noise = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
            coefficients, points = self.coefficients[:, 3:], self.points
            scale = self.scale + offset

            def error(
                this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None
            ) -> np.ndarray:
                landmarks = np.array([values.atPoint3(key) for key in this.keys()])
                if jacobians is not None:
                    for i in range(len(jacobians)):
                        jacobians[i] = coefficients[i]
                return np.einsum("nad,nd->a", coefficients, landmarks - points) - scale

            factor = gtsam.CustomFactor(noise, self.keys, error)
            if offset:
                return factor
            self._factor = factor
        return self._factor

    def sensitivities(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, indices: Sequence[int]
    ) -> np.ndarray:
        """(K, 12) derivative of each frame's [pose tangent (right perturbation, [w; v]);
        twist] at the optimum ``values`` of ``graph`` (holding this gauge's factor) with
        respect to the held scale: the Gauss-Newton step of the graph with the held value
        moved by one standard deviation, less the step without (the optimum's own
        tolerance), over that move. Far from the first frame it is the similarity's
        derivative (the turn's and scale's moves of p about c, the scale's of the
        velocity); next to it the motion model smooths the jump at X(k0) out."""
        if self.variance is None:
            raise ValueError("first-frame gauge: hold() it first")
        others = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            factor = graph.at(i)
            if factor is not None and not _holds(factor, self.keys):
                others.add(factor)
        step = float(np.sqrt(self.variance))
        steps = []
        for offset in (0.0, step):
            shifted = gtsam.NonlinearFactorGraph(others)
            shifted.add(self.factor(offset))
            steps.append(shifted.linearize(values).optimize())
        rows = np.empty((len(indices), 12))
        for row, k in zip(rows, indices, strict=True):
            row[:6] = steps[1].at(X(k)) - steps[0].at(X(k))
            row[6:] = steps[1].at(V(k)) - steps[0].at(V(k))
        return rows / step


def _holds(factor: gtsam.NonlinearFactor, keys: list[int]) -> bool:
    """Whether ``factor`` is a scale hold on ``keys`` (one row on exactly those landmarks)."""
    return factor.dim() == 1 and list(factor.keys()) == keys


def first_frame_gauge(
    index: int,
    added: Sequence[tuple[int, int, np.ndarray]],
    points: PointObservations | None,
) -> FirstFrameGauge | None:
    """The gauge of the first frame ``index`` from its observations ``added`` (track id,
    landmark key, m); None (nothing will be held) without points, below
    :data:`MIN_GAUGE_POINTS` landmarks, or when they fix no similarity (all at one place)."""
    if points is None or len(added) < MIN_GAUGE_POINTS:
        return None
    keys = [key for _, key, _ in added]
    m = np.array([m for _, _, m in added])
    try:
        gauge = FirstFrameGauge(keys, m, float(points.sigma), points.normal, points.distance)
    except InputError:  # degenerate first frame: the graph keeps its own scale
        return None
    gauge.first = int(index)
    return gauge


def hold_scale(gauge: FirstFrameGauge | None, backend: Backend) -> FirstFrameGauge | None:
    """Read the map's scale and its variance from the optimum of ``backend``'s frames so
    far (call it after :data:`HOLD_AFTER` frames: the same optimum for the default and
    the batch solver) and hold it in the final solve: the default solver's store (its
    online window is left as it is) or the batch solver's graph. The fixed-lag solver's
    online estimates are its final ones: nothing is held there (None)."""
    if gauge is None:
        return None
    if isinstance(backend, BatchBackend):
        graph = backend.graph
    elif isinstance(backend, WindowIsam2Backend):
        graph = backend.store.whole_graph()
    else:
        return None
    values = backend.values()  # the optimum of the frames so far (solved, then kept)
    # One ISAM2 elimination at it gives the joint marginal (as batch_marginals does); its
    # linearization point is held so the custom factors are not handed copies.
    isam = gtsam.ISAM2()
    theta = isam.getLinearizationPoint()
    isam.update(graph, values)
    covariance = isam.jointMarginalCovariance(gauge.keys).fullMatrix()
    del theta
    gauge.hold(np.array([values.atPoint3(key) for key in gauge.keys]), covariance)
    if isinstance(backend, BatchBackend):
        backend.graph.add(gauge.factor())
        backend._result = None  # the hold changes the optimum
    else:
        backend.store.add_landmark(gauge.keys[0], gauge.factor())
    return gauge


def release_tracks(
    gauge: FirstFrameGauge | None, backend: Backend, dropped: Collection[int]
) -> FirstFrameGauge | None:
    """The gauge once the landmarks ``dropped`` (rejected tracks) have left ``backend``'s
    final solve: unchanged if none of them is the first frame's; else None, its factor
    taken out (the scale read after the first frames was pulled by that off-plane point,
    whose back-projection is no plane point: the graph keeps its own scale instead)."""
    if gauge is None or gauge.scale is None or not set(gauge.keys) & set(dropped):
        return gauge
    old = gauge.factor()  # the batch solver's drop_landmarks took it out of its graph
    if isinstance(backend, WindowIsam2Backend):
        for factors in backend.store.landmarks.values():
            factors[:] = [factor for factor in factors if factor is not old]
    return None


def add_scale_share(
    gauge: FirstFrameGauge | None,
    backend: Backend,
    indices: Sequence[int],
    covariances: np.ndarray | None,
) -> None:
    """Add the held scale's share variance j j^T to each frame's final covariance
    ``covariances`` (K, 12, 12), in place (j: :meth:`FirstFrameGauge.sensitivities` at
    ``backend``'s optimum); nothing when no scale is held (or no covariances)."""
    if gauge is None or gauge.variance is None or covariances is None:
        return
    if isinstance(backend, BatchBackend):
        graph = backend.graph
    elif isinstance(backend, WindowIsam2Backend):
        graph = backend.store.whole_graph()
    else:
        return
    for i, j in enumerate(gauge.sensitivities(graph, backend.values(), indices)):
        covariances[i] += gauge.variance * np.outer(j, j)
