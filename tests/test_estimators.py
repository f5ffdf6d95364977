"""Estimators are unbiased on every bundled scene, deterministic, and match closed-form variances.

Statistical thresholds.  The mean of M = 4000 trials is compared with the reference by
z = (mean − reference)/sqrt(se_mean² + se_ref²).  Over all comparisons of
``test_every_estimator_is_unbiased`` (K of them, counted in the test) the per-comparison
threshold is the two-sided Bonferroni bound z* = Φ⁻¹(1 − α/(2K)) with α = 1e-3, so the
whole test fails by chance with probability ≤ 1e-3 under the normal approximation of the
mean of 4000 trials.  That approximation needs enough non-zero estimates; the BSDF-blind
techniques (uniform, cosine) are therefore held only at receivers where they meet the
light in at least ~13% of the trials (``BLIND_RECEIVERS``): on veach-plates a uniform
direction almost never meets the small lights in a glossy lobe, and the mean of 4000
trials there is far from normal (it is still unbiased, but no finite test could tell).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.stats import norm

from conftest import BUNDLED, concat_meshes, sky_environment

import warpis
from warpis.analysis.reference import reference
from warpis.stats import variance_interval
from warpis.kernels.engine import run_trials
from warpis.kernels.estimators import COMBINERS, Estimator, parse_estimator
from warpis.kernels.integrand import MATERIALS, evaluate_integrand
from warpis.kernels.patterns import PATTERNS
from warpis.kernels.techniques import TECHNIQUES, check_lights, direction_pdf, sample_directions
from warpis.runs.verify import default_techniques

TRIALS = 4000
N = 12  # divisible by 2 and 3, even per technique: every combination below can take it …


def n_for(est: Estimator) -> int:
    """N, or for a combiner with a pilot the first multiple of N that leaves its pattern a
    count it can take (a paired pattern needs an even count after the pilot)."""
    return next(n for n in range(N, 16 * N, N) if _takes(est, n))


def _takes(est: Estimator, n: int) -> bool:
    try:
        est.check_n(n)
    except warpis.WarpisError:
        return False
    return True
ALPHA = 1e-3
# The lobes of glossy materials: sampled only on scenes with such receivers.
LOBES = {m.bsdf_technique for m in MATERIALS.values() if not m.diffuse}
# BSDF-blind techniques: neither the lights nor a lobe.
BLIND = tuple(t for t, e in TECHNIQUES.items() if not e.light and t not in LOBES)
# Representative sets for the combiners of several techniques; "BSDF" stands for the
# scene's BSDF sampling (cosine, or the glossy receivers' lobe).
SETS = (("light-area", "BSDF"), ("light-solid-angle", "BSDF"), ("light-power", "uniform"),
        ("light-area", "light-solid-angle", "BSDF"))
# Receivers where BSDF-blind sampling meets the light often enough for a normal mean.
BLIND_RECEIVERS = {"veach-plates": [2, 3, 6, 7, 11, 15]}
# The receivers each estimator runs at.  A wrong weight, stratum or pdf biases the mean
# at every lit receiver, so four per scene of different kinds catch what all eight did
# (scripts/mutants.py: every mutant of this file still killed): fully lit, the brightest,
# a penumbra, and one that sees no light at all (its every estimate must be exactly 0).
# veach-plates keeps one receiver per plate–light pairing of interest (small and large
# lights on the least and most glossy plates).
RECEIVERS = {
    "occluded-quad": [0, 1, 3, 5],  # lit, brightest, occluded (F = 0), penumbra
    "heavy-occluder": [0, 3, 4, 6],  # lit, deep penumbra (F = 0.027), occluded (F = 0), partly lit
    "two-lights": [0, 1, 4, 6],  # both lights at several distances: F from 1.37 to 10.6
    "sky": [0, 1, 2, 4],  # on either side of the box (each loses sky to it), under the lamp, in the open
    "veach-plates": [0, 3, 5, 10, 12, 15],
}


def scene_techniques(scene: warpis.Scene) -> tuple[str, ...]:
    """Every registered technique, the lobes only where the scene has their material."""
    present = {MATERIALS.by_code(c).bsdf_technique for c in np.unique(scene.receivers.material)}
    return tuple(t for t, e in TECHNIQUES.items() if (t not in LOBES or t in present)
                 and (scene.environment is not None or not e.environment) and (scene.emitter_count or not e.light))


def technique_sets(scene: warpis.Scene) -> list[tuple[str, ...]]:
    """``SETS`` for this scene, plus each technique that no set names on any scene (a new
    entry) beside light-area."""
    bsdf = default_techniques(scene)[1]
    sets = [tuple(bsdf if t == "BSDF" else t for t in s) for s in SETS]
    covered = {t for s in SETS for t in s} | {m.bsdf_technique for m in MATERIALS.values()}
    return sets + [(t, "light-area") for t in scene_techniques(scene) if t not in covered]


# Combiners held on the first and last representative sets only (two and three
# techniques): each evaluates every pdf at every sample, or cuts balance by a threshold,
# and the suite's time is better spent on their own tests (tests/test_optimal_mis.py).
FEWER_SETS = ("cutoff", "optimal-oracle", "optimal")


# Each technique tuple of a combiner runs under every PATTERN_STRIDE-th pattern, the
# choice rotated from tuple to tuple and from combiner to combiner: every pattern meets
# every combiner, every tuple meets patterns of several kinds, and a scene runs about a
# third of the whole product (patterns and combiners are separate stages of the trial
# kernel: a wrong pattern or weight biases every estimator that uses it).
PATTERN_STRIDE = 3


def estimators_for(scene: warpis.Scene) -> list[Estimator]:
    """Every unbiased combiner over its technique tuples (one-technique combiners: every
    technique; the others: the representative sets), each tuple under a rotating share of
    the patterns (``PATTERN_STRIDE``; a half where a combiner has only two tuples), so
    that each combiner meets every pattern."""
    techs, sets = scene_techniques(scene), technique_sets(scene)
    unbiased = [c for c in COMBINERS.values() if c.unbiased]
    patterns = list(PATTERNS)
    out = []
    for c_index, c in enumerate(unbiased):
        tuples = (sets[:1] + sets[3:] if c.name in FEWER_SETS else sets) if c.several else [(t,) for t in techs]
        tuples = [s for s in tuples if _reaches_every_light(scene, Estimator(patterns[0], c.name, s))]
        stride = min(len(tuples), PATTERN_STRIDE)
        for j, s in enumerate(tuples):
            out += [Estimator(p, c.name, s) for i, p in enumerate(patterns) if (i + j + c_index) % stride == 0]
    return out


def _reaches_every_light(scene: warpis.Scene, est: Estimator) -> bool:
    """Whether the estimator's techniques see all of the scene's light (check_lights: on a
    scene with an environment and emitter triangles, light techniques alone do not)."""
    try:
        check_lights(scene, est.techniques)
    except warpis.WarpisError:
        return False
    return True


def receivers_for(scene_name: str, est: Estimator, count: int) -> list[int]:
    if any(t in BLIND for t in est.techniques) and scene_name in BLIND_RECEIVERS:
        return BLIND_RECEIVERS[scene_name]
    return RECEIVERS.get(scene_name, list(range(count)))


class _References(dict):
    """Scene name → (scene, {receiver: (reference, stderr)}), computed on first use."""

    def __missing__(self, name: str):
        scene = sky_scene() if name == "sky" else warpis.load_scene(name)
        self[name] = (scene, {r.index: (r.value, r.stderr) for r in reference(scene)})
        return self[name]


@pytest.fixture(scope="module")
def references() -> _References:
    return _References()


def sky_scene() -> warpis.Scene:
    """conftest's procedural sky over a floor with a box, and a small quad light: envmap
    in every pattern and combiner, with and without the light techniques."""
    floor = (np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]]),
             np.array([[0, 1, 2], [0, 2, 3]]), 0.0)
    box = (np.array([[0.3, -0.2, 0.0], [0.7, -0.2, 0.0], [0.7, 0.2, 0.0], [0.3, 0.2, 0.0], [0.3, -0.2, 0.5],
                     [0.7, -0.2, 0.5], [0.7, 0.2, 0.5], [0.3, 0.2, 0.5]]),
           np.array([[4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6],
                     [3, 0, 4], [3, 4, 7]]), 0.0)
    lamp = (np.array([[-0.6, -0.1, 1.0], [-0.4, -0.1, 1.0], [-0.4, 0.1, 1.0], [-0.6, 0.1, 1.0]]),
            np.array([[0, 2, 1], [0, 3, 2]]), 20.0)
    vertices, triangles, emission = concat_meshes([floor, box, lamp])
    return warpis.Scene.from_arrays(vertices, triangles, emission, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0],
                                                                    [-0.5, 0.3, 0.0], [0.5, -0.5, 0.0],
                                                                    [-1.0, -1.0, 0.0], [0.2, 0.9, 0.0]], [0, 0, 1], material="lambert",
                                    albedo=0.6, environment=sky_environment(), name="sky")


@pytest.mark.parametrize("name", BUNDLED + ("sky",))
def test_every_estimator_is_unbiased(references, name):
    """Every combiner over every technique tuple, each under a rotating third of the
    patterns (``estimators_for``: every pattern meets every combiner and every size of
    technique set): mean within z* of the reference.

    False-failure probability ≤ 2.5e-4 per scene, 1e-3 over the four bundled TOML scenes
    (Bonferroni over all comparisons of a scene).
    """
    scene, refs = references[name]
    cells = []
    estimators = estimators_for(scene)
    for est in estimators:
        rx = receivers_for(name, est, len(scene.receivers))
        values = run_trials(scene, est, n_for(est), TRIALS, seed=11, receivers=rx)
        for r, row in zip(rx, values):
            cells.append((name, est.spec, r, row.mean(), row.std(ddof=1) / np.sqrt(TRIALS), *refs[r]))
    k = len(cells)
    z_star = float(norm.ppf(1 - ALPHA / 4 / (2 * k)))
    failures = []
    for name, spec, r, mean, se, ref, ref_se in cells:
        se_total = np.hypot(se, ref_se)
        if se_total == 0:
            if mean != ref:
                failures.append(f"{name} {spec} receiver {r}: {mean} != {ref} with zero spread")
            continue
        z = (mean - ref) / se_total
        if abs(z) > z_star:
            failures.append(f"{name} {spec} receiver {r}: mean {mean:.6g} reference {ref:.6g} z = {z:.2f}")
    assert k >= 4 * len(estimators)
    unbiased = {c.name for c in COMBINERS.values() if c.unbiased}
    assert {(e.pattern, e.combiner) for e in estimators} == set(itertools.product(PATTERNS, unbiased))
    assert not failures, f"{len(failures)} of {k} cells beyond z* = {z_star:.2f}:\n" + "\n".join(failures[:20])


def _integral_of_f_times_g(scene: warpis.Scene, receiver: int, technique: str, samples: int = 1 << 18,
                           seed: int = 5) -> tuple[float, float]:
    """∫ f g dω by IS from light-solid-angle + the technique (a mixture), with its stderr."""
    rng = np.random.default_rng(seed)
    half = samples // 2
    dirs = []
    for tech in ("light-solid-angle", technique):
        d, _ = sample_directions(scene, receiver, tech, rng.random((half, 2)))
        dirs.append(d)
    d = np.vstack(dirs)
    valid = np.linalg.norm(d, axis=1) > 0
    mix = 0.5 * (direction_pdf(scene, receiver, "light-solid-angle", d) + direction_pdf(scene, receiver, technique, d))
    fg = evaluate_integrand(scene, receiver, d) * direction_pdf(scene, receiver, technique, d)
    h = np.where(valid & (mix > 0), fg / np.where(mix > 0, mix, 1.0), 0.0)
    # The two halves are stratified by technique, so the mixture estimate is the mean of
    # the per-technique means, each with its own variance.
    a, b = h[:half], h[half:]
    return float(0.5 * (a.mean() + b.mean())), float(0.5 * np.hypot(a.std(ddof=1) / np.sqrt(half),
                                                                     b.std(ddof=1) / np.sqrt(half)))


@pytest.mark.parametrize("scene_name,technique", [("occluded-quad", "cosine"), ("occluded-quad", "light-area"),
                                                  ("two-lights", "uniform"), ("veach-plates", "phong")])
def test_biased_estimator_converges_to_integral_of_f_times_g(references, scene_name, technique):
    """Seed eq. 18/19: the unweighted mean of f over X ~ g converges to ∫ f g, not to F.

    Four scenes × receivers compared at |z| ≤ 4.5 (two-sided 6.8e-6 each; union bound
    over ≤ 40 comparisons: false failure < 3e-4).
    """
    scene, refs = references[scene_name]
    rx = list(range(min(len(scene.receivers), 8)))
    values = run_trials(scene, f"independent:biased:{technique}", 16, TRIALS, seed=3, receivers=rx)
    for r, row in zip(rx, values):
        target, target_se = _integral_of_f_times_g(scene, r, technique)
        se = np.hypot(row.std(ddof=1) / np.sqrt(TRIALS), target_se)
        if se == 0:
            assert row.mean() == target
            continue
        assert abs(row.mean() - target) <= 4.5 * se, (r, row.mean(), target, se)
        if refs[r][0] > 0 and target > 0:
            assert not np.isclose(target, refs[r][0], rtol=1e-2), "∫ f g should differ from F here"


# --------------------------------------------------------------------------- determinism


@pytest.fixture(scope="module")
def quad():
    return warpis.load_scene("occluded-quad")


@pytest.mark.parametrize("spec", ["jittered:balance:light-area+cosine", "antithetic:mixture:light-solid-angle+uniform",
                                  "jittered-antithetic:power:light-power+cosine"])
def test_results_are_bit_identical_across_threads_and_chunks(quad, spec):
    """Random numbers depend on (seed, receiver, trial, technique, sample, dim) only."""
    a = run_trials(quad, spec, 16, 301, seed=9, threads=1, chunk=301)
    b = run_trials(quad, spec, 16, 301, seed=9, threads=2, chunk=7)
    c = run_trials(quad, spec, 16, 301, seed=9, threads=2, chunk=64)
    assert np.array_equal(a, b) and np.array_equal(a, c)


def test_results_do_not_depend_on_receiver_order(quad):
    """Receiver r's trials are the same whichever receivers run beside it."""
    full = run_trials(quad, "jittered:single:light-area", 8, 100, seed=2)
    picked = run_trials(quad, "jittered:single:light-area", 8, 100, seed=2, receivers=[6, 1, 5])
    assert np.array_equal(picked, full[[6, 1, 5]])


