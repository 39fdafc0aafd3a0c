"""The first frame's hold on the map of the tightly coupled smoother: the 4 degrees of
freedom of a similarity of the plane that no later frame observes.

A similarity of the world that keeps the plane n*^T X = d* (a shift t along it, a
rotation theta about n*, a scale 1 + s about a point c of it), applied to every
pose but the first (X(k0) = I is the world) and to every landmark, changes no later
projection: only the first frame's pixels observe it. The motion model's cost falls
with the square of the scale, so the joint maximum a posteriori trades the first
frame's pixels against it and shrinks the map, more so the longer the sequence (a
MAP bias on a multiplicative mode: the joint optimum ignores the volume that
shrinking the whole trajectory removes).

Here those 4 degrees of freedom are tied to the first frame's back-projection: with
b_j the plane point seen at m_j from X(k0) = I (in-plane coordinates u_j = E^T b_j,
E the plane's axes), the weighted least-squares similarity g = (t, theta, s) that
maps the map's landmarks onto the b_j,

    g(L) = Sigma_g sum_j A_j^T W_j E^T (b_j - L_j),   A_j = [I_2, J (u_j - c), u_j - c],

(W_j the information of u_j from the pixel noise, Sigma_g = (sum_j A_j^T W_j A_j)^-1
its covariance, J the quarter turn about n*, c the weighted centroid) is a linear
function of the landmarks held at 0 by a stiff factor (:meth:`FirstFrameGauge.factor`):
the motion model cannot move it, every other degree of freedom of the map stays free.
The estimate of the similarity is then the first frame's own, whose uncertainty
Sigma_g the graph no longer carries: :meth:`FirstFrameGauge.inflate` adds it back to
each frame's covariance through that frame's Jacobian with respect to g (a nuisance
shared by every frame; its correlation with the rest of the first frame's
information is neglected, a first-order approximation).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

import gtsam
import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.estimators.solvers import Backend, BatchBackend
from hvo_graph.estimators.tight_solvers import WindowIsam2Backend
from hvo_graph.types import PointObservations

__all__ = [
    "DEFAULT_GAUGE_STIFFNESS",
    "MIN_GAUGE_POINTS",
    "FirstFrameGauge",
    "hold_first_frame",
    "plane_axes",
    "plane_noise",
    "release_tracks",
    "with_nuisance",
]

#: How much stiffer than the first frame's own information on g the factor holding it
#: is (its standard deviations are sqrt(diag Sigma_g) over this): g's residual freedom
#: is 1e-6 of its variance, while QR stays well conditioned (the plane rows are stiffer).
DEFAULT_GAUGE_STIFFNESS: float = 1e3

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
    """The first frame's similarity of the plane, held by a factor and added back to the
    covariances (module docstring).

    Args:
        keys: (N,) landmark keys L(j) observed in the first frame (X(k0) = I).
        m: (N, 2) their normalized image coordinates (x/z, y/z) there.
        sigma: standard deviation of m (pixel sigma over the mean focal length).
        normal, distance: the plane n* (3,) and d* (m) in W.
        stiffness: :data:`DEFAULT_GAUGE_STIFFNESS`.

    Attributes:
        keys: the landmark keys (list of int); points: (N, 3) the back-projections b_j;
        center: (3,) c, the point the scale and rotation are about; axes: (3, 2) E;
        covariance: (4, 4) Sigma_g of g = (t_a, t_b, theta, s) from the first frame's
        pixel noise; coefficients: (N, 4, 3) dg/dL_j.

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
        #: The first frame's index (its pose is the world: no share of g), and whether the
        #: factor is in the online graph too (:func:`hold_first_frame`).
        self.first: int | None = None
        self.online = False
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

    def without(self, keys: Collection[int]) -> FirstFrameGauge | None:
        """The gauge of the points not in ``keys`` (rejected tracks), or None when fewer
        than :data:`MIN_GAUGE_POINTS` remain."""
        kept = [i for i, key in enumerate(self.keys) if key not in keys]
        if len(kept) < MIN_GAUGE_POINTS:
            return None
        m, sigma, normal, distance = self._inputs
        keep = [self.keys[i] for i in kept]
        return FirstFrameGauge(keep, m[kept], sigma, normal, distance, stiffness=self.stiffness)

    def similarity(self, landmarks: np.ndarray) -> np.ndarray:
        """g (4,) = (t_a, t_b, theta, s) of landmarks (N, 3) (rows in the order of
        :attr:`keys`): the similarity that maps them onto the first frame's back-projection."""
        offsets = self.points - np.asarray(landmarks, dtype=float).reshape(-1, 3)
        return -np.einsum("nad,nd->a", self.coefficients, offsets)

    def factor(self) -> gtsam.CustomFactor:
        """The factor g(L) = 0 with standard deviations sqrt(diag Sigma_g) / stiffness (a
        Gaussian of covariance Sigma_g / stiffness^2): linear in the landmarks."""
        noise = gtsam.noiseModel.Gaussian.Covariance(self.covariance / self.stiffness**2)
        coefficients, points = self.coefficients, self.points

        def error(
            this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None
        ) -> np.ndarray:
            landmarks = np.array([values.atPoint3(key) for key in this.keys()])
            if jacobians is not None:
                for i in range(len(jacobians)):
                    jacobians[i] = coefficients[i]
            return np.einsum("nad,nd->a", coefficients, landmarks - points)

        if self._factor is None:
            self._factor = gtsam.CustomFactor(noise, self.keys, error)
        return self._factor

    def jacobian(self, pose: gtsam.Pose3, twist: np.ndarray) -> np.ndarray:
        """(12, 4) derivative of [pose tangent (right perturbation, [w; v]); twist [w; v]]
        with respect to g: the similarity moves p to c + (1 + s) Rot(n*, theta)(p - c) + E t
        and turns R by Rot(n*, theta); it scales the body velocity by 1 + s."""
        R = pose.rotation().matrix()
        offset = np.asarray(pose.translation(), dtype=float) - self.center
        n = self._inputs[2]
        J = np.zeros((12, 4))
        J[0:3, 2] = R.T @ n
        J[3:6] = R.T @ np.column_stack((self.axes, np.cross(n, offset), offset))
        J[9:12, 3] = np.asarray(twist, dtype=float)[3:]
        return J

    def inflate(self, covariance: np.ndarray, pose: gtsam.Pose3, twist: np.ndarray) -> np.ndarray:
        """``covariance`` (12, 12) of a frame after the first plus the similarity's share
        J Sigma_g J^T (:meth:`jacobian`)."""
        J = self.jacobian(pose, twist)
        return np.asarray(covariance, dtype=float) + J @ self.covariance @ J.T


