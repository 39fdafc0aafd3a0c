"""n* fitted to many frames at once (hvo_graph.geometry.plane_normal) and to a whole
recorded sequence (hvo_graph.frontend.normal_search), against the simulation's truth:
exact without noise, its reported covariance matching its scatter with noise, robust to
a track off the plane, and a smoother run without n* close to one given n*."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from off_plane import with_off_plane_track

from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.frontend.normal_search import (
    TRANSLATION_ALPHA,
    UNOBSERVED_SIGMA_DEG,
    chi2_3_quantile,
    sequence_normal,
)
from hvo_graph.geometry.plane_normal import refine_plane_normal
from hvo_graph.pipeline import run_estimate
from hvo_graph.sim.scenario import paper_scenario, simulate
from hvo_graph.types import Plane

DISTANCE = 2.0
NORMAL = np.array([0.1, -0.3, 1.0]) / np.linalg.norm([0.1, -0.3, 1.0])
SIGMA = 0.3 / 800  # normalized units


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def views(rng: np.random.Generator, frames: int = 8, points: int = 10):
    """Plane points seen from a reference and ``frames`` moved cameras: the reference's
    normalized points, per frame (rows, m_cur) of the points in front, the true motions."""
    m = np.column_stack((rng.uniform(-0.3, 0.3, (points, 2)), np.ones(points)))
    X_star = DISTANCE * m / (m @ NORMAL)[:, None]
    frames_out, motions = [], []
    for _ in range(frames):
        R = gtsam.Rot3.Expmap(rng.normal(0.0, 0.05, 3)).matrix()
        T = rng.normal(0.0, 0.2, 3)
        X = X_star @ R.T + T
        frames_out.append((np.arange(points), X / X[:, 2:3]))
        motions.append((R, T))
    return m, frames_out, motions


def perturbed(motions, rng: np.random.Generator):
    return [
        (gtsam.Rot3.Expmap(rng.normal(0.0, 0.02, 3)).matrix() @ R, T + rng.normal(0.0, 0.03, 3))
        for R, T in motions
    ]


def noisy(m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return m + np.column_stack((SIGMA * rng.standard_normal((len(m), 2)), np.zeros(len(m))))


def test_noise_free_views_give_the_normal_and_the_motions_exactly():
    rng = np.random.default_rng(0)
    reference, frames, motions = views(rng)
    start = NORMAL + np.array([0.15, 0.1, 0.0])  # ~10 degrees off
    fit = refine_plane_normal(
        reference, frames, perturbed(motions, rng), start, DISTANCE, SIGMA, huber=2.0
    )
    assert angle_deg(fit.normal, NORMAL) < 1e-6
    for (R, T), (R_true, T_true) in zip(fit.motions, motions, strict=True):
        np.testing.assert_allclose(R, R_true, atol=1e-9)
        np.testing.assert_allclose(T, T_true, atol=1e-9)
    np.testing.assert_allclose(fit.reference, reference, atol=1e-12)


def test_the_reported_covariance_matches_the_scatter_over_noise_draws():
    """NEES of n* (2 dof) over 40 draws of the pixel noise, reference pixels included."""
    rng = np.random.default_rng(1)
    reference, frames, motions = views(rng)
    nees = []
    for _ in range(40):
        observed = [(rows, noisy(m, rng)) for rows, m in frames]
        fit = refine_plane_normal(noisy(reference, rng), observed, motions, NORMAL, DISTANCE, SIGMA)
        e = fit.basis @ NORMAL  # the truth's offset in the fit's tangent plane
        nees.append(e @ np.linalg.solve(fit.covariance, e) / 2)
    assert 0.6 < np.mean(nees) < 1.5, np.mean(nees)


@pytest.fixture(scope="module")
def paper():
    return simulate(paper_scenario(duration=10.0, num_points=8, seed=2))


def test_a_whole_sequence_gives_the_normal_within_its_reported_uncertainty(paper):
    s = paper
    sigma = s.pixel_sigma / s.camera.mean_focal
    fit = sequence_normal(s.observations, s.camera, s.plane.distance, sigma, ransac_px=1.1)
    assert fit is not None and len(fit.motions) >= 20
    error = angle_deg(fit.normal, s.plane.normal)
    # the streaming choice (first two agreeing frames) was 5-10 degrees off here
    assert error < 1.0 and error < 3.5 * fit.sigma_deg, (error, fit.sigma_deg)


def test_a_track_off_the_plane_does_not_tilt_the_normal(paper):
    s = paper
    sigma = s.pixel_sigma / s.camera.mean_focal
    clean = sequence_normal(s.observations, s.camera, s.plane.distance, sigma, ransac_px=1.1)
    tracks = with_off_plane_track(s, height=0.4)
    fit = sequence_normal(tracks, s.camera, s.plane.distance, sigma, ransac_px=1.1)
    assert fit is not None and clean is not None
    assert angle_deg(fit.normal, s.plane.normal) < max(
        1.0, 1.5 * angle_deg(clean.normal, s.plane.normal)
    )


def test_a_static_camera_leaves_the_normal_unobserved_and_the_error_bounded():
    """Without translation H_d = R whatever n*: the fit's n* means little (it fits the
    noise; ~20 degrees off here), but a wrong n* only matters through T, so the poses
    stay within ~3x their error with n* given (3.7 mm RMSE here)."""
    s = simulate(
        paper_scenario(duration=2.0, linear_amplitude=(0, 0, 0), angular_amplitude=(0, 0, 0))
    )
    unknown = dataclasses.replace(s, plane=Plane(s.plane.distance, None))
    trajectory = run_estimate(unknown.observations, unknown).trajectory
    errors = summarize(error_series(trajectory, s.groundtruth), t_start=0.5)
    assert errors.position_max < 0.03 and errors.orientation_max < 1.0, errors


def test_the_translation_test_calls_the_normal_unobserved_only_without_translation(paper):
    # Static and turning cameras: the joint fit's n* was 16-19 degrees off with a reported
    # standard deviation of about 1 degree (its curvature comes from the fitted noise).
    sigma = paper.pixel_sigma / paper.camera.mean_focal
    limit = chi2_3_quantile(1.0 - TRANSLATION_ALPHA / 200)
    for angular in [(0, 0, 0), (0.0, -0.05, 0.10)]:
        s = simulate(
            paper_scenario(
                duration=10.0, num_points=6, seed=1, linear_amplitude=(0, 0, 0),
                angular_amplitude=angular,
            )
        )  # fmt: skip
        fit = sequence_normal(s.observations, s.camera, s.plane.distance, sigma)
        assert fit is not None and fit.translation_chi2 is not None
        assert fit.translation_chi2 < limit
        assert fit.sigma_deg == pytest.approx(UNOBSERVED_SIGMA_DEG)
    moving = sequence_normal(paper.observations, paper.camera, paper.plane.distance, sigma)
    assert moving is not None and moving.translation_chi2 is not None
    assert moving.translation_chi2 > 100 * limit and moving.sigma_deg < 1.0


def test_the_chi2_quantile_matches_the_tables():
    # chi^2 with 3 degrees of freedom: 7.815 (95 %), 11.345 (99 %), 16.266 (99.9 %).
    assert chi2_3_quantile(0.95) == pytest.approx(7.8147, abs=1e-3)
    assert chi2_3_quantile(0.99) == pytest.approx(11.3449, abs=1e-3)
    assert chi2_3_quantile(0.999) == pytest.approx(16.2662, abs=1e-3)


def test_the_smoother_without_the_normal_is_close_to_the_smoother_given_it(paper):
    s = paper
    given = run_estimate(s.observations, s).trajectory
    unknown = dataclasses.replace(s, plane=Plane(s.plane.distance, None))
    run = run_estimate(unknown.observations, unknown)
    assert run.normal_fit is not None
    assert run.summary()["plane_normal_fit"]["frames"] == len(run.normal_fit.motions)
    a = summarize(error_series(given, s.groundtruth), t_start=1.0)
    b = summarize(error_series(run.trajectory, s.groundtruth), t_start=1.0)
    # n* ~0.5 deg off costs up to ~1.6x (the streaming choice, 5-10 deg off, cost ~15x)
    assert b.position_rmse < 2.0 * a.position_rmse, (a.position_rmse, b.position_rmse)
    assert b.orientation_rmse < 2.0 * a.orientation_rmse
