"""Integrand evaluations per second: warpis's Warp trial kernels against a numpy + Embree baseline
and, for ``independent:single:light-area``, against Mitsuba 3.

    python scripts/bench.py [--json PATH] [--scenes occluded-quad heavy-occluder] [--n 64]
                            [--repeat 5] [--seconds 1.5] [--threads T] [--device cpu] [--no-mitsuba]

For each scene and each of the estimators ``independent:single:light-area`` and
``jittered:balance:light-area+cosine`` it times :func:`warpis.kernels.engine.run_trials` and
:func:`baseline.baseline_trials` (``scripts/baseline.py``: the same estimator in numpy,
rays cast with trimesh's Embree intersector) on the same receivers (all of the scene's)
and the same N.
The rate is integrand evaluations per second, N per trial (one shadow ray each; the
emitter crossings that light-sampling pdfs need are not counted):
R × M × N / wall-clock seconds of the call, output array included.

Mitsuba 3 comparator (``scripts/mitsuba_baseline.py``, rows of
``independent:single:light-area`` only; it needs the ``mitsuba`` package and a libLLVM 19
for its ``llvm_ad_rgb`` variant, see that module; ``--no-mitsuba`` leaves it out, and so
does a failed import, with one line saying why).  Identical to warpis: the triangles
(``scene.vertices`` and ``scene.triangles`` in float32 on both sides, one ``mi.Mesh``), the
receivers (float32 positions and normals, ρ, warpis's self-hit slab δ: rays start at
x + (δ/n·ω)·ω), the emitters (warpis's float32 area CDF, its rescaling of u.x, its map of
the square to a triangle), the pdf (1/A)·t²/|cos θ_y|, one-sided emission, float32
arithmetic per sample and the sum over N in float64.  Different: the random numbers
(Mitsuba's ``independent`` sampler, TEA-scrambled PCG32 streams seeded per chunk of 2^22
samples, where warpis hashes (seed, receiver, trial, sample) with lowbias32); the ray
query (Embree 3, bundled with Mitsuba, on a BVH Embree builds, where warpis walks its own
4-wide BVH in Warp, ``warpis/kernels/bvh.py``); the execution (Dr.Jit's LLVM kernels over
a whole chunk of (receiver, trial, sample) at once, Embree called on packets of rays,
where warpis runs one thread per trial).  On these planar emitter sets warpis's light
sample takes its pdf from the sampled point and casts one any-hit shadow ray towards it
(``warpis/kernels/integrand.py``), the work of Mitsuba's any-hit mode; the baseline finds
the first hit and sums the pdf over every emitter crossing (a second query per sample).
Two modes: ``mitsuba`` finds the first hit (``ray_intersect_preliminary``), the one whose
rate is compared (column w/Mi = warpis / Mitsuba), as the issue that set the target
asked; ``mitsuba-anyhit`` casts a shadow ray towards the sampled point (``ray_test``),
shown for reference.
Before a scene is timed, each mode's per-receiver means from a few thousand trials are
held against warpis's (z on the pooled standard errors, |z| < 5 at every receiver); a
comparator that fails stops the bench rather than print a ratio for a different
integral.

Method: the scene's Warp meshes, the baseline's Embree BVHs and Mitsuba's scene are
built, and every kernel compiled and loaded, before anything is timed.  The build of each
side is timed on its own: warpis's 4-wide BVH (``build_wide_bvh``, without its disk
cache), warpis's upload (Warp mesh, emitter BVH, structs and slabs, after its in-process
cache is cleared; the wide BVH from its disk cache), the baseline's ``BaselineScene.build`` and BVH warm-up, and
Mitsuba's ``mi.load_dict`` (Embree's BVH build) apart from its JIT warm-up (compiling,
or loading from Dr.Jit's kernel cache on disk, both modes' kernels).  A short pilot run
of each side picks its number of trials M so that one measurement takes about
``--seconds`` (each side gets its own M; the rate does not depend on it).  The sides then
run alternately, warpis, baseline, Mitsuba, Mitsuba any-hit, warpis, … ``--repeat``
times, and the table shows the median rate of each side and the ratios.  Every side
uses ``--threads`` worker threads (default: every usable core): warpis issues one kernel
launch per chunk of trials from a thread pool, the baseline runs one task per
(receiver, chunk of trials) on a thread pool (Embree and numpy's large-array loops
release the GIL), Mitsuba runs on Dr.Jit's thread pool (``dr.set_thread_count``).

Peak memory is measured in a fresh child process per (scene, estimator, side) that loads
the scene, warms up and makes one measurement: its peak resident set size (VmHWM, which
is ``ru_maxrss`` of the child's own address space; Linux's ``getrusage`` would also carry
the parent's peak into the child) for the whole process (Python, Warp, trimesh, Mitsuba
where loaded, the scene and the run), and for the baseline also the tracemalloc peak of
the run itself (numpy's allocations; Warp's and Dr.Jit's native allocations are invisible
to tracemalloc, so warpis and Mitsuba get no such figure).  Mitsuba's probe runs the
closest-hit mode.  ``--no-memory`` skips it.

The machine's other load skews the rates: the header and footer print the 1-minute load
average, and the JSON keeps every run's rate besides the medians.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from baseline import BASELINE_ESTIMATORS, BaselineScene, baseline_trials  # scripts/baseline.py, beside this file
from mitsuba_baseline import (MITSUBA_ESTIMATOR, VARIANT, MitsubaScene, mean_z,  # scripts/mitsuba_baseline.py
                              mitsuba_trials, mitsuba_unavailable)

import warpis
from warpis.errors import WarpisError
from warpis.kernels.bvh import build_wide_bvh
from warpis.kernels.device import clear_device_cache, upload
from warpis.kernels.engine import default_threads, run_trials

DEFAULT_SCENES = ("occluded-quad", "heavy-occluder")
PILOT_SECONDS = 0.25
MITSUBA_MODES = {"mitsuba": "closest", "mitsuba-anyhit": "anyhit"}  # side → mitsuba_trials mode
# Self-check of the Mitsuba comparator against warpis: per-receiver means of CHECK_TRIALS
# trials each must agree within CHECK_Z pooled standard errors.  A false failure has
# probability 2·(1 − Φ(5)) ≈ 5.7e-7 per receiver, below 1e-4 for any bench run of fewer
# than 170 (receiver, mode) pairs (union bound); a wrong pdf or integrand moves a mean
# by hundreds of standard errors at these trial counts.
CHECK_TRIALS = 2000
CHECK_Z = 5.0
CHECK_SEEDS = (9001, 9002)  # warpis, Mitsuba: fixed, so every run draws the same samples


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


@dataclass
class Built:
    """A loaded scene with each side's structures built, and how long each build took."""

    scene: Any  # warpis.Scene
    mitsuba: MitsubaScene | None = None
    mitsuba_refused: str | None = None  # why the comparator refused this scene
    seconds: dict[str, float | None] = field(default_factory=dict)


