"""Tests of warpis.testing.ChiSquareTest (its p-value is scipy's chi-square survival function).

The samplers here are pure numpy, so no Warp is needed. Every random test has a fixed
seed and is deterministic; the stated false-failure probability is the chance that a
correct implementation fails under another seed. A passing sampler run at significance
0.01 would fail 1% of the time if the p-value were exact; the quadrature of the expected
counts inflates the statistic by well under 1 (reported in the messages) against its
spread sqrt(2·dof) ≥ 40, which changes that by a negligible amount.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpis.testing import ChiSquareTest, orthonormal_frame

# ---------------------------------------------------------------------------------------
# numpy samplers
# ---------------------------------------------------------------------------------------


def gram_schmidt_frame(n):
    """A frame around n built differently from the test's (so the two grids disagree)."""
    n = np.asarray(n, dtype=np.float64)
    n = n / np.linalg.norm(n)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t = helper - (helper @ n) * n
    t /= np.linalg.norm(t)
    return t, np.cross(n, t), n


def local_to_world(frame, x, y, z):
    t, b, n = frame
    return x[:, None] * t + y[:, None] * b + z[:, None] * n


def cosine_sampler(normal, reported_pdf=None):
    """Cosine-weighted hemisphere around `normal` (Malley's method).

    Reports cos/π, or `reported_pdf(dirs)` when given (a sampler that lies consistently
    with a wrong pdf routine).
    """
    frame = gram_schmidt_frame(normal)

    def sample(count, seed):
        u = np.random.default_rng(seed).random((count, 2))
        r = np.sqrt(u[:, 0])
        phi = 2.0 * math.pi * u[:, 1]
        z = np.sqrt(1.0 - u[:, 0])
        d = local_to_world(frame, r * np.cos(phi), r * np.sin(phi), z)
        return d, (z / math.pi if reported_pdf is None else reported_pdf(d))

    return sample


def cosine_pdf(normal):
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    return lambda d: np.maximum(d @ n, 0.0) / math.pi


def uniform_sphere_sampler(reported_pdf=None):
    def sample(count, seed):
        u = np.random.default_rng(seed).random((count, 2))
        z = 1.0 - 2.0 * u[:, 0]
        r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        phi = 2.0 * math.pi * u[:, 1]
        d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
        return d, (np.full(count, 1.0 / (4.0 * math.pi)) if reported_pdf is None else reported_pdf(d))

    return sample


def uniform_sphere_pdf(d):
    return np.full(d.shape[0], 1.0 / (4.0 * math.pi))


def cap_sampler_and_pdf(centre, cos_max):
    """Uniform sampling of the spherical cap {ω : ω·c >= cos_max}; pdf = indicator / area."""
    frame = gram_schmidt_frame(centre)
    c = frame[2]
    area = 2.0 * math.pi * (1.0 - cos_max)

    def sample(count, seed):
        u = np.random.default_rng(seed).random((count, 2))
        z = 1.0 - u[:, 0] * (1.0 - cos_max)
        r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        phi = 2.0 * math.pi * u[:, 1]
        return local_to_world(frame, r * np.cos(phi), r * np.sin(phi), z), np.full(count, 1.0 / area)

    def pdf(d):
        return np.where(d @ c >= cos_max, 1.0 / area, 0.0)

    return sample, pdf


TILTED = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])

# ---------------------------------------------------------------------------------------
# the frame
# ---------------------------------------------------------------------------------------


def test_orthonormal_frame():
    """Duff et al.'s frame is orthonormal and right-handed for random axes and the hard cases
    ±z, near −z and the coordinate axes (to 1e-14). Deterministic."""
    rng = np.random.default_rng(5)
    axes = list(rng.normal(size=(200, 3))) + [
        np.array(v, dtype=float) for v in
        ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, 0], [1e-9, 0, -1], [0, 1e-12, -1], [-1e-17, 0, -1])]
    for a in axes:
        b1, b2, n = orthonormal_frame(a)
        m = np.stack([b1, b2, n])
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(np.cross(b1, b2), n, atol=1e-14)
        np.testing.assert_allclose(n, a / np.linalg.norm(a), atol=1e-15)
    with pytest.raises(ValueError):
        orthonormal_frame([0.0, 0.0, 0.0])


# ---------------------------------------------------------------------------------------
# correct samplers pass
# ---------------------------------------------------------------------------------------


