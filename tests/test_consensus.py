"""The consensus pre-check that lets the front end skip RANSAC (hvo_graph.geometry._consensus).

RANSAC is skipped only where every point lies within the threshold of the homography
of the other points, or exactly one does not and the rest are one consensus set
without it. References: OpenCV's own fits (``cv2.findHomography`` by least
squares on the other points, and its RANSAC), on simulated frames of the paper's
scenario whose ground truth says which points are on the plane.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from off_plane import with_off_plane_track

from hvo_graph.frontend import FrontEndConfig, MeasurementFrontEnd, _batch
from hvo_graph.geometry import discrete
from hvo_graph.geometry._consensus import consensus_inliers, deleted_distances
from hvo_graph.geometry.discrete import estimate_homography
from hvo_graph.sim.scenario import paper_scenario, simulate


def _frames(points: int, seed: int = 0, frames: int = 31) -> tuple[np.ndarray, np.ndarray, float]:
    """(m_ref (N, 3), m_cur (F, N, 3), the front end's RANSAC threshold in normalized units)
    of the paper's noisy scenario with ``points`` points."""
    scenario = simulate(paper_scenario(seed=seed, num_points=points, duration=(frames - 1) / 30.0))
    camera = scenario.camera
    m = np.array([camera.pixel_to_normalized(o.uv) for o in scenario.observations])
    threshold = FrontEndConfig(pixel_sigma=scenario.pixel_sigma).ransac_px / camera.mean_focal
    return m[0], m[1:], threshold


def _opencv_left_out(m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """(N,) each point's transfer distance from OpenCV's homography (least squares, then
    Levenberg-Marquardt on the transfer error) of the other points."""
    out = []
    for i in range(len(m_ref)):
        others = np.arange(len(m_ref)) != i
        H, _ = cv2.findHomography(m_ref[others, :2], m_cur[others, :2], 0)
        x = H @ m_ref[i]
        out.append(np.linalg.norm(x[:2] / x[2] - m_cur[i, :2]))
    return np.array(out)


def _textbook_left_out(m_ref: np.ndarray, m_cur: np.ndarray) -> np.ndarray:
    """(N,) the same from the normalized DLT (Hartley & Zisserman, algorithm 4.2) of the
    other points, refitted for each point."""

    def normalize(m):
        c = m[:, :2].mean(axis=0)
        s = np.sqrt(2.0) / np.mean(np.linalg.norm(m[:, :2] - c, axis=1))
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])

    out = []
    for i in range(len(m_ref)):
        a, b = m_ref[np.arange(len(m_ref)) != i], m_cur[np.arange(len(m_ref)) != i]
        Ta, Tb = normalize(a), normalize(b)
        rows = []
        for p, q in zip(a @ Ta.T, b @ Tb.T, strict=True):
            rows.append(np.concatenate((np.zeros(3), -q[2] * p, q[1] * p)))
            rows.append(np.concatenate((q[2] * p, np.zeros(3), -q[0] * p)))
        H = np.linalg.inv(Tb) @ np.linalg.svd(np.array(rows))[2][-1].reshape(3, 3) @ Ta
        x = H @ m_ref[i]
        out.append(np.linalg.norm(x[:2] / x[2] - m_cur[i, :2]))
    return np.array(out)


@pytest.mark.parametrize("points", [6, 8, 20, 50])
def test_deleted_distances_match_fits_of_the_other_points(points: int) -> None:
    m_ref, m_cur, _ = _frames(points, frames=6)
    m_cur = m_cur.copy()
    m_cur[:3, 0, :2] += 3e-3  # one point ~2.4 px off in some frames: residuals large and small
    got = deleted_distances(m_ref, m_cur)
    for k in range(len(m_cur)):
        # First order in the left-out point: within a few % of the refitted DLT ...
        np.testing.assert_allclose(got[k], _textbook_left_out(m_ref, m_cur[k]), rtol=0.08)
        # ... and, from 8 points on, of OpenCV's fit (its error differs a little).
        if points >= 8:
            np.testing.assert_allclose(got[k], _opencv_left_out(m_ref, m_cur[k]), rtol=0.15)