def load(scene_name: str, device: str, baseline: bool = True, mitsuba: bool = False, n: int = 64) -> Built:
    """A scene with warpis's upload, the baseline's BVHs (``baseline``) and Mitsuba's scene
    and kernels at N = ``n`` (``mitsuba``) built now, each build timed."""
    scene = warpis.load_scene(scene_name, device=device)
    built = Built(scene, seconds={"warpis_bvh_build_s": None, "warpis_build_s": None, "embree_build_s": None,
                                  "mitsuba_load_s": None, "mitsuba_warmup_s": None})
    t0 = time.perf_counter()
    build_wide_bvh(scene.vertices, scene.triangles, scene.emitters)
    built.seconds["warpis_bvh_build_s"] = time.perf_counter() - t0
    clear_device_cache()  # time a full upload, not a cache hit
    t0 = time.perf_counter()
    up = upload(scene)
    built.seconds["warpis_build_s"] = time.perf_counter() - t0
    if baseline:
        t0 = time.perf_counter()
        bs = BaselineScene.build(scene)
        bs.warm_up()  # Embree builds lazily: force it now
        built.seconds["embree_build_s"] = time.perf_counter() - t0
        up.cached("baseline", lambda: bs)  # the runs use this very build (baseline.baseline_scene)
    if mitsuba:
        try:
            built.mitsuba = MitsubaScene.build(scene)
        except WarpisError as exc:
            built.mitsuba_refused = str(exc)
            return built
        built.seconds["mitsuba_load_s"] = built.mitsuba.load_seconds
        built.seconds["mitsuba_warmup_s"] = built.mitsuba.warm_up(n)
    return built