def test_cosine_hemisphere_passes():
    """Cosine-weighted hemisphere around a tilted normal, tested on a grid around that normal
    (built differently from the sampler's frame): passes at significance 0.01 (false-failure
    probability ≈ 0.01). The lower hemisphere has expected count 0 and gets pooled."""
    test = ChiSquareTest(cosine_sampler(TILTED), cosine_pdf(TILTED), TILTED, sample_count=1_000_000, seed=1)
    assert test.run(0.01), test.messages
    assert test.pdf_integral == pytest.approx(1.0, abs=1e-4)
    assert test.histogram.shape == (40, 80) and test.expected.shape == (40, 80)
    assert test.histogram.sum() == 1_000_000
    assert test.histogram[:20].sum() == 0  # nothing below the horizon
    assert 1000 < test.dof < 1700
    assert "p-value" in test.messages and "largest contributions" in test.messages


def test_uniform_sphere_passes():
    """Uniform sphere on a grid around an oblique axis: passes at significance 0.01
    (false-failure probability ≈ 0.01); with a constant pdf the quadrature is exact, so
    the integral is 1 to rounding and every cell expects N/cells."""
    axis = np.array([1.0, 1.0, 1.0])
    test = ChiSquareTest(uniform_sphere_sampler(), uniform_sphere_pdf, axis, sample_count=500_000, seed=2)
    assert test.run(0.01), test.messages
    assert test.pdf_integral == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(test.expected, 500_000 / 3200, rtol=1e-12)
    assert test.dof == 3199


def test_discontinuous_cap_passes():
    """Uniform sampling of a spherical cap (pdf = indicator/area, a discontinuity crossing
    ~120 cells obliquely) on a grid around z: passes at significance 0.01 (false-failure
    probability ≈ 0.01). The cells the edge crosses are found and re-integrated, and the
    estimated inflation of the statistic from the quadrature stays below 2."""
    sample, pdf = cap_sampler_and_pdf(np.array([0.5, 0.5, 0.7071]), 0.3)
    test = ChiSquareTest(sample, pdf, [0.0, 0.0, 1.0], sample_count=1_000_000, seed=3)
    assert test.run(0.01), test.messages
    assert test.refined_cells > 50
    assert test.pdf_integral == pytest.approx(1.0, abs=2e-4)
    inflation = float(test.messages.split("(errs high) ")[1].split()[0])
    assert inflation < 2.0, test.messages


def test_p_values_are_calibrated():
    """For a correct sampler the p-value is uniform on (0, 1): 48 runs of the cosine sampler
    with different seeds (2·10⁴ samples, 10 × 20 grid, pooled horizon cells). Kolmogorov–
    Smirnov distance to U(0, 1) must be < 0.32, the asymptotic critical value for n = 48
    at level 1e-4 (sqrt(ln(2/1e-4)/96)): false-failure probability ≈ 1e-4. This checks
    the dof bookkeeping and pooling: an off-by-one or a mis-pooled bin skews the p-values."""
    normal = np.array([0.0, 0.6, 0.8])
    p = []
    for seed in range(48):
        test = ChiSquareTest(cosine_sampler(normal), cosine_pdf(normal), normal, sample_count=20_000,
                             res=(10, 20), ires=8, seed=1000 + seed)
        test.run(0.01)
        p.append(test.p_value)
    p = np.sort(p)
    k = np.arange(1, p.size + 1)
    ks = max(np.max(k / p.size - p), np.max(p - (k - 1) / p.size))
    assert ks < 0.32, (ks, p)


def test_invalid_samples_allowed_when_declared():
    """A sampler that fails (zero vector, pdf 0) for z < −0.5 with a pdf that integrates to the
    valid fraction 0.75: passes with allow_invalid=True (false-failure probability ≈ 0.01) and
    fails without it. Also fails when the pdf claims 1 and still the sampler gives up."""
    def sample(count, seed):
        d, pdf = uniform_sphere_sampler()(count, seed)
        bad = d[:, 2] < -0.5
        d[bad] = 0.0
        pdf[bad] = 0.0
        return d, pdf

    def pdf(d):
        return np.where(d[:, 2] >= -0.5, 1.0 / (4.0 * math.pi), 0.0)

    ok = ChiSquareTest(sample, pdf, [0.0, 0.0, 1.0], sample_count=400_000, seed=4, allow_invalid=True)
    assert ok.run(0.01), ok.messages
    assert ok.valid_fraction == pytest.approx(0.75, abs=0.005)
    assert ok.pdf_integral == pytest.approx(0.75, abs=1e-3)

    strict = ChiSquareTest(sample, pdf, [0.0, 0.0, 1.0], sample_count=400_000, seed=4)
    assert not strict.run(0.01)
    assert "invalid samples" in strict.messages

    def pdf_claims_all(d):  # renormalised to 1 over the valid region: wrong for this sampler
        return np.where(d[:, 2] >= -0.5, 1.0 / (3.0 * math.pi), 0.0)

    def sample_consistent(count, seed):
        d, p = sample(count, seed)
        p[p > 0] = 1.0 / (3.0 * math.pi)
        return d, p

    wrong = ChiSquareTest(sample_consistent, pdf_claims_all, [0.0, 0.0, 1.0], sample_count=400_000, seed=4,
                          allow_invalid=True)
    assert not wrong.run(0.01), wrong.messages


