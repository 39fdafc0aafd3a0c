"""The command's conveniences: --version, the progress bar on a terminal, make help."""

from __future__ import annotations

import io
import os
import pty
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import cv2
from layouts import CAMERA, PLANE, render

from hvo_graph.cli import main
from hvo_graph.io.config import SceneConfig, save_scene
from hvo_graph.report.progress import ProgressBar

ROOT = Path(__file__).resolve().parents[1]


def test_version_prints_the_installed_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"hvo-graph {version('hvo_graph')}\n"


def test_progress_bar_shows_the_rate():
    stream = io.StringIO()
    now = [0.0]
    bar = ProgressBar(10, label="tracking", stream=stream, width=4, clock=lambda: now[0],
                      rate_unit="frames")  # fmt: skip
    now[0] = 4.0
    bar.update(10)  # ten frames in 4 s
    assert stream.getvalue().splitlines()[-1] == (
        "tracking [####] 10/10 100%  elapsed 0:04  ETA 0:00  2.5 frames/s"
    )


def run_estimate(tmp_path: Path, stderr_tty: bool) -> str:
    """Run ``hvo-graph estimate --images`` in a child process; its stderr, on a pseudo-terminal
    or a pipe."""
    folder = tmp_path / "seq"
    folder.mkdir(exist_ok=True)
    for k, image in enumerate(render()[:4]):
        assert cv2.imwrite(str(folder / f"{k}.png"), image)
    save_scene(tmp_path / "camera.yaml", SceneConfig(CAMERA, PLANE))
    command = [sys.executable, "-m", "hvo_graph", "estimate", "--camera"]
    command += [str(tmp_path / "camera.yaml"), "--images", str(folder), "--fps", "20"]
    command += ["--method", "measurements", "--out", str(tmp_path / "out")]
    if not stderr_tty:
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        return done.stderr
    master, slave = pty.openpty()
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=slave)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    assert child.wait() == 0
    os.close(master)
    return b"".join(chunks).decode()


def test_a_terminal_gets_a_progress_bar_and_a_pipe_gets_nothing(tmp_path):
    shown = run_estimate(tmp_path, stderr_tty=True)
    assert "tracking [" in shown and "4/4 100%" in shown
    assert re.search(r"\d+\.\d frames/s", shown)
    assert "\r" in shown  # redrawn in place
    piped = run_estimate(tmp_path, stderr_tty=False)
    assert "\r" not in piped and "tracking [" not in piped and "frames/s" not in piped
    # only the front end's one-line health report, which logs need too
    assert len(piped.splitlines()) == 1 and "front end:" in piped


def test_make_help_lists_every_target_with_a_line():
    makefile = (ROOT / "Makefile").read_text()
    phony = re.search(r"^\.PHONY:(.*)$", makefile, re.M).group(1).split()
    done = subprocess.run(["make", "-s", "-C", str(ROOT), "help"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    listed = [line.split()[1] for line in lines]
    assert sorted(listed) == sorted(phony)
    assert all(len(line.split(maxsplit=2)) == 3 for line in lines)  # each with a description