def test_four_points_have_no_spare_point_to_judge() -> None:
    m_ref, m_cur, threshold = _frames(4, frames=3)
    assert np.all(np.isinf(deleted_distances(m_ref, m_cur)))
    inliers, decided = consensus_inliers(m_ref, m_cur, threshold)
    assert not inliers.any() and not decided.any()


@pytest.mark.parametrize(("points", "skipped"), [(8, 0.0), (20, 0.6), (50, 0.6)])
def test_clean_frames_skip_ransac_where_opencv_agrees_every_point_is_an_inlier(
    points: int, skipped: float
) -> None:
    m_ref, m_cur, threshold = _frames(points)
    decided = consensus_inliers(m_ref, m_cur, threshold)[0].all(axis=1)
    # With many points most clean frames skip RANSAC; with few, a left-out point's
    # homography is too uncertain to vouch for it, and RANSAC judges.
    assert decided.mean() >= skipped
    for k in np.flatnonzero(decided):
        # Every point within the threshold of OpenCV's fit of the others (to first order) ...
        assert np.all(_opencv_left_out(m_ref, m_cur[k]) <= 1.15 * threshold)
        # ... so OpenCV's RANSAC could find no larger consensus set: it returns all points
        # or fewer, and with the decision estimate_homography keeps all of them.
        _, mask = cv2.findHomography(m_ref[:, :2], m_cur[k][:, :2], cv2.RANSAC, threshold)
        assert mask.sum() <= points
        _, inliers = estimate_homography(m_ref, m_cur[k], ransac_threshold=threshold)
        assert inliers.all()


@pytest.mark.parametrize("points", [6, 8, 20, 50])
@pytest.mark.parametrize("offset", [1.5, 2.0, 4.0])
def test_an_injected_outlier_is_left_out_alone_or_left_to_ransac(
    points: int, offset: float
) -> None:
    m_ref, m_cur, threshold = _frames(points, frames=11)
    m_cur = m_cur.copy()
    # A point `offset` thresholds off the plane's homography, diagonally.
    m_cur[:, 1, :2] += offset * threshold / np.sqrt(2.0)
    inliers, decided = consensus_inliers(m_ref, m_cur, threshold)
    if offset >= 2.0:  # (1.5 thresholds: noise can bring it within)
        assert not inliers.all(axis=1).any()
    for k in range(len(m_cur)):
        _, kept = estimate_homography(m_ref, m_cur[k], ransac_threshold=threshold)
        if decided[k]:
            np.testing.assert_array_equal(kept, inliers[k])
            left_out = np.flatnonzero(~kept)
            assert len(left_out) <= 1
            if offset >= 2.0:
                assert left_out.tolist() == [1]
            # The point left out is beyond the threshold of OpenCV's fit of the others,
            # and without it every other point is within it of OpenCV's fit of the rest:
            # those are the consensus set, without RANSAC.
            assert np.all(_opencv_left_out(m_ref, m_cur[k])[left_out] > 0.85 * threshold)
            rest = _opencv_left_out(m_ref[kept], m_cur[k][kept])
            assert np.all(rest <= 1.15 * threshold)
        else:  # RANSAC judges: the same inliers as OpenCV's
            _, mask = cv2.findHomography(m_ref[:, :2], m_cur[k][:, :2], cv2.RANSAC, threshold)
            np.testing.assert_array_equal(kept, mask.ravel().astype(bool))
        if offset == 4.0 and points >= 8:  # far off: rejected (with 6 points a sample
            assert not kept[1]  # of it and 3 good points may tie with the good ones)
    if points >= 20 and offset <= 2.0:  # a mild outlier among many points: decided
        assert decided.mean() >= 0.5


