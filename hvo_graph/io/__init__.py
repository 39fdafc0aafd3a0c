"""Readers and writers for the contract's files (YAML, tracks CSV, TUM, velocity CSV).

- :mod:`~hvo_graph.io.config`: the camera and scene YAML;
- :mod:`~hvo_graph.io.tracks`: feature tracks, ``frame,t,id,u,v``;
- :mod:`~hvo_graph.io.trajectory`: TUM poses, ``velocity.csv``, ``covariance.csv``
  and the estimate / ground-truth folders;
- :mod:`~hvo_graph.io.images`: image folders (with ``times.txt``) and videos;
- :mod:`~hvo_graph.io.sequences`: any recorded layout (folder, video, TUM RGB-D,
  EuRoC, ROS bag: :mod:`~hvo_graph.io.datasets`, :mod:`~hvo_graph.io.rosbag`);
- :mod:`~hvo_graph.io.calibration`: calibration files of other tools.

The readers and writers are re-exported here and imported on first use.
"""

from hvo_graph import _lazy_exports

__all__, __getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "hvo_graph.io.config": ("SceneConfig", "load_scene", "save_scene"),
        "hvo_graph.io.tracks": ("read_tracks", "write_tracks"),
        "hvo_graph.io.trajectory": (
            "read_tum",
            "write_tum",
            "read_velocity",
            "write_velocity",
            "read_covariance",
            "write_covariance",
            "read_estimate_dir",
            "write_estimate_dir",
            "read_groundtruth_dir",
            "write_groundtruth_dir",
        ),
        "hvo_graph.io.images": (
            "ImageSequence",
            "as_gray_image",
            "read_times",
            "load_image_sequence",
        ),
        "hvo_graph.io.sequences": ("Recording", "open_recording"),
        "hvo_graph.io.calibration": ("Calibration", "load_calibration"),
    },
)
