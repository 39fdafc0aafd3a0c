"""``hvo-graph batch`` and the Monte Carlo seeds on a Dask cluster (a LocalCluster here):
a failed sequence is reported and the others go on, a rerun skips finished outputs, an
interrupted run leaves nothing half-written, and the numbers are the same wherever the
jobs ran."""

from __future__ import annotations

import json
from pathlib import Path

import distributed  # the [cluster] extra, in [test] too
import pytest

from hvo_graph.batch import find_sequences, run_batch, run_sequence
from hvo_graph.cli import main
from hvo_graph.errors import InputError
from hvo_graph.eval.metrics import error_series, summarize
from hvo_graph.io.trajectory import read_estimate_dir, read_groundtruth_dir
from hvo_graph.montecarlo import FamilySeed, run_seeds
from hvo_graph.parallel import check_scheduler
from hvo_graph.sim.scenario import paper_scenario, simulate, write_scenario

DATA_FILES = ("trajectory.txt", "velocity.csv", "covariance.csv", "evaluation.json", "run.json")


@pytest.fixture(scope="module")
def sequences(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of three sequences: two simulated ones and one with a broken tracks file."""
    root = tmp_path_factory.mktemp("sequences")
    for name, seed in (("alpha", 1), ("beta", 2)):
        write_scenario(root / name, simulate(paper_scenario(seed=seed, duration=1.5)))
    bad = root / "broken"
    bad.mkdir()
    (bad / "camera.yaml").write_text((root / "alpha" / "camera.yaml").read_text())
    (bad / "tracks.csv").write_text("frame,t,id,u,v\n0,0.0,1,10.0\n")
    (root / "notes").mkdir()  # not a sequence: ignored inside a parent folder
    return root


@pytest.fixture(scope="module")
def cluster():
    # In-process workers (threads), one task at a time each: quick to start in a test.
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as local:
        yield local.scheduler_address


def read_outputs(out: Path, name: str) -> dict[str, bytes]:
    return {f: (out / name / f).read_bytes() for f in DATA_FILES if (out / name / f).exists()}


def test_find_sequences_reads_a_parent_folder_and_rejects_collisions(sequences, tmp_path):
    jobs = find_sequences([sequences])
    assert [j.name for j in jobs] == ["alpha", "beta", "broken"]
    assert [j.groundtruth for j in jobs] == [True, True, False]
    assert [j.name for j in find_sequences([sequences / "beta"])] == ["beta"]
    with pytest.raises(InputError, match="same sequence name"):
        find_sequences([sequences, sequences / "alpha"])
    with pytest.raises(InputError, match=r"notes: expected camera.yaml with tracks.csv"):
        find_sequences([sequences / "notes"])
    with pytest.raises(InputError, match=r"missing: expected a sequence folder"):
        find_sequences([tmp_path / "missing"])


def test_batch_reports_a_failure_goes_on_and_reruns_only_what_is_missing(
    sequences, tmp_path, capsys
):
    out = tmp_path / "out"
    argv = ["batch", str(sequences), "--out", str(out), "--workers", "1", "--no-progress"]
    assert main(argv) == 1  # one sequence failed
    captured = capsys.readouterr()
    assert "broken: failed: " in captured.err and "tracks.csv:2: expected 5" in captured.err
    assert "3 sequences (smoother): 2 done, 0 skipped" in captured.out
    report = {r["sequence"]: r for r in json.loads((out / "batch.json").read_text())}
    assert [report[n]["status"] for n in ("alpha", "beta", "broken")] == ["done", "done", "failed"]
    assert sorted(p.name for p in out.iterdir()) == ["alpha", "batch.json", "beta"]  # no leftovers
    # the evaluation is evaluate's own, on the files written
    truth = read_groundtruth_dir(sequences / "alpha")
    expected = summarize(error_series(read_estimate_dir(out / "alpha"), truth)).as_dict()
    assert json.loads((out / "alpha" / "evaluation.json").read_text()) == expected
    assert report["alpha"]["position_m"] == expected["position_m"]

    # a rerun skips the finished sequences (their files untouched) and retries the failed one
    before = (out / "alpha" / "trajectory.txt").stat().st_mtime_ns
    assert main(argv) == 1
    assert "0 done, 2 skipped" in capsys.readouterr().out
    assert (out / "alpha" / "trajectory.txt").stat().st_mtime_ns == before
    report = {r["sequence"]: r for r in json.loads((out / "batch.json").read_text())}
    assert report["alpha"]["status"] == "skipped"
    assert report["alpha"]["position_m"] == expected["position_m"]


def test_batch_interrupted_while_writing_leaves_no_output(sequences, tmp_path, monkeypatch):
    import hvo_graph.batch

    def interrupted(directory, record):
        raise KeyboardInterrupt

    monkeypatch.setattr(hvo_graph.batch, "write_run_record", interrupted)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_sequence(find_sequences([sequences / "alpha"])[0], out)
    assert list(out.iterdir()) == []  # neither alpha/ nor its staging folder


def test_batch_on_a_dask_cluster_writes_the_same_bytes_as_locally(sequences, tmp_path, cluster):
    jobs = [j for j in find_sequences([sequences]) if j.name != "broken"]
    options = {"covariance": True}
    local = run_batch(jobs, tmp_path / "local", options=options, workers=1, progress=False)
    pool = run_batch(jobs, tmp_path / "pool", options=options, workers=2, progress=False)
    dask = run_batch(jobs, tmp_path / "dask", options=options, scheduler=cluster, progress=False)
    for outcomes in (local, pool, dask):
        assert [o.status for o in outcomes] == ["done", "done"]
    for job in jobs:
        reference = read_outputs(tmp_path / "local", job.name)
        assert set(reference) == set(DATA_FILES)
        assert read_outputs(tmp_path / "pool", job.name) == reference
        assert read_outputs(tmp_path / "dask", job.name) == reference


def test_a_failed_sequence_on_dask_is_reported_and_the_others_finish(sequences, tmp_path, cluster):
    outcomes = run_batch(find_sequences([sequences]), tmp_path, scheduler=cluster, progress=False)
    assert [(o.name, o.status) for o in outcomes] == [
        ("alpha", "done"),
        ("beta", "done"),
        ("broken", "failed"),
    ]
    assert "tracks.csv:2" in outcomes[2].message


def test_monte_carlo_seeds_on_dask_equal_the_local_run(cluster):
    configs = [paper_scenario(seed=s, duration=1.5) for s in (4, 5)]
    methods = ["kalman", "smoother", "smoother-online"]
    local = run_seeds(configs, methods, workers=1, progress=False, keep_series=False)
    dask = run_seeds(configs, methods, progress=False, keep_series=False, scheduler=cluster)
    assert [r.seed for r in dask] == [4, 5]
    assert [r.summaries for r in dask] == [r.summaries for r in local]
    draws = [FamilySeed("hover", 3, duration=2.0)]
    assert (
        run_seeds(draws, ["smoother"], progress=False, scheduler=cluster)[0].nees
        == run_seeds(draws, ["smoother"], progress=False, workers=1)[0].nees
    )


def test_scheduler_errors_are_one_line_input_errors():
    with pytest.raises(InputError, match=r"scheduler: expected an address like tcp://"):
        check_scheduler("localhost:8786")
    with pytest.raises(InputError, match=r"workers: does not apply with a scheduler"):
        check_scheduler("tcp://127.0.0.1:8786", workers=2)


def test_an_unreachable_scheduler_exits_2(sequences, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("hvo_graph.parallel.CONNECT_TIMEOUT_S", 0.5)
    argv = ["batch", str(sequences / "alpha"), "--out", str(tmp_path), "--no-progress"]
    assert main([*argv, "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hvo-graph: error: scheduler: cannot connect to tcp://127.0.0.1:9")
    assert len(err.splitlines()) == 1
    assert main([*argv, "--scheduler", "tcp://127.0.0.1:9", "--workers", "2"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_batch_options_are_checked_like_estimate(sequences, tmp_path, capsys):
    config = tmp_path / "options.yaml"
    config.write_text("lag: 0.5\n")
    argv = ["batch", str(sequences / "alpha"), "--out", str(tmp_path / "o"), "--workers", "1"]
    assert main([*argv, "--method", "kalman", "--config", str(config)]) == 2
    assert "--lag: does not apply to method 'kalman'" in capsys.readouterr().err
    config.write_text("lag: 0.5\nrobust: huber\n")
    assert main([*argv, "--method", "fixed-lag", "--config", str(config)]) == 0
    record = json.loads((tmp_path / "o" / "alpha" / "run.json").read_text())
    assert record["options"]["lag"] == 0.5 and record["options"]["robust"] == "huber"


def test_without_dask_the_scheduler_option_says_what_to_install(monkeypatch):
    import sys

    from hvo_graph.parallel import executor

    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    with pytest.raises(
        InputError, match=r'needs dask.distributed: pip install "hvo_graph\[cluster\]"'
    ):
        with executor(1, "tcp://127.0.0.1:8786"):
            pass
