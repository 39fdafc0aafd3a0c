"""The tightly coupled plane-landmark smoother (``--method tight``): the pixels themselves
in the factor graph, with the plane (n*, d*) as a constraint on the landmarks.

The homography graph (:mod:`hvo_graph.estimators.smoother`) fuses per-frame H_d
poses, each computed from the reference frame's pixels and the current ones; the
reference's noise is shared by every pose and a memoryless pose is only as good as
one frame pair allows. Here every pixel observation is its own factor, so the motion
model pools the information of every frame on the landmarks and on the poses.

Variables (keys from ``gtsam.symbol_shorthand``): X(k), the pose T_wc
(``gtsam.Pose3``, W = F*, the first camera frame); V(k), the body twist [w; v]
(6-vector, contract sign); L(j), one ``Point3`` in W per track (a new key when a
track comes back after its landmark left the online problem). Factors:

- world: X(k0) = I (standard deviation :data:`DEFAULT_WORLD_SIGMA`); together with
  the plane it fixes the gauge (W is the first camera frame by definition, so this
  prior is exact: the first frame's pixel noise enters through the landmarks);
- plane: n*^T L(j) = d*, a ``PriorFactorPoint3`` whose square-root information
  has one stiff row along n* (standard deviation ``plane_sigma``) and two loose
  in-plane rows (:data:`IN_PLANE_SIGMA`): a linear constraint, built in C++;
- projection: one ``GenericProjectionFactorCal3_S2`` per observation with the unit
  calibration on the undistorted normalized coordinates m = (x/z, y/z) of the
  front end (:class:`~hvo_graph.types.PointObservations`), so every camera model
  (radial-tangential, fisheye) goes through :class:`~hvo_graph.geometry.camera.CameraModel`;
  isotropic noise of the frame's ``sigma`` (pixel sigma over the mean focal length)
  under a Huber loss (threshold ``robust_threshold`` on the whitened residual), but
  Gaussian in the first frame, whose pixels alone observe the scale and place of the map;
- first frame: that similarity of the plane (shift along it, turn about n*, scale) held
  at the first frame's back-projection, its uncertainty added to the covariances
  (:mod:`~hvo_graph.estimators.plane_gauge`: else the motion model shrinks the map);
- motion: the white-noise-acceleration prior as trapezoid and twist random walk (with
  GTSAM's factor the window's early wild twists pulled the poses off on a noisy
  few-point draw), Q fitted on the front end's H_d poses unless ``acceleration_sigma``;
- no H_d or H_c factors: they are made of the same pixels. They give the initial
  values: X(k) from H_d (the motion-model prediction without one), V(k) from H_c,
  and a new landmark from its first ray cut with the plane at that initial pose.

Off-plane tracks: a point off the plane is consistent with a plane landmark only
while the camera has not moved (no parallax). After each update the whitened
residual of every new observation is checked against ``reject_chi2`` (chi^2, 2
dof); a track failing in ``reject_after`` consecutive observations is rejected: no
more of its observations enter, and the final solve drops all of its factors.
That gate sees one observation at a time, after the landmark has moved in the
plane to fit it: an off-plane point the front end excludes after a few frames never
fails it, yet pulls the poses of those frames and, through the landmarks, the
world frame. Before the final solve (solvers "isam2" and "batch") every track is
therefore tested as a whole at the smoothed poses
(:func:`~hvo_graph.estimators.plane_tracks.off_plane_statistic`, chi^2 with 1 dof
for a plane point); above ``track_chi2``, and again with the poses uncertain
(:func:`~hvo_graph.estimators.tight_solvers.confirm_off_plane`), it is rejected.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from hvo_graph.errors import InputError, as_integer, as_number
from hvo_graph.estimators import plane_gauge
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.choices import (
    DEFAULT_INITIAL_TWIST_SIGMA,
    DEFAULT_WORLD_SIGMA,
    TIGHT_SOLVERS,
)
from hvo_graph.estimators.landmarks import DEFAULT_MAX_LANDMARKS, back_project, farthest_points
from hvo_graph.estimators.motion_model import MotionFactors
from hvo_graph.estimators.noise_estimation import ProcessNoiseSchedule
from hvo_graph.estimators.plane_tracks import DEFAULT_TRACK_CHI2, off_plane_keys
from hvo_graph.estimators.process_noise import DEFAULT_ACCELERATION_SIGMA
from hvo_graph.estimators.process_noise import acceleration_sigma as check_acceleration_sigma
from hvo_graph.estimators.solvers import Backend, BatchBackend
from hvo_graph.estimators.tight_covariance import backend_error_covariances
from hvo_graph.estimators.tight_solvers import (
    LandmarkFixedLagBackend,
    WindowIsam2Backend,
    confirm_off_plane,
    drop_landmarks,
    tight_isam2_params,
)
from hvo_graph.types import FrameMeasurement, PointObservations, StateEstimate, Trajectory

__all__ = [
    "DEFAULT_PIXEL_THRESHOLD",
    "DEFAULT_PLANE_SIGMA",
    "DEFAULT_REJECT_AFTER",
    "DEFAULT_REJECT_CHI2",
    "TightSmoother",
    "back_project",
]

#: Huber threshold on the whitened 2-D pixel residual: sqrt of chi^2_2(0.95), so an
#: inlier observation is down-weighted 5 % of the time.
DEFAULT_PIXEL_THRESHOLD: float = math.sqrt(5.991464547107979)

#: Standard deviation (m) of n*^T L - d*: the landmarks lie on the plane.
DEFAULT_PLANE_SIGMA: float = 1e-6

#: Standard deviation (m) of the in-plane rows of the plane factor (no information).
IN_PLANE_SIGMA: float = 1e2

#: chi^2 (2 dof) of an observation's whitened residual beyond which it counts against
#: its track: the 99.9 % quantile.
DEFAULT_REJECT_CHI2: float = 13.815510557964274

#: A track failing the gate in this many consecutive observations is rejected.
DEFAULT_REJECT_AFTER: int = 3

_ZERO6 = np.zeros(6)

_MOTION_FORM = "wna-pair"  # the motion prior's form (motion_model.STORED_FORMS)
_UNIT_CALIBRATION = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


class TightSmoother(Estimator):
    """Pixels of plane points fused with the motion model in one GTSAM graph.

    Args:
        solver: "isam2" (default; ``--method tight``): ISAM2 over a rebuilt window
            online (:class:`~hvo_graph.estimators.tight_solvers.WindowIsam2Backend`),
            the batch optimum from its estimates for :meth:`trajectory`, solved in chunks
            of frames (:func:`~hvo_graph.estimators.factor_store.solve_in_chunks`); "batch"
            (``tight-batch``); "fixed-lag" (``tight-fixed-lag``, ``lag`` seconds).
        lag: window of the fixed-lag solver, seconds (> 0).
        acceleration_sigma: (s_w, s_v) of the white-noise-acceleration model, one
            number for both, or "auto" (default): fitted by maximum likelihood on
            the front end's H_d poses (as the homography smoother does).
        robust_threshold: Huber threshold on the whitened pixel residual norm
            (default :data:`DEFAULT_PIXEL_THRESHOLD`).
        compute_covariance: also return the 12x12 covariance of [pose tangent; twist]
            per frame: online, the ISAM2 marginal after the frame's update; smoothed, the
            pose's marginal, the twist's error covariance (``tight_covariance``).
        plane_sigma: standard deviation (m) of the plane constraint n*^T L = d*.
        reject_chi2, reject_after: the off-plane track gate (module docstring).
        track_chi2: threshold of the whole-track off-plane test at the end (module
            docstring; :data:`~hvo_graph.estimators.plane_tracks.DEFAULT_TRACK_CHI2`).
        relinearize_threshold, relinearize_skip: ISAM2's relinearization settings.
        max_iterations: most Levenberg-Marquardt iterations of the final solve.
        max_landmarks: most landmarks observed per frame (None: every point). Tracks
            that already have a landmark keep it; new ones fill the free places,
            each the farthest (in the image) from the points already used, so the
            landmarks stay spread over the view (:data:`DEFAULT_MAX_LANDMARKS`).

    Frames must carry ``points`` (:class:`~hvo_graph.types.PointObservations`, made
    by :class:`~hvo_graph.frontend.MeasurementFrontEnd`); a frame without them (the
    plane normal not yet known) is predicted by the motion model.
    """

    name = "tight"

    def __init__(
        self,
        *,
        solver: str = "isam2",
        lag: float = 1.0,
        acceleration_sigma: float | Sequence[float] | str = "auto",
        robust_threshold: float | None = None,
        compute_covariance: bool = False,
        plane_sigma: float = DEFAULT_PLANE_SIGMA,
        reject_chi2: float = DEFAULT_REJECT_CHI2,
        reject_after: int = DEFAULT_REJECT_AFTER,
        track_chi2: float = DEFAULT_TRACK_CHI2,
        relinearize_threshold: float = 0.05,
        relinearize_skip: int = 10,
        max_iterations: int = 100,
        max_landmarks: int | None = DEFAULT_MAX_LANDMARKS,
    ) -> None:
        super().__init__()
        if solver not in TIGHT_SOLVERS:
            raise InputError(f"solver: expected one of {', '.join(TIGHT_SOLVERS)}, got {solver!r}")
        self.solver = solver
        self.name = TIGHT_SOLVERS[solver]
        self.lag = as_number(lag, "lag", above=0.0)
        self.process_noise = ProcessNoiseSchedule(acceleration_sigma, DEFAULT_ACCELERATION_SIGMA)
        self._motion = MotionFactors()
        self._set_acceleration_sigma(self.process_noise.sigma)
        self.robust_threshold = (
            DEFAULT_PIXEL_THRESHOLD
            if robust_threshold is None
            else as_number(robust_threshold, "robust_threshold", above=0.0)
        )
        self.compute_covariance = bool(compute_covariance)
        self.plane_sigma = as_number(plane_sigma, "plane_sigma", above=0.0)
        self.reject_chi2 = as_number(reject_chi2, "reject_chi2", above=0.0)
        self.reject_after = as_integer(reject_after, "reject_after", 1)
        self.track_chi2 = as_number(track_chi2, "track_chi2", above=0.0)
        threshold = as_number(relinearize_threshold, "relinearize_threshold", above=0.0)
        skip = as_integer(relinearize_skip, "relinearize_skip", 1)
        max_iterations = as_integer(max_iterations, "max_iterations", 1)
        self.max_landmarks = (
            None if max_landmarks is None else as_integer(max_landmarks, "max_landmarks", 4)
        )
        self.backend: Backend
        if solver == "batch":
            self.backend = BatchBackend(
                max_iterations=max_iterations, compute_covariance=self.compute_covariance
            )
        elif solver == "fixed-lag":
            self.backend = LandmarkFixedLagBackend(
                tight_isam2_params(threshold, skip),
                self.lag,
                compute_covariance=self.compute_covariance,
            )
        else:
            # Rebuilt windows by Cholesky (half QR's time per update at 20 landmarks, the
            # same estimates to rounding); the first one, with the world prior, by QR.
            self.backend = WindowIsam2Backend(
                tight_isam2_params(threshold, skip),
                max_iterations=max_iterations,
                compute_covariance=self.compute_covariance,
                pixel_noise=self._pixel_noise_model,
                rebuilt=tight_isam2_params(threshold, skip, "CHOLESKY"),
            )
        self._world_noise = gtsam.noiseModel.Isotropic.Sigma(6, DEFAULT_WORLD_SIGMA)
        self._twist_prior = gtsam.noiseModel.Isotropic.Sigma(6, DEFAULT_INITIAL_TWIST_SIGMA)
        self._indices: list[int] = []
        self._times: list[float] = []
        self._pose = gtsam.Pose3()
        self._twist = _ZERO6
        #: track id -> its current landmark key.
        self._landmarks: dict[int, int] = {}
        self._next_landmark = 0
        self._strikes: dict[int, int] = {}
        #: Track ids rejected as off the plane.
        self.rejected_tracks: set[int] = set()
        self._rejected_keys: set[int] = set()
        #: landmark key -> its track id, and per frame (index, keys (N,), m (N, 2), sigma)
        #: of the observations added (compact: the whole-track test reads them at the end).
        self._key_track: dict[int, int] = {}
        self._observations: list[tuple[int, np.ndarray, np.ndarray, float]] = []
        self._plane: tuple[np.ndarray, float] | None = None
        self._tracks_checked = False  # since the latest frame
        self._pruned_keys: set[int] = set()
        self._pixel_noise: dict[float, gtsam.noiseModel.Base] = {}
        #: Projection factors added, and landmarks started.
        self.counts = {"observations": 0, "landmarks": 0}
        #: The first frame's similarity of the plane, held (plane_gauge), or None.
        self.gauge: plane_gauge.FirstFrameGauge | None = None

    def _set_acceleration_sigma(self, value: float | Sequence[float]) -> None:
        #: (s_w, s_v) of the motion factors added from now on.
        self.acceleration_sigma = check_acceleration_sigma(value)

    def run(self, frames: Iterable[FrameMeasurement], *, online: bool = True) -> Trajectory:
        """Fuse a whole sequence; "auto" process noise is fitted on all of it first (the
        window also places new landmarks and gates pixels: it runs whatever ``online``)."""
        frames = list(frames)
        if not self._indices:
            self.process_noise.fit_all(frames)
            self._set_acceleration_sigma(self.process_noise.sigma)
        return super().run(frames)

    # -- per frame --------------------------------------------------------------------------

    def _update(self, frame: FrameMeasurement) -> StateEstimate:
        k, t = int(frame.index), float(frame.t)
        if self._times and not t > self._times[-1]:
            raise InputError(f"frame {k}: time {t} does not increase")
        points = frame.points
        if points is not None:
            m = np.asarray(points.m, dtype=float)
            if m.ndim != 2 or m.shape[1] != 2 or len(m) != len(points.ids):
                raise InputError(f"frame {k}: points.m must be (N, 2) with N = len(points.ids)")
        if self.process_noise.observe(frame):
            self._set_acceleration_sigma(self.process_noise.sigma)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        twist_guess = (
            np.asarray(frame.velocity.twist, dtype=float)
            if frame.velocity is not None
            else self._twist
        )
        store = self.backend.store  # the final solve's copy of the factors (or nothing)
        store.add_frame(k)
        if not self._indices:
            for prior in (
                gtsam.PriorFactorPose3(X(k), gtsam.Pose3(), self._world_noise),
                gtsam.PriorFactorVector(V(k), _ZERO6, self._twist_prior),
            ):
                graph.add(prior)
                store.add_factor(prior)
            pose_guess = gtsam.Pose3()
        else:
            previous, dt = self._indices[-1], t - self._times[-1]
            for factor in self._motion(_MOTION_FORM, previous, k, dt, self.acceleration_sigma):
                graph.add(factor)
            store.add_motion(dt, self.acceleration_sigma, _MOTION_FORM)  # as numbers
            if frame.pose is not None:
                world = self.pose_in_world(frame.pose)
                pose_guess = gtsam.Pose3(gtsam.Rot3(world.rotation), world.position)
            else:
                step = gtsam.Pose3.Expmap((0.5 * dt) * (self._twist + twist_guess))
                pose_guess = self._pose.compose(step)
        new = self._observe(graph, values, k, pose_guess, points) if points is not None else None
        if not self._indices:  # the first frame holds the map's similarity (plane_gauge)
            added = [] if new is None else list(zip(*new, strict=True))
            self.gauge = plane_gauge.first_frame_gauge(k, added, points)
        values.insert(X(k), pose_guess)
        values.insert(V(k), twist_guess)
        self._indices.append(k)
        self._times.append(t)
        self._tracks_checked = False
        pose, twist, covariance = self.backend.add(graph, values, k, t - self._times[0])
        if len(self._indices) == plane_gauge.HOLD_AFTER:  # the scale is in: hold it
            self.gauge = plane_gauge.hold_scale(self.gauge, self.backend)
        self._pose, self._twist = pose, np.asarray(twist, dtype=float)
        if new is not None and len(new[1]):
            sigma = float(points.sigma)  # type: ignore[union-attr]
            self._observations.append((k, np.array(new[1], dtype=np.uint64), new[2], sigma))
            self._gate(pose, new, sigma)
        return StateEstimate(
            index=k,
            t=t,
            rotation=pose.rotation().matrix(),
            position=np.asarray(pose.translation(), dtype=float),
            twist=self._twist.copy(),
            covariance=covariance,
        )

    def _observe(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        k: int,
        pose_guess: gtsam.Pose3,
        points: PointObservations,
    ) -> tuple[list[int], list[int], np.ndarray]:
        """Projection factors of the frame's points (new landmarks as needed); returns the
        track ids, landmark keys and m (N, 2) of the observations added."""
        anchor = not self._indices  # the first frame: Gaussian (module docstring)
        noise = self._pixel_noise_model(float(points.sigma), robust=not anchor)
        normal = np.asarray(points.normal, dtype=float)
        distance = float(points.distance)
        self._plane = (normal, distance)
        tracks, coordinates = self._admitted(np.asarray(points.ids), np.asarray(points.m, float))
        pose = X(k)
        used, keys, rows = [], [], []
        for i, (track, m) in enumerate(zip(tracks, coordinates, strict=True)):
            key = self._landmarks.get(track)
            if key is None or not self._live(key):
                point = back_project(pose_guess, m, normal, distance)
                if point is None:
                    continue
                key = L(self._next_landmark)
                self._next_landmark += 1
                self._landmarks[track] = key
                self._key_track[key] = track
                self.counts["landmarks"] += 1
                values.insert(key, point)
                stiff = plane_gauge.plane_noise(normal, self.plane_sigma, IN_PLANE_SIGMA)
                graph.add(plane := gtsam.PriorFactorPoint3(key, point, stiff))
                self.backend.store.add_landmark(key, plane)  # the final solve's copy
            graph.add(gtsam.GenericProjectionFactorCal3_S2(m, noise, pose, key, _UNIT_CALIBRATION))
            used.append(track)
            keys.append(key)
            rows.append(i)
        self.counts["observations"] += len(keys)
        m = coordinates if len(rows) == len(tracks) else coordinates[rows]  # the final solve's:
        self.backend.store.add_observations(keys, m, float(points.sigma), robust=not anchor)
        return used, keys, m

    def _admitted(self, ids: np.ndarray, m: np.ndarray) -> tuple[list[int], np.ndarray]:
        """The frame's observations to use: not rejected, and at most ``max_landmarks``
        (tracks with a live landmark first, then new ones farthest-point first)."""
        tracks = ids.tolist()
        usable = [i for i, track in enumerate(tracks) if track not in self.rejected_tracks]
        if self.max_landmarks is None or len(usable) <= self.max_landmarks:
            return [tracks[i] for i in usable], m[usable]
        kept, new = [], []
        for i in usable:
            key = self._landmarks.get(tracks[i])
            (kept if key is not None and self._live(key) else new).append(i)
        kept = kept[: self.max_landmarks]
        picks = farthest_points(m[new], m[kept], self.max_landmarks - len(kept))
        kept += [new[i] for i in picks]
        kept.sort()
        return [tracks[i] for i in kept], m[kept]

    def _pixel_noise_model(self, sigma: float, robust: bool = True) -> gtsam.noiseModel.Base:
        sigma = as_number(sigma, "points.sigma", above=0.0)
        model = self._pixel_noise.get(sigma) if robust else None
        if model is None:
            model = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
            if robust:
                huber = gtsam.noiseModel.mEstimator.Huber.Create(self.robust_threshold)
                model = self._pixel_noise[sigma] = gtsam.noiseModel.Robust.Create(huber, model)
        return model

    def _live(self, key: int) -> bool:
        """Whether landmark ``key`` is still a variable of the online solver."""
        live = getattr(self.backend, "live", None)
        if live is not None:
            return key in live
        isam = getattr(self.backend, "isam", None)
        return True if isam is None else bool(isam.valueExists(key))

    def _points(self, keys: list[int]) -> np.ndarray:
        """(N, 3) the current estimates of the landmarks ``keys``."""
        isam, live = getattr(self.backend, "isam", None), getattr(self.backend, "live", None)
        if isam is None:
            return np.array([self.backend.initial.atPoint3(key) for key in keys])  # type: ignore[attr-defined]
        if live is None or live.issuperset(keys):
            return np.array([isam.calculateEstimatePoint3(key) for key in keys])
        at = self.backend.initial.atPoint3  # type: ignore[attr-defined]  # left the window
        return np.array([isam.calculateEstimatePoint3(k) if k in live else at(k) for k in keys])

    def _gate(self, pose: gtsam.Pose3, added: tuple[list, list, np.ndarray], sigma: float) -> None:
        """Count the observations (track ids, landmark keys, m (N, 2)) whose whitened
        residual fails the chi^2 gate."""
        tracks, keys, m = added
        R = pose.rotation().matrix()
        p = np.asarray(pose.translation(), dtype=float)
        # all observations at once: c = R^T (L - p) per row, in the camera frame
        c = (self._points(keys) - p) @ R
        ahead = c[:, 2] > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):  # behind the camera: inf
            r = (m - c[:, :2] / c[:, 2:]) / sigma
        chi2s = np.where(ahead, np.einsum("ij,ij->i", r, r), math.inf).tolist()
        for track, key, chi2 in zip(tracks, keys, chi2s, strict=True):
            if chi2 <= self.reject_chi2:
                self._strikes.pop(track, None)
                continue
            self._strikes[track] = self._strikes.get(track, 0) + 1
            if self._strikes[track] >= self.reject_after:
                self.rejected_tracks.add(track)
                self._rejected_keys.add(key)

    # -- results ----------------------------------------------------------------------------

    def _check_tracks(self) -> None:
        """Reject the tracks whose observations, at the smoothed poses, no plane point fits
        (:func:`~hvo_graph.estimators.plane_tracks.off_plane_statistic` above
        ``track_chi2``), and still none with the poses uncertain
        (:func:`~hvo_graph.estimators.tight_solvers.confirm_off_plane`): the online gate
        sees one observation at a time; an off-plane point dropped early never fails it."""
        backend = self.backend
        if self._tracks_checked or self._plane is None or backend.solver == "fixed-lag":
            return
        self._tracks_checked = True
        final = list(backend.final(self._indices, marginals=False))
        frames = np.concatenate([np.full(len(keys), k) for k, keys, _, _ in self._observations])
        observed = (
            frames,
            np.concatenate([keys for _, keys, _, _ in self._observations]),
            np.concatenate([m for _, _, m, _ in self._observations]),
            np.concatenate([np.full(len(k), s) for _, k, _, s in self._observations]),
        )
        candidates = off_plane_keys(
            np.array([pose.rotation().matrix() for pose, _, _ in final]),
            np.array([pose.translation() for pose, _, _ in final]),
            np.searchsorted(self._indices, frames),  # frame indices increase
            *observed[1:],
            self._plane,
            self.track_chi2,
            skip=self._rejected_keys,
        )
        plane_noise = plane_gauge.plane_noise(self._plane[0], self.plane_sigma, IN_PLANE_SIGMA)
        failed = confirm_off_plane(backend, candidates, observed, plane_noise, self.track_chi2)
        for key in failed:
            track = self._key_track[key]
            self.rejected_tracks.add(track)
            self._rejected_keys.update(k for k, t in self._key_track.items() if t == track)

    def _prune(self) -> None:
        """Drop the factors and values of rejected landmarks from the final graph."""
        if not self._rejected_keys <= self._pruned_keys:
            drop_landmarks(self.backend, self._rejected_keys)
            self.gauge = plane_gauge.release_tracks(self.gauge, self.backend, self._rejected_keys)
            self._pruned_keys = set(self._rejected_keys)

    def trajectory(self) -> Trajectory:
        """The smoothed estimate of every frame so far (the class docstring per solver)."""
        n = len(self._indices)
        rotations, positions, twists = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 6))
        covariances = np.empty((n, 12, 12)) if self.compute_covariance else None
        if n:
            self._check_tracks()
            if self._key_track and self._rejected_keys >= self._key_track.keys():
                raise InputError(
                    f"tracks: the tight graph found every track ({len(self.rejected_tracks)}) off "
                    "the plane: are the pixels noisier than noise.pixel_sigma says?"
                )
            self._prune()
            marginal = self.backend.solver == "fixed-lag"  # else marginal pose, error twist
            finals = self.backend.final(self._indices, marginals=marginal)
            for i, (pose, twist, cov) in enumerate(finals):
                rotations[i], positions[i] = pose.rotation().matrix(), pose.translation()
                twists[i] = twist
                if covariances is not None and marginal:
                    covariances[i] = cov
            if covariances is not None and not marginal:
                covariances[:] = backend_error_covariances(self.backend, self._indices, self._times)
            plane_gauge.add_scale_share(self.gauge, self.backend, self._indices, covariances)
        return Trajectory(np.asarray(self._times, float), rotations, positions, twists, covariances)
