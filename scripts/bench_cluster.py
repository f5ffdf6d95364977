"""Benchmark: a study run here against the same study on a local Dask cluster, in one run.

Measures, side by side (needs the cluster extra: ``pip install -e ".[bench]"``):

1. the demo study (``warpis demo``) run locally with ``--threads W`` and on ``--workers W``
   single-threaded worker processes: wall times (the cluster's start-up separately),
   their ratio, medians over interleaved repeats;
2. the cost of one Dask task here (median round trip of a no-op task over many);
3. what travels per cell: the pickled scene (once per worker), a trial unit's arguments,
   a block's moments and a cell's rows;
4. a simulated scale-out: a study of ≥ 200 one-block cells whose trial tasks sleep
   ``--delay`` seconds per block (standing in for the compute of remote machines), on
   1, 2, 4 and 8 workers: wall time and speed-up against one worker.

    python scripts/bench_cluster.py [--workers 2] [--repeats 3] [--json PATH]

Machines are shared and noisy: read ratios and medians, not single times.
"""

from __future__ import annotations

import argparse
import json
import pickle
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from warpis.kernels.engine import BLOCK, block_count, run_block_moments
from warpis.runs import cluster
from warpis.runs.cell import LocalRunner
from warpis.runs.study_file import demo_study, load_study
from warpis.runs.study import cell_job, run_study


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def demo_times(workers: int, repeats: int, scratch: Path) -> dict:
    """Interleaved local and cluster runs of the demo, each into a fresh folder."""
    local, dask, startup = [], [], []
    for k in range(repeats):
        study = demo_study(threads=workers)
        local.append(timed(lambda: run_study(study, scratch / f"local{k}", runner=LocalRunner(workers))))
        start = time.perf_counter()
        with cluster.connect(workers=workers) as runner:
            startup.append(time.perf_counter() - start)
            dask.append(timed(lambda: run_study(study, scratch / f"dask{k}", runner=runner)))
    med = statistics.median
    return {"workers": workers, "repeats": repeats, "local_s": med(local), "cluster_s": med(dask),
            "cluster_startup_s": med(startup), "ratio": med(dask) / med(local),
            "ratio_with_startup": (med(dask) + med(startup)) / med(local),
            "runs": {"local": local, "cluster": dask, "startup": startup}}


def task_overhead(count: int = 400) -> dict:
    """Median round trip of a no-op task on a 2-worker local cluster (submit → result here)."""
    with cluster.connect(workers=2) as runner:
        client = runner.client
        trips = []
        for k in range(count):
            start = time.perf_counter()
            client.submit(cluster.worker_version, pure=False, key=f"noop-{k}").result()
            trips.append(time.perf_counter() - start)
        start = time.perf_counter()
        client.gather(client.map(lambda x: x, range(count), pure=False))
        batch = time.perf_counter() - start
    return {"tasks": count, "round_trip_ms": 1e3 * statistics.median(trips), "pipelined_ms": 1e3 * batch / count}


def bytes_per_cell() -> dict:
    """Pickled sizes of what a demo cell moves (the scene goes once to each worker)."""
    study = demo_study()
    jobs = [cell_job(study, c) for c in study.cells()]
    units = cluster.plan_units(jobs)
    job = jobs[0]
    block = run_block_moments(job.scene, job.estimator, job.n, job.trials, job.seed, list(job.receivers),
                              blocks=range(1))[0]
    items = [cluster.UnitItem(jobs[c].scene.digest, jobs[c].estimator.spec, jobs[c].n, jobs[c].trials,
                              jobs[c].seed, jobs[c].receivers, first, stop) for unit in units for c, first, stop in unit]
    blocks = sum(stop - first for unit in units for _, first, stop in unit)
    _, measured = next(LocalRunner().measure([job]))
    return {"scene_bytes": len(pickle.dumps(job.scene)), "cells": len(jobs), "units": len(units),
            "blocks": blocks, "unit_args_bytes_per_cell": len(pickle.dumps(items)) / len(jobs),
            "block_moments_bytes": len(pickle.dumps(block)),
            "moments_bytes_per_cell": len(pickle.dumps(block)) * blocks / len(jobs),
            "rows_bytes_per_cell": len(pickle.dumps(measured.rows))}


SCALE_STUDY = '''[study]
name = "scale-out"
trials = {trials}
n = [{n}]
scenes = ["occluded-quad"]
receivers = [0]
estimators = [{estimators}]
predictions = false
outputs = []
'''


def scale_out(delay: float, scratch: Path, worker_counts=(1, 2, 4, 8)) -> dict:
    """Wall time of a ≥200-block study whose blocks each sleep ``delay`` s, per worker count."""
    ests = ", ".join(f'"{p}:single:{t}"' for p in ("independent", "jittered")
                     for t in ("uniform", "cosine", "light-area", "light-power", "light-solid-angle"))
    path = scratch / "scale.toml"
    # 10 estimators × 2 N = 20 cells of 10 blocks; one receiver and N ≤ 2 keep the real compute small
    path.write_text(SCALE_STUDY.format(trials=10 * BLOCK, n="1, 2", estimators=ests))
    study = load_study(path)
    blocks = sum(block_count(study.trials) for _ in study.cells())
    out = {"delay_s_per_block": delay, "blocks": blocks, "cells": len(study.cells()), "wall_s": {}}
    for w in worker_counts:
        with cluster.connect(workers=w) as runner:
            runner.unit_evaluations = 1  # one block per task
            run_study(study, scratch / f"warm{w}", runner=runner)  # references and kernels: not timed
            runner.delay = delay
            out["wall_s"][w] = timed(lambda: run_study(study, scratch / f"scale{w}", runner=runner))
    base = out["wall_s"][worker_counts[0]]
    out["speedup"] = {w: base / t for w, t in out["wall_s"].items()}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, default=2, help="threads here and workers there (default 2)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved demo runs per side (default 3)")
    p.add_argument("--delay", type=float, default=0.2, help="simulated seconds of remote work per block")
    p.add_argument("--skip-demo", action="store_true", help="only the overhead, bytes and scale-out parts")
    p.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = p.parse_args(argv)
    scratch = Path(tempfile.mkdtemp(prefix="warpis-bench-cluster-"))
    try:
        result = {}
        if not args.skip_demo:
            result["demo"] = d = demo_times(args.workers, args.repeats, scratch)
            print(f"demo: local {d['local_s']:.1f} s, {d['workers']} workers {d['cluster_s']:.1f} s "
                  f"(+{d['cluster_startup_s']:.1f} s start-up): ratio {d['ratio']:.3f} "
                  f"({d['ratio_with_startup']:.3f} with start-up), medians of {d['repeats']}", flush=True)
        result["task"] = t = task_overhead()
        print(f"task: {t['round_trip_ms']:.1f} ms round trip, {t['pipelined_ms']:.2f} ms per task pipelined",
              flush=True)
        result["bytes"] = b = bytes_per_cell()
        print(f"bytes: scene {b['scene_bytes']:,} once per worker; per cell: unit arguments "
              f"{b['unit_args_bytes_per_cell']:,.0f}, block moments {b['moments_bytes_per_cell']:,.0f}, "
              f"rows {b['rows_bytes_per_cell']:,}", flush=True)
        result["scale_out"] = s = scale_out(args.delay, scratch)
        print(f"scale-out ({s['blocks']} blocks × {s['delay_s_per_block']} s): "
              + ", ".join(f"{w} worker(s) {s['wall_s'][w]:.1f} s (×{s['speedup'][w]:.2f})" for w in s["wall_s"]))
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