class Side:
    """One implementation under test: a callable (trials, seed) → (R, M) estimates."""

    def __init__(self, name: str, built: Built, estimator: str, n: int, threads: int):
        self.name = name
        self.estimator = estimator
        self.n = n
        scene = built.scene
        self.rows = len(scene.receivers)
        if name == "warpis":
            self.call = lambda m, seed: run_trials(scene, estimator, n, m, seed=seed, threads=threads)
        elif name == "baseline":
            self.call = lambda m, seed: baseline_trials(scene, estimator, n, m, seed=seed, threads=threads)
        else:
            ms, mode = built.mitsuba, MITSUBA_MODES[name]
            self.call = lambda m, seed: mitsuba_trials(ms, estimator, n, m, seed=seed, mode=mode, threads=threads)

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


def self_check(built: Built, n: int, threads: int) -> dict[str, float]:
    """Largest |z| per Mitsuba mode of its per-receiver means against warpis's; stops the
    bench when any receiver reaches ``CHECK_Z`` (the comparator computes another integral)."""
    w = run_trials(built.scene, MITSUBA_ESTIMATOR, n, CHECK_TRIALS, seed=CHECK_SEEDS[0], threads=threads)
    worst = {}
    for side, mode in MITSUBA_MODES.items():
        m = mitsuba_trials(built.mitsuba, MITSUBA_ESTIMATOR, n, CHECK_TRIALS, seed=CHECK_SEEDS[1], mode=mode,
                           threads=threads)
        z = mean_z(w, m)
        worst[side] = float(np.max(np.abs(z)))
        if not np.all(np.abs(z) < CHECK_Z):
            bad = ", ".join(f"receiver {i}: warpis {w[i].mean():.6g}, {side} {m[i].mean():.6g}, z = {z[i]:.1f}"
                            for i in np.flatnonzero(~(np.abs(z) < CHECK_Z)))
            raise SystemExit(f"bench: self-check failed on {built.scene.name}: the Mitsuba comparator ({side}) "
                             f"disagrees with warpis on {MITSUBA_ESTIMATOR} at N = {n} ({bad}); no ratio printed")
    return worst


def probe(args: argparse.Namespace) -> None:
    """Child process: one measurement of one side, then its peak memory as JSON on stdout."""
    built = load(args.scenes[0], args.device, baseline=args.probe == "baseline", mitsuba=args.probe == "mitsuba",
                 n=args.n)
    if args.probe == "mitsuba" and built.mitsuba is None:
        raise SystemExit(built.mitsuba_refused)
    side = Side(args.probe, built, args.estimators[0], args.n, args.threads)
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


def parse_args(argv: list[str] | None) -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    ap = argparse.ArgumentParser(
        description="Integrand evaluations per second of warpis's trial kernels, of a numpy + Embree baseline "
                    "of the same estimators and of a Mitsuba 3 (Dr.Jit LLVM) comparator of "
                    f"{MITSUBA_ESTIMATOR}, on the same receivers and N; medians of interleaved repeats.")
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
                    help="trials per measurement for every side, instead of --seconds")
    ap.add_argument("--threads", type=int, default=None,
                    help="worker threads for every side (default: warpis.kernels.engine.default_threads(), "
                         "i.e. WARPIS_THREADS or every usable core)")
    ap.add_argument("--device", default="cpu",
                    help="Warp device of warpis's side, e.g. cpu or cuda:0 (the baseline and Mitsuba always run "
                         "on the CPU) (default: %(default)s)")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write the rows as JSON to PATH")
    ap.add_argument("--no-memory", action="store_true",
                    help="skip the peak-memory child processes (the memory columns read n/a)")
    ap.add_argument("--no-mitsuba", action="store_true",
                    help=f"leave out the Mitsuba 3 comparator ({VARIANT}) and its columns")
    ap.add_argument("--probe", choices=("warpis", "baseline", "mitsuba"), help=argparse.SUPPRESS)
    return ap, ap.parse_args(argv)


