"""Integrand evaluations per second: warpis's Warp trial kernels against a numpy + Embree baseline.

    python scripts/bench.py [--json PATH] [--scenes occluded-quad heavy-occluder] [--n 64]
                            [--repeat 5] [--seconds 1.5] [--threads T] [--device cpu]

For each scene and each of the estimators ``independent:single:light-area`` and
``jittered:balance:light-area+cosine`` it times :func:`warpis.kernels.engine.run_trials` and
:func:`baseline.baseline_trials` (``scripts/baseline.py``: the same estimator in numpy,
rays cast with trimesh's Embree intersector) on the same receivers (all of the scene's)
and the same N.
The rate is integrand evaluations per second, N per trial (one shadow ray each; the
emitter crossings that light-sampling pdfs need are not counted):
R × M × N / wall-clock seconds of the call, output array included.

Method: the scene's Warp meshes and the baseline's Embree BVHs are built, and every
kernel compiled and loaded, before anything is timed.  A short pilot run of each side
picks its number of trials M so that one measurement takes about ``--seconds`` (each
side gets its own M; the rate does not depend on it).  The two sides then run
alternately, warpis, baseline, warpis, baseline, … ``--repeat`` times, and the table
shows the median rate of each side and warpis / baseline.  Both sides use ``--threads``
worker threads (default: every usable core): warpis issues one kernel launch per chunk
of trials from a thread pool, the baseline runs one task per (receiver, chunk of
trials) on a thread pool (Embree and numpy's large-array loops release the GIL).

Peak memory is measured in a fresh child process per (scene, estimator, side) that loads
the scene, warms up and makes one measurement: its peak resident set size (VmHWM, which
is ``ru_maxrss`` of the child's own address space; Linux's ``getrusage`` would also carry
the parent's peak into the child) for the whole process (Python, Warp, trimesh, the
scene and the run), and for the baseline also the tracemalloc peak of the run itself
(numpy's allocations; Warp's native allocations are invisible to tracemalloc, so warpis
gets no such figure).  ``--no-memory`` skips it.

The machine's other load skews the rates: the header and footer print the 1-minute load
average, and the JSON keeps every run's rate besides the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from baseline import BASELINE_ESTIMATORS, baseline_scene, baseline_trials  # scripts/baseline.py, beside this file

import warpis
from warpis.kernels.engine import default_threads, run_trials

DEFAULT_SCENES = ("occluded-quad", "heavy-occluder")
PILOT_SECONDS = 0.25


def _status_mb(key: str) -> float | None:
    """A ``kB`` field of /proc/self/status (VmRSS, VmHWM) in MiB; None where unavailable."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return None


def peak_rss_mb() -> float:
    """Peak resident set size of this process's own address space, in MiB.

    ``ru_maxrss`` of a child started by fork + exec also carries the parent's peak on
    Linux (the kernel keeps the larger of the two across exec), so it would report the
    bench's own peak for every child; VmHWM is the same high-water mark for the child's
    address space alone.  ``ru_maxrss`` is the fallback where /proc is missing.
    """
    hwm = _status_mb("VmHWM")
    return hwm if hwm is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class Side:
    """One implementation under test: a callable (trials, seed) → (R, M) estimates."""

    def __init__(self, name: str, scene, estimator: str, n: int, threads: int):
        self.name = name
        self.estimator = estimator
        self.n = n
        self.rows = len(scene.receivers)
        if name == "warpis":
            self.call = lambda m, seed: run_trials(scene, estimator, n, m, seed=seed, threads=threads)
        else:
            self.call = lambda m, seed: baseline_trials(scene, estimator, n, m, seed=seed, threads=threads)

    def warm_up(self) -> None:
        self.call(2, 0)

    def time(self, trials: int, seed: int) -> float:
        """Evaluations per second of one call with ``trials`` trials."""
        t0 = time.perf_counter()
        out = self.call(trials, seed)
        dt = time.perf_counter() - t0
        assert out.shape == (self.rows, trials)
        return self.rows * trials * self.n / dt

    def calibrate(self, seconds: float) -> int:
        """Trials for one measurement of about ``seconds``, from pilot runs."""
        trials = 16
        while True:
            t0 = time.perf_counter()
            self.call(trials, 1)
            dt = time.perf_counter() - t0
            if dt >= PILOT_SECONDS or trials >= 1 << 24:
                break
            trials *= 2 if dt > PILOT_SECONDS / 8 else 8
        return max(2, int(round(trials * seconds / dt)))


