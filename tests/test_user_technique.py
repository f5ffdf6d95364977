"""A technique written by a user as a Warp ``sample``/``pdf`` pair, registered from Python.

The user's technique is a cosine-power lobe about the receiver normal,
g(ω) = (k+1)/(2π) cos^k θ with k = 3, sampled by inverting its cdf.  It is registered by
a fixture for the duration of each test and removed afterwards.

*Chi-square.*  The same harness and thresholds as tests/test_techniques.py: 10⁶ samples
binned on the whole sphere about the normal, the run passing when its p-value is at least
``sidak_threshold(1e-3, CHI2_RUNS)`` of that module (so it is at most as likely to fail
by chance as any chi-square run there); the wrong pdf (× 1.05) must reach p < 1e-30.

*Unbiasedness.*  The mean of 4000 trials at N = 16 on the lit, unoccluded receiver 0 of
occluded-quad is held against its reference (closed form there) by
z = (mean − reference)/sqrt(se_mean² + se_ref²), for two estimators, at the two-sided
Bonferroni threshold z* = Φ⁻¹(1 − 1e-3/4) ≈ 3.48: the test fails by chance with
probability ≤ 1e-3 under the normal approximation of the mean.

*Theory.*  The predictions for the user technique: eq17 carries a reason (no ∫ 1/g dω),
the exact form is computed and matches the measured variance (see its test).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp
from scipy.stats import norm
from test_techniques import BITE_P, CHI2_RUNS, FAMILY_ALPHA, SAMPLES

import warpis
from warpis.analysis.reference import reference
from warpis.stats import sidak_threshold, variance_interval
from warpis.analysis.quadrature import exact_variance
from warpis.analysis.theory import predictions
from warpis.kernels import estimators, evaluate, techniques
from warpis.kernels.engine import run_trials
from warpis.kernels.integrand import ShadingPoint
from warpis.kernels.precompiled import CPU_COMPILER_FLAGS
from warpis.kernels.registered import BUILT_IN, registered_kernels
from warpis.kernels.techniques import TECHNIQUES
from warpis.testing import ChiSquareTest

NAME = "test-cosine-cubed"
K = 3.0


@wp.func
def _lobe_frame(n: wp.vec3, local: wp.vec3) -> wp.vec3:
    """``local`` (z along n) in world coordinates."""
    a = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        a = wp.vec3(0.0, 1.0, 0.0)
    t = wp.normalize(wp.cross(a, n))
    b = wp.cross(n, t)
    return local[0] * t + local[1] * b + local[2] * n


@wp.func
def cosine_cubed_sample(sp: ShadingPoint, u: wp.vec2) -> wp.vec3:
    cos_t = wp.pow(1.0 - u[0], 1.0 / (K + 1.0))  # 1 − u ∈ (0, 1]: never cos θ = 0 exactly
    sin_t = wp.sqrt(wp.max(0.0, 1.0 - cos_t * cos_t))
    phi = 2.0 * wp.pi * u[1]
    return _lobe_frame(sp.n, wp.vec3(sin_t * wp.cos(phi), sin_t * wp.sin(phi), cos_t))


@wp.func
def cosine_cubed_pdf(sp: ShadingPoint, w: wp.vec3) -> float:
    c = wp.dot(w, sp.n)
    if c <= 0.0:
        return 0.0
    return (K + 1.0) / (2.0 * wp.pi) * wp.pow(c, K)


@pytest.fixture
def lobe():
    entry = warpis.register_technique(NAME, cosine_cubed_sample, cosine_cubed_pdf,
                                      description="(k+1)/(2π) cos^k θ about the normal, k = 3")
    try:
        yield entry
    finally:
        warpis.unregister_technique(NAME)


@pytest.fixture(scope="module")
def quad():
    return warpis.load_scene("occluded-quad")


def _chi2(scene, r: int, scale: float, seed: int) -> ChiSquareTest:
    def pdf_func(d):
        return scale * techniques.direction_pdf(scene, r, NAME, d)

    def sample_func(count, s):
        u = np.random.default_rng(s).random((count, 2), dtype=np.float32)
        d, p = techniques.sample_directions(scene, r, NAME, u)
        return d, scale * p

    return ChiSquareTest(sample_func, pdf_func, scene.receivers.normals[r], sample_count=SAMPLES, seed=seed)


def test_registration_adds_an_entry_without_theory(lobe):
    assert TECHNIQUES[NAME] is lobe
    assert lobe.code == max(e.code for e in TECHNIQUES.values())
    assert lobe.inverse_pdf_integral is None and not lobe.light


def test_user_technique_passes_the_chi_square_test(lobe, quad):
    test = _chi2(quad, 0, 1.0, seed=2024)
    assert test.run(FAMILY_ALPHA, CHI2_RUNS), test.messages
    assert test.p_value >= sidak_threshold(FAMILY_ALPHA, CHI2_RUNS)
    assert test.invalid_count == 0


def test_chi_square_bites_a_wrong_user_pdf(lobe, quad):
    test = _chi2(quad, 0, 1.05, seed=2025)
    assert not test.run(FAMILY_ALPHA, CHI2_RUNS)
    assert test.p_value < BITE_P


def test_reported_pdf_matches_the_closed_form(lobe, quad):
    u = np.random.default_rng(1).random((1000, 2), dtype=np.float32)
    d, p = techniques.sample_directions(quad, 0, NAME, u)
    c = d.astype(float) @ quad.receivers.normals[0]
    np.testing.assert_allclose(p, (K + 1) / (2 * math.pi) * c**K, rtol=1e-5)


@pytest.mark.parametrize("spec", [f"independent:single:{NAME}", f"jittered:balance:light-area+{NAME}"])
def test_user_technique_is_unbiased(lobe, quad, spec):
    ref = reference(quad, receivers=[0])[0]
    values = run_trials(quad, spec, 16, 4000, seed=5, receivers=[0])[0]
    z = (values.mean() - ref.value) / math.hypot(values.std(ddof=1) / math.sqrt(len(values)), ref.stderr)
    assert values.std() > 0.0
    assert abs(z) < norm.ppf(1 - 1e-3 / 4), f"{spec}: mean {values.mean():.6g} reference {ref.value:.6g} z = {z:.2f}"


@pytest.mark.parametrize("spec", [f"independent:single:{NAME}", f"jittered:balance:light-area+{NAME}"])
def test_theory_predicts_the_user_technique_and_says_what_it_cannot(lobe, quad, spec):
    """The exact form comes from the user's kernels (theory's evaluate kernel knows them);
    eq17 needs ∫ 1/g dω, which a registered technique does not give: a reason, no error.
    Measured variance of 20000 trials within 4.5 of its standard errors of the exact form
    (false-failure probability ~1e-5 per case under the normal approximation of s²)."""
    pred = predictions(quad, 0, spec, 16)
    if spec.startswith("independent"):
        assert "not known" in pred.reasons["eq17"]
        assert abs(pred["eq1"].value - pred["exact"].value) <= 4.5 * math.hypot(pred["eq1"].stderr,
                                                                               pred["exact"].stderr)
    v = variance_interval(run_trials(quad, spec, 16, 20000, seed=3, receivers=[0])[0])
    exact = pred["exact"]
    assert abs(v.variance - exact.value) <= 4.5 * math.hypot(v.variance_stderr, exact.stderr), (v, exact)


def test_without_user_techniques_the_built_in_kernels_run(quad):
    assert techniques.user_techniques() == ()
    assert registered_kernels() is BUILT_IN
    assert BUILT_IN.all == (estimators.trial_kernel, estimators.pilot_kernel, techniques.sample_kernel,
                            techniques.pdf_kernel, evaluate.evaluate_kernel)


def test_a_user_technique_gets_its_kernels_compiled_together_once(lobe, quad):
    """Every kernel that dispatches on technique codes is rebuilt around the user's
    technique, all in one Warp module: the numpy sampling, the trials (pilot included) and
    the quadrature load it once between them, and registering the same code again gives
    the same kernels (nothing compiled twice)."""
    kernels = registered_kernels()
    assert not set(kernels.all) & set(BUILT_IN.all)
    (module,) = {k.module for k in kernels.all}
    assert module.name.startswith("warpis_registered_")
    assert module.options["cpu_compiler_flags"] == CPU_COMPILER_FLAGS  # CPUs sharing a cache build it once
    techniques.sample_directions(quad, 0, NAME, np.full((4, 2), 0.5, np.float32))
    loaded = dict(module.execs)
    assert len(loaded) == 1
    run_trials(quad, f"independent:optimal:light-area+{NAME}", 8, 4, receivers=[0])
    exact_variance(quad, 0, f"jittered:balance:light-area+{NAME}", 8)
    assert module.execs == loaded  # the same executable: the module was not built again
    warpis.unregister_technique(NAME)
    assert registered_kernels() is BUILT_IN
    again = warpis.register_technique(NAME, cosine_cubed_sample, cosine_cubed_pdf)
    assert again is not lobe and registered_kernels() is kernels


def test_the_numpy_path_says_which_import_builds_its_kernels(lobe, quad, monkeypatch):
    monkeypatch.setattr(techniques, "_registered_pair", [])
    with pytest.raises(warpis.WarpisError, match=r"warpis\.kernels\.registered, which is not imported"):
        techniques.sample_directions(quad, 0, NAME, np.full((4, 2), 0.5, np.float32))


def test_registering_a_taken_name_fails():
    with pytest.raises(warpis.WarpisError):
        warpis.register_technique("cosine", cosine_cubed_sample, cosine_cubed_pdf)
