"""Image front end: rendered images -> KLT tracks -> homography measurements.

Ground truth is built here, independently of hvo_graph.sim.scenario: poses from
a constant body twist integrated exactly with gtsam's Expmap, the texture
placement and the pinhole projection written out in the test (the texture
rule is the one documented in hvo_graph.sim.render), back-projection of pixels
onto the plane by ray-plane intersection.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.frontend import measure_sequence
from hvo_graph.frontend.tracking import TrackerConfig, track_images, tracks_from_images
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.io.images import load_image_sequence
from hvo_graph.sim.render import make_texture, render_plane_images
from hvo_graph.types import FrameObservations, Plane

CAMERA = CameraModel(fx=310.0, fy=295.0, cx=158.3, cy=121.7, width=320, height=240)
NORMAL = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
DISTANCE = 2.0
PLANE = Plane(DISTANCE, NORMAL)
# Body twist [w; v]: sideways, up and forward while turning; the image content
# slides by ~4 px per frame, so the first frame's points leave the view.
TWIST = np.array([0.05, -0.1, 0.15, 0.8, -0.2, 0.15])
FPS = 30.0
NUM_FRAMES = 60
POSES = [gtsam.Pose3.Expmap(TWIST * k / FPS) for k in range(NUM_FRAMES)]
TIMES = [k / FPS for k in range(NUM_FRAMES)]


def project(pose: gtsam.Pose3, X: np.ndarray, camera: CameraModel = CAMERA) -> np.ndarray:
    """Pixel of world point X: K R_wc^T (X - p_wc), dehomogenized (OpenCV with distortion)."""
    R_cw = pose.rotation().matrix().T
    Xc = R_cw @ (X - pose.translation())
    if camera.has_distortion:
        uv, _ = cv2.projectPoints(Xc[None], np.zeros(3), np.zeros(3), camera.K, camera.distortion)
        return uv.ravel()
    return np.array([camera.fx * Xc[0] / Xc[2] + camera.cx, camera.fy * Xc[1] / Xc[2] + camera.cy])


def back_project(pose: gtsam.Pose3, uv: np.ndarray, camera: CameraModel = CAMERA) -> np.ndarray:
    """World point on the plane n^T X = d seen at pixel uv: ray-plane intersection."""
    if camera.has_distortion:
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        xy = cv2.undistortPoints(
            np.asarray(uv, float).reshape(1, 1, 2), camera.K, camera.distortion, criteria=criteria
        ).ravel()
    else:
        xy = np.array([(uv[0] - camera.cx) / camera.fx, (uv[1] - camera.cy) / camera.fy])
    ray = pose.rotation().matrix() @ np.array([xy[0], xy[1], 1.0])
    p = pose.translation()
    return p + (DISTANCE - NORMAL @ p) / (NORMAL @ ray) * ray


def track_errors(
    tracks: list[FrameObservations], camera: CameraModel = CAMERA
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Reprojection error of every observation after a track's first.

    Each track's plane point is the back-projection of its first observation
    through the true pose; it is reprojected through the true later poses.
    Returns errors (px), track ages (frames) and each id's largest error.
    """
    first: dict[int, tuple[np.ndarray, int]] = {}
    errors, ages, worst = [], [], {}
    for obs in tracks:
        pose = POSES[obs.index]
        for i, uv in zip(obs.ids.tolist(), obs.uv, strict=True):
            if i not in first:
                first[i] = (back_project(pose, uv, camera), obs.index)
                continue
            e = float(np.linalg.norm(project(pose, first[i][0], camera) - uv))
            errors.append(e)
            ages.append(obs.index - first[i][1])
            worst[i] = max(worst.get(i, 0.0), e)
    return np.array(errors), np.array(ages), worst


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    return render_plane_images(CAMERA, PLANE, POSES, noise_sigma=1.0, seed=3)


@pytest.fixture(scope="module")
def tracks(images) -> list[FrameObservations]:
    return track_images(images, TIMES, CAMERA)


# -- rendering ---------------------------------------------------------------------------------


