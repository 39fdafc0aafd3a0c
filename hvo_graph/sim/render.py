"""Synthetic images of a textured scene plane, for tests, demos and users.

Geometry (every step is an exact projective map, so a texture point lands on
the pixel a pinhole model predicts for its plane point):

1. **Texture -> plane.** Texel (a, b) (OpenCV convention: the centre of the
   top-left texel is (0, 0), a right, b down) is the plane point, in the
   reference frame F* = W,

       X* = O + s (a - c_a) e_u + s (b - c_b) e_v = A [a, b, 1]^T,
       A  = [s e_u | s e_v | O - s c_a e_u - s c_b e_v]            (3 x 3)

   with s the texel size (metres), (c_a, c_b) = ((W_t - 1)/2, (H_t - 1)/2) the
   texture centre, O = d* n* the plane point closest to the reference optical
   centre, and (e_u, e_v, n*) a right-handed orthonormal frame:
   e_u = normalize(e_x - (n*^T e_x) n*) and e_v = n* x e_u (for a plane
   nearly perpendicular to e_x, |n*_x| > 0.9: e_v = normalize(e_y - (n*^T e_y) n*)
   and e_u = e_v x n*). For a fronto-parallel plane (n* = e_z), texture axes
   and image axes agree. So n*^T X* = d* for every texel. With ``tile=True``
   (the default) the texture repeats over the whole plane.
2. **Plane -> camera k.** With the pose T_wc = (R_wc, p_wc) the paper's
   motion is R = R_wc^T, T = -R_wc^T p_wc and X = R X* + T (NOTES eq. 1).
3. **Camera -> pixel.** m = X / z, then pixel = K m (through OpenCV's lens
   distortion when the camera has one).

Together the texture-to-normalized-image map is the plane-induced homography

    G_k = R A + T e_3^T,   m ~ G_k [a, b, 1]^T,

and without distortion the texture-to-pixel homography is K G_k
(:func:`texture_to_image_homography`). Each output pixel is rendered by the
inverse map: its (undistorted) ray m gives [a, b, w]^T ~ G_k^-1 m with
w = 1 / z, so pixels whose ray meets the plane behind the camera (w <= 0,
above the horizon) stay black. Sampling is bilinear (``cv2.remap``); the
default texture is band-limited so that sampling does not alias at
magnifications near one.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from hvo_graph.errors import InputError, as_integer, as_matrix, as_number, as_rotation, as_vector
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import Plane

#: Side of one block of the procedural texture, in texels.
DEFAULT_BLOCK_TEXELS = 8
#: The procedural texture spans this many times the first image's footprint.
_FOOTPRINT_FACTOR = 4.0
#: Largest side of the procedural texture, texels (64 MB of float32).
_MAX_TEXTURE_TEXELS = 4096


def default_texel_size(camera: CameraModel, plane: Plane) -> float:
    """d* / f: metres per texel so that one texel spans about one pixel at distance d*."""
    return plane.distance / camera.mean_focal


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane unit axes (e_u, e_v) of the texture, with (e_u, e_v, n*) right-handed.

    Args:
        normal: (3,) unit plane normal n*.
    Returns:
        e_u, e_v: (3,) each (see the module docstring for the rule).
    """
    n = np.asarray(normal, dtype=float)
    if abs(n[0]) <= 0.9:
        e_u = np.array([1.0, 0.0, 0.0]) - n[0] * n
        e_u /= np.linalg.norm(e_u)
        return e_u, np.cross(n, e_u)
    e_v = np.array([0.0, 1.0, 0.0]) - n[1] * n
    e_v /= np.linalg.norm(e_v)
    return np.cross(e_v, n), e_v


def texture_to_plane(plane: Plane, texture_shape: tuple[int, int], texel_size: float) -> np.ndarray:
    """The matrix A with X* = A [a, b, 1]^T for texel (a, b) (module docstring, step 1).

    Args:
        plane: n* (required) and d* in the reference frame.
        texture_shape: (H_t, W_t) texture size in texels.
        texel_size: s, metres per texel.
    Returns:
        (3, 3) A.
    """
    normal = _plane_normal(plane)
    e_u, e_v = plane_axes(normal)
    c_a, c_b = (texture_shape[1] - 1) / 2.0, (texture_shape[0] - 1) / 2.0
    origin = plane.distance * normal
    return np.column_stack(
        (texel_size * e_u, texel_size * e_v, origin - texel_size * (c_a * e_u + c_b * e_v))
    )


