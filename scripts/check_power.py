"""The power and the false-failure rate of ``warpis check``'s checks, measured (docs/check.md).

Power: each check is given a subject with a planted error of growing size, at the default
budget (10⁶ samples per frame, 4 frames, family-wise level 1e-3, every statistical test of
a full run in the family), over several seeds; the smallest size that the check catches in
every seed is its power figure.  False failures: correct subjects checked in full at a
family-wise level high enough to count failures (0.1), over many seeds.

    python scripts/check_power.py --power              # the power table (about 30 minutes on 2 cores)
    python scripts/check_power.py --false-failures     # the measured false-failure rates
    python scripts/check_power.py --power --seeds 3 --checks chi-square,pdf-integral

Planted errors (a numpy Lambertian technique, albedo 0.8, sampled cosine-weighted, at the
4 views of a spread; the light checks on occluded-quad's light-area at 4 receivers):

chi-square       the pdf and the density claimed ×(1 + ε) in the cap cos θ > 0.5 and
                 renormalised below it (∫pdf stays 1: only the histogram can tell)
pdf-integral     the pdf ×(1 + ε)
pdf-at-sample    the reported pdf ×(1 + ε)
zero-pdf         the pdf 0 in a cap about the normal holding a fraction ε of the samples
measure          the pdf × (t/t₀)^ε, t the distance to the light (an area density: ε = −2)
unbiased         the closed form ×(1 + ε) (a bias −ε of the estimator)
eval-quadrature  the sampler never draws cos θ < √ε (a fraction ε of the albedo)
energy           the albedo 1 + ε
weights-sum      balance weights ×(1 + ε)
weight           Mitsuba's GGX roughconductor (α 0.55, 4 views) with its sample weight ×(1 + ε)
reciprocity      the same with f(a → b) ×(1 + ε) at every pair
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import warpis  # noqa: E402
from warpis.check.entries import NumpyTechnique  # noqa: E402
from warpis.check.run import Budget, CombinerSubject, count_tests, run_combiner, run_subjects  # noqa: E402
from warpis.check.subjects import Subject, builtin_weights, numpy_technique, warp_technique  # noqa: E402
from warpis.kernels.estimators import COMBINERS  # noqa: E402

LADDERS = {
    "chi-square": [1e-3, 2e-3, 5e-3, 1e-2, 2e-2],
    "pdf-integral": [1e-4, 2e-4, 5e-4, 1e-3, 2e-3],
    "pdf-at-sample": [5e-4, 1e-3, 1.1e-3, 2e-3],
    "zero-pdf": [3e-6, 1e-5, 2e-5, 5e-5],
    "measure": [-0.0005, -0.001, -0.002, -0.005, -0.01],
    "unbiased": [2e-4, 5e-4, 1e-3, 2e-3],
    "eval-quadrature": [1e-4, 2e-4, 5e-4, 1e-3, 2e-3],
    "energy": [2e-4, 5e-4, 1e-3, 2e-3],
    "weights-sum": [1e-7, 1e-6, 2e-6, 1e-5],
    "weight": [5e-4, 1e-3, 1.1e-3, 2e-3],
    "reciprocity": [5e-4, 1e-3, 1.1e-3, 2e-3],
}


def tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(a, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def lambert(check: str | None = None, eps: float = 0.0) -> NumpyTechnique:
    """A cosine-weighted Lambertian technique with the planted error of ``check``."""
    albedo = 1.0 + eps if check == "energy" else 0.8
    cut = math.sqrt(eps) if check == "eval-quadrature" else 0.0
    zero_cos = math.sqrt(1.0 - eps) if check == "zero-pdf" else 2.0  # the cap cos θ > √(1 − ε) holds ε of them
    outside = 1.0 - eps * 0.75 / 0.25 if check == "chi-square" else 1.0

    def density(n, w):
        c = np.sum(n * w, axis=1)
        p = np.where(c > cut, c / (math.pi * (1.0 - cut * cut)), 0.0)
        if check == "chi-square":
            p = p * np.where(c > 0.5, 1.0 + eps, outside)
        if check == "pdf-integral":
            p = p * (1.0 + eps)
        if check == "zero-pdf":
            p = np.where(c > zero_cos, 0.0, p)
        return p

    def sample(n, wo, u):
        t, b = tangents(n)
        z = np.sqrt(1.0 - (1.0 - cut * cut) * u[:, 0])
        r, phi = np.sqrt(1.0 - z * z), 2.0 * math.pi * u[:, 1]
        w = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + z[:, None] * n
        p = density(n, w) * (1.0 + eps if check == "pdf-at-sample" else 1.0)
        return w, p

    def evaluate(n, wo, w):
        return albedo * np.maximum(np.sum(n * w, axis=1), 0.0) / math.pi

    return NumpyTechnique("lambert", sample, lambda n, wo, w: density(n, w), evaluate)


def light_subject(check: str | None = None, eps: float = 0.0) -> Subject:
    scene = warpis.load_scene("occluded-quad")
    subject = warp_technique(scene, "light-area", None, 4)
    if check == "unbiased":
        run = subject.unbiased.run
        subject.unbiased = dataclasses.replace(subject.unbiased, run=lambda trials, seed: [
            (label, mean, se, ref * (1.0 + eps)) for label, mean, se, ref in run(trials, seed)])
    if check == "measure":
        p0 = scene.receivers.positions
        for f in subject.frames:
            f.moved = _planted_moved(f, eps, float(2.0 - p0[f.receiver][2]))
            f.pdf = _scaled_by_distance(f.pdf, scene.receivers.positions[f.receiver], eps, float(2.0 - p0[f.receiver][2]))
    return subject


def _scaled_by_distance(pdf, position, k, t0):
    """pdf × (t/t0)^k, t the distance along each direction to the light's plane z = 2."""
    def scaled(d):
        t = np.where(d[:, 2] > 0.0, (2.0 - position[2]) / np.maximum(d[:, 2], 1e-12), t0)
        return pdf(d) * (t / t0) ** k
    return scaled


