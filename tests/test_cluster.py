"""Studies and verify on a Dask cluster (``warpis.runs.cluster``): the same files as a local run.

A ``LocalCluster`` of two single-threaded worker processes stands in for a cluster.  The
checks are exact, not statistical: a cell's trials are reduced in the same blocks and
merged in the same order wherever they run, so every column of ``results.csv`` but the
timing (``seconds``, ``seconds_per_estimate``, ``efficiency``) must be equal as text, cell keys included.
"""

from __future__ import annotations

import csv
import os
import signal
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")

import warpis  # noqa: E402
from warpis.kernels.engine import BLOCK  # noqa: E402
from warpis.kernels.estimators import parse_estimator  # noqa: E402
from warpis.runs import cluster  # noqa: E402
from warpis.runs.cell import CellJob  # noqa: E402
from warpis.runs.study_file import TIMING_COLUMNS, load_study  # noqa: E402
from warpis.runs.study import run_study  # noqa: E402
from warpis.runs.verify import verify  # noqa: E402

from conftest import one_error_line  # noqa: E402

STUDY = '''[study]
name = "cluster"
trials = {trials}
n = {n}
scenes = ["occluded-quad"]
receivers = [0, 1, 2]
estimators = ["independent:single:light-area", "jittered:balance:light-area+cosine",
              "jittered:power:light-area+cosine", "independent:mixture:light-area+cosine"]
outputs = []
'''


def numbers(path: Path) -> list[list[str]]:
    """results.csv without its timing columns (``TIMING_COLUMNS``)."""
    rows = list(csv.reader(path.open()))
    keep = [k for k, name in enumerate(rows[0]) if name not in TIMING_COLUMNS]
    return [[row[k] for k in keep] for row in rows]


def write_study(tmp_path: Path, trials: int = 600, n: str = "[4, 16]") -> Path:
    path = tmp_path / "study.toml"
    path.write_text(STUDY.format(trials=trials, n=n))
    return path


@pytest.fixture(scope="module")
def runner():
    with cluster.connect(workers=2) as r:
        yield r


def test_a_study_on_two_workers_writes_the_local_results(tmp_path, runner):
    # 20000 trials: two blocks per cell, so a cell's blocks are merged across units.
    study = load_study(write_study(tmp_path, trials=BLOCK + 3616))
    run_study(study, tmp_path / "local")
    run_study(study, tmp_path / "dask", runner=runner)
    local, dask = numbers(tmp_path / "local" / "results.csv"), numbers(tmp_path / "dask" / "results.csv")
    assert len(local) == 1 + 8 * 3 and dask == local
    assert (tmp_path / "local" / "summary.json").read_text() == (tmp_path / "dask" / "summary.json").read_text()


def test_verify_on_two_workers_gives_the_local_rows(runner):
    scene = warpis.load_scene("occluded-quad")
    ests = ["jittered:balance:light-area+cosine", "independent:biased:cosine"]
    local = verify(scene, estimators=ests, n_values=[4, 16], trials=200, receivers=[0, 3])
    dask = verify(scene, estimators=ests, n_values=[4, 16], trials=200, receivers=[0, 3], runner=runner)
    assert dask.rows == local.rows and len(local.rows) == 8



def test_a_receivers_moments_are_one_task_for_all_its_technique_sets(runner, monkeypatch):
    """As a local run finds them (RunCache): one moments task per receiver, each technique
    of its sets evaluated once, and the rows a local run gives."""
    submitted = []
    real = runner.client.submit
    monkeypatch.setattr(runner.client, "submit",
                        lambda fn, *args, **kwargs: submitted.append((fn.__name__, args)) or real(fn, *args, **kwargs))
    scene = warpis.load_scene("occluded-quad")
    ests = ["independent:single:light-area", "independent:balance:light-area+cosine", "independent:single:cosine"]
    dask = verify(scene, estimators=ests, n_values=[4], trials=200, receivers=[0, 2], runner=runner)
    sets = [("light-area",), ("light-area", "cosine"), ("cosine",)]
    assert [args[1:] for name, args in submitted if name == "moments_task"] == [(0, sets), (2, sets)]
    assert dask.rows == verify(scene, estimators=ests, n_values=[4], trials=200, receivers=[0, 2]).rows

def test_a_study_started_on_the_cluster_is_finished_locally(tmp_path, runner):
    """Cells keep their keys whatever ran them: the cluster's cells are skipped locally."""
    run_study(load_study(write_study(tmp_path, n="[4]")), tmp_path / "out", runner=runner)
    resumed = run_study(load_study(write_study(tmp_path, n="[4, 16]")), tmp_path / "out")
    assert (resumed.skipped, resumed.computed) == (4, 4)
    run_study(load_study(write_study(tmp_path, n="[4, 16]")), tmp_path / "whole")
    assert numbers(tmp_path / "out" / "results.csv") == numbers(tmp_path / "whole" / "results.csv")


