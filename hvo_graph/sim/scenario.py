"""The paper's simulation (Section IV; paper/NOTES.md section 6), with its gaps filled in.

The paper states: four static coplanar points always in view, 30 frames per
second, linear velocity sinusoidal along all three axes, angular velocity zero
about x and sinusoidal about y and z, one noise-free run and one run with
zero-mean Gaussian pixel noise of variance 0.05 px^2. It gives no intrinsics,
plane, amplitudes or duration; this module's defaults (all fields of
:class:`ScenarioConfig`) are:

- **Camera**: fx = fy = 800 px, cx = 320 px, cy = 240 px, 640 x 480 pixels, no
  distortion.
- **Plane**: d* = 2.0 m, n* = normalize([0, -0.2, 1]) in the first camera frame
  F* (a plane tilted by 11.3 deg about the camera's x axis, so that no code path
  can rely on n* = e3).
- **Points**: the four corners of a square of side 0.5 m on the plane, centred
  where the optical axis of F* meets the plane (0, 0, d*/n*_z) and aligned with
  the in-plane directions a = e1 (n* has no x component) and b = n* x a. In the
  first image they sit near (220, 141), (420, 141), (416, 334), (224, 334) px.
  With ``num_points`` = N > 4, the remaining N - 4 points are drawn uniformly
  in the same square (seeded), so every point lies inside the corners' hull.
- **Motion**: body twist [w; v] in the current camera frame (contract sign,
  d/dt T_wc = T_wc [w; v]^), each component a sine

      xi_i(t) = A_i sin(2 pi h_i f0 (t - t0))

  with base frequency f0 = 0.1 Hz, phase time t0 = 1.0 s, and
  linear amplitudes A_v = (0.12, -0.10, 0.15) m/s at harmonics h_v = (1, 2, 3),
  angular amplitudes A_w = (0, -0.10, 0.20) rad/s at harmonics h_w = (1, 1, 2)
  (zero about x, as in the paper). The camera thus sweeps about 0.35 m, 0.18 m
  and 0.21 m (peak to peak) along x, y, z and turns by up to 17.6 deg.
- **Duration** 10 s (301 frames at 30 fps, t = 0, 1/30, ..., 10 s).

Because every component is odd about t0 (xi(t0 + s) = -xi(t0 - s)) and all
frequencies are integer multiples of f0, the flow of d/dt T = T xi^ satisfies
T(t0 + 1/f0) = T(t0) exactly (time reversal retraces the path), so the motion
is periodic with period 1/f0 = 10 s and never drifts: any duration stays in
view. With the defaults every point stays at least 93 px inside the image
border over the whole period.

Poses are integrated on SE(3) by the fourth-order Magnus method (two-point
Gauss-Legendre; Iserles, Munthe-Kaas, Norsett, Zanna, Acta Numerica 2000,
eq. 4.6 adapted to right multiplication)::

    T_{n+1} = T_n Exp( h/2 (xi_1 + xi_2) + sqrt(3)/12 h^2 [xi_1, xi_2] )

with xi_j = xi(t_n + c_j h), c_{1,2} = 1/2 -+ sqrt(3)/6, [.,.] the se(3) Lie
bracket, and ``substeps`` = 8 steps per frame (global error below 1e-12 over 10 s).

Pixels are the projection of X_c = R_wc^T (X_w - p_wc) through the camera
(OpenCV, with distortion when set), plus i.i.d. Gaussian noise of standard
deviation sqrt(noise_var) drawn from ``numpy.random.default_rng(seed)``. The
extra points for N > 4 come from an independent stream
(``SeedSequence(seed, spawn_key=(1,))``), so the noise of a given seed does not
depend on how the layout was drawn.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from hvo_graph.errors import InputError, as_integer, as_number
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io._common import staged_output
from hvo_graph.io.config import SceneConfig, save_scene
from hvo_graph.io.tracks import write_tracks
from hvo_graph.io.trajectory import GROUNDTRUTH_FILES, write_groundtruth_dir
from hvo_graph.types import FrameObservations, Plane, Trajectory

#: The paper's noisy run: pixel variance 0.05 px^2 (sigma 0.2236 px).
PAPER_NOISE_VAR = 0.05


def default_camera() -> CameraModel:
    """fx = fy = 800 px, cx = 320, cy = 240, 640 x 480, no distortion."""
    return CameraModel(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)


def default_plane() -> Plane:
    """d* = 2 m, n* = normalize([0, -0.2, 1]) (tilted about the camera's x axis)."""
    return Plane(distance=2.0, normal=np.array([0.0, -0.2, 1.0]))


@dataclass(frozen=True)
class ScenarioConfig:
    """Settings of a simulated sequence; the defaults are the paper's noisy run.

    Attributes:
        duration: seconds; frames at t = k / fps for k = 0 .. floor(duration * fps).
        fps: frames per second.
        noise_var: variance of the pixel noise, px^2 (0.05 in the paper's noisy
            run, 0 for the noise-free run).
        num_points: number of plane points N >= 4.
        seed: seed of the pixel noise (and of the layout of points beyond 4).
        camera: the camera model.
        plane: the plane (n*, d*) in the first camera frame; n* is required.
        half_size: half the side of the square of points on the plane, metres.
        base_frequency: f0, Hz; the motion is periodic with period 1 / f0.
        phase_time: t0, seconds; every twist component is A sin(2 pi h f0 (t - t0)).
        linear_amplitude: A_v, (3,) m/s along the camera's x, y, z.
        linear_harmonics: h_v, (3,) positive integers.
        angular_amplitude: A_w, (3,) rad/s about the camera's x, y, z.
        angular_harmonics: h_w, (3,) positive integers.
        view_margin: every point must stay this many pixels inside the image.
        substeps: Magnus integration steps per frame interval.
    """

    duration: float = 10.0
    fps: float = 30.0
    noise_var: float = PAPER_NOISE_VAR
    num_points: int = 4
    seed: int = 0
    camera: CameraModel = field(default_factory=default_camera)
    plane: Plane = field(default_factory=default_plane)
    half_size: float = 0.25
    base_frequency: float = 0.1
    phase_time: float = 1.0
    linear_amplitude: tuple[float, float, float] = (0.12, -0.10, 0.15)
    linear_harmonics: tuple[int, int, int] = (1, 2, 3)
    angular_amplitude: tuple[float, float, float] = (0.0, -0.10, 0.20)
    angular_harmonics: tuple[int, int, int] = (1, 1, 2)
    view_margin: float = 10.0
    substeps: int = 8

    def __post_init__(self) -> None:
        for name in ("duration", "fps", "half_size", "base_frequency"):
            as_number(getattr(self, name), f"ScenarioConfig.{name}", above=0.0)
        for name in ("noise_var", "view_margin"):
            as_number(getattr(self, name), f"ScenarioConfig.{name}", at_least=0.0)
        as_number(self.phase_time, "ScenarioConfig.phase_time")
        for name, minimum in (("num_points", 4), ("seed", 0), ("substeps", 1)):
            as_integer(getattr(self, name), f"ScenarioConfig.{name}", minimum)
        if self.duration * self.fps < 1.0 - 1e-9:
            raise InputError(
                f"ScenarioConfig.duration: expected at least one frame interval "
                f"(1/fps = {1.0 / self.fps:.4g} s), got {self.duration!r}"
            )
        for name in ("linear_amplitude", "angular_amplitude"):
            a = np.asarray(getattr(self, name), dtype=object)
            if a.shape != (3,) or not all(
                isinstance(x, int | float | np.integer | np.floating)
                and not isinstance(x, bool)
                and math.isfinite(x)
                for x in a
            ):
                raise InputError(f"ScenarioConfig.{name}: expected 3 finite numbers, got {a!r}")
        for name in ("linear_harmonics", "angular_harmonics"):
            h = getattr(self, name)
            if len(h) != 3 or not all(
                isinstance(x, int | np.integer) and not isinstance(x, bool) and x >= 1 for x in h
            ):
                raise InputError(
                    f"ScenarioConfig.{name}: expected 3 integers >= 1 (multiples of "
                    f"base_frequency keep the motion periodic), got {h!r}"
                )
        if not isinstance(self.camera, CameraModel):
            raise InputError(
                f"ScenarioConfig.camera: expected a CameraModel, got {type(self.camera).__name__}"
            )
        if not isinstance(self.plane, Plane) or self.plane.normal is None:
            raise InputError("ScenarioConfig.plane: expected a Plane with a normal n*")
        if self.plane.normal[2] <= 0.1:
            raise InputError(
                "ScenarioConfig.plane: the normal n* must point away from the camera "
                f"(n*_z > 0.1) so that the optical axis meets the plane, got {self.plane.normal}"
            )

    @property
    def num_frames(self) -> int:
        """floor(duration * fps) + 1 frames, the first at t = 0."""
        return math.floor(self.duration * self.fps + 1e-9) + 1

    @property
    def pixel_sigma(self) -> float:
        """Standard deviation of the pixel noise, sqrt(noise_var)."""
        return math.sqrt(self.noise_var)


@dataclass
class Scenario:
    """A simulated sequence with its ground truth.

    Attributes:
        config: the settings it was made from.
        camera: the camera model.
        plane: the plane (n*, d*) in the world frame W = F*.
        points_world: (N, 3) plane points X* in W (n*^T X* = d*).
        groundtruth: poses T_wc and body twists [w; v] at the frame times.
        observations: noisy tracks, one FrameObservations per frame, ids 0..N-1.
        clean_observations: the same without noise.
        pixel_sigma: standard deviation of the pixel noise, pixels.
    """

    config: ScenarioConfig
    camera: CameraModel
    plane: Plane
    points_world: np.ndarray
    groundtruth: Trajectory
    observations: list[FrameObservations]
    clean_observations: list[FrameObservations]
    pixel_sigma: float


def paper_scenario(noisy: bool = True, **overrides: object) -> ScenarioConfig:
    """The paper's scenario: noisy (variance 0.05 px^2) or noise-free, with overrides.

    Args:
        noisy: True for the paper's second run, False for the first (noise-free) run.
        overrides: any :class:`ScenarioConfig` field (e.g. ``seed=3, duration=20``).
    Raises:
        InputError: for an unknown field or a bad value.
    """
    names = {f.name for f in dataclasses.fields(ScenarioConfig)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise InputError(f"paper_scenario: unknown setting '{unknown[0]}'")
    settings: dict[str, object] = {"noise_var": PAPER_NOISE_VAR if noisy else 0.0}
    settings.update(overrides)
    return ScenarioConfig(**settings)  # type: ignore[arg-type]


def body_twist(config: ScenarioConfig, t: np.ndarray | float) -> np.ndarray:
    """The ground-truth body twist xi(t) = [w; v], each component A sin(2 pi h f0 (t - t0)).

    Args:
        config: amplitudes A, harmonics h, base frequency f0, phase time t0.
        t: time(s), seconds, any shape S.
    Returns:
        (*S, 6) twists [w (rad/s); v (m/s)] in the current camera frame.
    """
    t = np.asarray(t, dtype=float)[..., None]
    amplitude = np.concatenate((config.angular_amplitude, config.linear_amplitude))
    harmonic = np.concatenate((config.angular_harmonics, config.linear_harmonics))
    omega = 2.0 * np.pi * config.base_frequency * harmonic
    return amplitude * np.sin(omega * (t - config.phase_time))


def _bracket(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """se(3) bracket of twists [w; v]: (a^ b^ - b^ a^)^v = [w_a x w_b; w_a x v_b + v_a x w_b]."""
    wa, va, wb, vb = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
    return np.concatenate((np.cross(wa, wb), np.cross(wa, vb) + np.cross(va, wb)), axis=-1)


def integrate_poses(config: ScenarioConfig, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integrate d/dt T_wc = T_wc xi(t)^ from T_wc(0) = I to the times ``t``.

    Fourth-order Magnus steps (see the module docstring), ``config.substeps``
    per interval between consecutive times.

    Args:
        config: the motion.
        t: (K,) increasing times with t[0] = 0.
    Returns:
        rotations (K, 3, 3) R_wc and positions (K, 3) p_wc.
    """
    n = config.substeps
    c = np.array([0.5 - math.sqrt(3.0) / 6.0, 0.5 + math.sqrt(3.0) / 6.0])
    # Step starts and lengths, shape (K-1, n); all Magnus exponents computed at once.
    h = np.diff(t)[:, None] / n
    starts = t[:-1, None] + h * np.arange(n)
    xi1 = body_twist(config, starts + c[0] * h)
    xi2 = body_twist(config, starts + c[1] * h)
    hh = h[..., None]
    omega = hh / 2.0 * (xi1 + xi2) + math.sqrt(3.0) / 12.0 * hh**2 * _bracket(xi1, xi2)
    rotations = np.empty((len(t), 3, 3))
    positions = np.empty((len(t), 3))
    pose = gtsam.Pose3()
    rotations[0], positions[0] = np.eye(3), np.zeros(3)
    for k, frame_steps in enumerate(omega, start=1):
        for step in frame_steps:
            pose = pose.compose(gtsam.Pose3.Expmap(step))
        rotations[k] = pose.rotation().matrix()
        positions[k] = pose.translation()
    return rotations, positions


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal (3,) directions in the plane of unit ``normal``: x projected onto
    the plane, and normal x that."""
    n = np.asarray(normal, dtype=float)
    a = np.array([1.0, 0.0, 0.0]) - n[0] * n
    a /= np.linalg.norm(a)
    return a, np.cross(n, a)


def plane_points(config: ScenarioConfig) -> np.ndarray:
    """(N, 3) points X* on the plane n*^T X* = d* (corners of the square first)."""
    n, d, s = config.plane.normal, config.plane.distance, config.half_size
    centre = np.array([0.0, 0.0, d / n[2]])
    a, b = plane_axes(n)
    coords = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * s
    extra = config.num_points - 4
    if extra > 0:
        rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(1,)))
        coords = np.vstack((coords, rng.uniform(-s, s, size=(extra, 2))))
    return centre + coords[:, :1] * a + coords[:, 1:] * b


def simulate(config: ScenarioConfig | None = None) -> Scenario:
    """Simulate a sequence: ground-truth poses and twists, clean and noisy tracks.

    Args:
        config: settings (default: the paper's noisy scenario, ``ScenarioConfig()``).
    Returns:
        The :class:`Scenario`.
    Raises:
        InputError: naming the config when a point leaves the image (with
            ``view_margin``) or passes behind the camera at some frame.
    """
    config = ScenarioConfig() if config is None else config
    if not isinstance(config, ScenarioConfig):
        raise InputError(f"config: expected a ScenarioConfig, got {type(config).__name__}")
    camera = config.camera
    k = config.num_frames
    t = np.arange(k) / config.fps
    rotations, positions = integrate_poses(config, t)
    X = plane_points(config)
    # X_c = R_wc^T (X_w - p_wc) for every frame at once: (K, N, 3).
    Xc = np.einsum("kji,knj->kni", rotations, X[None, :, :] - positions[:, None, :])

    def fail(frame: int, point: int, what: str) -> InputError:
        return InputError(
            f"ScenarioConfig: point {point} {what} at frame {frame} (t = {t[frame]:.3f} s); "
            "reduce the motion amplitudes, half_size or view_margin"
        )

    behind = Xc[..., 2] <= 1e-3
    if behind.any():
        frame, point = np.argwhere(behind)[0]
        raise fail(int(frame), int(point), "is behind the camera")
    clean = camera.project(Xc.reshape(-1, 3)).reshape(k, -1, 2)
    inside = camera.in_view(clean.reshape(-1, 2), margin=config.view_margin).reshape(k, -1)
    if not inside.all():
        frame, point = np.argwhere(~inside)[0]
        raise fail(
            int(frame), int(point), f"leaves the image (view_margin {config.view_margin} px)"
        )

    sigma = config.pixel_sigma
    noise = np.random.default_rng(config.seed).standard_normal(clean.shape)
    noisy = clean + sigma * noise
    ids = np.arange(config.num_points)
    groundtruth = Trajectory(
        t=t, rotations=rotations, positions=positions, twists=body_twist(config, t)
    )
    return Scenario(
        config=config,
        camera=camera,
        plane=config.plane,
        points_world=X,
        groundtruth=groundtruth,
        observations=[
            FrameObservations(index=i, t=float(t[i]), ids=ids.copy(), uv=noisy[i]) for i in range(k)
        ],
        clean_observations=[
            FrameObservations(index=i, t=float(t[i]), ids=ids.copy(), uv=clean[i]) for i in range(k)
        ],
        pixel_sigma=sigma,
    )


def write_scenario(directory: str | Path, scenario: Scenario) -> None:
    """Write a ``simulate`` folder: camera.yaml (with noise.pixel_sigma), tracks.csv
    (noisy), groundtruth.txt (TUM, T_wc) and groundtruth_velocity.csv. Creates the folder."""
    files = ("camera.yaml", "tracks.csv", *GROUNDTRUTH_FILES)
    # All files or none (a failure or Ctrl-C leaves the folder as it was); camera.yaml
    # last, so a folder with a camera file is a complete sequence.
    with staged_output(directory, owned=files, last=("camera.yaml",)) as stage:
        save_scene(
            stage / "camera.yaml",
            SceneConfig(
                camera=scenario.camera, plane=scenario.plane, pixel_sigma=scenario.pixel_sigma
            ),
        )
        write_tracks(stage / "tracks.csv", scenario.observations)
        write_groundtruth_dir(stage, scenario.groundtruth)