# ---------------------------------------------------------------------------------------
# wrong samplers fail
# ---------------------------------------------------------------------------------------


def uniform_hemisphere_pdf(d):
    return np.where(d[:, 2] > 0.0, 1.0 / (2.0 * math.pi), 0.0)


def test_cosine_sampler_with_uniform_pdf_fails():
    """Cosine-distributed directions checked against a uniform-hemisphere pdf (the sampler
    reports that same wrong pdf, so only the histogram can tell): fails with a p-value
    below 1e-100 (probability of a false pass: effectively 0, the statistic is ~300 σ out)."""
    z = np.array([0.0, 0.0, 1.0])
    test = ChiSquareTest(cosine_sampler(z, reported_pdf=uniform_hemisphere_pdf), uniform_hemisphere_pdf, z,
                         sample_count=200_000, seed=5)
    assert not test.run(0.01)
    assert test.p_value < 1e-100
    assert "problem" not in test.messages  # the failure is the statistic's, not a pdf mismatch
    assert "FAILED" in test.messages


def test_pdf_off_by_five_percent_in_one_region_fails():
    """Uniform-sphere directions against a pdf that claims 5% more density in the cap z > 0.5
    (and correspondingly less elsewhere, so it still integrates to 1); the sampler reports the
    same wrong pdf. Expected excess of the statistic ≈ 800 against a spread of 80 at 10⁶
    samples: p < 1e-6 asserted (false-pass probability < 1e-6)."""
    hi = 1.05 / (4.0 * math.pi)
    lo = (1.0 - 1.05 * 0.25) / 0.75 / (4.0 * math.pi)

    def pdf(d):
        return np.where(d[:, 2] > 0.5, hi, lo)

    test = ChiSquareTest(uniform_sphere_sampler(reported_pdf=pdf), pdf, [0.0, 0.0, 1.0],
                         sample_count=1_000_000, seed=6)
    assert not test.run(0.01)
    assert test.pdf_integral == pytest.approx(1.0, abs=1e-4)
    assert test.p_value < 1e-6, test.messages
    assert "problem" not in test.messages


def test_reported_pdf_mismatch_fails():
    """A correct cosine sampler that reports its pdf 1% too high: the histogram is fine but
    the reported-pdf check fails the test, with a message. Deterministic."""
    test = ChiSquareTest(cosine_sampler(TILTED, reported_pdf=lambda d: 1.01 * cosine_pdf(TILTED)(d)),
                         cosine_pdf(TILTED), TILTED, sample_count=100_000, seed=7)
    assert not test.run(0.01)
    assert "differs from pdf_func" in test.messages
    assert test.p_value > 1e-3


def test_samples_where_pdf_is_zero_fail():
    """Uniform-sphere samples against a pdf that is 0 on the polar cap cos θ > 0.95 (one whole
    row of cells): those cells hold samples that the pdf says are impossible, which fails the
    test with a message even when reported-pdf mismatches are tolerated. Deterministic."""
    def pdf(d):
        return np.where(d[:, 2] > 0.95, 0.0, 1.0 / (4.0 * math.pi * 0.975))

    test = ChiSquareTest(uniform_sphere_sampler(), pdf, [0.0, 0.0, 1.0], sample_count=100_000, seed=8,
                         pdf_mismatch_fraction=1.0)
    assert not test.run(0.01)
    assert "impossible" in test.messages


def test_sidak_correction_used():
    """run(significance, test_count) compares the p-value with the Šidák threshold. Deterministic."""
    test = ChiSquareTest(uniform_sphere_sampler(), uniform_sphere_pdf, [0.0, 0.0, 1.0], sample_count=20_000,
                         res=(10, 20), seed=9)
    test.run(0.5, test_count=1)
    p = test.p_value
    assert test.run(significance=min(1.0, 1.01 * p), test_count=1) is False
    assert test.run(significance=min(1.0, 1.01 * p), test_count=1000) is True
    assert "Šidák" in test.messages
