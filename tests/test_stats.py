"""Tests of warpis.stats: variance intervals (accuracy and coverage), z-scores, slope fits.

Every random test uses a fixed seed, so its outcome is deterministic; the stated
false-failure probability is the chance that a correct implementation fails the same
test under a different seed.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy.stats import binom, chi2

from warpis.stats import SlopeFit, VarianceEstimate, fit_slope, sidak_threshold, variance_interval, zscore
from warpis.errors import WarpisError

# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------


def binomial_acceptance(n: int, p: float, alpha: float) -> tuple[int, int]:
    """Region [a, b] with P(X < a) <= alpha/2 and P(X > b) <= alpha/2, X ~ Bin(n, p)."""
    k = np.arange(n + 1)
    a = int(k[binom.cdf(k - 1, n, p) <= alpha / 2][-1])
    b = int(k[binom.sf(k, n, p) <= alpha / 2][0])
    return a, b


def coverage(draw, true_variance: float, reps: int, trials: int, seed: int, batch: int = 250):
    """Fractions of fourth-moment and normal-theory 95% intervals that contain the truth."""
    rng = np.random.default_rng(seed)
    q_hi = chi2.ppf(0.975, trials - 1)
    q_lo = chi2.ppf(0.025, trials - 1)
    hits4 = hitsn = 0
    for start in range(0, reps, batch):
        x = draw(rng, (min(batch, reps - start), trials))
        est = variance_interval(x)
        hits4 += int(np.count_nonzero((est.lo <= true_variance) & (true_variance <= est.hi)))
        n_lo = (trials - 1) * est.variance / q_hi
        n_hi = (trials - 1) * est.variance / q_lo
        hitsn += int(np.count_nonzero((n_lo <= true_variance) & (true_variance <= n_hi)))
    return hits4 / reps, hitsn / reps


# ---------------------------------------------------------------------------------------
# thresholds and z-scores
# ---------------------------------------------------------------------------------------


def test_sidak_threshold():
    """Šidák's per-test level: identity for one run, the closed form otherwise, exact for tiny
    alpha (no cancellation). Deterministic."""
    assert sidak_threshold(0.01, 1) == pytest.approx(0.01, rel=1e-15)
    assert sidak_threshold(0.01, 10) == pytest.approx(1.0 - 0.99 ** 0.1, rel=1e-12)
    assert sidak_threshold(1e-12, 1000) == pytest.approx(1e-15, rel=1e-9)
    assert sidak_threshold(0.05, 20) < 0.05 / 20 * 1.03 and sidak_threshold(0.05, 20) > 0.05 / 20
    with pytest.raises(ValueError):
        sidak_threshold(0.01, 0)


def test_zscore_inf_safe():
    """z = (measured − predicted)/stderr, with stderr 0 giving 0 or ±inf and no warnings. Deterministic."""
    assert zscore(3.0, 0.5, 2.0) == 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z = zscore([1.0, 1.0, 2.0, 0.0, np.nan], [0.0, 0.0, 0.0, 1.0, 1.0], [1.0, 2.0, 1.0, 1.0, 1.0])
    assert z[0] == 0.0 and z[1] == -np.inf and z[2] == np.inf and z[3] == -1.0 and np.isnan(z[4])


# ---------------------------------------------------------------------------------------
# variance_interval
# ---------------------------------------------------------------------------------------


def test_variance_interval_constant_data():
    """Constant data: variance, its stderr and the interval are exactly 0. Deterministic."""
    est = variance_interval(np.full((3, 50), 7.25))
    assert isinstance(est, VarianceEstimate)
    np.testing.assert_array_equal(est.mean, 7.25)
    np.testing.assert_array_equal(est.variance, 0.0)
    np.testing.assert_array_equal(est.variance_stderr, 0.0)
    np.testing.assert_array_equal(est.lo, 0.0)
    np.testing.assert_array_equal(est.hi, 0.0)
    assert est.trials == 50


def test_variance_interval_hand_computed():
    """x = 1..4: s² = 5/3, m4 = 2.5625, Var(s²) = (m4 − s⁴·(M−3)/(M−1))/M, z = 1.96. Deterministic."""
    est = variance_interval([1.0, 2.0, 3.0, 4.0])
    m = 4
    s2 = 5.0 / 3.0
    m4 = (2 * 1.5 ** 4 + 2 * 0.5 ** 4) / 4
    se = math.sqrt((m4 - s2 * s2 * (m - 3) / (m - 1)) / m)
    assert est.mean == pytest.approx(2.5, rel=1e-15)
    assert est.variance == pytest.approx(s2, rel=1e-15)
    assert est.mean_stderr == pytest.approx(math.sqrt(s2 / m), rel=1e-15)
    assert est.variance_stderr == pytest.approx(se, rel=1e-14)
    z = 1.959963984540054
    assert est.hi == pytest.approx(s2 + z * se, rel=1e-14)
    assert est.lo == max(0.0, s2 - z * se)
    wider = variance_interval([1.0, 2.0, 3.0, 4.0], level=0.99)
    assert wider.hi > est.hi


def test_variance_interval_shapes_and_axis():
    """(R, M) gives per-receiver results; axis=0 on the transpose gives the same. Deterministic."""
    rng = np.random.default_rng(11)
    x = rng.normal(size=(5, 64)) * np.arange(1, 6)[:, None]
    a = variance_interval(x)
    b = variance_interval(x.T, axis=0)
    assert a.variance.shape == (5,)
    np.testing.assert_allclose(a.variance, np.var(x, axis=1, ddof=1), rtol=1e-13)
    np.testing.assert_allclose(a.mean, x.mean(axis=1), rtol=1e-13)
    for field in ("mean", "mean_stderr", "variance", "variance_stderr", "lo", "hi"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-14)
    c = variance_interval(rng.normal(size=(2, 3, 40)), axis=1)
    assert c.variance.shape == (2, 40) and c.trials == 3
    with pytest.raises(WarpisError, match="at least 2 trials"):
        variance_interval([1.0])


def test_variance_interval_numerical_stability():
    """Estimates 1000 + 1e-3·noise: the variance (~1e-6) comes out to 1e-6 relative (two-pass,
    float64), whereas the one-pass E[x²] − E[x]² formula is off by far more. Deterministic
    (fixed seed; the reference is computed on x − 1000, which is exact by Sterbenz's lemma)."""
    rng = np.random.default_rng(2024)
    x = 1000.0 + 1e-3 * rng.standard_normal((4, 20000))
    ref = np.var(x - 1000.0, axis=1, ddof=1)
    est = variance_interval(x)
    np.testing.assert_allclose(est.variance, ref, rtol=1e-6)
    np.testing.assert_allclose(est.mean - 1000.0, np.mean(x - 1000.0, axis=1), rtol=1e-6, atol=1e-12)
    dev = x - 1000.0
    ref_m4 = np.mean((dev - dev.mean(axis=1, keepdims=True)) ** 4, axis=1)
    m = x.shape[1]
    ref_se = np.sqrt((ref_m4 - ref ** 2 * (m - 3) / (m - 1)) / m)
    np.testing.assert_allclose(est.variance_stderr, ref_se, rtol=1e-6)
    one_pass = (np.mean(x * x, axis=1) - np.mean(x, axis=1) ** 2) * m / (m - 1)
    assert np.max(np.abs(one_pass / ref - 1.0)) > 1e-4  # what the two-pass computation avoids


def test_variance_interval_coverage_normal():
    """COVERAGE, normal data: 2000 repetitions of M = 1000 standard normals; the fraction of
    95% fourth-moment intervals that contain σ² = 1 must lie in the exact Bin(2000, 0.95)
    acceptance region [1860, 1936]/2000 = [0.930, 0.968] (P(X < 1860) = 4.1e-5,
    P(X > 1936) = 3.4e-5: false-failure probability 7.4e-5 if the coverage were exactly
    0.95; the interval is asymptotic and its actual coverage at M = 1000, measured with
    50 000 repetitions, is 0.9485 ± 0.001, for which the probability is 1.6e-4)."""
    a, b = binomial_acceptance(2000, 0.95, 1e-4)
    assert (a, b) == (1860, 1936)
    cov4, _ = coverage(lambda r, s: r.standard_normal(s), 1.0, reps=2000, trials=1000, seed=101)
    assert a / 2000 <= cov4 <= b / 2000, cov4


def test_variance_interval_coverage_gamma():
    """COVERAGE, skewed data: 2000 repetitions of M = 10 000 draws of gamma(shape 2)
    (σ² = 2, excess kurtosis 3); coverage of the 95% fourth-moment interval must lie in
    the Bin(2000, 0.95) acceptance region [0.930, 0.968] (false-failure probability 7.4e-5
    at exact coverage 0.95, 8.6e-5 at the measured 0.9495 ± 0.001). M is 10 000 rather than
    1000 because the interval is asymptotic: at M = 1000 the skewness of s² lowers its
    coverage to 0.937 (50 000 repetitions), which the region would reject 9% of the time;
    the deficit is O(M^-1/2) and at M = 10 000 it is gone within the measurement error."""
    a, b = binomial_acceptance(2000, 0.95, 1e-4)
    cov4, covn = coverage(lambda r, s: r.gamma(2.0, size=s), 2.0, reps=2000, trials=10_000, seed=202)
    assert a / 2000 <= cov4 <= b / 2000, cov4
    assert covn < 0.85, covn  # the normal-theory interval is already badly off here (0.79)


def test_variance_interval_heavy_tail_ordering():
    """Heavy tail: lognormal(0, 1) (excess kurtosis ≈ 111), 2000 repetitions of M = 1000.
    The normal-theory chi-square interval under-covers badly (0.277 measured with 20 000
    repetitions) and the fourth-moment interval covers far better though still short of
    0.95 (0.820). Asserted: fourth-moment ≥ 0.75, normal-theory ≤ 0.45 and a gap ≥ 0.40.
    With 2000 repetitions each fraction has a standard deviation ≤ 0.011, so the margins
    are ≥ 6 standard deviations (false-failure probability < 1e-8)."""
    s2 = (math.e - 1.0) * math.e
    cov4, covn = coverage(lambda r, s: r.lognormal(0.0, 1.0, size=s), s2, reps=2000, trials=1000, seed=303)
    assert cov4 >= 0.75, cov4
    assert covn <= 0.45, covn
    assert cov4 - covn >= 0.40, (cov4, covn)


# ---------------------------------------------------------------------------------------
# fit_slope
# ---------------------------------------------------------------------------------------


def test_fit_slope_exact_power_law():
    """Noise-free power law: slope and intercept exact; the unweighted interval collapses. Deterministic."""
    n = 2.0 ** np.arange(1, 11)
    v = 3.0 * n ** -1.5
    fit = fit_slope(n, v)
    assert isinstance(fit, SlopeFit)
    assert fit.slope == pytest.approx(-1.5, abs=1e-12)
    assert fit.intercept == pytest.approx(math.log(3.0), abs=1e-11)
    assert fit.slope_hi - fit.slope_lo < 1e-10
    assert fit.dof == 8 and not fit.weighted
    wfit = fit_slope(n, v, 0.01 * v)
    assert wfit.slope == pytest.approx(-1.5, abs=1e-12) and wfit.weighted
    # known stderrs: se(slope) = sqrt(1/Σw(x − x̄)²) with w = 1/0.01²
    x = np.log(n)
    assert wfit.slope_stderr == pytest.approx(0.01 / math.sqrt(np.sum((x - x.mean()) ** 2)), rel=1e-12)


def test_fit_slope_recovers_noisy_slope():
    """Synthetic measurements v = 3·n^-1.5·(1 + 0.05ε) at 12 points with known se =
    0.05·v_true: both fits (weighted, normal quantile; unweighted, Student's t with 10
    dof) recover −1.5 within their own standard error, and their 95% intervals are
    slope ∓ quantile·se and narrow.

    False-failure rate (deterministic for the fixed seed; under another seed):
    |slope + 1.5|/se exceeds the two-sided 1e-5 quantile (normal for the weighted fit,
    t(10) for the unweighted, whose se comes from the residuals) with probability 1e-5
    each; the unweighted interval's width 2·t₀.₉₇₅(10)·se exceeds 0.05 only when the
    residual scale is > 1.86× the truth (χ²₁₀ > 34.6: 1.5e-4), the weighted width is fixed
    (0.024).  In all ≤ 1.7e-4.  (The former check — both 95% intervals contain −1.5 — failed
    a correct fit 10% of the time.)"""
    from scipy.stats import norm, t

    rng = np.random.default_rng(7)
    n = 2.0 ** np.arange(2, 14)
    truth = 3.0 * n ** -1.5
    v = truth * (1.0 + 0.05 * rng.standard_normal(n.size))
    weighted, plain = fit_slope(n, v, 0.05 * truth), fit_slope(n, v)
    for fit, q95, q_tail in ((weighted, norm.ppf(0.975), norm.isf(0.5e-5)),
                             (plain, t.ppf(0.975, n.size - 2), t.isf(0.5e-5, n.size - 2))):
        assert fit.dof == n.size - 2
        assert abs(fit.slope + 1.5) <= q_tail * fit.slope_stderr, fit
        assert fit.slope_lo == pytest.approx(fit.slope - q95 * fit.slope_stderr, rel=1e-9), fit
        assert fit.slope_hi == pytest.approx(fit.slope + q95 * fit.slope_stderr, rel=1e-9), fit
        assert fit.slope_hi - fit.slope_lo < 0.05, fit


def test_fit_slope_interval_coverage():
    """COVERAGE of the slope intervals, 2000 fits each of 6 points (log-normal noise, sd 0.1):
    unweighted with Student's t (4 dof) and weighted with known stderrs must both cover in the
    Bin(2000, 0.95) region [0.930, 0.968] (false-failure probability 7.4e-5 each; both
    intervals are exact for Gaussian noise in log space). A normal quantile in place of t would
    cover only 0.878 at 4 dof, far outside the region."""
    a, b = binomial_acceptance(2000, 0.95, 1e-4)
    rng = np.random.default_rng(99)
    n = np.array([4.0, 8.0, 16.0, 32.0, 64.0, 128.0])
    truth = 0.7 * n ** -1.0
    hits_t = hits_w = 0
    for _ in range(2000):
        v = truth * np.exp(0.1 * rng.standard_normal(n.size))
        ft = fit_slope(n, v)
        fw = fit_slope(n, v, 0.1 * v)  # se(log v) = se(v)/v = 0.1
        hits_t += ft.slope_lo <= -1.0 <= ft.slope_hi
        hits_w += fw.slope_lo <= -1.0 <= fw.slope_hi
    assert a <= hits_t <= b, hits_t / 2000
    assert a <= hits_w <= b, hits_w / 2000


def test_fit_slope_rejects_bad_input():
    """Non-positive variances or stderrs, too few points and a single n are errors. Deterministic."""
    with pytest.raises(ValueError):
        fit_slope([1, 2, 4], [1.0, 0.0, 0.5])
    with pytest.raises(ValueError):
        fit_slope([1, 2], [1.0, 0.5])  # unweighted needs 3 points
    with pytest.raises(ValueError):
        fit_slope([2, 2, 2], [1.0, 0.9, 1.1])
    with pytest.raises(ValueError):
        fit_slope([1, 2, 4], [1.0, 0.5, 0.25], [0.1, 0.0, 0.1])
    assert fit_slope([1, 2], [1.0, 0.5], [0.1, 0.05]).slope == pytest.approx(-1.0)