def bench_row(args: argparse.Namespace, built: Built, est: str) -> dict:
    """Time every side on one (scene, estimator): calibrate, then interleaved repeats."""
    scene = built.scene
    names = ["warpis", "baseline"]
    if built.mitsuba is not None and est == MITSUBA_ESTIMATOR:
        names += list(MITSUBA_MODES)
    sides = [Side(name, built, est, args.n, args.threads) for name in names]
    for s in sides:
        s.warm_up()
    trials = {s.name: args.trials or s.calibrate(args.seconds) for s in sides}
    rates: dict[str, list[float]] = {s.name: [] for s in sides}
    for rep in range(args.repeat):
        for s in sides:
            rates[s.name].append(s.time(trials[s.name], 100 + rep))
    med = {name: statistics.median(r) for name, r in rates.items()}
    row = {
        "scene": scene.name, "estimator": est,
        "warpis_per_s": med["warpis"], "baseline_per_s": med["baseline"], "ratio": med["warpis"] / med["baseline"],
        "mitsuba_per_s": med.get("mitsuba"), "mitsuba_anyhit_per_s": med.get("mitsuba-anyhit"),
        "ratio_mitsuba": med["warpis"] / med["mitsuba"] if "mitsuba" in med else None,
        "threads": args.threads,
        "warpis_peak_mb": None, "baseline_peak_mb": None, "baseline_numpy_peak_mb": None, "mitsuba_peak_mb": None,
        "device": args.device, "n": args.n, "receivers": len(scene.receivers),
        "triangles": scene.triangle_count, **built.seconds,
        "mitsuba_refused": built.mitsuba_refused,
    }
    for name in names:
        key = name.replace("-", "_")
        row[f"{key}_trials"] = trials[name]
        row[f"{key}_runs_per_s"] = rates[name]
    text = ", ".join(f"{name} {med[name] / 1e6:.3g} M/s (M = {trials[name]})" for name in names)
    print(f"  {scene.name} {est}: {text}", flush=True)
    return row


