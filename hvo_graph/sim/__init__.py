"""Simulation: the paper's scenario (tracks and ground truth) and rendered images of the plane.

- :mod:`~hvo_graph.sim.scenario`: the paper's Section IV scenario, its gaps filled in:
  ground-truth poses and twists, clean and noisy tracks, ``hvo-graph simulate`` folders;
- :mod:`~hvo_graph.sim.render`: synthetic images of a textured plane.

The public names are re-exported here and imported on first use.
"""

from hvo_graph import _lazy_exports

__all__, __getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "hvo_graph.sim.scenario": (
            "PAPER_NOISE_VAR",
            "ScenarioConfig",
            "Scenario",
            "default_camera",
            "default_plane",
            "paper_scenario",
            "body_twist",
            "integrate_poses",
            "plane_points",
            "simulate",
            "write_scenario",
        ),
        "hvo_graph.sim.render": (
            "make_texture",
            "default_texel_size",
            "plane_axes",
            "texture_to_plane",
            "texture_to_image_homography",
            "render_plane_images",
        ),
    },
)