def texture_to_image_homography(
    camera: CameraModel,
    plane: Plane,
    rotation_wc: np.ndarray,
    position_wc: np.ndarray,
    texture_shape: tuple[int, int],
    texel_size: float,
) -> np.ndarray:
    """Plane-induced homography K (R A + T e_3^T) from texels to (undistorted) pixels.

    Args:
        camera: intrinsics K (distortion is not part of a homography).
        plane: n*, d* in the reference frame.
        rotation_wc: (3, 3) R_wc of the camera.
        position_wc: (3,) p_wc of the camera.
        texture_shape: (H_t, W_t) texels.
        texel_size: metres per texel.
    Returns:
        (3, 3) homography: [u, v, 1]^T ~ H [a, b, 1]^T.
    """
    R_wc = as_matrix(rotation_wc, "rotation_wc", (3, 3))
    p_wc = as_vector(position_wc, "position_wc", 3)
    A = texture_to_plane(plane, texture_shape, texel_size)
    R, T = R_wc.T, -R_wc.T @ p_wc
    return camera.K @ (R @ A + np.outer(T, [0.0, 0.0, 1.0]))


def make_texture(
    size: int, *, block_texels: int = DEFAULT_BLOCK_TEXELS, seed: int = 0
) -> np.ndarray:
    """A seamless (periodic) random texture with many good corners.

    Random gray blocks at two scales (``block_texels`` and half of it), summed
    and blurred with a Gaussian of sigma = block_texels / 8 texels under
    periodic boundary conditions, so tiles join without a seam and the texture
    is band-limited (no aliasing when rendered near unit magnification).

    Args:
        size: side of the square texture in texels (rounded up to a multiple
            of ``block_texels``).
        block_texels: side of the coarse blocks in texels (>= 2).
        seed: random seed.
    Returns:
        (S, S) float32 in [20, 235].
    """
    as_integer(block_texels, "block_texels", 2)
    if size < 1:
        raise InputError(f"size: expected a positive number of texels, got {size}")
    rng = np.random.default_rng(seed)
    cells = max(4, -(-int(size) // block_texels))
    side = cells * block_texels
    coarse = np.kron(rng.uniform(size=(cells, cells)), np.ones((block_texels, block_texels)))
    fine_block = block_texels // 2
    fine_cells = -(-side // fine_block)
    fine = np.kron(rng.uniform(size=(fine_cells, fine_cells)), np.ones((fine_block, fine_block)))
    texture = (0.7 * coarse + 0.3 * fine[:side, :side]).astype(np.float32)
    sigma = block_texels / 8.0
    pad = int(np.ceil(4 * sigma)) + 1
    padded = np.pad(texture, pad, mode="wrap")  # periodic blur: tiles join seamlessly
    blurred = cv2.GaussianBlur(padded, (0, 0), sigma)[pad:-pad, pad:-pad]
    low, high = float(blurred.min()), float(blurred.max())
    return (20.0 + 215.0 * (blurred - low) / max(high - low, 1e-6)).astype(np.float32)


def render_plane_images(
    camera: CameraModel,
    plane: Plane,
    poses_wc: Sequence[object],
    *,
    texture: np.ndarray | None = None,
    texture_size_m: float | None = None,
    tile: bool = True,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> list[np.ndarray]:
    """Render the images a camera at ``poses_wc`` sees of a textured plane.

    Args:
        camera: intrinsics, image size and distortion of the rendered images.
        plane: n* (required) and d* in the reference frame F* = W.
        poses_wc: K camera poses T_wc, each a ``gtsam.Pose3`` or a pair
            (R_wc (3, 3), p_wc (3,)).
        texture: (H_t, W_t) gray or (H_t, W_t, 3) BGR texture, uint8 or float
            gray levels in [0, 255]; None: :func:`make_texture` (seeded).
        texture_size_m: width of the texture on the plane, metres (texels are
            square). None: one texel per pixel at distance d*
            (:func:`default_texel_size`); the procedural texture then spans
            four times the first image's footprint. The procedural texture
            has at most 4096 texels a side (coarser texels beyond that).
        tile: repeat the texture over the whole plane; False: black outside it.
        noise_sigma: std of additive Gaussian image noise, gray levels.
        seed: seeds the procedural texture and the image noise.
    Returns:
        K uint8 images, (height, width) for a gray texture, (height, width, 3)
        for a color one. Pixels whose ray misses the plane are 0.
    Raises:
        InputError: no plane normal, a bad pose, a camera behind or on the plane.
    """
    normal = _plane_normal(plane)
    as_number(noise_sigma, "noise_sigma", at_least=0.0)
    if texture_size_m is not None:
        as_number(texture_size_m, "texture_size_m", above=0.0)
    rng = np.random.default_rng(seed)
    if texture is None:
        side = _FOOTPRINT_FACTOR * max(camera.width, camera.height)
        if texture_size_m is not None:
            side = texture_size_m / default_texel_size(camera, plane)
        side = min(side, _MAX_TEXTURE_TEXELS)  # a huge plane gets coarser texels instead
        tex = make_texture(int(np.ceil(side)), seed=int(rng.integers(2**31)))
    else:
        tex = _as_texture(texture)
    if texture_size_m is None:
        texel = default_texel_size(camera, plane)
    else:
        texel = texture_size_m / tex.shape[1]
    A = texture_to_plane(plane, tex.shape[:2], texel)
    rays = _pixel_rays(camera)  # (3, H*W) undistorted normalized rays m
    images = []
    for k, pose in enumerate(poses_wc):
        R_wc, p_wc = _as_pose(pose, f"poses_wc[{k}]")
        R, T = R_wc.T, -R_wc.T @ p_wc
        if not plane.distance + (R @ normal) @ T > 1e-9:
            raise InputError(
                f"poses_wc[{k}]: the camera centre is on or behind the plane "
                "(expected n*^T p_wc < d*)"
            )
        G = R @ A + np.outer(T, [0.0, 0.0, 1.0])
        abw = np.linalg.solve(G, rays)  # [a, b, 1/z] up to the ray's scale, which is 1
        visible = abw[2] > 1e-12
        w = np.where(visible, abw[2], 1.0)
        a, b = abw[0] / w, abw[1] / w
        if tile:
            # Wrap before float32 conversion: keeps map precision, remap wraps the seam.
            a, b = np.mod(a, tex.shape[1]), np.mod(b, tex.shape[0])
        else:
            visible &= (a > -1) & (a < tex.shape[1]) & (b > -1) & (b < tex.shape[0])
        a, b = np.where(visible, a, -2.0), np.where(visible, b, -2.0)
        shape = (camera.height, camera.width)
        image = cv2.remap(
            tex,
            a.reshape(shape).astype(np.float32),
            b.reshape(shape).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP if tile else cv2.BORDER_CONSTANT,
        )
        mask = visible.reshape(shape)
        image[~mask] = 0.0
        if noise_sigma > 0:
            image = image + rng.normal(0.0, noise_sigma, image.shape)
        images.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
    return images


def _plane_normal(plane: Plane) -> np.ndarray:
    if plane.normal is None:
        raise InputError("plane.normal: rendering needs the plane normal n*")
    return np.asarray(plane.normal, dtype=float)


def _as_texture(texture: np.ndarray) -> np.ndarray:
    tex = np.asarray(texture)
    if not (tex.ndim == 2 or (tex.ndim == 3 and tex.shape[2] == 3)) or min(tex.shape[:2]) < 2:
        raise InputError(
            f"texture: expected a (H, W) gray or (H, W, 3) BGR image, got shape {tex.shape}"
        )
    if not (np.issubdtype(tex.dtype, np.integer) or np.issubdtype(tex.dtype, np.floating)):
        raise InputError(f"texture: expected integer or float gray levels, got {tex.dtype}")
    tex = tex.astype(np.float32)
    if not np.all(np.isfinite(tex)):
        raise InputError("texture: contains NaN or inf")
    return tex


def _as_pose(pose: object, name: str) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(pose, "rotation") and hasattr(pose, "translation"):  # gtsam.Pose3
        R, p = pose.rotation().matrix(), np.asarray(pose.translation(), dtype=float)  # type: ignore[attr-defined]
    else:
        try:
            R, p = pose  # type: ignore[misc]
        except (TypeError, ValueError):
            raise InputError(f"{name}: expected a gtsam.Pose3 or a pair (R_wc, p_wc)") from None
    return as_rotation(R, f"{name} rotation"), as_vector(p, f"{name} position", 3)


def _pixel_rays(camera: CameraModel) -> np.ndarray:
    """(3, H*W) normalized rays m = [x, y, 1] of every pixel centre, undistorted."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    uv = np.column_stack((u.ravel(), v.ravel())).astype(float)
    if camera.is_fisheye:
        xy = camera.pixel_to_normalized(uv)[:, :2]
    elif camera.has_distortion:
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPoints(
            uv.reshape(-1, 1, 2), camera.K, camera.distortion, criteria=criteria
        ).reshape(-1, 2)
    else:
        xy = np.column_stack(
            ((uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy)
        )
    return np.vstack((xy.T, np.ones(len(xy))))
