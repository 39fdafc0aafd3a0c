"""Measurement front end: feature tracks -> per-frame pose and velocity measurements.

For every frame k (paper Section III, NOTES sections 2-3):

- **pose** from the discrete homography H_d between the reference frame F*
  (frame 0 or a keyframe) and frame k: DLT on the normalized points shared
  with the reference (RANSAC from 6 points), Euclidean normalization, then
  (R, T) with the known n*, d* by the known-normal path, refined by
  Gauss-Newton steps on the transfer error (the near-maximum-likelihood pose
  under pixel noise); points failing a chi^2 gate at the refined pose are left
  out, and tracks failing it repeatedly are excluded (off the plane).
  Optionally (``pose_solver="ippe"``) OpenCV's ``solvePnP(SOLVEPNP_IPPE)``.
- **velocity** from the continuous homography H_c between frames k-1 and k
  (:func:`~hvo_graph.frontend.velocity.flow_twist`), with the plane moved to
  mid-interval: n(t) = R n*, d(t) = d* + n(t)^T T.

Covariances are first-order propagations of isotropic pixel noise sigma
(``pixel_sigma``, pixels, over the mean focal length). The pose's,
(J^T Sigma^-1 J)^-1 with Sigma_i = s^2 (I + A_i A_i^T), is reported in two
parts (:func:`~hvo_graph.geometry.transfer.pose_noise`): the
reference frame's pixel noise (``PoseMeasurement.reference_covariance``) is one
draw shared by every pose measured against it, the current frame's is
independent from frame to frame. A flow shares its pixels with the two poses
it lies between; the velocity covariance does not say so. See docs/method.md.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_integer, as_number
from hvo_graph.frontend._batch import measure_frames
from hvo_graph.frontend._points import (
    HUBER,
    CollinearMemo,
    TrackedFrame,
    common_points,
    kept_points,
    normalized_by_id,
    shared_count,
)
from hvo_graph.frontend.keyframe_tilt import KeptFrames, keep_frame, leave_keyframe
from hvo_graph.frontend.pose_gate import gated_pose
from hvo_graph.frontend.velocity import flow_twist, mid_interval_plane
from hvo_graph.geometry._fit import PlaneTransfer, dlt, euclidean, known_normal_motion
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.geometry.continuous import motion_after_twist
from hvo_graph.geometry.decomposition import decompose_homography, physically_valid_solutions
from hvo_graph.geometry.discrete import estimate_homography, ippe_motion
from hvo_graph.geometry.plane_normal import NormalFit
from hvo_graph.geometry.transfer import keyframe_plane_jacobian
from hvo_graph.measurement_table import MeasurementTable
from hvo_graph.types import (
    FrameMeasurement,
    FrameObservations,
    Plane,
    PoseMeasurement,
    TiltMeasurement,
    VelocityMeasurement,
)

#: The paper's noisy run: pixel variance 0.05 px^2.
DEFAULT_PIXEL_SIGMA = float(np.sqrt(0.05))

MIN_PIXEL_SIGMA = 1e-3  # noise-free input still gets covariances from it (pixels)

#: Automatic RANSAC threshold: this many pixel sigmas of transfer distance (standard
#: deviation sigma sqrt(2) per axis, two noisy observations; 5 sigma keeps nearly every
#: inlier), and at least MIN_RANSAC_PX pixels (noise-free input).
RANSAC_SIGMAS = 5.0
MIN_RANSAC_PX = 0.5

#: Fewest shared points for RANSAC and the gates. With 5, a 4-point sample has one
#: spare point to judge and a good point is often "rejected": on a near-hover draw
#: dropping a corner left a near-degenerate 4-point pose with 3x its error (NEES 7).
ROBUST_MIN_POINTS = 6

#: Per-point gate after the pose refinement: chi^2 (2 dof) of the transfer residual
#: under its covariance; 13.8 is the 99.9 % quantile.
OUTLIER_CHI2 = 13.815510557964274

POSE_SOLVERS = ("homography", "ippe")

#: Points this many pixel sigmas (RMS) from a line fix no homography: no measurement.
COLLINEAR_SIGMAS = 3.0


@dataclass(frozen=True)
class FrontEndConfig:
    """Front-end settings.

    Attributes:
        pixel_sigma: std of feature coordinates, pixels (drives the covariances).
            Zero (noise-free input) is floored at ``MIN_PIXEL_SIGMA`` so the
            covariances, and the fusion built on them, stay well posed.
        min_points: fewest shared points for a measurement (>= 4).
        ransac: RANSAC (OpenCV) on H_d whenever a frame shares at least
            ``ROBUST_MIN_POINTS`` (6) points with its reference; False: least
            squares on every point.
        ransac_threshold_px: RANSAC inlier threshold in pixels; None:
            ``RANSAC_SIGMAS`` pixel sigmas, at least ``MIN_RANSAC_PX``.
        outlier_chi2: after the pose refinement, points whose transfer residual
            exceeds this chi^2 (2 dof) under its covariance are rejected and the
            pose refined again; None: no gate. Off-plane points agree with the
            plane until the camera has moved (parallax), so this catches what
            the first frames' RANSAC cannot.
        reject_after: a track rejected in this many frames is left out of every
            later pose and velocity (it does not lie on the plane); None: never.
        refine_iterations: Gauss-Newton steps refining the homography pose.
        pose_solver: "homography" (the paper's H_d) or "ippe" (OpenCV solvePnP).
        min_parallax: ||T|| / d* a frame needs before its decomposition is
            used to estimate an unknown plane normal.
        keyframe_min_points: below this many points shared with the reference,
            the previous frame becomes the new reference (keyframe) if it shares
            at least twice as many (or when the reference shares fewer than
            ``min_points``); poses are then measured against the keyframe.
            The keyframe's own pose rests on the points it shares with the old
            reference, so switching while that is still many points pays: on
            rendered images 30 gave a quarter of the raw pose error of 8
            (docs/images.md). None: always measure against frame 0.
    """

    pixel_sigma: float = DEFAULT_PIXEL_SIGMA
    min_points: int = 4
    ransac: bool = True
    ransac_threshold_px: float | None = None
    outlier_chi2: float | None = OUTLIER_CHI2
    reject_after: int | None = 3
    refine_iterations: int = 2
    pose_solver: str = "homography"
    min_parallax: float = 0.05
    keyframe_min_points: int | None = 30

    def __post_init__(self) -> None:
        as_number(self.pixel_sigma, "pixel_sigma", at_least=0.0, what="a number")
        as_integer(self.min_points, "min_points", 4)
        as_integer(self.refine_iterations, "refine_iterations", 0)
        if self.keyframe_min_points is not None:
            as_integer(self.keyframe_min_points, "keyframe_min_points", self.min_points)
        as_number(self.min_parallax, "min_parallax", at_least=0.0)
        if self.pose_solver not in POSE_SOLVERS:
            raise InputError(
                f"pose_solver: expected one of {', '.join(POSE_SOLVERS)}, got {self.pose_solver!r}"
            )
        if self.ransac_threshold_px is not None:
            as_number(self.ransac_threshold_px, "ransac_threshold_px", above=0.0)
        if self.outlier_chi2 is not None:
            as_number(self.outlier_chi2, "outlier_chi2", above=0.0)
        if self.reject_after is not None:
            as_integer(self.reject_after, "reject_after", 1)
        if not isinstance(self.ransac, bool):
            raise InputError(f"ransac: expected true or false, got {self.ransac!r}")

    @property
    def ransac_px(self) -> float | None:
        """The RANSAC threshold in force (pixels), or None without RANSAC."""
        if not self.ransac:
            return None
        if self.ransac_threshold_px is not None:
            return float(self.ransac_threshold_px)
        return max(RANSAC_SIGMAS * self.pixel_sigma, MIN_RANSAC_PX)


class MeasurementFrontEnd:
    """Streaming front end: one :meth:`process` call per frame, in order.

    The first processed frame is the reference F* (world frame). Points are
    matched by id. When tracks leave the view the reference moves to a
    keyframe (see ``FrontEndConfig.keyframe_min_points``) and pose
    measurements become relative to it (``PoseMeasurement.reference``). A frame
    with fewer than ``min_points`` points shared with the reference gets no
    pose; fewer shared with the previous frame, no velocity. Without n*, a whole
    sequence (:meth:`process_all`) has it fitted to all of its frames first
    (:attr:`normal_fit`); frame by frame, it comes from the first two that agree.
    """

    def __init__(self, camera: CameraModel, plane: Plane, config: FrontEndConfig | None = None):
        self.camera = camera
        self.plane = plane
        self.config = config or FrontEndConfig()
        self._sigma = max(self.config.pixel_sigma, MIN_PIXEL_SIGMA) / camera.mean_focal
        self._reference: TrackedFrame | None = None
        self._earlier: list[TrackedFrame] = []  # former references (re-identified tracks)
        self._previous: TrackedFrame | None = None
        self._normal: np.ndarray | None = None if plane.normal is None else plane.normal
        if self.config.pose_solver == "ippe" and self._normal is None:
            raise InputError("pose_solver 'ippe' needs the plane normal in the camera file")
        self._normal_candidates: list[list[np.ndarray]] = []
        #: frames in which each track id was rejected; ids at ``reject_after`` are excluded.
        self._rejections: dict[int, int] = {}
        self._excluded: set[int] = set()
        self._rejected_ids: list[int] = []  # the current frame's gate rejections
        self._last_twist = np.zeros(6)  # the latest measured [w; v] (predicts lost frames)
        # (reference frame, n*, its plane) of the reference in use, and that plane's basis.
        self._reference_plane: tuple | None = None
        self._collinear = CollinearMemo(COLLINEAR_SIGMAS * self._sigma)
        self._fit: PlaneTransfer | None = None  # the latest pose fit
        self.normal_fit: NormalFit | None = None
        self._kept = KeptFrames()  # frames against the reference (keyframe_tilt)
        self._tilt: dict[int, np.ndarray] = {}  # n_r's covariance by reference index
        self._previous_rotation_covariance: np.ndarray | None = None
        self._tilt_measurement: TiltMeasurement | None = None  # for the current record

    @property
    def normal(self) -> np.ndarray | None:
        """n*: the known plane normal, or the one estimated so far (None before)."""
        return self._normal

    def process(self, obs: FrameObservations) -> FrameMeasurement:
        """Measure one frame. Returns a record with pose and/or velocity (None when impossible)."""
        if self._previous is not None and not obs.t > self._previous.t:
            raise InputError(
                f"frame {obs.index}: time {obs.t} does not increase (previous {self._previous.t})"
            )
        ids, m = normalized_by_id(self.camera, obs)
        if self._excluded:
            keep = ~np.isin(ids, list(self._excluded))
            ids, m = ids[keep], m[keep]
        self._rejected_ids = []
        if self._reference is None:
            self._reference = TrackedFrame(obs.index, obs.t, ids, m, np.eye(3), np.zeros(3))
            self._world_index = obs.index
            self._tilt[obs.index] = np.zeros((3, 3))
        try:
            R, T, pose = self._measure_pose(ids, m)
        except InputError:  # points geometry refuses (degenerate, behind the camera): no pose
            R, T, pose = None, None, None
        prev = self._previous  # no pose: carry the last motion on at the last twist
        if pose is None and self._normal is not None and prev is None:  # W, too few points
            R, T = np.eye(3), np.zeros(3)  # (the next frame with enough points re-acquires)
        elif pose is None and self._normal is not None and prev.R is not None:
            R, T = motion_after_twist(prev.R, prev.T, self._last_twist, obs.t - prev.t)
        frame = TrackedFrame(obs.index, obs.t, ids, m, R, T)
        velocity = self._measure_velocity(frame) if prev is not None else None
        self._last_twist = self._last_twist if velocity is None else np.asarray(velocity.twist)
        limit = self.config.keyframe_min_points  # a new reference must see this many points
        if (
            pose is None
            and R is not None
            and limit
            and len(ids) >= limit
            and shared_count(self._reference.ids, ids) < self.config.min_points
        ):
            # Re-acquisition: a new reference at its predicted pose; the estimators re-place
            # the plane at their own estimate of it (keyframe plane Jacobian).
            self._move_reference(frame)
        self._previous = frame
        self._previous_rotation_covariance = None if pose is None else pose.covariance[:3, :3]
        if pose is not None:
            keep_frame(self, frame)
        rejected = len(self._rejected_ids) + len(obs.ids) - len(ids)
        points = kept_points(ids, m, self._rejected_ids, self._sigma, self._normal, self.plane)
        tilt, self._tilt_measurement = self._tilt_measurement, None
        counts = (len(obs.ids), rejected)
        return FrameMeasurement(obs.index, obs.t, pose, velocity, *counts, points, tilt)

    def process_all(self, observations: Iterable[FrameObservations]) -> list[FrameMeasurement]:
        """:meth:`process` of every frame in order (same-track stretches measured at once)."""
        return list(measure_frames(self, observations, ROBUST_MIN_POINTS, HUBER))

    def process_table(self, observations: Iterable[FrameObservations]) -> MeasurementTable:
        """:meth:`process_all` into a :class:`~hvo_graph.measurement_table.MeasurementTable`."""
        out = measure_frames(self, observations, ROBUST_MIN_POINTS, HUBER, MeasurementTable())  # type: ignore[arg-type]
        return out.compact()  # type: ignore[attr-defined]

    @property
    def excluded_tracks(self) -> frozenset[int]:
        """Ids of the tracks left out as not on the plane (see ``reject_after``)."""
        return frozenset(self._excluded)

    def _reject(self, ids: np.ndarray) -> None:
        """Count one rejection for each id; exclude the ids that reached ``reject_after``."""
        self._rejected_ids.extend(ids.tolist())
        limit = self.config.reject_after
        for i in ids.tolist():
            self._rejections[i] = self._rejections.get(i, 0) + 1
            if limit is not None and self._rejections[i] >= limit:
                self._excluded.add(i)

    # -- pose from H_d -------------------------------------------------------------------------

    def _measure_pose(
        self, ids: np.ndarray, m: np.ndarray
    ) -> tuple[np.ndarray | None, np.ndarray | None, PoseMeasurement | None]:
        """Pose of the current frame against the reference (frame 0 or the latest keyframe).

        Returns the motion (R, T) from the world frame into the current frame
        (for the velocity's plane) and the pose measurement T_rc, or Nones.
        """
        assert self._reference is not None
        m_ref, m_cur, shared = common_points(self._reference, ids, m, with_ids=True)
        earlier = self._earlier_reference(len(m_ref), ids)
        if earlier is not None or self._switch_keyframe(len(m_ref), ids, m):
            self._move_reference(earlier or leave_keyframe(self))
            m_ref, m_cur, shared = common_points(self._reference, ids, m, with_ids=True)
        ref = self._reference
        if len(m_ref) < self.config.min_points or self._collinear(m_ref) or self._collinear(m_cur):
            return None, None, None
        if self._normal is None:  # only while still on frame 0: estimate n* from parallax
            motion = self._homography_motion(m_ref, m_cur, None)
            if motion is None:
                return None, None, None
        plane = self._plane_in(ref)
        # The reference's constants are kept while the reference and tracks stay the same.
        fit = self._fit = PlaneTransfer.reuse(self._fit, m_ref, m_cur, plane, self._sigma)
        if self.config.pose_solver == "ippe":
            R, T = ippe_motion(m_ref, m_cur, plane)
            start = np.ones(len(m_ref), dtype=bool)
        else:
            motion = self._homography_motion(m_ref, m_cur, plane, fit.basis)
            if motion is None:
                return None, None, None
            R, T, start = motion
        # RANSAC's inliers start the refinement; the gate at the refined pose, on every
        # shared point, decides (RANSAC's mask comes from a noisy minimal sample).
        gate = self.config.outlier_chi2 if len(m_ref) >= ROBUST_MIN_POINTS else None
        steps = 0 if self.config.pose_solver == "ippe" else self.config.refine_iterations + 1
        huber = HUBER if gate is not None else None
        R, T, _, keep, lin, _ = gated_pose(fit, R, T, start, steps, huber, gate)
        if np.count_nonzero(keep) < self.config.min_points:
            return None, None, None
        self._reject(shared[~keep])
        refit = not np.array_equal(keep, start)
        if not keep.all():
            fit, lin = fit.subset(keep), None
            m_ref, m_cur = m_ref[keep], m_cur[keep]
        if refit:
            R, T, _ = fit.refine(R, T, steps)
            lin = None
        R_rc = R.T.copy()  # the camera pose T_rc (camera_pose_from_motion)
        p_rc = -R.T @ T
        covariance, shared_covariance, shared_jacobian = fit.noise(
            fit.linearize(R, T) if lin is None else lin
        )
        keyframe: dict[str, np.ndarray] = {}
        if ref.index != self._world_index:
            # The keyframe's plane comes from its *measured* pose: say which, and how T_rc
            # moves with it, so an estimator can re-place the plane at its own estimate.
            R_wr, p_wr = ref.R.T.copy(), -ref.R.T @ ref.T
            keyframe = {
                "reference_rotation": R_wr,
                "reference_position": p_wr,
                "plane_jacobian": keyframe_plane_jacobian(
                    R, T, m_ref, m_cur, plane, self._sigma, None if refit else huber
                ),
            }
        pose = PoseMeasurement(
            *(R_rc, p_rc, covariance),
            reference=0 if ref.index == self._world_index else ref.index,  # 0: W
            reference_covariance=shared_covariance,
            reference_jacobian=shared_jacobian,
            reference_ids=shared[keep],
            **keyframe,
        )
        # Motion world -> current: X = R (R_ref X_w + T_ref) + T.
        return R @ ref.R, R @ ref.T + T, pose

    def _move_reference(self, frame: TrackedFrame | None) -> None:
        assert frame is not None and self._reference is not None
        self._earlier = [f for f in self._earlier if f.index != frame.index][-15:]
        self._earlier.append(self._reference)
        self._reference = frame
        self._kept = KeptFrames()

    def _earlier_reference(
        self, shared_with_reference: int, ids: np.ndarray
    ) -> TrackedFrame | None:
        """A former reference that sees the current points again (the tracker re-identified
        them after a loss) when the reference has too few: the one sharing the most, at
        least ``keyframe_min_points`` (``min_points`` without keyframes)."""
        need = max(self.config.min_points, self.config.keyframe_min_points or 0)
        if shared_with_reference >= need or not self._earlier:
            return None
        counts = [shared_count(f.ids, ids) for f in self._earlier]
        best = int(np.argmax(counts))
        return self._earlier[best] if counts[best] >= need else None

    def _switch_keyframe(self, shared_with_reference: int, ids: np.ndarray, m: np.ndarray) -> bool:
        """Make the previous frame the reference when it sees clearly more of the current points.

        Each switch chains one more relative pose (and its error), so it happens
        only when the reference shares fewer than ``min_points`` points, or
        fewer than ``keyframe_min_points`` while the previous frame shares at
        least twice as many.
        """
        prev, limit = self._previous, self.config.keyframe_min_points
        if limit is None or prev is None or prev.index == self._reference.index or prev.R is None:
            return False
        if shared_with_reference >= limit:
            return False
        shared_with_previous = shared_count(prev.ids, ids)
        if shared_with_reference < self.config.min_points:
            return shared_with_previous >= self.config.min_points
        return shared_with_previous >= 2 * shared_with_reference

    def _plane_in(self, frame: TrackedFrame) -> Plane:
        """The plane in ``frame``'s camera frame: n = R n*, d = d* + n^T T (kept while
        ``frame`` stays the reference)."""
        cached = self._reference_plane
        if cached is not None and cached[0] is frame and cached[1] is self._normal:
            return cached[2]
        n = frame.R @ self._normal
        plane = Plane(self.plane.distance + float(n @ frame.T), n)
        self._reference_plane = (frame, self._normal, plane)
        return plane

    def _homography_motion(
        self,
        m_ref: np.ndarray,
        m_cur: np.ndarray,
        plane: Plane | None,
        basis: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(R, T, inlier mask) from H_d with the plane in the reference frame
        (``basis``: :func:`~hvo_graph.geometry._fit.plane_basis` of its normal).

        With ``plane`` None (n* unknown), feeds the normal estimation and
        returns None until n* is known.
        """
        threshold = self.config.ransac_px if len(m_ref) >= ROBUST_MIN_POINTS else None
        if threshold is None:  # the DLT of estimate_homography, on the checked points
            H, inliers = dlt(m_ref, m_cur), np.ones(len(m_ref), dtype=bool)
        else:
            H, inliers = estimate_homography(
                m_ref, m_cur, ransac_threshold=threshold / self.camera.mean_focal
            )
        if np.count_nonzero(inliers) < self.config.min_points:
            return None
        if not inliers.all():
            m_ref, m_cur = m_ref[inliers], m_cur[inliers]
        H = euclidean(H, m_ref, m_cur)
        if plane is None or basis is None:
            found = self._estimate_normal(H, m_ref, m_cur)
            return (np.eye(3), np.zeros(3), inliers) if found else None
        R, t = known_normal_motion(H, plane.normal, basis)
        return R, plane.distance * t, inliers

    def _estimate_normal(self, H: np.ndarray, m_ref: np.ndarray, m_cur: np.ndarray) -> bool:
        """Pick n* from two frames with parallax: of each one's two valid decompositions,
        the true normal is the one both agree on (the spurious one moves with the motion)."""
        valid = physically_valid_solutions(decompose_homography(H), m_ref, m_cur)
        if not valid or np.linalg.norm(valid[0].translation) < self.config.min_parallax:
            return False
        normals = [s.normal for s in valid]
        if not self._normal_candidates:
            self._normal_candidates.append(normals)
            return False
        first = self._normal_candidates[0]
        best = max(((a, b) for a in first for b in normals), key=lambda ab: float(ab[0] @ ab[1]))
        if float(best[0] @ best[1]) < np.cos(np.deg2rad(5.0)):
            return False  # no agreement yet (too little motion between the frames)
        n = best[0] + best[1]
        self._normal = n / np.linalg.norm(n)
        return True

    # -- velocity from H_c ---------------------------------------------------------------------

    def _measure_velocity(self, frame: TrackedFrame) -> VelocityMeasurement | None:
        prev = self._previous
        assert prev is not None
        if self._normal is None:
            return None
        m0, m1 = common_points(prev, frame.ids, frame.m)
        if len(m0) < self.config.min_points or self._collinear(m0):
            return None
        motions = [(f.R, f.T) for f in (prev, frame) if f.R is not None]
        plane = mid_interval_plane(motions, self._normal, self.plane.distance, 0.5 * (m0 + m1))
        if plane is None:
            return None
        limit = self.config.outlier_chi2 if len(m0) >= ROBUST_MIN_POINTS else None
        return flow_twist(
            m0, m1, prev.t, frame.t, plane, self._sigma, limit, self.config.min_points
        )


def measure_sequence(
    observations: Iterable[FrameObservations],
    camera: CameraModel,
    plane: Plane,
    config: FrontEndConfig | None = None,
    **overrides: object,
) -> list[FrameMeasurement]:
    """Run the front end over a whole sequence: one :class:`FrameMeasurement` per frame.

    Args:
        observations: frames in time order (e.g. from :func:`hvo_graph.io.tracks.read_tracks`).
        camera: the calibrated camera.
        plane: d* (and n* when known) in the first frame.
        config: front-end settings; keyword ``overrides`` replace single fields
            (e.g. ``pixel_sigma=0.5``).
    """
    if overrides:
        config = FrontEndConfig(**{**(config or FrontEndConfig()).__dict__, **overrides})
    return MeasurementFrontEnd(camera, plane, config).process_all(observations)