def test_a_killed_worker_costs_nothing_but_time(tmp_path):
    """SIGKILL one of two workers once the first cell has finished: Dask reruns its tasks
    (they are pure) and the study ends with the local results."""
    study = load_study(write_study(tmp_path, trials=2000, n="[4, 16, 64]"))
    run_study(study, tmp_path / "local")
    killed = []
    with cluster.connect(workers=2) as r:
        pids = sorted(r.client.run(os.getpid).values())

        def progress(done: int, total: int) -> None:
            if done == 1 and not killed:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])

        run_study(study, tmp_path / "dask", progress=progress, runner=r)
    assert killed
    assert numbers(tmp_path / "dask" / "results.csv") == numbers(tmp_path / "local" / "results.csv")


def test_units_cover_every_block_of_every_cell_once_in_order():
    scene = warpis.load_scene("occluded-quad")
    jobs = [CellJob(scene, (0, 1), parse_estimator("independent:single:cosine"), n, trials, 0)
            for n, trials in ((4, 5 * BLOCK + 1), (1024, 3 * BLOCK), (16, 10), (4, 1))]
    units = cluster.plan_units(jobs, budget=2 * 4 * 4 * BLOCK)
    for c, job in enumerate(jobs):
        ranges = [(first, stop) for unit in units for cell, first, stop in unit if cell == c]
        blocks = [b for first, stop in ranges for b in range(first, stop)]
        assert blocks == list(range(-(-job.trials // BLOCK))), (c, ranges)
    assert len(units) < sum(-(-job.trials // BLOCK) for job in jobs)  # small cells are batched


def test_a_worker_on_another_version_is_refused(monkeypatch, runner):
    monkeypatch.setattr(cluster, "worker_version", lambda: "0.0.0-other")
    with pytest.raises(warpis.WarpisError, match=r"worker tcp://\S+ runs warpis 0\.1\.0, this is warpis 0\.0\.0-other"):
        runner.check_workers()


def test_the_cli_runs_a_study_on_workers(tmp_path, cli):
    path = write_study(tmp_path, trials=200, n="[4]")
    result = cli("study", path, "--workers", "2", "--out", tmp_path / "dask")
    assert result.status == 0, result.err
    assert cli("study", path, "--out", tmp_path / "local").status == 0
    assert numbers(tmp_path / "dask" / "results.csv") == numbers(tmp_path / "local" / "results.csv")


@pytest.mark.parametrize("args, problem", [
    (["--scheduler", "tcp://127.0.0.1:9"], "--scheduler tcp://127.0.0.1:9: cannot reach the scheduler"),
    (["--scheduler", ""], "--scheduler: must name a scheduler address"),
    (["--scheduler", "foo"], "--scheduler foo: cannot reach the scheduler (ValueError: missing port number"),
    (["--workers", "100000"], "--workers: at most 64"),
    (["--workers", "0"], "--workers"),
    (["--workers", "2", "--scheduler", "tcp://x:1"], "not allowed with argument"),
])
def test_bad_cluster_options_are_one_line(tmp_path, cli, monkeypatch, args, problem):
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 2)
    path = write_study(tmp_path, trials=200, n="[4]")
    line = one_error_line(cli("study", path, "--out", tmp_path / "out", *args))
    assert problem in line, line
    assert not (tmp_path / "out" / "results.csv").exists()


def test_without_dask_the_options_name_the_extra(tmp_path, cli, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed → ImportError
    path = write_study(tmp_path, trials=200, n="[4]")
    line = one_error_line(cli("study", path, "--workers", "2", "--out", tmp_path / "out"))
    assert 'pip install "warpis[cluster]"' in line


def test_a_local_run_imports_no_dask(tmp_path):
    code = ("import sys; from warpis.cli import main; "
            f"main(['study', {str(write_study(tmp_path, trials=8, n='[4]'))!r}, '--out', {str(tmp_path / 'o')!r}]); "
            "print('distributed' in sys.modules, 'dask' in sys.modules)")
    import subprocess

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False False"



def test_a_scheduler_that_goes_away_ends_the_run_in_one_line_keeping_finished_cells(tmp_path, monkeypatch):
    import logging

    import distributed

    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 2)
    local = distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0",
                                     silence_logs=logging.CRITICAL)
    study = load_study(write_study(tmp_path, trials=2000, n="[4, 16, 64]"))

    def progress(done: int, total: int) -> None:
        if done == 1:
            local.close()

    with cluster.connect(scheduler=local.scheduler_address) as runner:
        with pytest.raises(warpis.WarpisError, match=r"^--scheduler tcp://\S+: lost the cluster \(.*\); finished "
                                                     r"cells are kept$"):
            run_study(study, tmp_path / "out", progress=progress, runner=runner)
    kept = numbers(tmp_path / "out" / "results.csv")
    assert len(kept) > 1 and (len(kept) - 1) % 3 == 0  # whole cells of 3 receivers
    resumed = run_study(study, tmp_path / "out")  # finished here
    assert resumed.skipped == (len(kept) - 1) // 3 and resumed.computed == 12 - resumed.skipped
