"""Analytic sphere lights against their tessellation: integrand evaluations per second on
the Veach scenes, side by side in one run.

    python scripts/bench_spheres.py [--scene mitsuba-veach-plates] [--n 64] [--repeat 5]
                                    [--seconds 1.5] [--threads T] [--json PATH]

The scene is loaded twice: as it is (its spheres analytic: light-solid-angle samples each
one's cone, rays meet it in float64) and with every sphere tessellated into 1,280
triangles pushed out to keep its area (what warpis did before spheres were analytic: a
TOML scene's ``[[sphere]]`` with ``tessellate = true``, a Mitsuba scene's receivers file
with ``tessellate = true``).  Same receivers, same estimators, same N and threads.  For
each estimator the two variants run alternately ``--repeat`` times after a pilot run
that sizes each to about ``--seconds``; the table gives each one's median rate (R × M × N
/ wall-clock seconds of ``run_trials``) and the ratio analytic / tessellated.  The
machine's 1-minute load average is printed before and after: read ratios, not rates.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import warpis
from warpis.kernels.engine import run_trials
from warpis.scenes import resolve_scene_path

ESTIMATORS = ("independent:single:light-solid-angle", "independent:single:light-area",
              "independent:single:bsdf", "independent:balance:light-solid-angle+bsdf")


def tessellated_copy(scene: str, folder: Path) -> Path:
    """The scene file of a copy of ``scene`` whose spheres are tessellated."""
    source = resolve_scene_path(scene)
    target = folder / source.parent.name
    shutil.copytree(source.parent, target)
    copy = target / source.name
    if copy.suffix == ".xml":
        side = copy.with_name(copy.stem + ".receivers.toml")
        side.write_text("tessellate = true\n" + side.read_text())
    else:
        text = copy.read_text().replace("[[sphere]]\n", "[[sphere]]\ntessellate = true\n")
        copy.write_text(text)
    return copy


def rate(scene: warpis.Scene, spec: str, n: int, trials: int, threads: int | None) -> float:
    start = time.perf_counter()
    out = run_trials(scene, spec, n, trials, seed=1, threads=threads)
    return out.size * n / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="mitsuba-veach-plates")
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=1.5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        variants = {"analytic": warpis.load_scene(args.scene),
                    "tessellated": warpis.load_scene(tessellated_copy(args.scene, Path(tmp)))}
    assert variants["analytic"].spheres is not None and variants["tessellated"].spheres is None
    rows = []
    for spec in ESTIMATORS:
        sizes = {}
        for name, scene in variants.items():
            pilot = rate(scene, spec, args.n, 64, args.threads)  # compiles and uploads, then sizes M
            sizes[name] = max(64, int(args.seconds * pilot / (len(scene.receivers) * args.n)))
        runs: dict[str, list[float]] = {name: [] for name in variants}
        for _ in range(args.repeat):
            for name, scene in variants.items():
                runs[name].append(rate(scene, spec, args.n, sizes[name], args.threads))
        med = {name: statistics.median(r) for name, r in runs.items()}
        rows.append({"estimator": spec, "median": med, "runs": runs, "ratio": med["analytic"] / med["tessellated"]})
        print(f"{spec:<45} analytic {med['analytic'] / 1e6:8.3f} M/s   tessellated {med['tessellated'] / 1e6:8.3f} M/s"
              f"   ratio {rows[-1]['ratio']:.2f}", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")
    if args.json is not None:
        args.json.write_text(json.dumps({"scene": args.scene, "n": args.n, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
