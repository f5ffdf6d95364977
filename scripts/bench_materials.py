"""Microfacet evaluation must not dominate a trial: integrand evaluations per second of the
microfacet materials against Lambert on the same scene.

    python scripts/bench_materials.py [--json PATH] [--n 64] [--repeat 5] [--seconds 1.5]
                                      [--threads T] [--device cpu] [--no-plastic]

The scene is the bundled ``mitsuba-veach-plates`` (four GGX roughconductor plates, alpha
0.3 to 0.01, lit by four spheres; 16 receivers on the plates).  It is measured in up to
three material variants that differ in the receivers' material alone (same positions,
normals, view directions, same geometry and emitters):

* ``lambert``: every receiver lambert with albedo 0.5;
* ``conductor``: the scene as loaded (roughconductor, GGX, the file's alpha, eta and k);
* ``plastic``: every receiver roughplastic with the plates' alpha and distribution,
  diffuse albedo 0.5, specular reflectance 1 (spread over the colour channels by the
  scene's channel weights, as the Mitsuba importer does), eta 1.5 in every channel and
  Mitsuba's lobe-choice weight s / (d + s) = 2/3.  ``--no-plastic`` leaves it out.

For each of the estimators ``independent:single:light-solid-angle``,
``independent:single:bsdf`` and ``independent:balance:light-solid-angle+bsdf`` it times
:func:`warpis.kernels.engine.run_trials` on every variant with the same N and threads.
The ``bsdf`` technique is each material's own: cosine-weighted sampling for lambert,
visible-normal sampling for the microfacet materials.  The rate is integrand evaluations
per second, N per trial (one shadow ray each): R × M × N / wall-clock seconds of the call,
output array included.

Method: every variant is uploaded (Warp mesh, BVH, roughplastic's tables) and every
kernel compiled and loaded before anything is timed.  A short pilot run of each variant
picks its number of trials M so that one measurement takes about ``--seconds`` (each
variant gets its own M; the rate does not depend on it).  The variants then run
alternately, lambert, conductor, plastic, lambert, … ``--repeat`` times, and the table
shows the median rate of each.

Last, where the ``bsdf`` estimator's time goes: one launch (one core) of 2^22 ``bsdf``
samples per variant, first sampling the direction and its pdf alone, then also casting
the shadow ray and evaluating f as a trial does.  The difference between the variants in
the first column is the material's cost; in the second it is mostly where the rays go
(a microfacet lobe aims its rays at the lights, spheres of 1280 triangles each; cosine
directions mostly leave the scene), which no cheaper material could remove.

How to read it: the ratio columns are lambert's rate over the microfacet variant's, i.e.
how many times longer a trial takes when the receivers are microfacet surfaces; the
target is a ratio of at most 1.5 for every estimator.  A ratio near 1 means tracing the
shadow ray dominates a trial and the material costs little beside it.  The machine's
other load skews the rates (the variants run interleaved so that it skews them alike):
the header and footer print the 1-minute load average, and the JSON keeps every run's
rate besides the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp
from bench import Side  # scripts/bench.py, beside this file

import warpis
from warpis.kernels.engine import default_threads, run_trials
from warpis.kernels.device import ReceiverData, SceneData, upload
from warpis.kernels.integrand import MATERIALS, integrand, shading_point
from warpis.kernels.techniques import TECHNIQUES, LightTable, light_table, sample_technique

SCENE = "mitsuba-veach-plates"
ESTIMATORS = ("independent:single:light-solid-angle", "independent:single:bsdf",
              "independent:balance:light-solid-angle+bsdf")
ALBEDO = 0.5  # lambert's albedo and roughplastic's diffuse reflectance
PLASTIC_SPECULAR = 1.0  # roughplastic's specular reflectance
PLASTIC_ETA = 1.5
TARGET = 1.5  # lambert / microfacet rate, at most


def variants(scene, plastic: bool) -> dict:
    """The material variants of ``scene``: name → scene, lambert first."""
    rx = scene.receivers
    count = len(rx)
    conductor = MATERIALS["roughconductor"].code
    if not (rx.material == conductor).all():
        raise SystemExit(f"{scene.name}: expected every receiver to be roughconductor")
    out = {"lambert": replace(scene, receivers=replace(
        rx, material=np.full(count, MATERIALS["lambert"].code, np.int32), albedo=np.full(count, ALBEDO)))}
    out["conductor"] = scene
    if plastic:
        weights = rx.specular / rx.specular.sum(axis=1, keepdims=True)  # the scene's channel weights
        out["plastic"] = replace(scene, receivers=replace(
            rx, material=np.full(count, MATERIALS["roughplastic"].code, np.int32), albedo=np.full(count, ALBEDO),
            eta=np.full((count, 3), PLASTIC_ETA), k=np.zeros((count, 3)), specular=PLASTIC_SPECULAR * weights,
            specular_weight=np.full(count, PLASTIC_SPECULAR / (ALBEDO + PLASTIC_SPECULAR))))
    return out


class Variant(Side):
    """One material variant under one estimator: bench.py's Side (pilot calibration,
    timing) over warpis's run_trials on that variant's scene."""

    def __init__(self, name: str, scene, estimator: str, n: int, threads: int):
        self.name = name
        self.estimator = estimator
        self.n = n
        self.rows = len(scene.receivers)
        self.call = lambda m, seed: run_trials(scene, estimator, n, m, seed=seed, threads=threads)


@wp.kernel
def _bsdf_cost_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, technique: wp.int32, cast: wp.int32,
                      seed: wp.uint32, out: wp.array(dtype=float)):
    """One ``bsdf`` sample per thread at receiver tid mod R: its direction and pdf, and with
    ``cast`` also the shadow ray and f (the integrand), as a trial computes them."""
    i = wp.tid()
    sp = shading_point(scene, recv, i % recv.position.shape[0])
    state = wp.rand_init(wp.int32(seed), i)
    w, p = sample_technique(technique, scene, table, sp, wp.vec2(wp.randf(state), wp.randf(state)))
    value = p
    if cast != 0 and p > 0.0:
        value = integrand(scene, sp, w) / p
    out[i] = value


def cost_split(scenes: dict, device: str, samples: int = 1 << 22) -> dict:
    """ns per ``bsdf`` sample on one core (one launch), sampling alone and with the ray:
    which part of the gap between the variants is the material and which the rays its
    directions cast (a microfacet lobe aims at the lights, whose spheres are 1280
    triangles each; cosine directions mostly leave the scene)."""
    code = TECHNIQUES["bsdf"].code
    out = {}
    for name, scene in scenes.items():
        scene = scene.on(device)
        up, table = upload(scene), light_table(scene)
        result = wp.zeros(samples, dtype=float, device=up.device)
        ns = []
        for cast in (0, 1):
            times = []
            for rep in range(4):  # the first launch compiles and warms up
                t0 = time.perf_counter()
                wp.launch(_bsdf_cost_kernel, dim=samples, device=up.device,
                          inputs=[up.data, up.receiver_data, table, code, cast, rep, result])
                wp.synchronize_device(up.device)
                times.append(time.perf_counter() - t0)
            ns.append(statistics.median(times[1:]) / samples * 1e9)
        out[name] = (ns[0], ns[1])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=f"Integrand evaluations per second on {SCENE} with its roughconductor receivers, the same "
                    "receivers as lambert and as roughplastic; same estimator, N and threads; medians of "
                    "interleaved repeats.")
    ap.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), metavar="EST",
                    help=f"estimators to time (default: {' '.join(ESTIMATORS)})")
    ap.add_argument("--n", type=int, default=64, help="samples per trial, N (default: %(default)s)")
    ap.add_argument("--repeat", type=int, default=5,
                    help="interleaved measurements per variant; the median is reported (default: %(default)s)")
    ap.add_argument("--seconds", type=float, default=1.5,
                    help="target duration of one measurement; sets each variant's trials (default: %(default)s)")
    ap.add_argument("--trials", type=int, default=None,
                    help="trials per measurement for every variant, instead of --seconds")
    ap.add_argument("--threads", type=int, default=None,
                    help="worker threads (default: warpis.kernels.engine.default_threads(), "
                         "i.e. WARPIS_THREADS or every usable core)")
    ap.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0 (default: %(default)s)")
    ap.add_argument("--no-plastic", action="store_true", help="leave out the roughplastic variant")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write the rows as JSON to PATH")
    args = ap.parse_args(argv)
    args.threads = max(1, args.threads or default_threads())
    if args.n < 2 or args.n % 2:
        ap.error("--n must be even and at least 2 (the balance estimator splits N between two techniques)")
    if args.repeat < 1:
        ap.error("--repeat must be at least 1")

    scene = warpis.load_scene(SCENE, device=args.device)
    scenes = variants(scene, plastic=not args.no_plastic)
    names = list(scenes)
    micro = names[1:]
    load_before = os.getloadavg()
    print(f"warpis material bench: {scene.name}, {len(scene.receivers)} receivers, "
          f"alpha {scene.receivers.alpha.min():.3g}..{scene.receivers.alpha.max():.3g}; variants "
          f"{', '.join(names)}; {args.threads} thread(s), device {args.device}, N = {args.n}, median of "
          f"{args.repeat} interleaved runs, {os.cpu_count()} CPUs, {platform.processor() or platform.machine()}; "
          f"load average at start {load_before[0]:.2f}", flush=True)
    rows = []
    for est in args.estimators:
        runs = [Variant(name, scenes[name], est, args.n, args.threads) for name in names]
        for v in runs:
            v.warm_up()
        trials = {v.name: args.trials or v.calibrate(args.seconds) for v in runs}
        rates: dict[str, list[float]] = {v.name: [] for v in runs}
        for rep in range(args.repeat):
            for v in runs:
                rates[v.name].append(v.time(trials[v.name], 100 + rep))
        median = {name: statistics.median(r) for name, r in rates.items()}
        row = {
            "scene": scene.name, "estimator": est,
            **{f"{name}_per_s": median[name] for name in names},
            **{f"ratio_{name}": median["lambert"] / median[name] for name in micro},
            "threads": args.threads, "device": args.device, "n": args.n, "receivers": len(scene.receivers),
            **{f"{name}_trials": trials[name] for name in names},
            **{f"{name}_runs_per_s": rates[name] for name in names},
        }
        rows.append(row)
        print(f"  {est}: " + ", ".join(f"{name} {median[name] / 1e6:.3g} M/s (M = {trials[name]})"
                                       for name in names), flush=True)
    load_after = os.getloadavg()

    print()
    header = (f"{'estimator':<43} {'thr':>3} " + " ".join(f"{name + ' eval/s':>17}" for name in names)
              + " " + " ".join(f"{'lam/' + name[:5]:>10}" for name in micro))
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['estimator']:<43} {r['threads']:>3} " + " ".join(f"{r[f'{name}_per_s']:>17.4g}" for name in names)
              + " " + " ".join(f"{r[f'ratio_{name}']:>10.2f}" for name in micro))
    print()
    print(f"eval/s: integrand evaluations (one shadow ray each, N per trial) per second, median of {args.repeat}; "
          f"lam/X = lambert eval/s / X eval/s (target: at most {TARGET:g}).")
    worst = max(r[f"ratio_{name}"] for r in rows for name in micro)
    failing = [f"{r['estimator']} ({name})" for r in rows for name in micro if r[f"ratio_{name}"] > TARGET]
    if failing:
        print(f"largest ratio {worst:.2f}: the {TARGET:g}x target does NOT hold for " + ", ".join(failing) + ".")
    else:
        print(f"largest ratio {worst:.2f}: the {TARGET:g}x target holds for every estimator and microfacet variant.")
    spread = [max(v) / min(v) for r in rows for v in (r[f"{name}_runs_per_s"] for name in names)]
    print(f"largest max/min spread of a variant's {args.repeat} runs: {max(spread):.2f}; 1-min load average "
          f"{load_before[0]:.2f} at start, {load_after[0]:.2f} after the timed runs "
          f"(other processes competing for the {os.cpu_count()} CPUs skew the rates)")

    split = cost_split(scenes, args.device)
    print("\nwhere the bsdf estimator's time goes, one core, ns per sample (median of 3 launches of 2^22 samples):")
    for name, (sample_only, with_ray) in split.items():
        print(f"  {name:<10} sample + pdf {sample_only:6.1f}   + shadow ray and f {with_ray - sample_only:6.1f}"
              f"   = {with_ray:6.1f}")

    if args.json:
        doc = {
            "bsdf_cost_split_ns": {k: {"sample_and_pdf": a, "with_ray": b} for k, (a, b) in split.items()},
            "rows": rows, "scene": scene.name, "variants": names, "target_ratio": TARGET,
            "target_holds": worst <= TARGET,
            "n": args.n, "repeat": args.repeat, "threads": args.threads, "device": args.device,
            "cpu_count": os.cpu_count(), "numpy": np.__version__, "warpis": warpis.__version__,
            "loadavg_start": load_before[0], "loadavg_after_timing": load_after[0],
            "materials": {"lambert": f"albedo {ALBEDO}",
                          "conductor": "as loaded (GGX roughconductor)",
                          "plastic": f"roughplastic, the plates' alpha and distribution, albedo {ALBEDO}, specular "
                                     f"{PLASTIC_SPECULAR}, eta {PLASTIC_ETA}"},
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
