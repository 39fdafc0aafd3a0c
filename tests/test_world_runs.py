"""The offline smoother's runs of world-posed frames, added in bulk (estimators._world_runs):
the same store, initial values, bookkeeping and trajectory as one update per frame."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from hvo_graph import measurement_table
from hvo_graph.errors import InputError
from hvo_graph.estimators import _world_runs
from hvo_graph.estimators.smoother import FactorGraphSmoother
from hvo_graph.frontend import measure_sequence
from hvo_graph.measurement_table import MeasurementTable
from hvo_graph.sim.families import draw
from hvo_graph.types import FrameMeasurement


def state(smoother: FactorGraphSmoother) -> dict:
    """Everything a run leaves behind that the final solve or a later update reads."""
    store, log = smoother.backend.store, smoother._online
    initial = getattr(smoother.backend, "initial", gtsam.Values())  # none: fixed-lag
    return {
        "index": store._index.view().copy(),
        "motion": store._motion.view().copy(),
        "prior": store._prior.view().copy(),
        "other": len(store._other),
        "initial": {
            key: initial.atPose3(key).matrix()
            if gtsam.Symbol(key).chr() == ord("x")
            else np.asarray(initial.atVector(key))
            for key in initial.keys()
        },
        "counts": dict(smoother.velocity_factor_counts),
        "reference_cov": np.array(smoother._reference_cov),
        "log": (log._index[: len(log)].copy(), log._values[: len(log)].copy()),
        "last": (smoother._indices[-1], smoother._times[-1], smoother._last_reference),
        "pose": smoother._pose.matrix(),
        "twist": np.asarray(smoother._twist),
    }


def equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        if name == "initial":
            assert a[name].keys() == b[name].keys()
            for key in a[name]:
                assert np.array_equal(a[name][key], b[name][key]), (name, key)
        elif name == "log":
            assert all(np.array_equal(x, y) for x, y in zip(a[name], b[name], strict=True))
        else:
            assert (
                np.array_equal(a[name], b[name])
                if isinstance(a[name], np.ndarray)
                else (a[name] == b[name])
            ), name


def assert_same_run(runs: tuple, each: tuple, frames, *, expect_runs: str) -> None:
    """Runs (smoother, trajectory, frames added in runs) against one update per frame:
    the frames added in runs (``expect_runs``: "none", "some" or "all but the first"),
    the same state and trajectory to the last bit."""
    added, none = runs[2], each[2]
    assert none == 0
    if expect_runs == "none":
        assert added == 0
    elif expect_runs == "some":
        assert 0 < added < len(frames) - 1
    else:
        assert added == len(frames) - 1
    equal(state(runs[0]), state(each[0]))
    for field in ("t", "rotations", "positions", "twists"):
        assert np.array_equal(getattr(runs[1], field), getattr(each[1], field))


def offline(frames, monkeypatch, bulk: bool, **options):
    """(smoother, trajectory, frames added in bulk) of run(frames, online=False); not
    ``bulk``: one update per frame."""
    added: list[int] = []
    apply = _world_runs._apply

    def counted(smoother, run):
        added.append(apply(smoother, run))
        return added[-1]

    monkeypatch.setattr(_world_runs, "_apply", counted)
    if not bulk:
        real = _world_runs._eligible

        def none_eligible(smoother, rows):
            eligible, factor = real(smoother, rows)
            return np.zeros_like(eligible), factor

        monkeypatch.setattr(_world_runs, "_eligible", none_eligible)
        frames = list(frames)
    smoother = FactorGraphSmoother(**options)
    trajectory = smoother.run(frames, online=False)
    monkeypatch.undo()
    return smoother, trajectory, sum(added)


def as_container(frames: list, container: str) -> list | MeasurementTable:
    if container == "list":
        return frames
    if container == "table":
        return MeasurementTable(frames)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(measurement_table, "BLOCK_FRAMES", 64)
        table = MeasurementTable()
        table.extend(frames)  # blocks of 64 frames stored, the rest left open
    assert 0 < table.sealed_blocks()[-1][1] < len(table)
    return table


def family_frames(family: str, seed: int) -> list[FrameMeasurement]:
    scenario = draw(family, seed).scenario
    return measure_sequence(
        scenario.observations, scenario.camera, scenario.plane, pixel_sigma=scenario.pixel_sigma
    )


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"shared_reference_noise": False},
        {"motion_model": "wnj", "acceleration_sigma": (0.1, 0.1)},
        {"velocity_factors": "all"},
    ],
    ids=["default", "no-split", "wnj", "all-twists"],
)
@pytest.mark.parametrize("data", ["paper", "traverse", "outliers-dropouts"])
@pytest.mark.parametrize("container", ["list", "table", "open-table"])
def test_runs_in_bulk_leave_what_updates_leave(container, data, options, noisy_run, monkeypatch):
    # A list's runs come from its records; a table's straight from its arrays, block by
    # block (its open records, not yet stored as arrays, through their records).
    frames = noisy_run[1] if data == "paper" else family_frames(data, 1)
    frames = as_container(frames, container)
    bulk = offline(frames, monkeypatch, True, **options)
    each = offline(frames, monkeypatch, False, **options)
    # Every frame posed against the world after the first goes in bulk (dropped frames
    # included), unless it has a twist that becomes a factor ("all"); the traverse's
    # keyframe poses go one by one.
    expect = "some" if data == "traverse" else "all but the first"
    expect = "none" if options.get("velocity_factors") == "all" else expect
    assert_same_run(bulk, each, frames, expect_runs=expect)


@pytest.mark.parametrize("field", ["t", "index"])
@pytest.mark.parametrize("container", ["list", "table"])
def test_a_frame_out_of_order_inside_a_run_fails_as_its_update_does(
    container, field, noisy_run, monkeypatch
):
    frames = list(noisy_run[1][:80])
    # Without its twist: only the time (or the index) tells that it is out of order.
    late = {"t": frames[49].t} if field == "t" else {"index": 49}
    frames[50] = dataclasses.replace(frames[50], velocity=None, **late)
    k, t = frames[50].index, frames[50].t
    message = (
        rf"^frame {k} \(t={t}\) does not follow frame 49 \(t={frames[49].t}\): "
        "frames must arrive in increasing order$"
    )
    added: list[int] = []
    apply = _world_runs._apply
    monkeypatch.setattr(
        _world_runs, "_apply", lambda *args: added.append(apply(*args)) or added[-1]
    )
    smoother = FactorGraphSmoother()
    with pytest.raises(InputError, match=message):
        smoother.run(as_container(frames, container), online=False)
    assert sum(added) == 49  # frames 1-49 in bulk: frame 50 failed in its own update
    assert smoother._indices == list(range(50))


def test_no_bulk_while_streamed_refits_are_due(noisy_run):
    # Frames streamed first ("auto": refits after 30, 60, ... frames) refit on what comes
    # next, frame by frame: the smoother takes no runs then; with fixed values it does.
    for sigma, takes_runs in (("auto", False), ((0.05, 0.05), True)):
        smoother = FactorGraphSmoother(acceleration_sigma=sigma)
        for frame in noisy_run[1][:10]:
            smoother.update(frame)
        assert smoother.process_noise.refits is not takes_runs
        assert _world_runs._applies(smoother) is takes_runs


def test_records_of_other_types_take_their_own_update(noisy_run, monkeypatch):
    # A time that is a numpy float, an index that is a numpy int: the update converts
    # them; a run does not take them (nor the frame after, judged against them).
    frames = list(noisy_run[1][:60])
    frames[20] = dataclasses.replace(frames[20], t=np.float64(frames[20].t))
    frames[40] = dataclasses.replace(frames[40], index=np.int64(40))
    bulk, bulk_trajectory, added = offline(frames, monkeypatch, True)
    each, each_trajectory, _ = offline(frames, monkeypatch, False)
    assert added == len(frames) - 1 - 4  # the first frame, 20, 21, 40 and 41 one by one
    equal(state(bulk), state(each))
    assert np.array_equal(bulk_trajectory.positions, each_trajectory.positions)


def windowed_run(frames, monkeypatch, bulk: bool, online: bool, **options):
    """(smoother, trajectory, frames added in runs) of run(frames, online=online) with a
    back end that updates per frame; not ``bulk``: no runs (every frame screened, checked
    and updated on its own)."""
    added: list[int] = []
    update_each = _world_runs._update_each
    monkeypatch.setattr(
        _world_runs, "_update_each", lambda *args: added.append(update_each(*args)) or added[-1]
    )
    if not bulk:
        monkeypatch.setattr(_world_runs, "_applies", lambda smoother: False)
    smoother = FactorGraphSmoother(**options)
    trajectory = smoother.run(frames, online=online)
    monkeypatch.undo()
    return smoother, trajectory, sum(added)


@pytest.mark.parametrize(
    ("solver", "online", "options"),
    [
        ("fixed-lag", False, {}),
        ("fixed-lag", False, {"motion_model": "wnj", "acceleration_sigma": (0.1, 0.1)}),
        ("fixed-lag", False, {"shared_reference_noise": False}),
        ("isam2", True, {}),
        ("batch", False, {}),
    ],
    ids=["fixed-lag", "fixed-lag-wnj", "fixed-lag-no-split", "isam2-online", "batch"],
)
@pytest.mark.parametrize("data", ["paper", "traverse", "outliers-dropouts"])
@pytest.mark.parametrize("container", ["list", "table"])
def test_windowed_runs_update_each_frame_as_its_own_update_does(
    container, data, solver, online, options, noisy_run, monkeypatch
):
    # Runs of world-posed frames go to a windowed back end one update each, built without
    # the per-frame checks: the online log, the trajectory and what the next frame reads
    # equal those of one checked update per frame.
    frames = noisy_run[1] if data == "paper" else family_frames(data, 1)
    frames = as_container(frames, container)
    options = {"solver": solver, **options}
    runs = windowed_run(frames, monkeypatch, True, online, **options)
    each = windowed_run(frames, monkeypatch, False, online, **options)
    expect = "some" if data == "traverse" else "all but the first"
    assert_same_run(runs, each, frames, expect_runs=expect)


@pytest.mark.parametrize("solver", ["fixed-lag", "batch"])
def test_a_failing_update_inside_a_run_leaves_what_the_updates_leave(solver, noisy_run):
    # Should GTSAM raise on frame 50 (inside a run), the frames before it are estimated
    # and logged, frame 50 is in the bookkeeping but not the log: as with one update each.
    frames = list(noisy_run[1][:80])

    def failing(smoother: FactorGraphSmoother) -> FactorGraphSmoother:
        add = smoother.backend.add

        def add_until_50(graph, values, index, stamp_time):
            if index == 50:
                raise RuntimeError("indeterminant system")
            return add(graph, values, index, stamp_time)

        smoother.backend.add = add_until_50
        return smoother

    left = []
    for runs in (True, False):
        smoother = failing(FactorGraphSmoother(solver=solver, acceleration_sigma=(0.05, 0.05)))
        with pytest.MonkeyPatch.context() as patch:
            if not runs:
                patch.setattr(_world_runs, "_applies", lambda smoother: False)
            with pytest.raises(RuntimeError, match=r"^indeterminant system$"):
                smoother.run(frames)
        assert len(smoother._online) == 50 and smoother._indices[-1] == 50
        left.append(state(smoother))
    equal(*left)
