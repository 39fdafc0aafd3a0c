"""The column-by-column stores of the command line's path give back exactly what went in.

MeasurementTable is checked against the records the front end makes (the list of
``process_all`` and ``process`` frame by frame are the reference): every field equal bit
for bit and of the same type, over several sealed blocks, with records it must keep as
given (keyframe-relative poses, hand-made records). TrackTable is checked against
``read_tracks``; the written files against their own readers across a piece boundary.
"""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pytest

from hvo_graph import measurement_table
from hvo_graph.frontend import FrontEndConfig, MeasurementFrontEnd
from hvo_graph.frontend.health import front_end_health
from hvo_graph.io.tracks import read_track_table, read_tracks, write_tracks
from hvo_graph.io.trajectory import read_estimate_dir, write_estimate_dir
from hvo_graph.measurement_table import MeasurementTable, frame_columns
from hvo_graph.sim import paper_scenario, simulate
from hvo_graph.types import FrameMeasurement, FrameObservations, PoseMeasurement, Trajectory


def _identical(a: object, b: object, path: str) -> None:
    assert type(a) is type(b), f"{path}: {type(a)} vs {type(b)}"
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _identical(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, list):
        assert len(a) == len(b), path  # type: ignore[arg-type]
        for i, (x, y) in enumerate(zip(a, b, strict=True)):  # type: ignore[call-overload]
            _identical(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray)
        assert (a.dtype, a.shape) == (b.dtype, b.shape), path
        assert a.tobytes() == b.tobytes(), path
    else:
        assert a == b, path


def _renamed(observations: list[FrameObservations]) -> list[FrameObservations]:
    """Tracks lost and found under new ids (keyframes), a stretch with too few points."""
    out = []
    for o in observations:
        ids, uv = np.asarray(o.ids), np.asarray(o.uv, dtype=float)
        ids = ids + 100 * (((ids < 10) & (o.index >= 150)) | ((ids < 18) & (o.index >= 200)))
        order = np.argsort(ids)
        ids, uv = ids[order], uv[order]
        if 100 <= o.index < 103:
            ids, uv = ids[:3], uv[:3]
        out.append(FrameObservations(o.index, o.t, ids, uv))
    return out


@pytest.fixture
def small_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(measurement_table, "BLOCK_FRAMES", 64)


@pytest.mark.parametrize(("points", "renamed"), [(4, False), (20, True)])
def test_table_gives_back_every_record_bit_for_bit(small_blocks, points, renamed) -> None:
    scenario = simulate(paper_scenario(noisy=True, seed=5, duration=10.0, num_points=points))
    observations = list(scenario.observations)
    if renamed:
        observations = _renamed(observations)
    config = FrontEndConfig(pixel_sigma=scenario.pixel_sigma, keyframe_min_points=12)
    one = MeasurementFrontEnd(scenario.camera, scenario.plane, config)
    single = [one.process(o) for o in observations]  # records of the per-frame path too
    listed = MeasurementFrontEnd(scenario.camera, scenario.plane, config).process_all(observations)
    table = MeasurementFrontEnd(scenario.camera, scenario.plane, config).process_table(observations)
    assert isinstance(table, MeasurementTable) and len(table) == len(listed) == 301
    for k, (a, b) in enumerate(zip(listed, table, strict=True)):
        _identical(a, b, f"frame {k}")
    for k in (0, 63, 64, 200, -1, -301):
        _identical(listed[k], table[k], f"table[{k}]")
    _identical(listed[5:9], table[5:9], "table[5:9]")
    stored = MeasurementTable(single)
    for k, (a, b) in enumerate(zip(single, stored, strict=True)):
        _identical(a, b, f"process() frame {k}")
    with pytest.raises(IndexError):
        table[301]
    if renamed:  # keyframe-relative poses are kept as given
        assert any(f.pose is not None and f.pose.reference != 0 for f in table)


def test_columns_and_health_of_a_table_are_those_of_its_records(small_blocks) -> None:
    scenario = simulate(paper_scenario(noisy=True, seed=2, duration=10.0, num_points=20))
    observations = _renamed(list(scenario.observations))
    config = FrontEndConfig(pixel_sigma=scenario.pixel_sigma, keyframe_min_points=12)
    listed = MeasurementFrontEnd(scenario.camera, scenario.plane, config).process_all(observations)
    table = MeasurementTable(listed)
    a, b = frame_columns(listed), frame_columns(table)
    for f in dataclasses.fields(a):
        assert np.array_equal(getattr(a, f.name), getattr(b, f.name)), f.name
    assert not b.has_pose.all() and set(b.references.tolist()) - {-1, 0}  # gaps, keyframes
    assert front_end_health(table) == front_end_health(listed)


