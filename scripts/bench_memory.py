"""Peak memory of ``warpis estimate`` against the number of trials M: it must be flat.

Each M runs ``warpis estimate`` in a fresh Python process (so every peak is that run's
own) on a cheap job, one receiver of occluded-quad with ``independent:single:light-area``
at N = 1, and reads the child's peak resident set size (``ru_maxrss`` of the finished
child).  ``warpis estimate`` streams the trials into running moments, so the peak should
not grow with M; keeping every trial would cost 8·M bytes (800 MB at M = 1e8).

Usage::

    python scripts/bench_memory.py                      # M = 1e5, 1e7, 1e8
    python scripts/bench_memory.py --trials 1e5,1e6 --threads 2

A benchmark, not a test: M = 1e8 takes about a minute on two cores.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

SCENE = "occluded-quad"
ESTIMATOR = "independent:single:light-area"


def peak_rss(trials: int, threads: int | None) -> tuple[float, float]:
    """(peak RSS in MiB, wall seconds) of one ``warpis estimate`` run in a fresh process."""
    cmd = [sys.executable, "-m", "warpis.cli", "estimate", SCENE, "--estimator", ESTIMATOR, "--n", "1",
           "--trials", str(trials), "--receivers", "0"]
    if threads:
        cmd += ["--threads", str(threads)]
    start = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        # wait4 rather than Popen.wait: it returns this child's own resource usage.
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.perf_counter() - start
        if proc.returncode != 0:
            err.seek(0)
            sys.exit(f"bench_memory: {' '.join(cmd)} failed ({proc.returncode}): {err.read().decode().strip()}")
    return usage.ru_maxrss / 1024.0, seconds  # ru_maxrss is in KiB on Linux


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default="1e5,1e7,1e8", help="comma-separated M values (default 1e5,1e7,1e8)")
    p.add_argument("--threads", type=int, help="worker threads (default: all cores)")
    args = p.parse_args()
    counts = [int(float(t)) for t in args.trials.split(",")]
    print(f"warpis estimate {SCENE} --estimator {ESTIMATOR} --n 1 --receivers 0 --trials M")
    print(f"{'M':>12} {'peak RSS MiB':>13} {'seconds':>9} {'8·M MiB':>9}")
    for m in counts:
        mib, seconds = peak_rss(m, args.threads)
        print(f"{m:>12.3g} {mib:>13.1f} {seconds:>9.1f} {8 * m / 2**20:>9.1f}", flush=True)


if __name__ == "__main__":
    main()
