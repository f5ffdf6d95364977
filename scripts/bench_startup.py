"""Time to the first answer: ``warpis demo`` from a cold and from a warm cache, and what compiles.

Each repeat makes two fresh, empty cache folders (Warp's kernel cache, ``WARP_CACHE_PATH``,
and warpis's cache of BVHs and theory results, ``WARPIS_CACHE_DIR``) and runs ``warpis demo``
twice in fresh Python processes: *cold* (nothing compiled, no theory kept) and then *warm*
(every kernel cached, every exact variance and moment kept by the cold run:
``warpis/analysis/memo.py``), into two fresh output folders, and stops if the warm run's
``results.csv`` differs from the cold run's in any column but the timing ones. The
wall time of each run is that of the whole process, Python's start and ``import warpis``
included. Warp's own module-load lines ("Module … took … ms (compiled)"), which warpis
normally hides, are kept in the child and summed per module, so the table says which
modules compile and how long each takes.

    python scripts/bench_startup.py                    # 3 repeats, medians
    python scripts/bench_startup.py --repeats 1 --json

A benchmark, not a test: one repeat takes about three minutes on two cores. Report the
machine's load beside the figures (printed at the start and at the end).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from warpis.runs.study_file import TIMING_COLUMNS

ROOT = Path(__file__).resolve().parents[1]

# The child: warpis's CLI with Warp's module-load lines left on (warpis turns them off).
CHILD = """
import sys
import warp as wp
import warpis
import warpis.cli as cli

def loud_start():
    wp.init()
    wp.config.log_level = wp.LOG_INFO
    wp.config.quiet = False

cli.quiet_warp = loud_start
sys.exit(cli.main(sys.argv[1:]))
"""
LOAD_LINE = re.compile(r"Module (\S+) \S+ load on device '[^']+' took ([0-9.]+) ms\s*\((compiled|cached)\)")


def run_demo(caches: Path, out: Path, threads: int | None) -> tuple[float, dict[str, float], int]:
    """(wall seconds, compile ms per module, modules loaded) of one ``warpis demo`` process."""
    env = dict(os.environ, WARP_CACHE_PATH=str(caches / "warp"), WARPIS_CACHE_DIR=str(caches / "warpis"))
    cmd = [sys.executable, "-c", CHILD, "demo", "--out", str(out), "--quiet"]
    if threads:
        cmd += ["--threads", str(threads)]
    start = time.perf_counter()
    done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"warpis demo failed ({done.returncode}):\n{done.stderr[-2000:]}")
    compiled: dict[str, float] = defaultdict(float)
    loads = 0
    for name, ms, how in LOAD_LINE.findall(done.stdout + done.stderr):
        loads += 1
        if how == "compiled":
            compiled[name] += float(ms)
    return wall, dict(compiled), loads


def numbers(out: Path) -> list[list[str]]:
    """The demo's results.csv without its timing columns (the only ones a warm run may change)."""
    rows = list(csv.reader((out / "results.csv").open()))
    keep = [k for k, name in enumerate(rows[0]) if name not in TIMING_COLUMNS]
    return [[row[k] for k in keep] for row in rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="cold + warm pairs (default 3)")
    parser.add_argument("--threads", type=int, help="the demo's --threads (default: all cores)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args()
    load_before = os.getloadavg()
    cold, warm, per_module = [], [], defaultdict(list)
    loads = 0
    for r in range(args.repeats):
        with tempfile.TemporaryDirectory(prefix="warpis-startup-") as tmp:
            caches = Path(tmp)
            wall, compiled, loads = run_demo(caches, caches / "cold", args.threads)
            cold.append(wall)
            for name, ms in compiled.items():
                per_module[name].append(ms / 1000)
            wall, recompiled, _ = run_demo(caches, caches / "warm", args.threads)
            warm.append(wall)
            if recompiled:
                print(f"repeat {r}: the warm run compiled again: {sorted(recompiled)}", file=sys.stderr)
            if numbers(caches / "warm") != numbers(caches / "cold"):
                sys.exit(f"repeat {r}: the warm run's results.csv differs from the cold run's")
        print(f"repeat {r}: cold {cold[-1]:.1f} s, warm {warm[-1]:.1f} s", file=sys.stderr)
    figures = {
        "cold_s": cold, "warm_s": warm,
        "cold_median_s": statistics.median(cold), "warm_median_s": statistics.median(warm),
        "compile_s_median_by_module": {k: statistics.median(v) for k, v in
                                       sorted(per_module.items(), key=lambda kv: -statistics.median(kv[1]))},
        "modules_loaded": loads,
        "load_average_before": load_before, "load_average_after": os.getloadavg(), "cpu_count": os.cpu_count(),
    }
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    total = sum(figures["compile_s_median_by_module"].values())
    print(f"warpis demo, {args.repeats} repeat(s), {os.cpu_count()} cores; load average "
          f"{load_before[0]:.2f} before, {figures['load_average_after'][0]:.2f} after")
    print(f"  cold (empty caches): median {figures['cold_median_s']:.1f} s  ({', '.join(f'{x:.1f}' for x in cold)})")
    print(f"  warm (cached):       median {figures['warm_median_s']:.1f} s  ({', '.join(f'{x:.1f}' for x in warm)})")
    print(f"  compiled in the cold run: {total:.1f} s over {len(per_module)} module(s) of {loads} loaded")
    for name, seconds in figures["compile_s_median_by_module"].items():
        print(f"    {seconds:7.1f} s  {name}")


if __name__ == "__main__":
    main()