def test_trials_are_a_prefix_of_longer_runs(quad):
    """Trial t is the same estimate in a run of 50 or 500 trials (resumable studies rely on it)."""
    short = run_trials(quad, "independent:single:cosine", 8, 50, seed=4)
    long = run_trials(quad, "independent:single:cosine", 8, 500, seed=4)
    assert np.array_equal(short, long[:, :50])


def test_different_seeds_give_uncorrelated_trials(quad):
    """Seeds 0 and 1: correlation of paired estimates is within 4.5/√M of 0 (false failure 7e-6)."""
    a = run_trials(quad, "independent:single:light-area", 4, 4000, seed=0, receivers=[1])[0]
    b = run_trials(quad, "independent:single:light-area", 4, 4000, seed=1, receivers=[1])[0]
    assert abs(np.corrcoef(a, b)[0, 1]) < 4.5 / np.sqrt(4000)
    assert not np.array_equal(a, b)


# --------------------------------------------------------------------------- closed-form variances


@pytest.fixture(scope="module")
def dome(tmp_path_factory):
    """A receiver at the centre of a closed, inward-facing sphere of radiance 2, nothing else."""
    import trimesh

    d = tmp_path_factory.mktemp("dome")
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    sphere.invert()  # front faces inwards
    sphere.export(d / "dome.obj")
    (d / "scene.toml").write_text(
        'name = "dome"\n[[mesh]]\npath = "dome.obj"\nemission = 2.0\n'
        '[receivers]\npoints = [[0.0, 0.0, 0.0], [1.0, 2.0, 0.5]]\nnormals = [[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]]\n'
        '[material]\ntype = "irradiance"\n')
    return warpis.load_scene(d / "scene.toml")


