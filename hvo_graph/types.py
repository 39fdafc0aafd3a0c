"""Records passed between the layers of hvo_graph.

Conventions (docs/conventions.md, binding contract):

- metres, seconds, radians; camera frame x right, y down, z optical axis;
- world frame W = the camera frame at the first frame (the paper's F*);
- a pose is T_wc (camera to world): rotation R_wc, camera centre p_wc in W;
- a twist is the camera's body velocity ``[w; v]`` (GTSAM's Pose3 tangent
  order), expressed in the current camera frame: d/dt T_wc = T_wc [w; v]^;
- pose covariances live in GTSAM's Pose3 tangent space ``[rot; trans]`` with
  right perturbation: T_true = T_est * Exp(delta).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hvo_graph.errors import InputError, as_number, as_vector


@dataclass(frozen=True)
class Plane:
    """The scene plane in the reference frame F*: n*^T X* = d* for plane points X*.

    Attributes:
        normal: n*, (3,) unit normal pointing away from the camera, or None when
            it must be estimated from the images.
        distance: d* > 0, metres from the reference optical centre to the plane.
    """

    distance: float
    normal: np.ndarray | None = None

    def __post_init__(self) -> None:
        as_number(self.distance, "plane.distance", above=0.0)
        if self.normal is not None:
            n = as_vector(self.normal, "plane.normal", 3)
            norm = np.linalg.norm(n)
            if norm < 1e-12:
                raise InputError("plane.normal: expected a non-zero vector")
            object.__setattr__(self, "normal", n / norm)


@dataclass(frozen=True)
class FrameObservations:
    """The tracked points of one frame (one block of tracks.csv).

    Attributes:
        index: frame number (>= 0).
        t: time in seconds.
        ids: (N,) int point ids.
        uv: (N, 2) pixel coordinates (OpenCV convention).
    """

    index: int
    t: float
    ids: np.ndarray
    uv: np.ndarray


@dataclass(frozen=True)
class PoseMeasurement:
    """A camera pose measured from the discrete homography H_d.

    Attributes:
        rotation: (3, 3) R_rc, camera orientation in the reference frame.
        position: (3,) p_rc, camera centre in the reference frame (metres).
        covariance: (6, 6) in Pose3 tangent order [rot; trans], right perturbation.
        reference: frame index of the reference (keyframe); 0 is the world frame W.
        reference_rotation, reference_position: the keyframe pose T_wr (R_wr (3, 3),
            p_wr (3,)) the front end assumed to place the plane in the keyframe's frame
            (n_r = R_wr^T n*, d_r = d* - n*^T p_wr); None for reference 0.
        plane_jacobian: (6, 6) d xi_rc / d xi_wr: how the measured T_rc (right
            perturbation xi_rc) moves when the assumed T_wr is right-perturbed by
            xi_wr (through the plane only). An estimator whose keyframe estimate is
            T_wr_hat uses T_rc Exp(J Log(T_wr^-1 T_wr_hat)); None for reference 0.
        reference_covariance: (6, 6) the part of ``covariance`` due to the reference
            frame's pixel noise (shared by every pose measured against the same
            reference); ``covariance - reference_covariance`` is the part due to this
            frame's own pixels. None when not known.
        reference_jacobian: (6, 2N) d eta / d rho: how the pose error eta (right
            perturbation) moves with the reference frame's pixel noise of the N points
            ``reference_ids``, rho = e* / sigma ([u_1, v_1, u_2, ...], in pixel
            standard deviations), so ``reference_covariance`` = J J^T. The same draw
            enters every pose measured against that reference: an estimator can
            follow it across frames. None when not known.
        reference_ids: (N,) track ids of those reference points.
    """

    rotation: np.ndarray
    position: np.ndarray
    covariance: np.ndarray
    reference: int = 0
    reference_rotation: np.ndarray | None = None
    reference_position: np.ndarray | None = None
    plane_jacobian: np.ndarray | None = None
    reference_covariance: np.ndarray | None = None
    reference_jacobian: np.ndarray | None = None
    reference_ids: np.ndarray | None = None


@dataclass(frozen=True)
class VelocityMeasurement:
    """A body twist measured from the continuous homography H_c.

    The flow comes from a finite difference between frames k-1 and k, so the
    twist is the velocity at the middle of that interval (paper/NOTES.md 3).

    Attributes:
        twist: (6,) body velocity [w; v] (rad/s, m/s), contract sign.
        covariance: (6, 6) covariance of ``twist``.
        t: time the twist refers to (mid-interval, seconds).
        dt: length of the finite-difference interval (seconds).
    """

    twist: np.ndarray
    covariance: np.ndarray
    t: float
    dt: float


@dataclass(frozen=True)
class PointObservations:
    """The plane points of one frame as the front end kept them, for estimators that
    fuse the pixels themselves (the tightly coupled smoother).

    Attributes:
        ids: (N,) int track ids (tracks excluded as off the plane, and points the
            frame's gate rejected, are left out).
        m: (N, 2) normalized image coordinates (x/z, y/z), undistorted through the
            camera model.
        sigma: standard deviation of each coordinate of ``m`` (pixel sigma over the
            mean focal length, normalized units).
        normal: (3,) the plane normal n* in W the front end uses (known or estimated).
        distance: d*, metres.
    """

    ids: np.ndarray
    m: np.ndarray
    sigma: float
    normal: np.ndarray
    distance: float


@dataclass(frozen=True)
class TiltMeasurement:
    """A keyframe's tilt against the plane, fitted to the frames measured against it.

    Over the frames k measured against keyframe r, H_d = R + T n_r^T / d_r fixes the
    plane normal n_r in r's camera frame once the camera has translated
    (:mod:`hvo_graph.frontend.keyframe_tilt`): a measurement of r's attitude against
    the plane, n_r = R_wr^T n*, that the pose measurements (6 of H_d's 8 degrees of
    freedom) do not carry.

    Attributes:
        frame: the keyframe's index r.
        normal: (3,) unit n_r in r's camera frame.
        world_normal: (3,) unit n* in W, the plane the front end measures against.
        covariance: (3, 3) covariance of ``normal`` (rank 2: orthogonal to it).
    """

    frame: int
    normal: np.ndarray
    world_normal: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class FrameMeasurement:
    """Everything the front end measured at frame ``index``.

    Attributes:
        index: frame number.
        t: frame time, seconds.
        pose: pose from H_d (against frame 0 or a keyframe), or None.
        velocity: mid-interval twist from H_c (frames index-1 and index), or None.
        num_points: points observed in the frame.
        num_rejected: of those, points the front end rejected as outliers (RANSAC,
            the residual gate, or tracks already excluded as off the plane).
        points: the frame's kept plane points in normalized coordinates (None before
            the plane normal is known, or when not made by the front end).
        keyframe_tilt: the tilt of the keyframe the front end left at this frame,
            fitted to the frames measured against it, or None.

    ``pose`` or ``velocity`` is None when the frame had too few usable points;
    estimators then predict through the frame.
    """

    index: int
    t: float
    pose: PoseMeasurement | None = None
    velocity: VelocityMeasurement | None = None
    num_points: int = 0
    num_rejected: int = 0
    points: PointObservations | None = field(default=None, repr=False)
    keyframe_tilt: TiltMeasurement | None = None


@dataclass
class Trajectory:
    """Poses and body velocities over time (estimate or ground truth).

    Attributes:
        t: (K,) timestamps, seconds, strictly increasing.
        rotations: (K, 3, 3) R_wc.
        positions: (K, 3) p_wc, metres.
        twists: (K, 6) body velocity [w; v], or None when unknown.
        covariances: (K, 12, 12) marginal covariance of [pose tangent; twist], or None.
    """

    t: np.ndarray
    rotations: np.ndarray
    positions: np.ndarray
    twists: np.ndarray | None = None
    covariances: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.t)

    def _twists(self) -> np.ndarray:
        if self.twists is None:
            raise InputError("trajectory: has no velocities (twists is None)")
        return self.twists

    @property
    def angular_velocity(self) -> np.ndarray:
        """(K, 3) body angular velocity w."""
        return self._twists()[:, :3]

    @property
    def linear_velocity(self) -> np.ndarray:
        """(K, 3) body linear velocity v."""
        return self._twists()[:, 3:]

    def to_evo(self, name: str = "") -> object:
        """This trajectory as evo's ``PoseTrajectory3D`` (poses T_wc, for evo's plots,
        ``evo_res`` and metrics). Twists and covariances are not carried over.

        Raises:
            InputError: when evo is not installed (``pip install evo``).
        """
        trajectory: Any = _evo_trajectory_module()
        poses = np.tile(np.eye(4), (len(self.t), 1, 1))
        poses[:, :3, :3] = np.asarray(self.rotations, dtype=float)
        poses[:, :3, 3] = np.asarray(self.positions, dtype=float)
        out = trajectory.PoseTrajectory3D(
            timestamps=np.array(self.t, dtype=float), poses_se3=list(poses)
        )
        if name:
            out.meta["name"] = name
        return out

    @staticmethod
    def from_evo(evo_trajectory: object) -> Trajectory:
        """A Trajectory (no twists) from evo's ``PoseTrajectory3D``.

        Raises:
            InputError: when it has no timestamps (evo's ``PosePath3D``).
        """
        t = getattr(evo_trajectory, "timestamps", None)
        if t is None:
            raise InputError("from_evo: expected an evo PoseTrajectory3D (with timestamps)")
        poses = np.asarray(evo_trajectory.poses_se3, dtype=float).reshape(-1, 4, 4)  # type: ignore[attr-defined]
        return Trajectory(
            t=np.array(t, dtype=float),
            rotations=poses[:, :3, :3].copy(),
            positions=poses[:, :3, 3].copy(),
        )


def _evo_trajectory_module() -> object:
    try:
        from evo.core import trajectory
    except ImportError:
        raise InputError(
            "evo is not installed: pip install evo (needed only to hand trajectories to evo)"
        ) from None
    return trajectory


@dataclass(frozen=True)
class StateEstimate:
    """An estimator's belief about one frame.

    Attributes:
        index: frame index.
        t: time, seconds.
        rotation: (3, 3) R_wc.
        position: (3,) p_wc.
        twist: (6,) body velocity [w; v].
        covariance: (12, 12) covariance of [pose tangent; twist] or None.
    """

    index: int
    t: float
    rotation: np.ndarray
    position: np.ndarray
    twist: np.ndarray
    covariance: np.ndarray | None = None


def trajectory_from_states(states: list[StateEstimate]) -> Trajectory:
    """Stack per-frame estimates into a :class:`Trajectory`."""
    covs = [s.covariance for s in states]
    return Trajectory(
        t=np.array([s.t for s in states], dtype=float),
        rotations=np.array([s.rotation for s in states], dtype=float).reshape(-1, 3, 3),
        positions=np.array([s.position for s in states], dtype=float).reshape(-1, 3),
        twists=np.array([s.twist for s in states], dtype=float).reshape(-1, 6),
        covariances=np.array(covs, dtype=float)
        if states and all(c is not None for c in covs)
        else None,
    )