def _planted_moved(frame, k, t0):
    original = frame.moved

    def moved():
        f = original()
        return dataclasses.replace(f, pdf=_scaled_by_distance(f.pdf, _moved_position(frame), k, t0))
    return moved


def _moved_position(frame):
    scene = warpis.load_scene("occluded-quad")
    from warpis.check.subjects import MOVE_FACTOR

    tris = scene.triangle_vertices(scene.emitters)
    areas = np.asarray(scene.emitter_areas)
    c = (tris.mean(axis=1) * areas[:, None]).sum(axis=0) / areas.sum()
    return c + MOVE_FACTOR * (scene.receivers.positions[frame.receiver] - c)


def mitsuba_subject(check: str, eps: float) -> Subject:
    from warpis.check.mitsuba_bsdfs import bsdf_subjects

    subject = bsdf_subjects(str(Path(__file__).resolve().parents[1] / "docs" / "check-gallery" / "beckmann.xml"),
                            4)[1]
    for f in subject.frames:
        if check == "weight":
            f.draw = _scaled_weight(f.draw, eps)
        else:
            f.reciprocity = _scaled_pairs(f.reciprocity, eps)
    return subject


def _scaled_weight(draw, eps):
    def scaled(count, seed):
        d = draw(count, seed)
        return dataclasses.replace(d, weight=d.weight * (1.0 + eps))
    return scaled


def _scaled_pairs(pairs, eps):
    def scaled(count, seed):
        ab, ba = pairs(count, seed)
        return ab * (1.0 + eps), ba
    return scaled


def caught(check: str, eps: float, seed: int) -> bool:
    budget = Budget(seed=seed)
    if check == "weights-sum":
        scene = warpis.load_scene("occluded-quad")
        base = builtin_weights(COMBINERS["balance"])
        techs = [warp_technique(scene, t, None, 4) for t in ("light-area", "cosine")]
        run = run_combiner("power", CombinerSubject("planted", lambda p: base(p) * (1.0 + eps), techs),
                           dataclasses.replace(budget, checks=(check,)))
        return not run.passed
    if check in ("measure", "unbiased"):
        subject = light_subject(check, eps)
    elif check in ("weight", "reciprocity"):
        subject = mitsuba_subject(check, eps)
    else:
        subject = numpy_technique(lambert(check, eps), 4)
    # Only this check runs, held at the per-test level of a full run (its whole family).
    run = run_subjects(check, [subject], dataclasses.replace(budget, checks=(check,)),
                       tests=count_tests([subject], budget))
    return any(v.passed is False for v in run.verdicts if v.check == check)


def power(checks: list[str], seeds: int) -> None:
    print("| check | planted error | caught (of seeds) |")
    print("| --- | --- | --- |")
    for check in checks:
        for eps in LADDERS[check]:
            start = time.perf_counter()
            hits = sum(caught(check, eps, seed) for seed in range(seeds))
            print(f"| {check} | {eps:g} | {hits}/{seeds} ({time.perf_counter() - start:.0f} s) |", flush=True)


def false_failures(seeds: int, alpha: float) -> None:
    for name, make in (("numpy Lambert with eval, 4 views", lambda: [numpy_technique(lambert(), 4)]),
                       ("light-area at 4 receivers of occluded-quad", lambda: [light_subject()])):
        failed = 0
        start = time.perf_counter()
        for seed in range(seeds):
            run = run_subjects(name, make(), Budget(seed=1000 + seed, significance=alpha))
            failed += not run.passed
        print(f"{name}: {failed} of {seeds} full runs failed at family-wise level {alpha:g} "
              f"({time.perf_counter() - start:.0f} s)", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--power", action="store_true")
    parser.add_argument("--false-failures", action="store_true")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--alpha", type=float, default=0.1, help="family-wise level of the false-failure runs")
    parser.add_argument("--checks", default=",".join(LADDERS))
    args = parser.parse_args()
    if args.power:
        power(args.checks.split(","), args.seeds)
    if args.false_failures:
        false_failures(args.seeds, args.alpha)


if __name__ == "__main__":
    main()