def print_table(args: argparse.Namespace, rows: list[dict], builds: list[dict]) -> None:
    def num(x: float | None, spec: str) -> str:
        return "-" if x is None else format(x, spec)

    def mem(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.0f}"

    print()
    header = (f"{'scene':<15} {'estimator':<35} {'thr':>3} {'warpis eval/s':>14} {'baseline eval/s':>16} "
              f"{'w/b':>6} {'Mitsuba eval/s':>15} {'w/Mi':>6} {'any-hit eval/s':>15} {'warpis MB':>9} "
              f"{'baseline MB':>11} {'numpy MB':>8} {'Mitsuba MB':>10}")
    print(header)
    print("-" * len(header))
    for r in rows:
        mitsuba_mb = mem(r["mitsuba_peak_mb"]) if r["mitsuba_per_s"] is not None else "-"
        print(f"{r['scene']:<15} {r['estimator']:<35} {r['threads']:>3} {r['warpis_per_s']:>14.4g} "
              f"{r['baseline_per_s']:>16.4g} {r['ratio']:>6.2f} {num(r['mitsuba_per_s'], '.4g'):>15} "
              f"{num(r['ratio_mitsuba'], '.2f'):>6} {num(r['mitsuba_anyhit_per_s'], '.4g'):>15} "
              f"{mem(r['warpis_peak_mb']):>9} {mem(r['baseline_peak_mb']):>11} "
              f"{mem(r['baseline_numpy_peak_mb']):>8} {mitsuba_mb:>10}")
    print()
    header = (f"{'scene':<15} {'triangles':>9} {'warpis BVH s':>12} {'warpis upload s':>15} {'Embree build s':>14} "
              f"{'Mitsuba load_dict s':>19} {'Mitsuba JIT warm-up s':>21} {'self-check max |z|':>24}")
    print(header)
    print("-" * len(header))
    for b in builds:
        z = b["self_check_max_abs_z"]
        zs = "-" if z is None else f"{z['mitsuba']:.2f} / {z['mitsuba-anyhit']:.2f}"
        print(f"{b['scene']:<15} {b['triangles']:>9} {num(b['warpis_bvh_build_s'], '.3f'):>12} "
              f"{num(b['warpis_build_s'], '.3f'):>15} "
              f"{num(b['embree_build_s'], '.3f'):>14} {num(b['mitsuba_load_s'], '.3f'):>19} "
              f"{num(b['mitsuba_warmup_s'], '.3f'):>21} {zs:>24}")
    print()
    print("eval/s: integrand evaluations (one shadow ray each, N per trial) per second, median of "
          f"{args.repeat}; w/b = warpis / baseline; w/Mi = warpis / Mitsuba (closest hit); any-hit: Mitsuba "
          f"with shadow rays (ray_test), for reference; '-': no Mitsuba run ({MITSUBA_ESTIMATOR} rows only).  "
          "On planar emitters warpis's and Mitsuba's pdf is the sampled point's; the baseline sums over the "
          "emitter crossings, a second query per sample.")
    print("warpis MB, baseline MB, Mitsuba MB: peak RSS (VmHWM, the child's own ru_maxrss) of a fresh process that "
          "loaded the scene, warmed up and ran one measurement (whole process: Python, Warp, trimesh, Mitsuba "
          "where loaded, scene, run); numpy MB: tracemalloc peak of the baseline's run alone.")
    print("build: warpis's 4-wide BVH built in numpy (no disk cache); warpis's upload (Warp mesh, emitter BVH, "
          "slabs, the wide BVH from its disk cache) after clearing its in-process cache; the baseline's two "
          "Embree BVHs; Mitsuba's mi.load_dict (Embree 3 BVH), then compiling or loading from Dr.Jit's disk cache "
          f"both modes' kernels; self-check: largest |z| of Mitsuba's per-receiver means against warpis's "
          f"({CHECK_TRIALS} trials each, closest hit / any-hit; the bench stops at {CHECK_Z:g}).")