def load(scene_name: str, device: str, baseline: bool = True):
    """A scene, with its baseline BVHs built when ``baseline`` (Embree builds lazily: force it now)."""
    scene = warpis.load_scene(scene_name, device=device)
    if baseline:
        baseline_scene(scene).warm_up()
    return scene


def probe(args: argparse.Namespace) -> None:
    """Child process: one measurement of one side, then its peak memory as JSON on stdout."""
    scene = load(args.scenes[0], args.device, baseline=args.probe == "baseline")
    side = Side(args.probe, scene, args.estimators[0], args.n, args.threads)
    side.warm_up()
    rss_before = _status_mb("VmRSS")
    traced = args.probe == "baseline"
    if traced:
        tracemalloc.start()
    side.time(args.trials, 7)
    numpy_peak = tracemalloc.get_traced_memory()[1] / 2**20 if traced else None
    if traced:
        tracemalloc.stop()
    print(json.dumps({
        "peak_rss_mb": peak_rss_mb(),
        "rss_before_run_mb": rss_before,
        "tracemalloc_peak_mb": numpy_peak,
    }))


def peak_memory(args: argparse.Namespace, scene: str, estimator: str, side: str, trials: int) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--probe", side, "--scenes", scene,
           "--estimators", estimator, "--n", str(args.n), "--trials", str(trials),
           "--threads", str(args.threads), "--device", args.device]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode != 0 or not lines:
        sys.stderr.write(res.stderr)
        raise SystemExit(f"memory probe failed: {' '.join(cmd)}")
    return json.loads(lines[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Integrand evaluations per second of warpis's trial kernels and of a numpy + "
                    "Embree baseline of the same estimators, on the same receivers and N; "
                    "medians of interleaved repeats.")
    ap.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES), metavar="SCENE",
                    help=f"bundled scene names or scene files (default: {' '.join(DEFAULT_SCENES)})")
    ap.add_argument("--estimators", nargs="+", default=list(BASELINE_ESTIMATORS), metavar="EST",
                    choices=BASELINE_ESTIMATORS, help="estimators to time (default: both of %(choices)s)")
    ap.add_argument("--n", type=int, default=64, help="samples per trial, N (default: %(default)s)")
    ap.add_argument("--repeat", type=int, default=5,
                    help="interleaved measurements per side; the median is reported (default: %(default)s)")
    ap.add_argument("--seconds", type=float, default=1.5,
                    help="target duration of one measurement; sets each side's trials (default: %(default)s)")
    ap.add_argument("--trials", type=int, default=None,
                    help="trials per measurement for both sides, instead of --seconds")
    ap.add_argument("--threads", type=int, default=None,
                    help="worker threads for both sides (default: warpis.kernels.engine.default_threads(), "
                         "i.e. WARPIS_THREADS or every usable core)")
    ap.add_argument("--device", default="cpu",
                    help="Warp device of warpis's side, e.g. cpu or cuda:0 (the baseline always runs "
                         "on the CPU) (default: %(default)s)")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write the rows as JSON to PATH")
    ap.add_argument("--no-memory", action="store_true",
                    help="skip the peak-memory child processes (the memory columns read n/a)")
    ap.add_argument("--probe", choices=("warpis", "baseline"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.threads = max(1, args.threads or default_threads())
    if args.probe:
        probe(args)
        return 0
    if args.n < 2 or args.n % 2:
        ap.error("--n must be even and at least 2 (the balance estimator splits N between two techniques)")
    if args.repeat < 1:
        ap.error("--repeat must be at least 1")

    load_before = os.getloadavg()
    print(f"warpis bench: {args.threads} thread(s) per side, device {args.device} (baseline: CPU), "
          f"N = {args.n}, median of {args.repeat} interleaved runs, "
          f"{os.cpu_count()} CPUs, {platform.processor() or platform.machine()}; "
          f"load average at start {load_before[0]:.2f}", flush=True)
    rows = []
    for scene_name in args.scenes:
        scene = load(scene_name, args.device)
        for est in args.estimators:
            sides = [Side(name, scene, est, args.n, args.threads) for name in ("warpis", "baseline")]
            for s in sides:
                s.warm_up()
            trials = {s.name: args.trials or s.calibrate(args.seconds) for s in sides}
            rates: dict[str, list[float]] = {s.name: [] for s in sides}
            for rep in range(args.repeat):
                for s in sides:
                    rates[s.name].append(s.time(trials[s.name], 100 + rep))
            w, b = statistics.median(rates["warpis"]), statistics.median(rates["baseline"])
            row = {
                "scene": scene.name, "estimator": est,
                "warpis_per_s": w, "baseline_per_s": b, "ratio": w / b, "threads": args.threads,
                "warpis_peak_mb": None, "baseline_peak_mb": None, "baseline_numpy_peak_mb": None,
                "device": args.device, "n": args.n, "receivers": len(scene.receivers),
                "triangles": scene.triangle_count,
                "warpis_trials": trials["warpis"], "baseline_trials": trials["baseline"],
                "warpis_runs_per_s": rates["warpis"], "baseline_runs_per_s": rates["baseline"],
            }
            rows.append(row)
            print(f"  {scene.name} {est}: warpis {w / 1e6:.3g} M/s (M = {trials['warpis']}), "
                  f"baseline {b / 1e6:.3g} M/s (M = {trials['baseline']})", flush=True)

    load_after = os.getloadavg()  # before the memory probes, which are not timed
    if not args.no_memory:
        for row in rows:
            for side in ("warpis", "baseline"):
                got = peak_memory(args, row["scene"], row["estimator"], side, row[f"{side}_trials"])
                row[f"{side}_peak_mb"] = got["peak_rss_mb"]
                row[f"{side}_rss_before_run_mb"] = got["rss_before_run_mb"]
                if side == "baseline":
                    row["baseline_numpy_peak_mb"] = got["tracemalloc_peak_mb"]

    def mem(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.0f}"

    print()
    header = (f"{'scene':<15} {'estimator':<35} {'thr':>3} {'warpis eval/s':>14} {'baseline eval/s':>16} "
              f"{'ratio':>6} {'warpis MB':>9} {'baseline MB':>11} {'numpy MB':>8}")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['scene']:<15} {r['estimator']:<35} {r['threads']:>3} {r['warpis_per_s']:>14.4g} "
              f"{r['baseline_per_s']:>16.4g} {r['ratio']:>6.2f} {mem(r['warpis_peak_mb']):>9} "
              f"{mem(r['baseline_peak_mb']):>11} {mem(r['baseline_numpy_peak_mb']):>8}")
    print()
    print("eval/s: integrand evaluations (one shadow ray each, N per trial) per second, median of "
          f"{args.repeat}; ratio = warpis / baseline.")
    print("warpis MB, baseline MB: peak RSS (VmHWM, the child's own ru_maxrss) of a fresh process that loaded "
          "the scene, warmed up and ran one measurement (whole process: Python, Warp, trimesh, scene, run); "
          "numpy MB: tracemalloc peak of the baseline's run alone.")
    spread = [max(v) / min(v) for r in rows for v in (r["warpis_runs_per_s"], r["baseline_runs_per_s"])]
    print(f"largest max/min spread of a side's {args.repeat} runs: {max(spread):.2f}; 1-min load average "
          f"{load_before[0]:.2f} at start, {load_after[0]:.2f} after the timed runs "
          f"(other processes competing for the {os.cpu_count()} CPUs skew the rates)")

    if args.json:
        doc = {
            "rows": rows,
            "n": args.n, "repeat": args.repeat, "threads": args.threads, "device": args.device,
            "cpu_count": os.cpu_count(), "numpy": np.__version__, "warpis": warpis.__version__,
            "loadavg_start": load_before[0], "loadavg_after_timing": load_after[0],
            "memory": "peak_mb: peak RSS (VmHWM: ru_maxrss of the child's own address space) of a fresh "
                      "child process per (scene, estimator, side) that loaded the scene, warmed up and ran one "
                      "measurement; baseline_numpy_peak_mb: tracemalloc peak of that baseline run (numpy "
                      "allocations only)",
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
