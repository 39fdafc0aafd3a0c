"""Rendered image sequences of a simulated motion: ground truth, view check, seeded rendering.

The library side of ``experiments/images.py``: a motion
(:class:`~hvo_graph.sim.scenario.ScenarioConfig`) gives the true poses at the
frame times; :func:`check_view` makes sure every frame sees the textured plane
over the whole image; :func:`render_stream` renders the frames a chunk at a
time (bounded memory), each chunk with its own noise seed, so that any frame
can be rendered again on its own (:func:`render_chunk`) with the same pixels.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.sim.render import make_texture, render_plane_images
from hvo_graph.sim.scenario import ScenarioConfig, body_twist, integrate_poses
from hvo_graph.types import Plane, Trajectory

#: Frames rendered per call (one texture, a fresh noise stream per chunk).
CHUNK_FRAMES = 30

#: The procedural texture is this many first-image widths a side, then tiles (texels of
#: about one pixel at d*: hvo_graph.sim.render.default_texel_size).
TEXTURE_FOOTPRINTS = 4


def ground_truth(motion: ScenarioConfig) -> Trajectory:
    """Poses T_wc (Magnus-integrated) and body twists [w; v] at the frame times of ``motion``."""
    t = np.arange(motion.num_frames) / motion.fps
    rotations, positions = integrate_poses(motion, t)
    return Trajectory(t, rotations, positions, body_twist(motion, t))


def check_view(camera: CameraModel, plane: Plane, truth: Trajectory) -> tuple[float, float]:
    """Check that every frame sees the plane over the whole image; return the distance range.

    In camera k the plane is n_k^T X = d_k with n_k = R_wc^T n*, d_k = d* - n*^T p_wc.
    The camera is in front when d_k > 0, and the ray of a normalized point m meets the
    plane in front of the camera when n_k^T m > 0: linear in m, so the four image corners
    decide for the whole (convex) image. The texture tiles the plane, so a frame that
    meets the plane everywhere is textured everywhere.

    Returns:
        (min, max) of d_k over the frames, metres.
    Raises:
        InputError: naming the first frame that fails.
    """
    n = np.asarray(plane.normal, dtype=float)
    w, h = camera.width - 1.0, camera.height - 1.0
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    m = camera.pixel_to_normalized(corners)
    distances = plane.distance - np.asarray(truth.positions) @ n
    for k, (R_wc, d_k) in enumerate(zip(truth.rotations, distances, strict=True)):
        if not d_k > 0:
            raise InputError(
                f"frame {k} (t = {truth.t[k]:.3f} s): the camera is not in front of the plane"
            )
        if np.any(m @ (R_wc.T @ n) <= 0):
            raise InputError(
                f"frame {k} (t = {truth.t[k]:.3f} s): an image corner looks past the plane's "
                "horizon (part of the image would be untextured)"
            )
    return float(distances.min()), float(distances.max())


def chunk_seed(seed: int, chunk: int) -> int:
    """Independent noise seed of each rendered chunk of frames."""
    return int(np.random.SeedSequence([seed, chunk]).generate_state(1)[0])


def plane_texture(camera: CameraModel, seed: int) -> np.ndarray:
    """The seeded procedural texture, :data:`TEXTURE_FOOTPRINTS` image widths a side."""
    side = TEXTURE_FOOTPRINTS * max(camera.width, camera.height)
    return make_texture(side, seed=seed)


def render_chunk(
    camera: CameraModel,
    plane: Plane,
    truth: Trajectory,
    texture: np.ndarray,
    chunk: int,
    *,
    noise_sigma: float,
    seed: int,
) -> list[np.ndarray]:
    """The images of frames [chunk * 30, (chunk + 1) * 30), uint8 (height, width)."""
    start = chunk * CHUNK_FRAMES
    stop = min(len(truth), start + CHUNK_FRAMES)
    poses = list(zip(truth.rotations[start:stop], truth.positions[start:stop], strict=True))
    return render_plane_images(
        camera,
        plane,
        poses,
        texture=texture,
        noise_sigma=noise_sigma,
        seed=chunk_seed(seed, chunk),
    )


def render_stream(
    camera: CameraModel,
    plane: Plane,
    truth: Trajectory,
    texture: np.ndarray,
    *,
    noise_sigma: float,
    seed: int,
) -> Iterator[np.ndarray]:
    """Every frame's image, rendered a chunk at a time (bounded memory)."""
    for chunk in range(-(-len(truth) // CHUNK_FRAMES)):
        yield from render_chunk(
            camera, plane, truth, texture, chunk, noise_sigma=noise_sigma, seed=seed
        )


def render_frame(
    camera: CameraModel,
    plane: Plane,
    truth: Trajectory,
    texture: np.ndarray,
    k: int,
    *,
    noise_sigma: float,
    seed: int,
) -> np.ndarray:
    """Frame k's image, the same pixels as in :func:`render_stream`."""
    chunk = render_chunk(
        camera, plane, truth, texture, k // CHUNK_FRAMES, noise_sigma=noise_sigma, seed=seed
    )
    return chunk[k % CHUNK_FRAMES]
