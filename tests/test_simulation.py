"""The simulated ground truth is self-consistent and matches its documented definition."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.sim.scenario import ScenarioConfig, paper_scenario, simulate
from hvo_graph.types import Plane

# The motion as documented in hvo_graph/sim/scenario.py, written out independently:
# each twist component is A sin(2 pi h f0 (t - t0)), twist order [w; v].
F0, T0 = 0.1, 1.0
A = np.array([0.0, -0.10, 0.20, 0.12, -0.10, 0.15])
H = np.array([1, 1, 2, 1, 2, 3])


def documented_twist(t: float) -> np.ndarray:
    return A * np.sin(2.0 * np.pi * H * F0 * (t - T0))


def hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rk4_poses(times: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Classical RK4 on Rdot = R w^, pdot = R v (no Lie-group machinery)."""

    def f(t: float, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xi = documented_twist(t)
        return R @ hat(xi[:3]), R @ xi[3:]

    R, p, t = np.eye(3), np.zeros(3), 0.0
    Rs, ps = [R], [p]
    for t_next in times[1:]:
        n = int(np.ceil((t_next - t) / step))
        h = (t_next - t) / n
        for _ in range(n):
            k1 = f(t, R, p)
            k2 = f(t + h / 2, R + h / 2 * k1[0], p + h / 2 * k1[1])
            k3 = f(t + h / 2, R + h / 2 * k2[0], p + h / 2 * k2[1])
            k4 = f(t + h, R + h * k3[0], p + h * k3[1])
            R = R + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            p = p + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            t += h
        t = t_next
        Rs.append(R)
        ps.append(p)
    return np.array(Rs), np.array(ps)


def test_defaults_are_the_documented_paper_scenario(paper):
    c = paper.config
    assert (c.fps, c.duration, c.noise_var, c.num_points) == (30.0, 10.0, 0.05, 4)
    K = paper.camera.K
    np.testing.assert_array_equal(K, [[800, 0, 320], [0, 800, 240], [0, 0, 1]])
    assert (paper.camera.width, paper.camera.height) == (640, 480)
    np.testing.assert_allclose(paper.plane.normal, np.array([0, -0.2, 1]) / np.sqrt(1.04))
    assert paper.plane.distance == 2.0
    assert len(paper.observations) == 301
    np.testing.assert_allclose(paper.groundtruth.t, np.arange(301) / 30.0)
    assert paper.pixel_sigma == pytest.approx(np.sqrt(0.05))


def test_groundtruth_twists_are_the_documented_sines(paper):
    expected = np.array([documented_twist(t) for t in paper.groundtruth.t])
    np.testing.assert_allclose(paper.groundtruth.twists, expected, rtol=0, atol=1e-15)
    # The paper's motion: no angular velocity about x, all other components move.
    assert np.all(paper.groundtruth.twists[:, 0] == 0)
    assert np.all(np.ptp(paper.groundtruth.twists[:, 1:], axis=0) > 0.1)


def test_poses_integrate_the_twists(paper):
    """An independent RK4 integration of the documented twist reproduces the poses."""
    gt = paper.groundtruth
    R, p = rk4_poses(gt.t, step=1.0 / 300.0)
    np.testing.assert_allclose(gt.rotations, R, rtol=0, atol=1e-11)
    np.testing.assert_allclose(gt.positions, p, rtol=0, atol=1e-11)
    # Real motion, not a near-identity homography: tens of centimetres and degrees.
    assert np.ptp(gt.positions, axis=0).min() > 0.15
    angles = np.degrees(
        np.arccos(np.clip((np.trace(gt.rotations, axis1=1, axis2=2) - 1) / 2, -1, 1))
    )
    assert angles.max() > 10.0


def test_motion_is_periodic_with_period_one_over_f0():
    scenario = simulate(paper_scenario(duration=20.0, fps=10.0))
    gt = scenario.groundtruth
    for k in (100, 200):  # t = 10 s and 20 s
        np.testing.assert_allclose(gt.rotations[k], np.eye(3), atol=1e-12)
        np.testing.assert_allclose(gt.positions[k], np.zeros(3), atol=1e-12)
    # ... and not trivially so in between.
    assert np.linalg.norm(gt.positions[50]) > 0.05


def test_first_pose_is_the_world_frame_and_points_lie_on_the_plane(paper):
    np.testing.assert_array_equal(paper.groundtruth.rotations[0], np.eye(3))
    np.testing.assert_array_equal(paper.groundtruth.positions[0], np.zeros(3))
    X = paper.points_world
    assert X.shape == (4, 3)
    np.testing.assert_allclose(X @ paper.plane.normal, paper.plane.distance, atol=1e-12)
    # corners of a square: equal sides, equal diagonals
    sides = np.linalg.norm(np.roll(X, -1, axis=0) - X, axis=1)
    np.testing.assert_allclose(sides, 0.5, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(X[2] - X[0]), np.linalg.norm(X[3] - X[1]))


def test_clean_tracks_are_the_pinhole_projection_of_the_plane_points(paper):
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    for obs, R, p in zip(
        paper.clean_observations,
        paper.groundtruth.rotations,
        paper.groundtruth.positions,
        strict=True,
    ):
        Xc = (paper.points_world - p) @ R  # R^T (X - p), row-wise
        uvw = Xc @ K.T
        np.testing.assert_allclose(obs.uv, uvw[:, :2] / uvw[:, 2:], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(obs.ids, [0, 1, 2, 3])
        assert np.all(Xc[:, 2] > 1.0)


def test_tracks_obey_the_discrete_homography_of_the_groundtruth(paper):
    """m ~ H_d m*, H_d = R + T n*^T / d*, with R = R_wc^T, T = -R_wc^T p_wc (NOTES 2)."""
    n, d = paper.plane.normal, paper.plane.distance
    Kinv = np.linalg.inv(paper.camera.K)
    m0 = np.column_stack((paper.clean_observations[0].uv, np.ones(4))) @ Kinv.T
    for k in (50, 150, 250):
        Rwc, pwc = paper.groundtruth.rotations[k], paper.groundtruth.positions[k]
        R, T = Rwc.T, -Rwc.T @ pwc
        Hd = R + np.outer(T, n) / d
        mk = m0 @ Hd.T
        mk = mk[:, :2] / mk[:, 2:]
        observed = np.column_stack((paper.clean_observations[k].uv, np.ones(4))) @ Kinv.T
        np.testing.assert_allclose(mk, observed[:, :2], atol=1e-12)
        assert np.linalg.norm(Hd - np.eye(3)) > 0.02


def test_points_stay_in_view_with_margin(paper):
    uv = np.array([o.uv for o in paper.clean_observations])
    margin = paper.config.view_margin
    assert uv[..., 0].min() >= margin - 0.5 and uv[..., 0].max() <= 640 - 0.5 - margin
    assert uv[..., 1].min() >= margin - 0.5 and uv[..., 1].max() <= 480 - 0.5 - margin
    # the documented margin of the defaults
    assert (
        min(uv[..., 0].min(), 640 - uv[..., 0].max(), uv[..., 1].min(), 480 - uv[..., 1].max()) > 90
    )


def test_noise_statistics():
    s = simulate(paper_scenario(num_points=20, seed=7))
    noise = np.array(
        [o.uv - c.uv for o, c in zip(s.observations, s.clean_observations, strict=True)]
    )
    n = noise.size
    sigma = np.sqrt(0.05)
    assert abs(noise.mean()) < 4 * sigma / np.sqrt(n)
    assert noise.std() == pytest.approx(sigma, rel=0.03)
    # independent u and v noise
    assert abs(np.corrcoef(noise[..., 0].ravel(), noise[..., 1].ravel())[0, 1]) < 0.05


def test_noise_free_run():
    s = simulate(paper_scenario(noisy=False, duration=1.0))
    assert s.pixel_sigma == 0.0
    for o, c in zip(s.observations, s.clean_observations, strict=True):
        np.testing.assert_array_equal(o.uv, c.uv)


def test_same_seed_same_output_different_seed_different():
    a = simulate(paper_scenario(duration=1.0, seed=3, num_points=8))
    b = simulate(paper_scenario(duration=1.0, seed=3, num_points=8))
    c = simulate(paper_scenario(duration=1.0, seed=4, num_points=8))
    uv = [np.array([o.uv for o in s.observations]) for s in (a, b, c)]
    np.testing.assert_array_equal(uv[0], uv[1])
    np.testing.assert_array_equal(a.points_world, b.points_world)
    assert np.abs(uv[0] - uv[2]).max() > 0.01
    np.testing.assert_array_equal(a.groundtruth.positions, c.groundtruth.positions)


def test_more_points_lie_in_the_square_on_the_plane():
    s = simulate(paper_scenario(num_points=30, duration=1.0))
    X = s.points_world
    assert X.shape == (30, 3)
    np.testing.assert_allclose(X @ s.plane.normal, 2.0, atol=1e-12)
    np.testing.assert_array_equal(X[:4], simulate(paper_scenario(duration=1.0)).points_world)
    centre = np.array([0.0, 0.0, 2.0 / s.plane.normal[2]])
    b = np.cross(s.plane.normal, [1.0, 0.0, 0.0])
    assert np.all(np.abs((X - centre)[:, 0]) <= 0.25 + 1e-12)
    assert np.all(np.abs((X - centre) @ b) <= 0.25 + 1e-12)
    assert len(s.observations[0].ids) == 30


def test_distorted_camera_matches_opencv_projection():
    dist = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    cam = CameraModel(
        fx=700.0, fy=710.0, cx=330.0, cy=235.0, width=640, height=480, distortion=dist
    )
    s = simulate(paper_scenario(camera=cam, duration=2.0, noisy=False))
    for k in (0, 30, 60):
        R, p = s.groundtruth.rotations[k], s.groundtruth.positions[k]
        rvec, _ = cv2.Rodrigues(R.T)
        uv, _ = cv2.projectPoints(s.points_world, rvec, -R.T @ p, cam.K, dist)
        np.testing.assert_allclose(s.clean_observations[k].uv, uv.reshape(-1, 2), atol=1e-6)


def test_points_leaving_the_view_are_an_error_naming_the_config():
    with pytest.raises(InputError, match=r"ScenarioConfig: point \d+ leaves the image"):
        simulate(paper_scenario(linear_amplitude=(1.0, 0.5, 0.1)))
    with pytest.raises(InputError, match=r"ScenarioConfig: point \d+ is behind the camera"):
        simulate(
            paper_scenario(linear_amplitude=(0.0, 0.0, -4.0), angular_amplitude=(0.0, 0.0, 0.0))
        )


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("duration", -1.0, "ScenarioConfig.duration: expected a finite number > 0"),
        ("duration", 0.01, "ScenarioConfig.duration: expected at least one frame interval"),
        ("fps", float("nan"), "ScenarioConfig.fps: expected a finite number > 0"),
        ("noise_var", -0.1, "ScenarioConfig.noise_var: expected a finite number >= 0"),
        ("num_points", 3, "ScenarioConfig.num_points: expected an integer >= 4"),
        ("seed", -1, "ScenarioConfig.seed: expected an integer >= 0"),
        ("linear_harmonics", (1, 2.5, 3), "ScenarioConfig.linear_harmonics: expected 3 integers"),
        ("angular_amplitude", (0.0, 0.1), "ScenarioConfig.angular_amplitude: expected 3 finite"),
        ("plane", Plane(distance=2.0), "ScenarioConfig.plane: expected a Plane with a normal"),
        ("plane", Plane(2.0, np.array([0.0, 0.0, -1.0])), "ScenarioConfig.plane: the normal"),
    ],
)
def test_bad_config_values_name_the_field(field, value, message):
    with pytest.raises(InputError) as info:
        ScenarioConfig(**{field: value})
    assert str(info.value).startswith(message)


def test_paper_scenario_presets_and_unknown_override():
    assert paper_scenario().noise_var == 0.05
    assert paper_scenario(noisy=False).noise_var == 0.0
    assert paper_scenario(seed=5, fps=15.0).seed == 5
    with pytest.raises(InputError, match="paper_scenario: unknown setting 'speed'"):
        paper_scenario(speed=2.0)
