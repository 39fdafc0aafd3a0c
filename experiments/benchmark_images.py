"""Images for experiments/benchmark.py: the images path beside a bare OpenCV loop.

A 640 x 480 sequence of the paper's plane (the paper's camera, plane and motion,
a seeded procedural texture, image noise of 2 gray levels:
:func:`hvo_graph.sim.render.render_plane_images`) is written as PNG files, as a
user's image folder is. On those files:

- **bare OpenCV loop**: decode (``cv2.imread``, gray), ``goodFeaturesToTrack``
  (200 corners, re-detected when fewer than 100 remain) and one
  ``calcOpticalFlowPyrLK`` per frame with the tracker's window and pyramid, nothing
  else: what OpenCV itself needs to track these images;
- **tracking**: :func:`hvo_graph.frontend.tracking.tracks_from_images` with its
  defaults (the same decode, detection and KLT, plus the forward-backward check,
  the border and outlier gates, re-identification of lost tracks and the
  keyframe re-alignment);
- **end to end**: ``hvo-graph estimate --images DIR --fps 30`` in a fresh process,
  for the measurements alone and for the default smoother: reading, tracking, the
  front end, the estimator and every output file.

Each is timed in wall and CPU seconds beside the bare loop. experiments/benchmark.py
runs it (``--image-frames``); alone, ``python experiments/benchmark_images.py
[--frames N] [--out FILE]`` prints (or writes) the table.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2

from hvo_graph.frontend.tracker_config import TrackerConfig
from hvo_graph.frontend.tracking import tracks_from_images
from hvo_graph.io.config import load_camera
from hvo_graph.report.tables import markdown_table, write_text_atomic
from hvo_graph.sim.render import render_plane_images
from hvo_graph.sim.scenario import paper_scenario, simulate, write_scenario

FPS = 30.0
#: Methods run end to end on the image folder.
IMAGE_METHODS: tuple[str, ...] = ("measurements", "smoother")
#: Gray levels of image noise (as experiments/images.py).
IMAGE_NOISE = 2.0


@dataclass
class ImageStage:
    """One way through the image folder: frames per second (wall), CPU seconds."""

    stage: str
    frames: int
    wall_s: float
    cpu_s: float
    returncode: int = 0


def write_image_folder(folder: Path, frames: int, seed: int) -> Path:
    """Render ``frames`` frames of the paper's scenario into ``folder``/images/*.png and
    write its camera.yaml (``hvo-graph simulate``'s folder); returns the image folder."""
    scenario = simulate(paper_scenario(noisy=True, seed=seed, duration=(frames - 1) / FPS))
    write_scenario(folder, scenario)
    truth = scenario.groundtruth
    poses = [(R, p) for R, p in zip(truth.rotations, truth.positions, strict=True)]
    images = render_plane_images(
        scenario.camera, scenario.plane, poses, noise_sigma=IMAGE_NOISE, seed=seed
    )
    image_dir = folder / "images"
    image_dir.mkdir()
    for k, image in enumerate(images):
        cv2.imwrite(str(image_dir / f"{k:06d}.png"), image)
    return image_dir


def bare_opencv(files: list[Path], config: TrackerConfig) -> int:
    """Decode, detect, track: the OpenCV calls alone; returns the points tracked last."""
    criteria = (
        cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
        config.lk_iterations,
        config.lk_epsilon,
    )
    window = (config.lk_window, config.lk_window)
    previous, points = None, None
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if previous is not None and points is not None and len(points):
            points, status, _ = cv2.calcOpticalFlowPyrLK(
                previous, image, points, None,
                winSize=window, maxLevel=config.lk_levels, criteria=criteria,
            )  # fmt: skip
            points = points[status.ravel() == 1]
        if points is None or len(points) < config.min_tracked:
            points = cv2.goodFeaturesToTrack(
                image,
                config.max_features,
                config.quality_level,
                config.min_distance,
                blockSize=config.block_size,
            )
        previous = image
    return 0 if points is None else len(points)


def _timed(stage: str, frames: int, run: object) -> ImageStage:
    wall, cpu = time.perf_counter(), time.process_time()
    run()  # type: ignore[operator]
    return ImageStage(stage, frames, time.perf_counter() - wall, time.process_time() - cpu)


def _cli(folder: Path, image_dir: Path, method: str, out: Path, frames: int) -> ImageStage:
    command = [sys.executable, "-m", "hvo_graph", "estimate", "--camera"]
    command += [str(folder / "camera.yaml"), "--images", str(image_dir), "--fps", f"{FPS:g}"]
    command += ["--method", method, "--out", str(out)]
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    if code != 0 and process.stderr is not None:
        print(process.stderr.read().decode(errors="replace")[-500:], file=sys.stderr)
    return ImageStage(
        f"`hvo-graph estimate --images --method {method}`",
        frames,
        wall,
        usage.ru_utime + usage.ru_stime,
        code,
    )


def image_stages(frames: int, seed: int) -> list[ImageStage]:
    """Every way through one rendered folder (module docstring), the bare loop first."""
    config = TrackerConfig()
    with tempfile.TemporaryDirectory(prefix="hvo_images_") as tmp:
        folder = Path(tmp) / "sequence"
        image_dir = write_image_folder(folder, frames, seed)
        files = sorted(image_dir.glob("*.png"))
        camera = load_camera(folder / "camera.yaml")[0]
        stages = [
            _timed(
                "bare OpenCV loop (decode, detect, KLT)", frames, lambda: bare_opencv(files, config)
            ),
            _timed(
                "tracking (`tracks_from_images`)",
                frames,
                lambda: tracks_from_images(image_dir, camera, fps=FPS, config=config),
            ),
        ]
        for method in IMAGE_METHODS:
            stages.append(_cli(folder, image_dir, method, Path(tmp) / method, frames))
    return stages


def images_section(stages: list[ImageStage]) -> str:
    """Markdown: each way through the images beside the bare OpenCV loop (wall time, and
    CPU time: on a shared machine the steadier of the two)."""
    bare, bare_cpu = stages[0].wall_s, stages[0].cpu_s
    rows = [
        [
            s.stage,
            f"{s.frames:,}",
            f"{s.wall_s:.2f}" if s.returncode == 0 else f"failed ({s.returncode})",
            f"{s.cpu_s:.2f}" if s.stage.startswith(("bare", "tracking")) else f"{s.cpu_s:.1f}",
            f"{s.frames / s.wall_s:,.0f}",
            f"{s.wall_s / bare:.2f}",
            f"{s.cpu_s / bare_cpu:.2f}",
        ]
        for s in stages
    ]
    header = ["stage", "frames", "wall [s]", "CPU [s]", "frames/s", "time / bare OpenCV"]
    return markdown_table([*header, "CPU / bare OpenCV"], rows)


def main(argv: list[str] | None = None) -> int:
    """The images section alone: ``python experiments/benchmark_images.py [--frames N]``
    prints its table (``--out FILE`` writes it there instead)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=450, help="rendered frames (default 450)")
    parser.add_argument("--seed", type=int, default=0, help="pixel-noise seed")
    parser.add_argument("--out", type=Path, help="markdown file to write (default: print)")
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error(f"--frames: expected an integer >= 2, got {args.frames}")
    text = images_section(image_stages(args.frames, args.seed)) + "\n"
    if args.out is None:
        print(text, end="")
    else:
        write_text_atomic(args.out, text)
    return 0


__all__ = [
    "ImageStage", "bare_opencv", "image_stages", "images_section", "main", "write_image_folder",
]  # fmt: skip

if __name__ == "__main__":
    sys.exit(main())
