"""The images path on real photographs: OpenCV's sample data (fetched by ``make realdata``).

References come from the visible target and the data set, never from the code
measured: ``cv2.solvePnP`` on the chessboard corners found by
``cv2.findChessboardCorners`` + ``cv2.cornerSubPix``, and the graffiti pair's
published homography.

1. **pairs**: the 156 ordered pairs of the 13 chessboard views (left01..left14,
   calibrated by ``left_intrinsics.yml``), each a two-frame sequence; the H_d
   pose against solvePnP's relative pose, from the board's corners as tracks
   and from the images path's own features (``track_images`` told the target);
2. **sequence**: the 13 views as one image folder through
   ``hvo-graph estimate --plane auto --target chessboard:9x6:0.025 --method
   measurements``; each view's pose against the first, against solvePnP's;
3. **graf**: graf1 -> graf3 as a two-frame sequence for ``track_images``; the
   tracks' mean transfer error under ``H1to3p.xml``.

Writes ``<out-dir>/real_views.md`` and prints it.

Usage::

    make realdata
    python experiments/real_views.py                  # -> out/real_views/
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import cv2
import gtsam
import numpy as np

from hvo_graph.cli import main as cli_main
from hvo_graph.frontend import measure_sequence
from hvo_graph.frontend.target import parse_target
from hvo_graph.frontend.tracking import TrackerConfig, track_images
from hvo_graph.geometry.camera import CameraModel
from hvo_graph.types import FrameObservations, Plane

DATA = Path(__file__).resolve().parents[1] / "data" / "real" / "opencv"
VIEWS = [f"left{i:02d}.jpg" for i in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)]
TARGET = "chessboard:9x6:0.025"
#: Denser corners than the tracker's default: the board covers a fifth of some views.
PAIR_TRACKER = TrackerConfig(max_features=400, min_distance=5.0, ransac_threshold_px=0.5)


def read_matrix(path: Path, key: str) -> np.ndarray:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return np.asarray(storage.getNode(key).mat(), dtype=float)
    finally:
        storage.release()


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def board_references(camera: CameraModel) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per view: corners (54, 2), R_cb, t_cb from cv2.solvePnP (iterative)."""
    objects = np.zeros((54, 3))
    objects[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 1e-3)
    out = {}
    for name in VIEWS:
        gray = cv2.imread(str(DATA / name), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(gray, (9, 6))
        if not found:
            raise SystemExit(f"real_views: no chessboard in {name}")
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
        _, rvec, tvec = cv2.solvePnP(objects, corners, camera.K, camera.distortion)
        out[name] = (corners.reshape(-1, 2), cv2.Rodrigues(rvec)[0], tvec.ravel())
    return out


def plane_of(R: np.ndarray, t: np.ndarray) -> Plane:
    n = R[:, 2]
    return Plane(float(n @ t), n) if n @ t > 0 else Plane(float(-n @ t), -n)


def pair_errors(camera, refs) -> dict[str, np.ndarray]:
    """(156, 2) rotation error (deg) and position error (fraction of d*) per source."""
    spec = parse_target(TARGET)
    images = {name: cv2.imread(str(DATA / name), cv2.IMREAD_GRAYSCALE) for name in VIEWS}
    ids = np.arange(54)
    out: dict[str, list] = {"board corners": [], "images path": []}
    for a, b in itertools.permutations(VIEWS, 2):
        (uv_a, R_a, t_a), (uv_b, R_b, t_b) = refs[a], refs[b]
        plane = plane_of(R_a, t_a)
        R_ab = R_a @ R_b.T
        p_ab = t_a - R_ab @ t_b
        corners = [FrameObservations(0, 0.0, ids, uv_a), FrameObservations(1, 1.0, ids, uv_b)]
        tracked = track_images([images[a], images[b]], [0.0, 1.0], camera, PAIR_TRACKER, spec)
        for source, tracks, sigma in (("board corners", corners, 0.2),
                                      ("images path", tracked, 0.3)):  # fmt: skip
            pose = measure_sequence(tracks, camera, plane, pixel_sigma=sigma)[1].pose
            if pose is None:
                out[source].append((np.inf, np.inf))
                continue
            out[source].append((angle_deg(pose.rotation.T @ R_ab),
                                np.linalg.norm(pose.position - p_ab) / plane.distance))  # fmt: skip
    return {k: np.array(v) for k, v in out.items()}


def sequence_errors(refs) -> np.ndarray:
    """(13, 2) per view: rotation error (deg), position error (fraction of d*)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "views"
        folder.mkdir()
        for name in VIEWS:
            shutil.copy(DATA / name, folder / name)
        out = Path(tmp) / "est"
        code = cli_main(["estimate", "--camera", str(DATA / "left_intrinsics.yml"),
                         "--images", str(folder), "--fps", "1", "--plane", "auto",
                         "--target", TARGET, "--method", "measurements",
                         "--out", str(out)])  # fmt: skip
        if code != 0:
            raise SystemExit("real_views: estimate failed")
        rows = np.loadtxt(out / "trajectory.txt")
    _, R_0, t_0 = refs[VIEWS[0]]
    d = plane_of(R_0, t_0).distance
    errors = []
    for name, row in zip(VIEWS, rows, strict=True):
        _, R_k, t_k = refs[name]
        R_0k = R_0 @ R_k.T
        qx, qy, qz, qw = row[4:8]
        R_est = gtsam.Rot3.Quaternion(qw, qx, qy, qz).matrix()
        errors.append(
            (angle_deg(R_est.T @ R_0k), np.linalg.norm(row[1:4] - (t_0 - R_0k @ t_k)) / d)
        )
    return np.array(errors)


def graf_transfer() -> tuple[int, float]:
    a, b = cv2.imread(str(DATA / "graf1.png")), cv2.imread(str(DATA / "graf3.png"))
    H = read_matrix(DATA / "H1to3p.xml", "H13")
    h, w = a.shape[:2]
    first, second = track_images([a, b], [0.0, 1.0], CameraModel(w, w, w / 2, h / 2, w, h))
    _, ia, ib = np.intersect1d(first.ids, second.ids, return_indices=True)
    moved = cv2.perspectiveTransform(first.uv[ia].reshape(-1, 1, 2), H).reshape(-1, 2)
    return len(ia), float(np.linalg.norm(moved - second.uv[ib], axis=1).mean())


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=Path("out/real_views"))
    args = parser.parse_args(argv)
    if not (DATA / "H1to3p.xml").exists():
        print("real_views: OpenCV's sample images are absent; run `make realdata`", file=sys.stderr)
        return 2
    K = read_matrix(DATA / "left_intrinsics.yml", "camera_matrix")
    dist = read_matrix(DATA / "left_intrinsics.yml", "distortion_coefficients").ravel()
    camera = CameraModel(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480, dist)
    refs = board_references(camera)
    lines = ["# The images path on real photographs (OpenCV's sample data)", "",
             "Command: `make realdata && python experiments/real_views.py`", "",
             "| test | n | rotation error, deg (median / max) "
             "| position error, % of d* (median / max) |",
             "|---|---|---|---|"]  # fmt: skip
    rows = [(f"pairs, {k}", v) for k, v in pair_errors(camera, refs).items()]
    rows.append(
        (f"{len(VIEWS)} views as one sequence (estimate --plane auto)", sequence_errors(refs))
    )
    for title, e in rows:
        lines.append(f"| {title} | {len(e)} | {np.median(e[:, 0]):.3f} / {e[:, 0].max():.3f} | "
                     f"{100 * np.median(e[:, 1]):.3f} / {100 * e[:, 1].max():.3f} |")  # fmt: skip
    count, transfer = graf_transfer()
    lines += ["", f"graf1 -> graf3 through the images path: {count} tracks, mean transfer "
              f"error under H1to3p.xml {transfer:.3f} px."]  # fmt: skip
    page = "\n".join(lines) + "\n"
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / "real_views.md").write_text(page)
    print(page, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
