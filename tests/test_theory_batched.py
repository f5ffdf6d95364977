"""Exact variances of many receivers at once (``exact_variances``): agreement with the
single-receiver adaptive form and with measurement, independence of threads and
chunking, convergence with the point budget, and one-line errors.

Statistical thresholds (each test states its own).

* Batched against single-receiver: both are deterministic quadratures whose stderr
  comes from a jackknife over 8 replicas, so (a − b)/√(se_a² + se_b²) is a Welch t with
  at least 7 degrees of freedom.  The threshold is t7's Bonferroni quantile for an
  overall false-failure rate of 1e-3 over the K comparisons (8.78 for K = 20).
* Against measurement: the prediction must lie in the fourth-moment interval of s² at
  level 1 − 1e-4/K, widened by the same z times the prediction's own stderr, so a
  correct prediction fails the test with probability below 1e-4 (normal approximation
  of s², good at M = 20000 trials).
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from scipy.stats import norm, t

import warpis
from warpis.analysis import quadrature
from warpis.analysis.quadrature import MIN_POINTS, REPLICAS, SEED, Variances, exact_variance, exact_variances
from warpis.kernels.engine import run_moments

N = 16
PLATES_RECEIVERS = [0, 5, 10, 15]  # phong exponents 10, 50, 300, 2000
SINGLE_SPECS = ["independent:single:light-area", "jittered:balance:light-area+cosine",
                "antithetic:balance:light-area+cosine", "jittered:mixture:light-area+cosine",
                "independent:power:light-solid-angle+phong"]
MEASURED = [("two-lights", "independent:single:light-area"), ("two-lights", "jittered:balance:light-area+cosine"),
            ("two-lights", "antithetic:balance:light-area+cosine"),
            ("occluded-quad", "jittered:mixture:light-area+cosine"),
            ("occluded-quad", "jittered-antithetic:power:light-solid-angle+cosine"),
            ("veach-plates", "independent:power:light-solid-angle+phong")]
TRIALS = 20000


@pytest.fixture(scope="module")
def scenes() -> dict[str, warpis.Scene]:
    return {name: warpis.load_scene(name) for name in ("occluded-quad", "two-lights", "veach-plates")}


def test_batched_agrees_with_the_single_receiver_form(scenes):
    """Different points (another seed), the same variance: |z| below t7's Bonferroni
    quantile for α = 1e-3 over the 20 comparisons (module docstring).  The single form
    stops at 5% or two densities, to keep the test short."""
    plates = scenes["veach-plates"]
    k = len(SINGLE_SPECS) * len(PLATES_RECEIVERS)
    threshold = t.ppf(1 - 1e-3 / (2 * k), 7)
    for spec in SINGLE_SPECS:
        batched = exact_variances(plates, PLATES_RECEIVERS, spec, N, points=1 << 16, seed=SEED + 1)
        for i, r in enumerate(PLATES_RECEIVERS):
            single = exact_variance(plates, r, spec, N, rel_tol=0.05, max_points=2 * MIN_POINTS)
            assert single.value > 0 and batched.value[i] > 0
            z = (batched.value[i] - single.value) / math.hypot(batched.stderr[i], single.stderr)
            assert abs(z) < threshold, (spec, r, batched.value[i], batched.stderr[i], single)


@pytest.mark.parametrize("name, spec", MEASURED)
def test_batched_agrees_with_measurement(scenes, name, spec):
    """Every receiver's prediction lies in the measured variance's interval at level
    1 − 1e-4/K (K receivers), widened by z × the prediction's stderr: false failure
    below 1e-4 per case (module docstring)."""
    scene = scenes[name]
    receivers = list(range(len(scene.receivers)))
    pred = exact_variances(scene, receivers, spec, N, points=1 << 14)
    level = 1 - 1e-4 / len(receivers)
    z = norm.ppf(0.5 * (1 + level))
    iv = run_moments(scene, spec, N, TRIALS, seed=11, receivers=receivers).interval(level)
    inside = (iv.lo - z * pred.stderr <= pred.value) & (pred.value <= iv.hi + z * pred.stderr)
    assert inside.all(), (spec, pred.value[~inside], iv.variance[~inside], iv.lo[~inside], iv.hi[~inside])


@pytest.mark.parametrize("spec", ["jittered:balance:light-solid-angle+phong", "antithetic:mixture:light-area+phong",
                                  "independent:single:light-solid-angle"])
def test_a_receivers_values_do_not_depend_on_threads_chunks_or_the_other_receivers(scenes, spec, monkeypatch):
    """Bit-identical for threads 1 and 2, one receiver per chunk or all in one, any
    order and any company; progress counts receivers up to the total in the calling thread."""
    plates = scenes["veach-plates"]
    everyone = list(range(16))
    calls = []

    def progress(done: int, total: int) -> None:
        calls.append((done, total, threading.get_ident()))

    ref = exact_variances(plates, everyone, spec, N, points=512, threads=1, progress=progress)
    assert calls[-1][:2] == (16, 16) and all(c[2] == threading.get_ident() for c in calls)
    assert [c[0] for c in calls] == sorted(c[0] for c in calls)
    runs = [(everyone, 2), (everyone[::-1], 2), ([13, 2, 7], 1), ([9], 2)]
    monkeypatch.setattr(quadrature, "CHUNK_BYTES", 1)  # one receiver per chunk
    chunked = [exact_variances(plates, rows, spec, N, points=512, threads=threads) for rows, threads in runs]
    monkeypatch.undo()
    runs.append((everyone[::-1], 2))
    chunked.append(exact_variances(plates, everyone[::-1], spec, N, points=512, threads=2))
    for (rows, _), got in zip(runs, chunked):
        assert got.points == ref.points
        assert np.array_equal(got.value, ref.value[rows]) and np.array_equal(got.stderr, ref.stderr[rows])


def test_points_are_rounded_to_whole_sub_grids(scenes):
    """blocks · sub² · REPLICAS, the largest not above the budget, at least one point per
    block and replica; paired patterns add the reflected points, every technique its own."""
    quad = scenes["occluded-quad"]
    # jittered at m = 8: 8 blocks; 1000 // 64 = 15 → sub = 3
    assert exact_variances(quad, [1], "jittered:single:cosine", 8, points=1000).points == 8 * 9 * REPLICAS
    assert exact_variances(quad, [1], "jittered:single:cosine", 8, points=1).points == 8 * REPLICAS
    # independent: one block; 4096 // 8 = 512 → sub = 22; two techniques
    got = exact_variances(quad, [1], "independent:balance:light-area+cosine", N, points=4096)
    assert got.points == 2 * 22 * 22 * REPLICAS
    # antithetic: one block of pairs, both points of each pair evaluated
    assert exact_variances(quad, [1], "antithetic:single:cosine", N, points=4096).points == 2 * 22 * 22 * REPLICAS


def test_the_stderr_falls_as_the_points_grow(scenes):
    """×16 points: the jackknife stderr falls by 4 (1/√points) to 16 (a smooth integrand
    under the strata), about 8 where the strata cut edges; the median ratio over the 16
    receivers lies inside the loose [2, 40] (each stderr has 7 degrees of freedom).  The
    two values agree within 10 combined stderr (P(|t7| > 10) = 2e-5 each)."""
    plates = scenes["veach-plates"]
    coarse = exact_variances(plates, range(16), "jittered:single:light-solid-angle", 8, points=256)
    fine = exact_variances(plates, range(16), "jittered:single:light-solid-angle", 8, points=4096)
    assert (coarse.points, fine.points) == (256, 4096)  # 8 cells × sub² × 8 replicas, sub = 2 and 8
    ratio = np.median(coarse.stderr / fine.stderr)
    assert 2 < ratio < 40, ratio
    assert np.all(np.abs(fine.value - coarse.value) < 10 * np.hypot(fine.stderr, coarse.stderr))


def test_the_result_is_read_only(scenes):
    got = exact_variances(scenes["occluded-quad"], [0, 1], "independent:single:cosine", N, points=64)
    assert isinstance(got, Variances) and got.value.shape == got.stderr.shape == (2,)
    with pytest.raises(ValueError):
        got.value[0] = 1.0


@pytest.mark.parametrize("kwargs, message", [
    ({"estimator": "cmj:single:cosine"}, "no block decomposition nor pair form"),
    ({"estimator": "jittered:optimal:light-area+cosine"}, "ratio estimate from a random pilot"),
    ({"estimator": "jittered:balance:light-area+cosine", "n": 15}, "not divisible"),
    ({"n": 0}, "N: must be at least 1"),
    ({"points": 0}, "points: must be at least 1"),
    ({"points": 4.0}, "points: expected an integer"),
    ({"points": True}, "points: expected an integer"),
    ({"receivers": [8]}, "receiver 8 does not exist"),
    ({"receivers": []}, "no index given"),
    ({"threads": 0}, "threads: must be at least 1"),
    ({"seed": -1}, "seed: must be in [0, 2^32)"),
])
def test_bad_input_is_a_one_line_error(scenes, kwargs, message):
    args = {"receivers": [0], "estimator": "independent:single:cosine", "n": N} | kwargs
    with pytest.raises(warpis.WarpisError) as info:
        exact_variances(scenes["occluded-quad"], **args)
    text = str(info.value)
    assert message in text and "\n" not in text, text


def test_one_point_per_block_is_unbiased(scenes):
    """At the smallest budget — one point per block and replica (jittered at N = 256: 256
    blocks, 2048 points) — the pair-of-replicas estimator of E[P]² keeps the variance
    unbiased, where the squared replica mean would subtract Var(p̄) = 1/8 of each block's
    variance (−12.5%).  16 floor receivers of occluded-quad (lit, penumbra, umbra); the
    summed variance at 16 independent point sets (seeds) against one budget of 64 points
    per block and replica (bias, were it there, 1/512).  Every receiver sees the same
    points, so receivers do not average out the noise; seeds do: the mean ratio's
    standard error is about 0.009 (measured over these seeds), and the bound 0.045 is 5 of
    them (false failure ~1e-6), while the biased estimator gives 0.884."""
    base = scenes["occluded-quad"]
    g = np.linspace(-1.2, 1.2, 4)
    floor = np.array([[x, y, 0.0] for y in g for x in g])
    scene = warpis.Scene.from_arrays(base.vertices, base.triangles, base.emission, floor, (0.0, 0.0, 1.0))
    spec, n, blocks = "jittered:single:light-area", 256, 256
    high = exact_variances(scene, range(16), spec, n, points=blocks * REPLICAS * 64, seed=1)
    ratios = []
    for seed in range(100, 116):
        low = exact_variances(scene, range(16), spec, n, points=blocks * REPLICAS, seed=seed)
        assert low.points == blocks * REPLICAS
        ratios.append(low.value.sum() / high.value.sum())
    assert abs(np.mean(ratios) - 1) < 0.045, ratios
