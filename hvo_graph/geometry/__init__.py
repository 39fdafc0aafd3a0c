"""Pure geometry: camera model, rotations, discrete (H_d) and continuous (H_c) homographies.

Every public name of the five modules is re-exported here and imported on
first use, so ``import hvo_graph.geometry`` does not load OpenCV or GTSAM:

- :mod:`~hvo_graph.geometry.camera`: ``CameraModel`` (pixels <-> normalized m);
- :mod:`~hvo_graph.geometry.rotation`: ``skew``, the paper's Euler angles;
- :mod:`~hvo_graph.geometry.discrete`: H_d = R + T n*^T / d* (pose);
- :mod:`~hvo_graph.geometry.continuous`: H_c = w^ + v n^T / d (velocity);
- :mod:`~hvo_graph.geometry.transfer`: the transfer error of plane points under H_d,
  its Jacobians and normal equations (the pose refinement and its covariance).
"""

from hvo_graph import _lazy_exports

__all__, __getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "hvo_graph.geometry.camera": ("CameraModel",),
        "hvo_graph.geometry.rotation": (
            "GIMBAL_LOCK_COS",
            "skew",
            "nearest_rotation",
            "rot_x",
            "rot_y",
            "rot_z",
            "euler_to_rotation",
            "rotation_to_euler",
            "euler_rates",
            "wrap_angle",
        ),
        "hvo_graph.geometry.discrete": (
            "DEGENERACY_TOL",
            "normalized_points",
            "unit_normal",
            "positive_distance",
            "estimate_homography",
            "homography_from_motion",
            "euclidean_homography",
            "camera_pose_from_motion",
            "motion_from_camera_pose",
        ),
        "hvo_graph.geometry.decomposition": (
            "HomographySolution",
            "decompose_homography",
            "physically_valid_solutions",
            "check_points_in_front",
            "select_solution",
            "motion_from_homography_known_normal",
        ),
        "hvo_graph.geometry.continuous": (
            "ContinuousSolution",
            "plane_in_current_frame",
            "continuous_homography",
            "point_flow",
            "estimate_continuous_homography",
            "decompose_continuous_homography",
            "physically_valid_continuous_solutions",
            "select_continuous_solution",
            "velocity_design_matrix",
            "velocity_known_normal",
            "body_twist_from_scene_motion",
        ),
        "hvo_graph.geometry.transfer": (
            "TransferLinearization",
            "projection_jacobian",
            "linearize_transfer",
            "pose_normal_equations",
            "keyframe_plane_jacobian",
            "retract_motion",
        ),
    },
)
