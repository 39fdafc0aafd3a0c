"""Randomised scenario families: the paper's scenario is one case among many.

Each family draws a :class:`~hvo_graph.sim.scenario.ScenarioConfig` from a
seeded random generator: the plane's tilt and distance, the number of points,
the frame rate, the pixel noise and a periodic motion (base frequency f0,
harmonics 1-3, random amplitudes and phase). Together they span

- plane tilt 0-60 deg (wide lens at 35-60 deg), d* 1-3 m;
- 4-50 points, pixel noise 0.01-2 px^2;
- 10-120 frames per second;
- motion from near-hover to ~2 Hz, 1 m/s and 1 rad/s;
- off-plane tracks (outliers) and dropped frames;
- a traverse: the camera slides over a field of points that leave the view and
  new ones that enter it, so the front end takes keyframes.

A draw whose square of points does not fit the first image (a close plane)
shrinks the square by 0.8 until it does, then one whose points would leave the
image shrinks its motion amplitudes by 0.8 until they stay in view, so every
seed gives a valid sequence. The
generator is seeded by (seed, family name): family draws are reproducible and
independent of each other.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_integer
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.sim.scenario import (
    Scenario,
    ScenarioConfig,
    body_twist,
    integrate_poses,
    plane_axes,
    simulate,
)
from hvo_graph.types import FrameObservations, Plane, Trajectory

#: First id given to an off-plane (outlier) track.
OUTLIER_ID_START = 100_000

#: Times the motion amplitudes are shrunk (x0.8) before a draw is given up.
MAX_SHRINKS = 30


@dataclass(frozen=True)
class FamilyDraw:
    """One randomised sequence of a family.

    Attributes:
        family: the family's name (a key of :data:`FAMILIES`).
        seed: the seed it was drawn with.
        scenario: the simulated sequence (observations include the outliers and
            miss the dropped frames; the ground truth has every frame).
        outliers: number of off-plane tracks (ids from :data:`OUTLIER_ID_START`).
        dropped: indices of the frames removed from the observations.
    """

    family: str
    seed: int
    scenario: Scenario
    outliers: int = 0
    dropped: tuple[int, ...] = ()


#: Points a traverse's camera sees at once, on average over the draws (drawn in 40-90).
TRAVERSE_VISIBLE = (40, 90)


@dataclass(frozen=True)
class _Recipe:
    config: ScenarioConfig
    outliers: int = 0
    drop_fraction: float = 0.0
    traverse: bool = False


def _plane(rng: np.random.Generator, tilt_deg: tuple[float, float]) -> Plane:
    """A plane tilted by a random angle in ``tilt_deg`` about a random azimuth, d* in 1-3 m."""
    tilt = np.deg2rad(rng.uniform(*tilt_deg))
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    normal = np.array(
        [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
    )
    return Plane(distance=float(rng.uniform(1.0, 3.0)), normal=normal)


def _motion(
    rng: np.random.Generator,
    frequency: tuple[float, float],
    linear: float,
    angular: float,
    harmonics: tuple[int, ...] = (1, 2, 3),
) -> dict[str, object]:
    """ScenarioConfig motion fields: f0 in ``frequency`` Hz, amplitudes up to linear m/s and
    angular rad/s per axis, each axis on a random harmonic."""
    f0 = float(rng.uniform(*frequency))
    return {
        "base_frequency": f0,
        "linear_harmonics": tuple(int(h) for h in rng.choice(harmonics, 3)),
        "angular_harmonics": tuple(int(h) for h in rng.choice(harmonics, 3)),
        "linear_amplitude": tuple(float(a) for a in rng.uniform(-1, 1, 3) * linear),
        "angular_amplitude": tuple(float(a) for a in rng.uniform(-1, 1, 3) * angular),
        "phase_time": float(rng.uniform(0.0, 1.0 / f0)),
    }


def _wide_camera() -> CameraModel:
    return CameraModel(fx=350.0, fy=350.0, cx=320.0, cy=240.0, width=640, height=480)


def _paper_like(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=0.05,
            num_points=int(rng.integers(4, 9)),
            plane=_plane(rng, (0, 30)),
            **_motion(rng, (0.08, 0.15), 0.15, 0.2),
        )
    )


def _agile(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            fps=60.0,
            noise_var=0.1,
            num_points=8,
            half_size=0.3,
            plane=_plane(rng, (0, 20)),
            **_motion(rng, (0.5, 1.0), 1.0, 1.0, harmonics=(1, 2)),
        )
    )


def _hover(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=0.2,
            num_points=5,
            plane=_plane(rng, (0, 20)),
            **_motion(rng, (0.05, 0.3), 0.005, 0.005),
        )
    )


def _low_rate(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            fps=10.0,
            noise_var=0.1,
            num_points=6,
            plane=_plane(rng, (0, 30)),
            **_motion(rng, (0.1, 0.3), 0.3, 0.3),
        )
    )


def _high_rate(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            fps=120.0,
            duration=6.0,
            noise_var=0.05,
            num_points=4,
            plane=_plane(rng, (0, 30)),
            **_motion(rng, (0.1, 0.5), 0.3, 0.3),
        )
    )


def _many_points(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=0.5,
            num_points=int(rng.integers(30, 51)),
            plane=_plane(rng, (0, 30)),
            **_motion(rng, (0.1, 0.3), 0.3, 0.3),
        )
    )


def _noisy_few(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=float(rng.uniform(1.0, 2.0)),
            num_points=int(rng.integers(4, 7)),
            plane=_plane(rng, (0, 30)),
            **_motion(rng, (0.1, 0.3), 0.2, 0.2),
        )
    )


def _tilted_wide(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=0.1,
            num_points=10,
            camera=_wide_camera(),
            half_size=0.5,
            plane=_plane(rng, (35, 60)),
            **_motion(rng, (0.1, 0.3), 0.2, 0.2),
        )
    )


def _precise(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=0.01,
            num_points=20,
            plane=_plane(rng, (0, 40)),
            **_motion(rng, (0.1, 0.5), 0.5, 0.5),
        )
    )


def _outliers_dropouts(rng: np.random.Generator) -> _Recipe:
    return _Recipe(
        ScenarioConfig(
            noise_var=0.05,
            num_points=12,
            plane=_plane(rng, (0, 30)),
            **_motion(rng, (0.1, 0.3), 0.2, 0.2),
        ),
        outliers=2,
        drop_fraction=0.1,
    )


def _traverse(rng: np.random.Generator) -> _Recipe:
    # Sideways and forward up to ~1 m/s at 0.05-0.1 Hz (metres of travel), little
    # towards the plane and little rotation: the view moves, the plane stays ahead.
    motion = _motion(rng, (0.05, 0.1), 1.0, 0.05, harmonics=(1,))
    vx, vy, vz = motion["linear_amplitude"]  # type: ignore[misc]
    motion["linear_amplitude"] = (
        float(np.sign(vx) * rng.uniform(0.5, 1.0)),
        0.5 * float(vy),
        0.05 * float(vz),
    )
    return _Recipe(
        ScenarioConfig(
            noise_var=float(rng.uniform(0.05, 0.5)),
            plane=_plane(rng, (0, 20)),
            **motion,  # type: ignore[arg-type]
        ),
        traverse=True,
    )


#: Every family: name -> (one-line description, recipe drawn from a seeded generator).
FAMILIES: dict[str, tuple[str, Callable[[np.random.Generator], _Recipe]]] = {
    "paper-like": ("30 fps, 4-8 points, 0.05 px^2, 0.1 Hz motion, tilt 0-30 deg", _paper_like),
    "agile": ("60 fps, 8 points, 0.1 px^2, 0.5-2 Hz up to 1 m/s and 1 rad/s", _agile),
    "hover": ("30 fps, 5 points, 0.2 px^2, near-static (mm/s)", _hover),
    "10fps": ("10 fps, 6 points, 0.1 px^2, 0.1-0.9 Hz", _low_rate),
    "120fps": ("120 fps, 4 points, 0.05 px^2, 0.1-1.5 Hz", _high_rate),
    "many-points": ("30 fps, 30-50 points, 0.5 px^2", _many_points),
    "noisy-few": ("30 fps, 4-6 points, 1-2 px^2", _noisy_few),
    "tilted-wide": ("plane tilted 35-60 deg, 350 px focal length, 10 points", _tilted_wide),
    "precise": ("30 fps, 20 points, 0.01 px^2, up to 0.5 m/s", _precise),
    "outliers-dropouts": (
        "12 points + 2 off-plane tracks, 10 % of frames dropped",
        _outliers_dropouts,
    ),
    "traverse": (
        "30 fps, 0.05-0.5 px^2, up to 1 m/s over a field of points: they leave the view",
        _traverse,
    ),
}


def draw(family: str, seed: int, *, duration: float | None = None) -> FamilyDraw:
    """Draw sequence ``seed`` of ``family``.

    Args:
        family: a key of :data:`FAMILIES`.
        seed: integer >= 0; seeds the configuration, the pixel noise and the corruption.
        duration: overrides the family's duration (seconds), e.g. for short tests.
    Raises:
        InputError: unknown family or bad seed/duration.
    """
    if family not in FAMILIES:
        raise InputError(f"family: expected one of {', '.join(FAMILIES)}, got {family!r}")
    seed = as_integer(seed, "seed", 0)
    rng = np.random.default_rng([seed, sum(map(ord, family))])
    recipe = FAMILIES[family][1](rng)
    config = dataclasses.replace(recipe.config, seed=seed)
    if duration is not None:
        config = dataclasses.replace(config, duration=duration)
    if recipe.traverse:
        scenario = _traverse_scenario(config, rng, family, seed)
    else:
        scenario = _simulate_in_view(config, family, seed)
    outliers, dropped = 0, ()
    if recipe.outliers:
        scenario = _with_off_plane_tracks(scenario, recipe.outliers, rng)
        outliers = recipe.outliers
    if recipe.drop_fraction:
        scenario, dropped = _with_dropped_frames(scenario, recipe.drop_fraction, rng)
    return FamilyDraw(family, seed, scenario, outliers, dropped)


def _simulate_in_view(config: ScenarioConfig, family: str, seed: int) -> Scenario:
    """Simulate, shrinking the square of points until it fits the first image, then the
    motion until every point stays in view."""
    for _ in range(MAX_SHRINKS):
        first = dataclasses.replace(config, duration=1.0 / config.fps, substeps=1)
        try:
            simulate(first)
            break
        except InputError:  # the plane is close: the same layout, smaller
            config = dataclasses.replace(config, half_size=0.8 * config.half_size)
    for _ in range(MAX_SHRINKS):
        try:
            return simulate(config)
        except InputError:  # a point left the image: the same motion, smaller
            config = dataclasses.replace(
                config,
                linear_amplitude=tuple(0.8 * a for a in config.linear_amplitude),
                angular_amplitude=tuple(0.8 * a for a in config.angular_amplitude),
            )
    raise InputError(f"family {family!r}, seed {seed}: no draw keeps the points in view")


def _traverse_scenario(
    config: ScenarioConfig, rng: np.random.Generator, family: str, seed: int
) -> Scenario:
    """The config's motion over a field of plane points covering every frame's view,
    drawn so that a frame sees ~TRAVERSE_VISIBLE of them; each frame observes those in
    its image (``view_margin``), so points leave and enter. Motions that bring the camera
    within 0.4 d* of the plane shrink by 0.8."""
    camera, plane = config.camera, config.plane
    n, d = np.asarray(plane.normal, dtype=float), plane.distance
    t = np.arange(config.num_frames) / config.fps
    for _ in range(MAX_SHRINKS):
        rotations, positions = integrate_poses(config, t)
        if np.min(d - positions @ n) > 0.4 * d:
            break
        config = dataclasses.replace(
            config, linear_amplitude=tuple(0.8 * a for a in config.linear_amplitude)
        )
    else:
        raise InputError(f"family {family!r}, seed {seed}: no draw keeps the plane ahead")
    w, h = camera.width, camera.height
    corners = camera.pixel_to_normalized(np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]))
    rays = np.einsum("kij,cj->kci", rotations, corners)  # (K, 4, 3) in W
    depth = (d - positions @ n)[:, None] / (rays @ n)
    if not np.all(depth > 0):
        raise InputError(f"family {family!r}, seed {seed}: the view leaves the plane")
    hits = positions[:, None, :] + depth[..., None] * rays
    a, b = plane_axes(n)
    uv = np.stack((hits @ a, hits @ b), axis=-1)  # (K, 4, 2) plane coordinates
    x, y = uv[0, :, 0], uv[0, :, 1]
    footprint = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    lo, hi = uv.reshape(-1, 2).min(axis=0), uv.reshape(-1, 2).max(axis=0)
    count = int(np.prod(hi - lo) * rng.uniform(*TRAVERSE_VISIBLE) / footprint)
    coords = rng.uniform(lo, hi, size=(min(max(count, 50), 20_000), 2))
    points = d * n + coords[:, :1] * a + coords[:, 1:] * b
    noise = np.random.default_rng(config.seed)
    observations, clean_observations = [], []
    for k, (R, p) in enumerate(zip(rotations, positions, strict=True)):
        X = (points - p) @ R
        front = np.flatnonzero(X[:, 2] > 1e-3)
        clean = camera.project(X[front])
        inside = camera.in_view(clean, margin=config.view_margin)
        seen, clean = front[inside], clean[inside]
        noisy = clean + config.pixel_sigma * noise.standard_normal(clean.shape)
        observations.append(FrameObservations(k, float(t[k]), seen, noisy))
        clean_observations.append(FrameObservations(k, float(t[k]), seen.copy(), clean))
    truth = Trajectory(t=t, rotations=rotations, positions=positions, twists=body_twist(config, t))
    return Scenario(
        config, camera, plane, points, truth, observations, clean_observations, config.pixel_sigma
    )


def _with_off_plane_tracks(scenario: Scenario, count: int, rng: np.random.Generator) -> Scenario:
    """Add ``count`` tracks of points 0.2-0.5 m in front of the plane (towards the camera):
    they look like plane points until the camera moves (parallax)."""
    n = scenario.plane.normal
    base = scenario.points_world[rng.choice(len(scenario.points_world), count, replace=False)]
    points = base - n * rng.uniform(0.2, 0.5, (count, 1))
    truth, camera = scenario.groundtruth, scenario.camera
    observations = []
    for obs, R, p in zip(scenario.observations, truth.rotations, truth.positions, strict=True):
        X = (points - p) @ R
        uv = camera.project(X) + scenario.pixel_sigma * rng.standard_normal((count, 2))
        seen = camera.in_view(uv) & (X[:, 2] > 0)
        ids = np.concatenate((obs.ids, OUTLIER_ID_START + np.flatnonzero(seen)))
        observations.append(FrameObservations(obs.index, obs.t, ids, np.vstack((obs.uv, uv[seen]))))
    return dataclasses.replace(scenario, observations=observations)


def _with_dropped_frames(
    scenario: Scenario, fraction: float, rng: np.random.Generator
) -> tuple[Scenario, tuple[int, ...]]:
    """Remove a random ``fraction`` of the frames (never the first)."""
    keep = rng.uniform(size=len(scenario.observations)) >= fraction
    keep[0] = True
    dropped = tuple(o.index for o, k in zip(scenario.observations, keep, strict=True) if not k)
    observations = [o for o, k in zip(scenario.observations, keep, strict=True) if k]
    return dataclasses.replace(scenario, observations=observations), dropped


def describe(family: str) -> str:
    """The one-line description of ``family``."""
    if family not in FAMILIES:
        raise InputError(f"family: expected one of {', '.join(FAMILIES)}, got {family!r}")
    return FAMILIES[family][0]


__all__ = ["FAMILIES", "OUTLIER_ID_START", "FamilyDraw", "describe", "draw"]