def test_records_of_another_form_are_kept_as_given() -> None:
    odd = FrameMeasurement(
        3,
        0.1,
        PoseMeasurement(np.eye(3, dtype=np.float32), np.zeros(3), np.eye(6)),
        num_points=4,
    )
    plain = FrameMeasurement(4, 0.2, None, None, 5, 1)
    table = MeasurementTable([odd, plain] * 40)
    assert table[0] is odd and table[78] is odd
    _identical(table[79], plain, "plain")
    assert table.num_rejected.tolist() == [0, 1] * 40
    assert table.references.tolist() == [0, -1] * 40
    with pytest.raises(TypeError, match="FrameMeasurement"):
        table.append("frame")  # type: ignore[arg-type]


def test_a_table_holds_under_half_the_memory_of_the_records() -> None:
    scenario = simulate(paper_scenario(noisy=True, seed=1, duration=100.0))
    front = MeasurementFrontEnd(scenario.camera, scenario.plane)
    observations = list(scenario.observations)

    def held(make) -> int:
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            kept = make()
            return tracemalloc.get_traced_memory()[0] - before + 0 * len(kept)
        finally:
            tracemalloc.stop()

    listed = held(lambda: front.process_all(observations))
    front = MeasurementFrontEnd(scenario.camera, scenario.plane)
    table = held(lambda: front.process_table(observations))
    assert table < 0.5 * listed


def test_track_table_frames_are_those_of_read_tracks(tmp_path) -> None:
    rng = np.random.default_rng(0)
    frames = [
        FrameObservations(
            i,
            0.5 * i,
            np.sort(rng.choice(50, 3 + i % 4, replace=False)),
            rng.normal(300.0, 50.0, (3 + i % 4, 2)),
        )
        for i in range(0, 40, 3)
    ]
    path = tmp_path / "tracks.csv"
    write_tracks(path, frames)
    listed, table = read_tracks(path), read_track_table(path)
    assert len(table) == len(listed) == len(frames)
    for k in range(-len(table), len(table)):
        _identical(listed[k], table[k], f"frame {k}")
    _identical(listed[2:5], table[2:5], "slice")
    assert table[4].uv.flags.owndata  # a frame's arrays are its own
    with pytest.raises(IndexError):
        table[len(frames)]


def test_long_outputs_written_in_pieces_read_back_exactly(tmp_path) -> None:
    rng = np.random.default_rng(1)
    k = 9000  # more than two pieces
    q = rng.normal(size=(k, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    from scipy.spatial.transform import Rotation

    trajectory = Trajectory(
        t=np.arange(k) / 30.0,
        rotations=Rotation.from_quat(q).as_matrix(),
        positions=rng.normal(size=(k, 3)),
        twists=rng.normal(size=(k, 6)),
        covariances=np.tile(np.eye(12), (k, 1, 1)) * rng.uniform(1, 2, (k, 1, 1)),
    )
    write_estimate_dir(tmp_path, trajectory)
    back = read_estimate_dir(tmp_path)
    assert np.array_equal(back.t, trajectory.t)
    assert np.array_equal(back.positions, trajectory.positions)
    assert np.array_equal(back.twists, trajectory.twists)
    assert np.array_equal(back.covariances, trajectory.covariances)
    assert np.allclose(back.rotations, trajectory.rotations, atol=1e-12)
    lines = (tmp_path / "velocity.csv").read_text().splitlines()
    assert len(lines) == k + 1 and lines[0] == "t,vx,vy,vz,wx,wy,wz"


def test_iterating_gives_sealed_and_open_records_in_order(small_blocks) -> None:
    scenario = simulate(paper_scenario(noisy=True, seed=4, duration=5.0))
    config = FrontEndConfig(pixel_sigma=scenario.pixel_sigma)
    listed = MeasurementFrontEnd(scenario.camera, scenario.plane, config).process_all(
        list(scenario.observations)
    )
    table = MeasurementTable(listed[:130])  # two sealed blocks of 64, one of 2
    table.extend(listed[130:])  # 21 records still open (BLOCK_FRAMES = 64)
    assert len(table._open) == 21
    for k, (a, b) in enumerate(zip(listed, table, strict=True)):
        _identical(a, b, f"frame {k}")
    assert [f.index for f in table] == [f.index for f in listed]