def test_an_outlier_a_least_squares_fit_hides_is_still_found() -> None:
    # With 6 points the fit of all of them leans towards the outlier: its own residual is
    # within the threshold although it is 2 thresholds from the others' homography.
    m_ref, m_cur, threshold = _frames(6, frames=11)
    m_cur = m_cur.copy()
    m_cur[:, 1, :2] += 2.0 * threshold / np.sqrt(2.0)
    hidden = 0
    for k in range(len(m_cur)):
        H, _ = cv2.findHomography(m_ref[:, :2], m_cur[k][:, :2], 0)
        x = m_ref @ H.T
        hidden += np.all(np.hypot(*(x[:, :2] / x[:, 2:] - m_cur[k, :, :2]).T) <= threshold)
    assert hidden >= 5
    inliers, decided = consensus_inliers(m_ref, m_cur, threshold)
    assert not (decided & inliers[:, 1]).any()  # left out, or left to RANSAC


def test_estimate_homography_calls_ransac_only_when_a_point_disagrees(monkeypatch) -> None:
    m_ref, m_cur, threshold = _frames(20, frames=2)
    calls = []

    def counted(a, b, thr):
        calls.append(1)
        return np.ones(len(a), dtype=bool)

    monkeypatch.setattr(discrete, "_ransac_inliers", counted)
    assert consensus_inliers(m_ref, m_cur, threshold)[0][0].all()
    H, inliers = estimate_homography(m_ref, m_cur[0], ransac_threshold=threshold)
    assert not calls and inliers.all()
    H_cv, _ = cv2.findHomography(m_ref[:, :2], m_cur[0][:, :2], 0)  # the fit of all points
    np.testing.assert_allclose(H / H[2, 2], H_cv / H_cv[2, 2], atol=1e-3)
    bad = m_cur[0].copy()
    bad[3, :2] += np.sqrt(2.0) * threshold  # 2 thresholds off, diagonally
    H, inliers = estimate_homography(m_ref, bad, ransac_threshold=threshold)
    assert not calls and np.flatnonzero(~inliers).tolist() == [3]  # one point off: left out
    others = np.arange(len(bad)) != 3
    H_cv, _ = cv2.findHomography(m_ref[others, :2], bad[others, :2], 0)
    np.testing.assert_allclose(H / H[2, 2], H_cv / H_cv[2, 2], atol=1e-3)
    bad[3, :2] += 3.0 * threshold  # far off: the others' fits lean, more points beyond
    estimate_homography(m_ref, bad, ransac_threshold=threshold)
    assert calls


@pytest.mark.parametrize("points", [8, 20])
def test_front_end_still_excludes_an_off_plane_track(points: int, monkeypatch) -> None:
    scenario = simulate(paper_scenario(seed=2, num_points=points, duration=4.0))
    observations = with_off_plane_track(scenario)

    def run():
        front = MeasurementFrontEnd(
            scenario.camera, scenario.plane, FrontEndConfig(pixel_sigma=scenario.pixel_sigma)
        )
        frames = front.process_all(observations)
        rejected = [
            set(o.ids.tolist()) - set(f.points.ids.tolist())
            for o, f in zip(observations, frames, strict=True)
        ]
        # The reported counts are the points left out of the frame's record.
        assert [f.num_rejected for f in frames] == [len(r) for r in rejected]
        return front.excluded_tracks, sum(99 in r for r in rejected)

    with_check = run()

    def never(m_ref, m_cur, threshold):
        return np.zeros(m_cur.shape[:2], dtype=bool), np.zeros(len(m_cur), dtype=bool)

    monkeypatch.setattr(discrete, "consensus_inliers", never)
    monkeypatch.setattr(_batch, "consensus_inliers", never)
    ransac_always = run()
    # The track is excluded, after being rejected in as many frames, as with RANSAC always.
    assert with_check == ransac_always
    assert with_check[0] == {99}
