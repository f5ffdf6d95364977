"""How long ``warpis image`` takes, phase by phase, beside the bare trial engine on the same work.

    python scripts/bench_image.py [--scene veach-plates-camera] [--width 128 --height 96] [--n 16]
                                  [--trials 256] [--points 4096] [--threads T] [--device cpu]
                                  [--estimator SPEC ...] [--json PATH]

The run is the one ``warpis image`` does (``warpis.runs.image.run_image`` into a fresh
folder): every tile of every estimator measured, trial 0 of each, the reference image, the
exact predictions, the arrays, PNGs and index.html.  Defaults: the bundled
``veach-plates-camera`` at 128 × 96 with four estimators (light sampling, BSDF sampling,
balance and power MIS, all jittered), N = 16, 256 trials, 4096 prediction points per pixel
and technique; ``--scene mitsuba-veach-plates`` runs the Mitsuba twin (floor and backdrop
too: about five times as many pixels) through its sensor.

Baseline, in the same process right after: the same trials through
:func:`warpis.kernels.engine.run_moments` in one call per estimator over every pixel, no
tiles, no files.  The ratio image-measuring time ÷ bare time is the price of tiles,
resumability and progress; the rest of the table is what predictions, the reference and
the pictures add.  Times are wall-clock seconds on a machine that may be shared: the 1-minute
load average is printed beside them.  The target is the whole image under 5 minutes on a
2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_ESTIMATORS = ("jittered:single:light-solid-angle", "jittered:single:bsdf",
                      "jittered:balance:light-solid-angle+bsdf", "jittered:power:light-solid-angle+bsdf")
TARGET_SECONDS = 300.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="veach-plates-camera")
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--height", type=int, default=96)
    p.add_argument("--n", type=int, default=16)
    p.add_argument("--trials", type=int, default=256)
    p.add_argument("--points", type=int, default=4096)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--device", default="cpu")
    p.add_argument("--estimator", action="append", default=None)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    import warpis
    from warpis.kernels.engine import default_threads, run_moments
    from warpis.kernels.estimators import parse_estimator
    from warpis.runs import image

    estimators = tuple(parse_estimator(s) for s in (args.estimator or DEFAULT_ESTIMATORS))
    scene = warpis.load_scene(args.scene, device=args.device, camera=True, width=args.width, height=args.height)
    threads = args.threads or default_threads()
    run = image.ImageRun(scene, estimators, args.n, args.trials, 0, 0, args.points, threads=threads)
    # Compile and load every kernel before anything is timed.
    for est in estimators:
        run_moments(scene, est, args.n, 4, receivers=[0], threads=threads)
    print(f"{scene.name}: {len(scene.receivers)} pixels measured of {args.width} × {args.height}, "
          f"{len(estimators)} estimators, N = {args.n}, {args.trials} trials, {args.points} prediction points; "
          f"{threads} threads, {platform.processor() or platform.machine()}, load {os.getloadavg()[0]:.2f}",
          flush=True)

    phases: dict[str, float] = {}
    logged = time.perf_counter()

    def log(line: str) -> None:
        nonlocal logged
        now = time.perf_counter()
        phases[line] = now - logged
        logged = now

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        result = image.run_image(run, Path(tmp) / "out", log=log)
        total = time.perf_counter() - start
    measured = sum(v for k, v in phases.items() if k.startswith("measured"))
    singles = sum(v for k, v in phases.items() if k.startswith("trial 0"))
    reference = sum(v for k, v in phases.items() if k.startswith("reference image"))
    predicting = sum(v for k, v in phases.items() if k.startswith("predicted"))
    bare = {}
    for est in estimators:
        t = time.perf_counter()
        run_moments(scene, est, args.n, args.trials, threads=threads)
        bare[est.spec] = time.perf_counter() - t
    rows = [("measuring (tiles, saved as they finish)", measured),
            ("trial 0 of each estimator", singles),
            ("reference image", reference),
            ("predictions", predicting),
            ("arrays, pictures, index.html", total - measured - singles - reference - predicting),
            ("whole image", total)]
    print(f"{'phase':<44} {'seconds':>9}")
    for name, seconds in rows:
        print(f"{name:<44} {seconds:>9.1f}")
    bare_total = sum(bare.values())
    print(f"bare run_moments over every pixel, same trials: {bare_total:.1f} s "
          f"(image measuring ÷ bare = {measured / bare_total:.2f})")
    print(f"target: whole image under {TARGET_SECONDS:.0f} s: {'met' if total < TARGET_SECONDS else 'MISSED'}; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"prediction budget: {result.meta['prediction']}")
    for line in image.summary_lines(result):
        print(line)
    if args.json is not None:
        args.json.write_text(json.dumps({"scene": scene.name, "pixels": len(scene.receivers), "phases": dict(rows),
                                         "bare": bare, "threads": threads, "summary": result.meta["summary"],
                                         "prediction": result.meta["prediction"]}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