def _inside(measured: np.ndarray, predicted: float, z: float = 4.5) -> None:
    v = variance_interval(measured)
    assert np.all(np.abs(v.variance - predicted) <= z * v.variance_stderr), (v.variance, predicted, v.variance_stderr)


def test_uniform_sampling_of_a_constant_dome_has_the_closed_form_variance(dome):
    """f/pdf = 2πL cos θ with cos θ ~ U(0,1): Var = (2πL)²/12 per sample, /N for N samples.

    |s² − V| ≤ 4.5·se(s²) per receiver, and the mean within 4.5 of its standard errors of
    πL (2 receivers × 2 checks, two-sided normal 6.8e-6 each: false failure ≈ 2.7e-5).
    (The mean was held at 5e-3 relative, only 3.5 standard errors: 1.1e-3.)
    """
    n, trials, radiance = 8, 20000, 2.0
    values = run_trials(dome, "independent:single:uniform", n, trials, seed=1)
    se = values.std(axis=1, ddof=1) / np.sqrt(trials)
    assert np.all(np.abs(values.mean(axis=1) - np.pi * radiance) <= 4.5 * se), (values.mean(axis=1), se)
    _inside(values, (2 * np.pi * radiance) ** 2 / 12 / n)


def test_jittered_uniform_sampling_of_a_constant_dome_has_the_closed_form_variance(dome):
    """Jittered on a rows × cols grid: cos θ = u.x is uniform within a cell of width 1/cols,
    so Var = (2πL)² / (12 N cols²).

    |s² − V| ≤ 4.5·se(s²) per receiver (2 receivers, M = 20000; two-sided normal 6.8e-6
    each, false failure ≈ 1.4e-5)."""
    n, trials, radiance = 12, 20000, 2.0  # grid 3 × 4
    values = run_trials(dome, "jittered:single:uniform", n, trials, seed=1)
    _inside(values, (2 * np.pi * radiance) ** 2 / (12 * n * 4**2))