def texture_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The documented in-plane axes: e_u from e_x (or e_v from e_y when |n_x| > 0.9)."""
    if abs(n[0]) <= 0.9:
        e_u = np.array([1.0, 0.0, 0.0]) - n[0] * n
        e_u /= np.linalg.norm(e_u)
        return e_u, np.cross(n, e_u)
    e_v = np.array([0.0, 1.0, 0.0]) - n[1] * n
    e_v /= np.linalg.norm(e_v)
    return np.cross(e_v, n), e_v


def dot_centroid(image: np.ndarray, background: float) -> np.ndarray:
    w = np.clip(image.astype(float) - background - 10.0, 0.0, None)
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([(w * u).sum() / w.sum(), (w * v).sum() / w.sum()])


@pytest.mark.parametrize(
    ("normal", "view", "distortion"),
    [
        ([0.1, -0.2, 1.0], None, None),
        ([0.1, -0.2, 1.0], None, [-0.12, 0.03, 0.001, -0.0015, 0.0]),
        # A plane off to the side (the other texture-axes rule), seen by a turned camera.
        ([0.95, 0.05, 0.3], gtsam.Rot3.Ry(1.2), None),
    ],
)
def test_a_texture_dot_renders_at_the_projection_of_its_plane_point(normal, view, distortion):
    n = np.asarray(normal) / np.linalg.norm(normal)
    camera = CameraModel(310.0, 295.0, 158.3, 121.7, 320, 240, np.asarray(distortion or [0.0] * 5))
    height, width, texel = 401, 601, 0.004
    a0, b0 = 333.0, 180.0  # the dot's texel (OpenCV convention: texel centres at integers)
    b, a = np.mgrid[0:height, 0:width]
    texture = 40.0 + 200.0 * np.exp(-((a - a0) ** 2 + (b - b0) ** 2) / (2 * 2.5**2))
    # Texel -> plane point, as documented: O = d n, centred texture, axes e_u, e_v.
    e_u, e_v = texture_axes(n)
    X = DISTANCE * n + texel * ((a0 - (width - 1) / 2) * e_u + (b0 - (height - 1) / 2) * e_v)
    assert abs(n @ X - DISTANCE) < 1e-12
    start = gtsam.Pose3(view or gtsam.Rot3(), np.zeros(3))
    poses = [start.compose(gtsam.Pose3.Expmap(0.3 * TWIST * k / FPS)) for k in range(0, 60, 12)]
    rendered = render_plane_images(
        camera, Plane(DISTANCE, n), poses, texture=texture, texture_size_m=width * texel, tile=False
    )
    for image, pose in zip(rendered, poses, strict=True):
        expected = project(pose, X, camera)  # OpenCV's lens model when distorted
        assert camera.in_view(expected, margin=20.0)[0]
        assert np.linalg.norm(dot_centroid(image, 40.0) - expected) < 0.15


def test_rays_that_miss_the_plane_stay_black():
    n = np.array([0.0, 1.0, 0.3]) / np.linalg.norm([0.0, 1.0, 0.3])  # a floor below the camera
    image = render_plane_images(CAMERA, Plane(1.0, n), [gtsam.Pose3()])[0]
    v = np.mgrid[0 : CAMERA.height, 0 : CAMERA.width][0]
    ray_dot_n = n[1] * (v - CAMERA.cy) / CAMERA.fy + n[2]  # n^T K^-1 [u, v, 1]
    assert np.all(image[ray_dot_n <= 0] == 0)
    assert np.mean(image[ray_dot_n > 0.01] > 0) > 0.999
    assert 0.1 < np.mean(ray_dot_n <= 0) < 0.5  # the horizon really is in view


def test_rendering_rejects_a_camera_behind_the_plane_and_a_missing_normal():
    through = gtsam.Pose3(gtsam.Rot3(), 1.1 * DISTANCE * NORMAL)
    with pytest.raises(InputError, match=r"poses_wc\[1\]: the camera centre is on or behind"):
        render_plane_images(CAMERA, PLANE, [gtsam.Pose3(), through])
    with pytest.raises(InputError, match=r"plane\.normal: rendering needs the plane normal"):
        render_plane_images(CAMERA, Plane(DISTANCE), [gtsam.Pose3()])


def test_procedural_texture_is_seamless_and_seeded():
    texture = make_texture(256, seed=1)
    assert texture.shape == (256, 256)
    assert np.array_equal(texture, make_texture(256, seed=1))
    assert not np.array_equal(texture, make_texture(256, seed=2))
    # Periodic: the step across the wrap-around seam is like the steps across the
    # other block edges (8 texels apart); a hard seam would be ~2.5 times larger.
    for t in (texture, texture.T):
        seam = np.abs(t[:, 0] - t[:, -1]).mean()
        edges = np.mean([np.abs(t[:, j] - t[:, j - 1]).mean() for j in range(8, 256, 8)])
        assert 0.7 < seam / edges < 1.4


# -- tracking ----------------------------------------------------------------------------------


def check_accuracy(errors: np.ndarray, ages: np.ndarray, old: int = 40) -> None:
    assert np.median(errors) < 0.1
    assert np.percentile(errors, 99) < 0.3
    assert errors.max() < 1.0
    # Re-alignment against the first image: no drift with track age.
    assert np.median(errors[ages >= old]) < 0.1


def test_tracks_follow_the_true_projections_of_their_plane_points(tracks):
    errors, ages, _ = track_errors(tracks)
    assert len(errors) > 5000
    check_accuracy(errors, ages)


def test_few_tracks_per_replenishment_are_tracked_as_accurately(images):
    # Groups of new tracks too small for their own homography use the chained one.
    few = track_images(images, TIMES, CAMERA, TrackerConfig(max_features=12, min_tracked=11))
    errors, ages, _ = track_errors(few)
    assert len(errors) > 500
    check_accuracy(errors, ages)


def test_tracking_through_a_distorting_lens(images):
    camera = CameraModel(
        CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, 320, 240, np.array([-0.25, 0.08, 0, 0, 0])
    )
    distorted = render_plane_images(camera, PLANE, POSES[:30], noise_sigma=1.0, seed=3)
    tracks = track_images(distorted, TIMES[:30], camera)
    errors, ages, _ = track_errors(tracks, camera)
    assert len(errors) > 3000
    check_accuracy(errors, ages, old=20)


def test_plain_frame_to_frame_klt_stays_within_a_third_of_a_pixel(images):
    plain = track_images(images, TIMES, CAMERA, TrackerConfig(refine_max_px=None))
    errors, _, _ = track_errors(plain)
    assert np.median(errors) < 0.3
    assert np.mean(errors > 1.0) < 0.05


@pytest.mark.parametrize("distortion", [None, [-0.25, 0.08, 0.0, 0.0, 0.0]])
def test_a_wide_baseline_jump_is_bridged_by_the_feature_homography(distortion):
    """Two views 25 degrees and 0.6 m apart (the content moves by ~150 px): frame-to-frame
    KLT loses the tracks; the wide-baseline step (SIFT + MAGSAC, then the tracker's own
    corners aligned under that homography) keeps them at their true projections."""
    dist = np.zeros(5) if distortion is None else np.array(distortion)
    camera = CameraModel(CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, 320, 240, dist)
    far = gtsam.Pose3(gtsam.Rot3.Ypr(0.35, 0.2, 0.1), np.array([0.6, -0.2, 0.2]))
    poses = [gtsam.Pose3(), far]
    views = render_plane_images(camera, PLANE, poses, noise_sigma=1.0, seed=5)

    def shared(config):
        first, second = track_images(views, [0.0, 1.0], camera, config)
        _, ia, ib = np.intersect1d(first.ids, second.ids, return_indices=True)
        X = [back_project(poses[0], uv, camera) for uv in first.uv[ia]]
        moved = np.array([project(far, x, camera) for x in X]).reshape(-1, 2)
        motion = np.linalg.norm(moved - first.uv[ia], axis=1)
        return np.linalg.norm(moved - second.uv[ib], axis=1), motion

    errors, motion = shared(TrackerConfig())
    assert len(errors) >= 60 and np.median(motion) > 100
    assert np.median(errors) < 0.1 and errors.max() < 1.0
    plain, _ = shared(TrackerConfig(wide_baseline=False, reidentify_frames=0))
    assert len(plain) < len(errors) / 4


def test_ids_are_stable_and_tracks_are_replenished(tracks):
    config = TrackerConfig()
    seen_in: dict[int, list[int]] = {}
    for obs in tracks:
        assert len(np.unique(obs.ids)) == len(obs.ids) <= config.max_features
        assert obs.uv.shape == (len(obs.ids), 2)
        assert np.all(CAMERA.in_view(obs.uv, margin=config.border_margin_px))
        for i in obs.ids.tolist():
            seen_in.setdefault(i, []).append(obs.index)
    # An id lives in one unbroken run of frames: lost ids never come back.
    for frames in seen_in.values():
        assert frames == list(range(frames[0], frames[-1] + 1))
    assert sorted(tracks[0].ids.tolist()) == list(range(len(tracks[0].ids)))
    assert len(tracks[0].ids) == config.max_features
    replenished = 0
    for prev, obs in itertools.pairwise(tracks):
        survivors = np.isin(obs.ids, prev.ids)
        new = obs.ids[~survivors]
        if len(new):
            replenished += 1
            # New ids only when too few survived, and never reused.
            assert np.count_nonzero(survivors) < config.min_tracked
            assert new.min() > max(max(t.ids) for t in tracks[: obs.index])
    assert replenished >= 1
    # The motion takes points out of view, yet tracking goes on.
    reference = set(tracks[0].ids.tolist())
    assert len(reference & set(tracks[-1].ids.tolist())) < 0.3 * len(reference)
    assert min(len(obs.ids) for obs in tracks) >= 50


def test_tracks_on_an_independently_moving_object_are_dropped(images):
    patch = make_texture(48, seed=99)[:48, :48].astype(np.uint8)
    cluttered = []
    for k, image in enumerate(images):
        image = image.copy()
        x, y = 40 + 2 * k, 90 + k // 2  # moves right while the plane slides left
        image[y : y + 48, x : x + 48] = patch
        cluttered.append(image)

    def worst(config: TrackerConfig) -> np.ndarray:
        return np.array(
            list(track_errors(track_images(cluttered, TIMES, CAMERA, config))[2].values())
        )

    unchecked = worst(TrackerConfig(ransac_threshold_px=None, refine_max_px=None))
    assert np.count_nonzero(unchecked > 5.0) >= 10  # the object's tracks, followed for long
    # Relative motion is ~6 px per frame: any object track kept one frame would exceed 5 px.
    assert np.all(worst(TrackerConfig(refine_max_px=None)) < 5.0)
    assert np.all(worst(TrackerConfig()) < 2.0)


def test_gray_and_bgr_images_give_the_same_tracks(images):
    gray = track_images(images[:10], TIMES[:10], CAMERA)
    color = track_images(
        [cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) for im in images[:10]], TIMES[:10], CAMERA
    )
    for a, b in zip(gray, color, strict=True):
        assert np.array_equal(a.ids, b.ids)
        assert np.allclose(a.uv, b.uv)


# -- end to end --------------------------------------------------------------------------------


def test_rendered_images_give_accurate_homography_poses(tracks):
    frames = measure_sequence(tracks, CAMERA, PLANE, ransac_threshold_px=2.0)
    reference = set(tracks[0].ids.tolist())
    shared = [len(reference & set(obs.ids.tolist())) for obs in tracks]
    assert min(shared) >= 4  # every frame of this motion keeps >= 4 reference points
    world: dict[int, gtsam.Pose3] = {}  # poses against keyframes, chained to the world frame
    for frame, pose in zip(frames, POSES, strict=True):
        assert frame.pose is not None
        measured = gtsam.Pose3(gtsam.Rot3(frame.pose.rotation), frame.pose.position)
        ref = frame.pose.reference
        world[frame.index] = measured if ref == frame.index else world[ref].compose(measured)
        estimate = world[frame.index]
        assert np.linalg.norm(estimate.translation() - pose.translation()) < 2e-3  # m, at 2 m
        dR = gtsam.Rot3(estimate.rotation().matrix().T @ pose.rotation().matrix())
        assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(dR))) < 0.05
    for frame in frames[1:]:
        # Constant twist: the mid-interval velocity is the twist itself.
        assert frame.velocity is not None
        assert np.allclose(frame.velocity.twist, TWIST, atol=0.02)


# -- files -------------------------------------------------------------------------------------


def write_images(folder: Path, images: list[np.ndarray], names: list[str] | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, image in enumerate(images):
        assert cv2.imwrite(str(folder / (names[k] if names else f"frame_{k:04d}.png")), image)


def test_an_image_folder_tracks_like_the_arrays(tmp_path, images):
    write_images(tmp_path / "seq", images[:8])
    (tmp_path / "seq" / "notes.txt").write_text("not an image\n")
    times = [0.5 + 0.04 * k for k in range(8)]
    (tmp_path / "seq" / "times.txt").write_text("# seconds\n" + "\n".join(map(str, times)) + "\n")
    from_files = tracks_from_images(tmp_path / "seq", CAMERA)
    from_arrays = track_images(images[:8], times, CAMERA)
    assert [o.t for o in from_files] == times
    for a, b in zip(from_files, from_arrays, strict=True):
        assert np.array_equal(a.ids, b.ids) and np.array_equal(a.uv, b.uv)


def test_file_names_sort_by_number_and_fps_sets_the_times(tmp_path, images):
    # Unpadded numbers: frame_10 comes after frame_9, not after frame_1.
    write_images(tmp_path, images[:11], [f"frame_{k}.PNG" for k in range(11)])
    frames, times = load_image_sequence(tmp_path, fps=10.0)
    assert times == pytest.approx([k / 10.0 for k in range(11)])
    assert [Path(name).name for name in frames.names] == [f"frame_{k}.PNG" for k in range(11)]
    assert all(np.array_equal(a, b) for a, b in zip(frames, images[:11], strict=True))
    # No times.txt and no frame rate: an error, never a guessed rate.
    message = (
        f"{tmp_path}: no times.txt in the folder to give the images' timestamps; pass the "
        "frame rate (--fps) or write times.txt (one time in seconds per image)"
    )
    with pytest.raises(InputError) as info:
        load_image_sequence(tmp_path)
    assert str(info.value) == message


def test_a_video_file_is_read_frame_by_frame(tmp_path, images):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (320, 240), False)
    for image in images[:12]:
        writer.write(image)
    writer.release()
    frames, times = load_image_sequence(path, camera=CAMERA)
    # The container's per-frame timestamps (CAP_PROP_POS_MSEC): 40 ms apart at 25 fps.
    assert len(frames) == 12 and times == pytest.approx([k / 25.0 for k in range(12)], abs=1e-9)
    decoded = list(frames)
    assert all(f.shape == (240, 320) and f.dtype == np.uint8 for f in decoded)
    assert np.abs(decoded[5].astype(float) - images[5]).mean() < 3.0  # JPEG-compressed frame 5
    assert load_image_sequence(path, fps=50.0)[1][1] == pytest.approx(0.02)
    tracks = tracks_from_images(path, CAMERA)
    assert len(tracks) == 12 and len(tracks[-1].ids) > 100


# -- bad input ---------------------------------------------------------------------------------


def test_missing_path_and_empty_folder(tmp_path):
    with pytest.raises(InputError, match="nowhere: no such directory or video file"):
        load_image_sequence(tmp_path / "nowhere")
    with pytest.raises(InputError, match="no images in the directory"):
        load_image_sequence(tmp_path)


def test_unreadable_images_are_named(tmp_path, images):
    write_images(tmp_path, images[:3])
    (tmp_path / "frame_0001.png").write_bytes(b"definitely not a png")
    with pytest.raises(InputError, match=r"frame_0001\.png: cannot read the image"):
        tracks_from_images(tmp_path, CAMERA, fps=10.0)
    (tmp_path / "frame_0000.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"frame_0000\.png: cannot read the image"):
        load_image_sequence(tmp_path, fps=10.0)


def test_a_bad_file_read_ahead_fails_only_when_its_frame_comes(tmp_path, images):
    # Files are decoded ahead of the caller: the frames before a bad one still arrive, in
    # order, and the error names the bad file when the caller reaches it.
    write_images(tmp_path, images[:6])
    (tmp_path / "frame_0003.png").write_bytes(b"definitely not a png")
    frames, _ = load_image_sequence(tmp_path, fps=10.0)
    seen = []
    with pytest.raises(InputError, match=r"frame_0003\.png: cannot read the image"):
        for frame in frames:
            seen.append(frame)
    assert len(seen) == 3
    assert all(np.array_equal(a, b) for a, b in zip(seen, images[:3], strict=True))
    # A second pass reads the same frames again (the first one is not kept twice).
    again = []
    with pytest.raises(InputError, match=r"frame_0003\.png"):
        for frame in frames:
            again.append(frame)
    assert all(np.array_equal(a, b) for a, b in zip(again, images[:3], strict=True))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("0.0\n0.1\n", r"times\.txt: 2 times for 3 images; expected one per image"),
        ("0.0\n0.1\n0.1\n", r"times\.txt:3: time 0\.1 does not increase \(previous 0\.1\)"),
        ("0.0\nabc\n0.2\n", r"times\.txt:2: expected one time in seconds, got 'abc'"),
        ("0.0\n0.1\nnan\n", r"times\.txt:3: expected a finite time, got 'nan'"),
    ],
)
def test_bad_times_file(tmp_path, images, content, message):
    write_images(tmp_path, images[:3])
    (tmp_path / "times.txt").write_text(content)
    with pytest.raises(InputError, match=message):
        load_image_sequence(tmp_path)


def test_times_file_and_fps_together_are_refused(tmp_path, images):
    write_images(tmp_path, images[:2])
    (tmp_path / "times.txt").write_text("0\n1\n")
    with pytest.raises(InputError, match=r"fps: .*times\.txt already gives the timestamps"):
        load_image_sequence(tmp_path, fps=30.0)


def test_image_sizes_must_agree_with_each_other_and_the_camera(tmp_path, images):
    write_images(tmp_path / "mixed", [images[0], images[1][:200, :300]])
    with pytest.raises(InputError, match=r"frame_0001\.png: image size 300x200 differs from"):
        tracks_from_images(tmp_path / "mixed", CAMERA, fps=10.0)
    write_images(tmp_path / "small", [im[:200, :300] for im in images[:2]])
    with pytest.raises(InputError, match="image size 300x200 does not match the camera's 320x240"):
        tracks_from_images(tmp_path / "small", CAMERA, fps=10.0)
    with pytest.raises(InputError, match=r"images\[1\]: image size 300x200 does not match"):
        track_images([images[0], images[1][:200, :300]], TIMES[:2], CAMERA)


def test_bad_arrays_times_and_settings(images):
    with pytest.raises(InputError, match=r"images: 2 images for 3 times"):
        track_images(images[:2], TIMES[:3], CAMERA)
    with pytest.raises(InputError, match=r"images: more images than times \(2\)"):
        track_images(images[:3], TIMES[:2], CAMERA)
    with pytest.raises(InputError, match=r"times\[2\]: 0\.0 does not increase"):
        track_images(images[:3], [0.0, 0.1, 0.0], CAMERA)
    with pytest.raises(
        InputError, match=r"images\[0\]: expected uint8 or uint16 pixels, got float64"
    ):
        track_images([images[0] / 255.0], [0.0], CAMERA)
    with pytest.raises(InputError, match="min_tracked: expected at most max_features"):
        TrackerConfig(max_features=50, min_tracked=60)
    with pytest.raises(InputError, match="wide_baseline: expected true or false, got 'no'"):
        TrackerConfig(wide_baseline="no")
    with pytest.raises(InputError, match=r"reidentify_frames: expected an integer >= 0, got -1"):
        TrackerConfig(reidentify_frames=-1)
    with pytest.raises(InputError, match="fps: expected a number > 0"):
        load_image_sequence(".", fps=0.0)
