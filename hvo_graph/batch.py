"""Many sequences through :func:`~hvo_graph.pipeline.run_estimate`, locally or on a Dask cluster.

The library side of ``hvo-graph batch`` (docs/batch.md). A *sequence* is a folder
holding a camera file ``camera.yaml`` and either ``tracks.csv`` or an ``images/``
folder (the layout ``hvo-graph simulate`` writes); when it also holds
``groundtruth.txt`` the estimate is evaluated against it. Each sequence's output
goes to ``OUT/<sequence name>/``: the ``estimate`` files (``trajectory.txt``,
``velocity.csv``, ``covariance.csv`` with covariances), ``evaluation.json`` where
ground truth exists, and ``run.json`` last.

Reliability rules:

- An output folder appears whole or not at all: it is written under a hidden
  name in ``OUT`` and renamed into place (one ``os.rename``) when complete.
- A sequence that fails (bad file, estimator failure) is reported in its
  :class:`SequenceOutcome` and the others go on.
- A rerun skips every sequence whose output folder exists (it is complete by
  the rule above) and redoes the rest.
- Each sequence is a deterministic function of its files and options, so the
  outputs are identical wherever they ran (this process, local processes, Dask).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import as_completed
from dataclasses import dataclass, field
from pathlib import Path

from hvo_graph.errors import InputError
from hvo_graph.io.trajectory import write_estimate_dir, write_run_record
from hvo_graph.parallel import check_scheduler, executor, resolve_workers
from hvo_graph.pipeline import run_estimate
from hvo_graph.report.progress import ProgressBar

#: The files that make a folder a sequence: the camera, and tracks or images.
CAMERA_FILE = "camera.yaml"
TRACKS_FILE = "tracks.csv"
IMAGES_FOLDER = "images"
GROUNDTRUTH_FILE = "groundtruth.txt"
#: Written in each output folder when the sequence has ground truth.
EVALUATION_FILE = "evaluation.json"


@dataclass(frozen=True)
class SequenceJob:
    """One sequence folder to run.

    Attributes:
        name: the output folder's name (the sequence folder's own name).
        directory: the sequence folder.
        source: its ``tracks.csv`` or ``images/`` folder.
        groundtruth: whether it holds ``groundtruth.txt`` (then it is evaluated).
    """

    name: str
    directory: Path
    source: Path
    groundtruth: bool = False

    @property
    def images(self) -> bool:
        """True for an image folder, False for tracks."""
        return self.source.name == IMAGES_FOLDER


@dataclass
class SequenceOutcome:
    """What happened to one sequence.

    Attributes:
        name: the sequence's name.
        status: "done", "skipped" (its output existed) or "failed".
        message: why it failed ("" otherwise).
        seconds: wall time of the run (0 when skipped).
        evaluation: errors against ground truth (``ErrorSummary.as_dict``), if any.
    """

    name: str
    status: str
    message: str = ""
    seconds: float = 0.0
    evaluation: dict[str, object] = field(default_factory=dict)


def _as_sequence(directory: Path) -> SequenceJob | None:
    if not (directory / CAMERA_FILE).is_file():
        return None
    for source in (directory / TRACKS_FILE, directory / IMAGES_FOLDER):
        if source.exists():
            truth = (directory / GROUNDTRUTH_FILE).is_file()
            return SequenceJob(directory.resolve().name, directory, source, truth)
    return None


def find_sequences(paths: Sequence[str | os.PathLike]) -> list[SequenceJob]:
    """The sequences of ``paths``: each a sequence folder, or a folder of them (its
    subfolders that are sequences, sorted by name).

    Raises:
        InputError: a path that is no folder, a folder with no sequence in it, or two
            sequences with the same name (their outputs would collide).
    """
    if not paths:
        raise InputError("SEQUENCE_DIR: expected at least one folder")
    jobs: list[SequenceJob] = []
    for path in map(Path, paths):
        if not path.is_dir():
            raise InputError(f"{path}: expected a sequence folder or a folder of them")
        job = _as_sequence(path)
        found = [job] if job else [j for d in sorted(path.iterdir()) if (j := _as_sequence(d))]
        if not found:
            raise InputError(
                f"{path}: expected {CAMERA_FILE} with {TRACKS_FILE} or {IMAGES_FOLDER}/, "
                "here or in its subfolders"
            )
        jobs += found
    seen: dict[str, Path] = {}
    for job in jobs:
        if job.name in seen:
            raise InputError(
                f"{job.directory}: same sequence name as {seen[job.name]} (outputs would collide)"
            )
        seen[job.name] = job.directory
    return jobs


def _software() -> str:
    from importlib.metadata import PackageNotFoundError, version

    from hvo_graph.report.tables import software_versions

    try:
        own = version("hvo-graph")
    except PackageNotFoundError:
        own = "unknown"
    return f"hvo-graph {own}, {software_versions()}"


def _estimate_into(
    job: SequenceJob,
    stage: Path,
    method: str,
    options: dict[str, object],
    skip: float | None,
) -> dict[str, object]:
    """Run one sequence, writing its files into ``stage``; returns the evaluation."""
    from hvo_graph.eval.metrics import error_series, summarize
    from hvo_graph.io.config import load_scene
    from hvo_graph.io.tracks import read_tracks
    from hvo_graph.io.trajectory import read_estimate_dir, read_groundtruth_dir

    scene = load_scene(job.directory / CAMERA_FILE)
    if job.images:
        from hvo_graph.frontend.tracking import tracks_from_images

        observations = tracks_from_images(job.source, scene.camera)
    else:
        observations = read_tracks(job.source)
    run = run_estimate(observations, scene, method=method, **options)
    write_estimate_dir(stage, run.trajectory)
    evaluation: dict[str, object] = {}
    if job.groundtruth:
        truth = read_groundtruth_dir(job.directory)
        t_start = None if skip is None else float(truth.t[0]) + skip
        # The files as written, as ``hvo-graph evaluate`` would read them.
        written = read_estimate_dir(stage)
        evaluation = summarize(error_series(written, truth), t_start=t_start).as_dict()
        text = json.dumps(evaluation, indent=2, sort_keys=True) + "\n"
        (stage / EVALUATION_FILE).write_text(text, encoding="utf-8")
    record = {
        "command": "batch",
        **run.summary(),
        "inputs": {"sequence": str(job.directory), "source": job.source.name},
        "software": _software(),
    }
    write_run_record(stage, record)
    return evaluation


def run_sequence(
    job: SequenceJob,
    out: str | os.PathLike,
    method: str = "smoother",
    options: Mapping[str, object] | None = None,
    *,
    skip: float | None = None,
) -> SequenceOutcome:
    """Estimate one sequence into ``out/<name>/`` (see the module's rules); never raises
    for a bad sequence: the failure is the outcome's ``message``.

    Args:
        job: the sequence.
        out: the batch's output folder (created).
        method: ``--method``.
        options: library options of :func:`~hvo_graph.pipeline.estimate`.
        skip: evaluation leaves out the first ``skip`` seconds of ground truth.
    """
    out = Path(out)
    target = out / job.name
    if target.is_dir():
        done = target / EVALUATION_FILE
        evaluation = json.loads(done.read_text(encoding="utf-8")) if done.is_file() else {}
        return SequenceOutcome(job.name, "skipped", evaluation=evaluation)
    out.mkdir(parents=True, exist_ok=True)
    # os.mkdir, not tempfile.mkdtemp: the folder becomes the output, so it gets the
    # permissions of a plain mkdir (umask), not mkdtemp's private 0700.
    stage = out / f".{job.name}.partial-{secrets.token_hex(4)}"
    stage.mkdir()
    start = time.perf_counter()
    try:
        evaluation = _estimate_into(job, stage, method, dict(options or {}), skip)
        os.rename(stage, target)
    except InputError as exc:
        return SequenceOutcome(job.name, "failed", str(exc))
    except Exception as exc:  # one bad sequence must not stop the batch: report it
        return SequenceOutcome(job.name, "failed", f"{type(exc).__name__}: {exc}")
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return SequenceOutcome(
        job.name, "done", seconds=time.perf_counter() - start, evaluation=evaluation
    )


def run_batch(
    jobs: Sequence[SequenceJob],
    out: str | os.PathLike,
    method: str = "smoother",
    options: Mapping[str, object] | None = None,
    *,
    image_options: Mapping[str, object] | None = None,
    skip: float | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> list[SequenceOutcome]:
    """:func:`run_sequence` for every job, over local processes or a Dask cluster.

    Args:
        jobs: from :func:`find_sequences`.
        out: output folder; each sequence writes ``out/<name>/``.
        method: ``--method``.
        options: library options for every sequence.
        image_options: defaults added for image sequences (options given win).
        skip: seconds of ground truth left out of the evaluation.
        workers: local processes (1: this process; None: ``os.cpu_count()``); not with
            ``scheduler``.
        scheduler: a Dask scheduler's address, ``tcp://HOST:PORT``.
        progress: a progress bar on stderr.
    Returns:
        One outcome per job, in the jobs' order.
    """
    scheduler = check_scheduler(scheduler, workers)
    workers = resolve_workers(workers)
    jobs = list(jobs)
    Path(out).mkdir(parents=True, exist_ok=True)
    args = [
        (job, Path(out).resolve(), method, {**(image_options or {}), **(options or {})})
        if job.images
        else (job, Path(out).resolve(), method, dict(options or {}))
        for job in jobs
    ]
    outcomes: list[SequenceOutcome | None] = [None] * len(jobs)
    with ProgressBar(len(jobs), label="sequences", enabled=progress) as bar:
        if scheduler is None and (workers == 1 or len(jobs) <= 1):
            for i, a in enumerate(args):
                outcomes[i] = run_sequence(*a, skip=skip)
                bar.update()
        else:
            with executor(min(workers, max(len(jobs), 1)), scheduler) as pool:
                futures = {pool.submit(run_sequence, *a, skip=skip): i for i, a in enumerate(args)}
                for future in as_completed(futures):
                    i = futures[future]
                    error = future.exception()
                    outcomes[i] = (
                        future.result()
                        if error is None
                        else SequenceOutcome(
                            jobs[i].name, "failed", f"{type(error).__name__}: {error}"
                        )
                    )
                    bar.update()
    return [o for o in outcomes if o is not None]