def hold_first_frame(
    backend: Backend,
    graph: gtsam.NonlinearFactorGraph,
    index: int,
    added: Sequence[tuple[int, int, np.ndarray]],
    points: PointObservations | None,
) -> FirstFrameGauge | None:
    """The gauge of the first frame ``index`` from its observations ``added`` (track id,
    landmark key, m), its factor added to ``graph`` (the online problem: the batch and
    fixed-lag solvers) and to the final solve's store (the default solver's final solve:
    its online window, marginalized every 30 frames, is left as it is); None (nothing
    held) below :data:`MIN_GAUGE_POINTS` landmarks or without points."""
    if points is None or len(added) < MIN_GAUGE_POINTS:
        return None
    keys = [key for _, key, _ in added]
    m = np.array([m for _, _, m in added])
    gauge = FirstFrameGauge(keys, m, float(points.sigma), points.normal, float(points.distance))
    gauge.first = int(index)
    gauge.online = not isinstance(backend, WindowIsam2Backend)
    if gauge.online:
        graph.add(gauge.factor())
    backend.store.add_landmark(keys[0], gauge.factor())
    return gauge


def release_tracks(
    gauge: FirstFrameGauge | None, backend: Backend, dropped: Collection[int]
) -> FirstFrameGauge | None:
    """The gauge once the landmarks ``dropped`` (rejected tracks: off the plane, so their
    back-projection is no plane point) have left ``backend``'s final solve: rebuilt from
    the other first-frame points, its factor in place of the old one (None: too few left,
    nothing held). The fixed-lag solver's frames are final: its gauge stays."""
    if gauge is None or not set(gauge.keys) & set(dropped):
        return gauge
    if not isinstance(backend, (BatchBackend, WindowIsam2Backend)):
        return gauge
    old = gauge.factor()
    for factors in backend.store.landmarks.values():
        factors[:] = [factor for factor in factors if factor is not old]
    new = gauge.without(dropped)
    if new is None:
        return None
    new.first, new.online = gauge.first, gauge.online
    if isinstance(backend, BatchBackend):
        backend.graph.add(new.factor())  # drop_landmarks took the old one out
    else:
        backend.store.add_landmark(new.keys[0], new.factor())
    return new


def with_nuisance(
    gauge: FirstFrameGauge | None,
    index: int,
    covariance: np.ndarray | None,
    pose: gtsam.Pose3,
    twist: np.ndarray,
    *,
    online: bool = False,
) -> np.ndarray | None:
    """Frame ``index``'s ``covariance`` (12, 12) with the similarity's share added
    (:meth:`FirstFrameGauge.inflate`); unchanged without a gauge, for the first frame (the
    world), or ``online`` when the online graph does not hold the gauge."""
    if gauge is None or covariance is None or index == gauge.first or (online and not gauge.online):
        return covariance
    return gauge.inflate(covariance, pose, twist)