# --------------------------------------------------------------------------- the kernel against its formulas
#
# Every trial is a pure function of (seed, receiver, trial, technique, sample, dim)
# (warpis.kernels.rng.uniform_np is the numpy twin of the kernel's generator), so a trial
# of an independent-pattern estimator can be replayed in numpy: the same primary samples,
# mapped by the public sample_directions, with f from evaluate_integrand and every g_j from
# direction_pdf, combined by the combiner's formula as docs/theory.md ("One form for every
# estimator") writes it — written out here, not taken from warpis's numpy weights.


CUTOFF = 0.02  # the replayed cutoff: at receiver 0 of occluded-quad it differs from both balance and maximum


def _replay_combiner(name: str, f: np.ndarray, g: np.ndarray, k: np.ndarray) -> np.ndarray:
    """ψ of each sample: f (K,), g (K, N_g) every technique's pdf at it, k (K,) its technique."""
    gk = g[np.arange(len(f)), k]
    kept = g.astype(np.float32) >= np.float32(CUTOFF) * g.astype(np.float32).max(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        psi = {"single": f / gk, "mixture": f / g.mean(axis=1), "balance": f / g.mean(axis=1),
               "power": f * gk / (g * g).sum(axis=1), "biased": f,
               "maximum": np.where(np.argmax(g, axis=1) == k, f / gk, 0.0),
               "cutoff": np.where(kept[np.arange(len(f)), k], f / np.where(kept, g, 0.0).sum(axis=1), 0.0)}[name]
    valid = (f > 0) if name == "biased" else (f > 0) & (gk > 0)
    return np.where(valid, psi, 0.0)


def _samples(scene: warpis.Scene, r: int, techs: tuple[str, ...], k: int, u: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """f (K,) and every technique's pdf (K, N_g) at technique k's samples from u (K, 2):
    both 0 where the sample fails (no direction, or its own pdf 0)."""
    w = sample_directions(scene, r, techs[k], u)[0]
    g = np.stack([direction_pdf(scene, r, tech, w) for tech in techs], axis=1)
    valid = (np.linalg.norm(w, axis=1) > 0) & (g[:, k] > 0)
    f = np.where(valid, evaluate_integrand(scene, r, np.where(valid[:, None], w, 1.0)), 0.0)
    return f, np.where(valid[:, None], g, 0.0)


def _optimal_terms(f: np.ndarray, g: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """r = g/Σ g (e_k at a failed sample) and f/Σ g (0 there): docs/theory.md, "Optimal MIS"."""
    total = g.sum(axis=1, keepdims=True)
    valid = g[:, k:k + 1] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(valid, g / total, np.eye(g.shape[1])[k]), np.where(valid[:, 0], f / total[:, 0], 0.0)


def _replay_optimal(scene: warpis.Scene, r: int, est: Estimator, n: int, trials: int, seed: int) -> np.ndarray:
    """The trials of ``independent:optimal[-oracle]`` at receiver r, recomputed in numpy:
    α from the pilot (its own streams, a ridge of 1% of Â's mean diagonal) or the oracle,
    then Σ α + (1/m) Σ_k Σ_i (f − α·g)/Σ g."""
    from warpis.analysis.quadrature import optimal_alpha
    from warpis.kernels.estimators import PILOT_STREAM
    from warpis.kernels.rng import uniform_np

    techs, n_g = est.techniques, est.technique_count
    m, pilot = est.per_technique(n), est.pilot_samples(n)
    t = np.arange(trials)[:, None]
    alpha = np.repeat(optimal_alpha(scene, [r], techs), trials, axis=0)
    if pilot:
        a, b = np.zeros((trials, n_g, n_g)), np.zeros((trials, n_g))
        for k in range(n_g):
            u = np.stack([uniform_np(seed, r, t, PILOT_STREAM + k, np.arange(pilot)[None, :], d)
                          for d in (0, 1)], axis=-1).reshape(-1, 2)
            rr, fs = _optimal_terms(*_samples(scene, r, techs, k, u), k)
            rr, fs = rr.reshape(trials, pilot, n_g), fs.reshape(trials, pilot)
            a += np.einsum("tpi,tpj->tij", rr, rr)
            b += np.einsum("tp,tpi->ti", fs, rr)
        a += 0.01 * np.trace(a, axis1=1, axis2=2)[:, None, None] / n_g * np.eye(n_g)
        alpha = np.linalg.solve(a, b[..., None])[..., 0]
    total = alpha.sum(axis=1)
    for k in range(n_g):
        u = np.stack([uniform_np(seed, r, t, k, np.arange(m)[None, :], d) for d in (0, 1)], axis=-1).reshape(-1, 2)
        rr, fs = _optimal_terms(*_samples(scene, r, techs, k, u), k)
        total += (fs.reshape(trials, m) - np.einsum("tpi,ti->tp", rr.reshape(trials, m, n_g), alpha)).sum(axis=1) / m
    return total


def _replay(scene: warpis.Scene, r: int, est: Estimator, n: int, trials: int, seed: int) -> np.ndarray:
    """The trials of an ``independent:*`` estimator at receiver r, recomputed in numpy."""
    from warpis.kernels.estimators import PICK_STREAM
    from warpis.kernels.rng import uniform_np

    techs, n_g = est.techniques, est.technique_count
    split = est.combiner_entry.splits_n  # balance, power: m = N/N_g points per technique
    m = n // n_g if split else n
    t, i = np.arange(trials)[:, None], np.arange(m)[None, :]
    total = np.zeros(trials)
    for stream in range(n_g if split else 1):
        u = np.stack([uniform_np(seed, r, t, stream, i, d) for d in (0, 1)], axis=-1).reshape(-1, 2)
        if est.combiner == "mixture":  # the technique of each sample, from its own stream
            pick = uniform_np(seed, r, t, PICK_STREAM, i, 0).reshape(-1)
            k = np.minimum((pick * n_g).astype(int), n_g - 1)
        else:
            k = np.full(len(u), stream)
        w = np.zeros((len(u), 3), np.float32)
        for kk in set(k.tolist()):
            w[k == kk] = sample_directions(scene, r, techs[kk], u[k == kk])[0]
        valid = np.linalg.norm(w, axis=1) > 0
        f = np.where(valid, evaluate_integrand(scene, r, np.where(valid[:, None], w, 1.0)), 0.0)
        g = np.stack([direction_pdf(scene, r, tech, w) for tech in techs], axis=1)
        total += _replay_combiner(est.combiner, f, g, k).reshape(trials, m).sum(axis=1)
    return total / (n if est.combiner in ("mixture", "balance") else m)


@pytest.mark.parametrize("combiner", list(COMBINERS))
def test_trial_kernel_equals_each_combiners_formula_replayed_in_numpy(quad, combiner):
    """Every combiner of the registry (independent pattern, N = 8, 200 trials, lit receiver
    0 and penumbra receiver 2 of occluded-quad): each trial of the Warp kernel equals the
    documented formula replayed in numpy on the same random numbers, to 1e-5 relative
    (float32 pdfs and directions; measured ≤ 5e-7).  Deterministic: this pins the weights
    themselves — power's g_k²/Σ g_j² (β = 2) against the balance heuristic's g_k/Σ g_j,
    which is just as unbiased and which no test of the mean can tell apart — and each
    combiner's normalisation (1/N, 1/m)."""
    entry = COMBINERS[combiner]
    assert combiner in ("single", "mixture", "balance", "power", "biased", "maximum", "cutoff", "optimal",
                        "optimal-oracle"), f"write the formula of the new combiner {combiner!r} in _replay_combiner"
    est = Estimator("independent", combiner, ("light-area", "cosine") if entry.several else
                    (("cosine",) if combiner == "biased" else ("light-area",)),
                    CUTOFF if combiner == "cutoff" else None)
    replay_of = _replay_optimal if combiner.startswith("optimal") else _replay
    for r in (0, 2):
        kernel = run_trials(quad, est, 8, 200, seed=4, receivers=[r])[0]
        replay = replay_of(quad, r, est, 8, 200, 4)
        assert np.count_nonzero(replay) > 20, (combiner, r)  # the light is met in enough trials to tell
        np.testing.assert_allclose(kernel, replay, rtol=1e-5, atol=1e-12, err_msg=f"{est.spec} receiver {r}")


@pytest.mark.parametrize("combiner", ["optimal", "optimal-oracle"])
def test_optimal_mis_replayed_where_samples_fail(combiner):
    """Where a technique's samples fail (a rough-conductor reflection below the plate:
    9% of the bsdf samples at receiver 1 of mitsuba-veach-plates) each failed sample adds
    −α_k (docs/theory.md, "Optimal MIS"): the kernel equals the formula replayed in numpy
    there too (deterministic, as above)."""
    pytest.importorskip("mitsuba")
    plates = warpis.load_scene("mitsuba-veach-plates")
    est = Estimator("independent", combiner, ("light-area", "bsdf"))
    u = np.random.default_rng(0).random((4096, 2))
    failed = np.linalg.norm(sample_directions(plates, 1, "bsdf", u)[0], axis=1) == 0
    assert 0.05 < failed.mean() < 0.95, failed.mean()  # the case this test is for
    kernel = run_trials(plates, est, 8, 200, seed=4, receivers=[1])[0]
    replay = _replay_optimal(plates, 1, est, 8, 200, 4)
    np.testing.assert_allclose(kernel, replay, rtol=1e-5, atol=1e-12, err_msg=est.spec)


def test_cosine_sampling_of_a_constant_dome_has_zero_variance(dome):
    """f/pdf = πL exactly for every cosine-weighted sample."""
    values = run_trials(dome, "independent:single:cosine", 8, 100, seed=1)
    assert np.allclose(values, np.pi * 2.0, rtol=1e-5)


def test_antithetic_uniform_sampling_of_a_dome_cancels_exactly(dome):
    """Antithetic pairs cos θ = u and 1 − u: their mean 2πL·½ is exact, variance 0."""
    values = run_trials(dome, "antithetic:single:uniform", 8, 100, seed=1)
    assert np.allclose(values, np.pi * 2.0, rtol=1e-5)


def test_jittered_beats_independent_widely_on_a_smooth_receiver(quad, references):
    """Lit, unoccluded receiver 0 of occluded-quad at N = 256.

    Light sampling maps u smoothly onto the light: the variance ratio exceeds 30
    (light-area) and 20 (light-solid-angle).  Cosine sampling sees the light's edge as a
    discontinuity in u (variance ~N^-1.5 under jittering), so its gain is much smaller:
    it must still exceed 2.5.  Both variances carry fourth-moment intervals and the ratio
    of the interval ends (worst case, ind.lo / jit.hi) is tested.

    False-failure rate.  The true ratios (quadrature.exact_variance) are 66.8, 43.7 and 3.68.
    With M = 2000 each s² has a relative se of ~3.2%, so lo/hi ≈ 0.88 × (s²_ind/s²_jit) and
    ln(s²_ind/s²_jit) has sd ≈ 0.045.  Failing needs the log ratio to fall below its truth
    by ln(30/(0.88·66.8)) = −0.67 (15 sd), ln(20/(0.88·43.7)) = −0.65 (14 sd) and
    ln(2.5/(0.88·3.68)) = −0.26 (5.8 sd): P < 4e-9 in all (normal approximation).  (The
    former threshold of 3 for cosine sat 1.8 sd away: a 4% chance of failing.)
    """
    ref = references["occluded-quad"][1][0]
    assert ref[1] == 0.0, "receiver 0 should be closed-form (unoccluded)"
    for tech, factor in (("light-area", 30), ("light-solid-angle", 20), ("cosine", 2.5)):
        ind = variance_interval(run_trials(quad, f"independent:single:{tech}", 256, 2000, seed=7, receivers=[0])[0])
        jit = variance_interval(run_trials(quad, f"jittered:single:{tech}", 256, 2000, seed=7, receivers=[0])[0])
        assert ind.lo / jit.hi > factor, (tech, ind.variance, jit.variance)


# --------------------------------------------------------------------------- specs


@pytest.mark.parametrize("spec,n,needle", [
    ("jittered:balance:light-area+cosine", 7, "not divisible"),
    ("antithetic:single:cosine", 7, "even"),
    ("jittered-antithetic:balance:light-area+cosine", 6, "even"),
    ("independent:single:light-area+cosine", 8, "exactly one technique"),
    ("independent:balance:cosine", 8, "two or more"),
    ("independent:biased:cosine+uniform", 8, "exactly one technique"),
    ("stratified:single:cosine", 8, "unknown pattern"),
    ("independent:heuristic:cosine", 8, "unknown combiner"),
    ("independent:single:bxdf", 8, "unknown technique"),
    ("independent:balance:cosine+cosine", 8, "twice"),
    ("independent-single-cosine", 8, "PATTERN:COMBINER"),
])
def test_invalid_estimators_get_one_line_errors_that_list_what_is_valid(spec, n, needle):
    with pytest.raises(warpis.WarpisError) as err:
        parse_estimator(spec).check_n(n)
    message = str(err.value)
    assert needle in message and "\n" not in message
    assert spec.split(":")[0] in message or spec in message


def test_every_combination_of_the_vocabulary_parses_or_explains():
    """Every pattern × combiner × 1–2 techniques either runs or gives a one-line reason."""
    for pattern, combiner in itertools.product(PATTERNS, COMBINERS):
        for k in (1, 2):
            for techs in itertools.combinations(TECHNIQUES, k):
                try:
                    est = Estimator(pattern, combiner, techs)
                except warpis.WarpisError as exc:
                    assert "\n" not in str(exc)
                    continue
                assert parse_estimator(est.spec) == est
                est.check_n(8 if est.combiner_entry.pilot and est.pattern_entry.paired else 4)  # m = 4: pilot 2, pairs 2