def run_bench(args: argparse.Namespace) -> int:
    mitsuba_off = "--no-mitsuba" if args.no_mitsuba else None
    if mitsuba_off is None and MITSUBA_ESTIMATOR not in args.estimators:
        mitsuba_off = f"--estimators leaves out {MITSUBA_ESTIMATOR}"
    if mitsuba_off is None:
        mitsuba_off = mitsuba_unavailable()
    load_before = os.getloadavg()
    print(f"warpis bench: {args.threads} thread(s) per side, device {args.device} (baseline, Mitsuba: CPU), "
          f"N = {args.n}, median of {args.repeat} interleaved runs, "
          f"{os.cpu_count()} CPUs, {platform.processor() or platform.machine()}; "
          f"load average at start {load_before[0]:.2f}", flush=True)
    if mitsuba_off is not None:
        print(f"Mitsuba comparator off: {mitsuba_off}", flush=True)
    rows, builds = [], []
    for scene_name in args.scenes:
        built = load(scene_name, args.device, mitsuba=mitsuba_off is None, n=args.n)
        if built.mitsuba_refused:
            print(f"Mitsuba comparator skips {built.scene.name}: {built.mitsuba_refused}", flush=True)
        worst = self_check(built, args.n, args.threads) if built.mitsuba is not None else None
        if worst is not None:
            print(f"  {built.scene.name}: self-check of Mitsuba against warpis passed, largest |z| "
                  f"{worst['mitsuba']:.2f} (closest hit), {worst['mitsuba-anyhit']:.2f} (any-hit) over "
                  f"{len(built.scene.receivers)} receivers", flush=True)
        builds.append({"scene": built.scene.name, "triangles": built.scene.triangle_count, **built.seconds,
                       "self_check_max_abs_z": worst, "mitsuba_refused": built.mitsuba_refused})
        for est in args.estimators:
            row = bench_row(args, built, est)
            row["self_check_max_abs_z"] = worst if row["mitsuba_per_s"] is not None else None
            rows.append(row)

    load_after = os.getloadavg()  # before the memory probes, which are not timed
    if not args.no_memory:
        for row in rows:
            sides = ("warpis", "baseline") + (("mitsuba",) if row["mitsuba_per_s"] is not None else ())
            for side in sides:
                got = peak_memory(args, row["scene"], row["estimator"], side, row[f"{side}_trials"])
                row[f"{side}_peak_mb"] = got["peak_rss_mb"]
                row[f"{side}_rss_before_run_mb"] = got["rss_before_run_mb"]
                if side == "baseline":
                    row["baseline_numpy_peak_mb"] = got["tracemalloc_peak_mb"]

    print_table(args, rows, builds)
    spread = [max(v) / min(v) for r in rows for k, v in r.items() if k.endswith("_runs_per_s")]
    print(f"largest max/min spread of a side's {args.repeat} runs: {max(spread):.2f}; 1-min load average "
          f"{load_before[0]:.2f} at start, {load_after[0]:.2f} after the timed runs "
          f"(other processes competing for the {os.cpu_count()} CPUs skew the rates)")
    if args.json:
        write_json(args, rows, builds, mitsuba_off, load_before[0], load_after[0])
    return 0


def write_json(args: argparse.Namespace, rows: list[dict], builds: list[dict], mitsuba_off: str | None,
               load_start: float, load_after: float) -> None:
    try:
        mitsuba_version = importlib.metadata.version("mitsuba")
    except importlib.metadata.PackageNotFoundError:
        mitsuba_version = None
    doc = {
        "rows": rows, "scenes": builds,
        "n": args.n, "repeat": args.repeat, "threads": args.threads, "device": args.device,
        "cpu_count": os.cpu_count(), "numpy": np.__version__, "warpis": warpis.__version__,
        "mitsuba": {"version": mitsuba_version, "variant": VARIANT, "off": mitsuba_off,
                    "drjit_libllvm_path": os.environ.get("DRJIT_LIBLLVM_PATH"),
                    "self_check_trials": CHECK_TRIALS, "self_check_z_limit": CHECK_Z},
        "loadavg_start": load_start, "loadavg_after_timing": load_after,
        "memory": "peak_mb: peak RSS (VmHWM: ru_maxrss of the child's own address space) of a fresh "
                  "child process per (scene, estimator, side) that loaded the scene, warmed up and ran one "
                  "measurement (Mitsuba: closest hit); baseline_numpy_peak_mb: tracemalloc peak of that baseline "
                  "run (numpy allocations only)",
        "build": "warpis_build_s: warpis.kernels.device.upload after clear_device_cache; embree_build_s: "
                 "BaselineScene.build + warm_up; mitsuba_load_s: mi.load_dict of the scene; mitsuba_warmup_s: "
                 "first launch of both Mitsuba modes at N (JIT compile or Dr.Jit kernel-cache load)",
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.json}")


def main(argv: list[str] | None = None) -> int:
    ap, args = parse_args(argv)
    args.threads = max(1, args.threads or default_threads())
    if args.probe:
        probe(args)
        return 0
    if args.n < 2 or args.n % 2:
        ap.error("--n must be even and at least 2 (the balance estimator splits N between two techniques)")
    if args.repeat < 1:
        ap.error("--repeat must be at least 1")
    return run_bench(args)


if __name__ == "__main__":
    sys.exit(main())
