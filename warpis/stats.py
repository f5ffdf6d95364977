"""Statistics for variance measurements: intervals, z-scores, slope fits and quantiles.

Everything here is pure numpy (plus :mod:`math`), in float64.

The central object is :func:`variance_interval`: from M independent estimates of one
quantity it returns the sample mean, the unbiased sample variance s² and a confidence
interval for the true variance that uses the fourth central moment of the sample.
Estimators of rendering are heavy-tailed, so the normal-theory (chi-square) interval,
which assumes a kurtosis of 3, is wrong for them; the fourth-moment interval is only
asymptotic but holds whatever the distribution, provided its fourth moment exists.

The module also carries the few special functions that warpis needs and that would
otherwise pull in scipy: the normal quantile (:func:`normal_quantile`), the normal CDF
(:func:`normal_cdf`), Student's t quantile (:func:`t_quantile`), the regularised upper
incomplete gamma function (:func:`gammaincc`) and the chi-square survival function
(:func:`chi2_sf`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "VarianceEstimate",
    "SlopeFit",
    "variance_interval",
    "zscore",
    "fit_slope",
    "sidak_threshold",
    "normal_quantile",
    "normal_cdf",
    "t_quantile",
    "gammaincc",
    "chi2_sf",
]

FloatArray = NDArray[np.float64]


def _scalar_or_array(x: np.ndarray) -> FloatArray | float:
    """Return a 0-d array as a Python float, anything else unchanged."""
    return float(x) if x.ndim == 0 else x


# ---------------------------------------------------------------------------------------
# Normal distribution
# ---------------------------------------------------------------------------------------

_erfc = np.vectorize(math.erfc, otypes=[np.float64])

# Acklam's rational approximations to the normal quantile (relative error < 1.15e-9).
_ACKLAM_A = (-3.969683028665376e01, 2.209460984245205e02, -2.759285104469687e02,
             1.383577518672690e02, -3.066479806614716e01, 2.506628277459239e00)
_ACKLAM_B = (-5.447609879822406e01, 1.615858368580409e02, -1.556989798598866e02,
             6.680131188771972e01, -1.328068155288572e01)
_ACKLAM_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e00,
             -2.549732539343734e00, 4.374664141464968e00, 2.938163982698783e00)
_ACKLAM_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00,
             3.754408661907416e00)
_ACKLAM_P_LOW = 0.02425


def normal_cdf(x: ArrayLike) -> FloatArray | float:
    """Standard normal cumulative distribution function Φ(x).

    Parameters
    ----------
    x : array_like
        Points at which to evaluate Φ.

    Returns
    -------
    float or ndarray
        Φ(x) = ½ erfc(−x/√2), evaluated elementwise with :func:`math.erfc` (the
        complementary form keeps full relative precision in the lower tail, where
        ½(1 + erf(x/√2)) would cancel). A float for scalar input.
    """
    x = np.asarray(x, dtype=np.float64)
    return _scalar_or_array(0.5 * _erfc(-x / math.sqrt(2.0)))


def normal_quantile(p: ArrayLike) -> FloatArray | float:
    """Inverse of the standard normal CDF, Φ⁻¹(p).

    Acklam's rational approximation (relative error below 1.15e-9 everywhere) followed
    by one Halley step on Φ(x) − p, with Φ evaluated through :func:`math.erfc`; the
    result agrees with the exact quantile to a few units in the last place for
    1e-300 < p < 1 − 1e-16. The step is made on the lower tail, min(p, 1 − p), and the
    sign restored, so both tails are equally accurate in terms of min(p, 1 − p).

    Parameters
    ----------
    p : array_like
        Probabilities.

    Returns
    -------
    float or ndarray
        Φ⁻¹(p): −inf at p = 0, +inf at p = 1, NaN outside [0, 1] or for NaN input.
        A float for scalar input.
    """
    p = np.asarray(p, dtype=np.float64)
    q = np.minimum(p, 1.0 - p)  # lower-tail probability, in (0, 0.5]
    out = np.full(p.shape, np.nan)
    ok = (q > 0.0) & np.isfinite(q)
    qq = np.where(ok, q, 0.25)

    a, b, c, d = _ACKLAM_A, _ACKLAM_B, _ACKLAM_C, _ACKLAM_D
    # Lower tail region.
    t = np.sqrt(-2.0 * np.log(np.where(qq < _ACKLAM_P_LOW, qq, 0.01)))
    x_tail = (((((c[0] * t + c[1]) * t + c[2]) * t + c[3]) * t + c[4]) * t + c[5]) / (
        (((d[0] * t + d[1]) * t + d[2]) * t + d[3]) * t + 1.0)
    # Central region.
    s = qq - 0.5
    r = s * s
    x_mid = (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * s / (
        ((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0)
    x = np.where(qq < _ACKLAM_P_LOW, x_tail, x_mid)  # x <= 0

    # One Halley step on Φ(x) − q; x <= 0 so erfc's argument is >= 0 (no cancellation).
    e = 0.5 * _erfc(-x / math.sqrt(2.0)) - qq
    u = e * math.sqrt(2.0 * math.pi) * np.exp(0.5 * x * x)
    x = x - u / (1.0 + 0.5 * x * u)

    out[ok] = np.where(p[ok] > 0.5, -x[ok], x[ok])
    out[p == 0.0] = -np.inf
    out[p == 1.0] = np.inf
    out[p == 0.5] = 0.0
    return _scalar_or_array(out)


# ---------------------------------------------------------------------------------------
# Student's t quantile
# ---------------------------------------------------------------------------------------


def _hill_t(p2: float, n: float) -> float:
    """Hill (1970), Algorithm 396: t > 0 with P(|T_n| > t) = p2, for 0 < p2 <= 1."""
    if n == 1.0:
        return math.cos(p2 * math.pi / 2.0) / math.sin(p2 * math.pi / 2.0)
    if n == 2.0:
        return math.sqrt(2.0 / (p2 * (2.0 - p2)) - 2.0)
    a = 1.0 / (n - 0.5)
    b = 48.0 / (a * a)
    c = ((20700.0 * a / b - 98.0) * a - 16.0) * a + 96.36
    d = ((94.5 / (b + c) - 3.0) / b + 1.0) * math.sqrt(a * math.pi / 2.0) * n
    x = d * p2
    y = x ** (2.0 / n)
    if y > 0.05 + a:
        # Asymptotic inverse expansion about the normal quantile.
        x = float(normal_quantile(0.5 * p2))
        y = x * x
        if n < 5.0:
            c = c + 0.3 * (n - 4.5) * (x + 0.6)
        c = (((0.05 * d * x - 5.0) * x - 7.0) * x - 2.0) * x + b + c
        y = (((((0.4 * y + 6.3) * y + 36.0) * y + 94.5) / c - y - 3.0) / b + 1.0) * x
        y = math.expm1(a * y * y)
    else:
        y = ((1.0 / (((n + 6.0) / (n * y) - 0.089 * d - 0.822) * (n + 2.0) * 3.0)
              + 0.5 / (n + 4.0)) * y - 1.0) * (n + 1.0) / (n + 2.0) + 1.0 / y
    return math.sqrt(n * y)


def t_quantile(p: ArrayLike, dof: ArrayLike) -> FloatArray | float:
    """Quantile of Student's t distribution with `dof` degrees of freedom.

    Hill's approximation (G. W. Hill, "Algorithm 396: Student's t-quantiles",
    CACM 13(10), 1970): exact closed forms for dof = 1 and dof = 2, otherwise an
    expansion about the normal quantile (or, far in the tails, about the t tail
    power law). Measured against exact quantiles for 1e-15 <= p <= 1 − 1e-6, the
    relative error is below 1.5e-5 for dof >= 3 (integer or not), below 1e-6 for
    dof >= 10 and below 1e-7 for dof >= 15: far below what a confidence interval
    needs. The expansion is poor for non-integer dof below 3, which are refused.

    Parameters
    ----------
    p : array_like
        Probabilities (lower tail).
    dof : array_like
        Degrees of freedom: 1, 2 or any real >= 3; ``inf`` gives the normal quantile.

    Returns
    -------
    float or ndarray
        t with P(T <= t) = p; NaN for p outside (0, 1) (−inf/+inf at p = 0/1).
        A float for scalar input.

    Raises
    ------
    ValueError
        For dof < 1, NaN dof, or non-integer dof below 3.
    """
    p, dof = np.broadcast_arrays(np.asarray(p, dtype=np.float64),
                                 np.asarray(dof, dtype=np.float64))
    bad = ~((dof >= 3.0) | (dof == 1.0) | (dof == 2.0))
    if np.any(bad):
        raise ValueError(f"t_quantile needs dof of 1, 2 or >= 3, got {dof[bad].ravel()[0]}")
    out = np.full(p.shape, np.nan)
    out[p == 0.0] = -np.inf
    out[p == 1.0] = np.inf
    for idx in np.ndindex(p.shape):
        pi, ni = float(p[idx]), float(dof[idx])
        if not 0.0 < pi < 1.0:
            continue
        if math.isinf(ni):
            out[idx] = normal_quantile(pi)
            continue
        if pi == 0.5:
            out[idx] = 0.0
            continue
        t = _hill_t(2.0 * min(pi, 1.0 - pi), ni)
        out[idx] = t if pi > 0.5 else -t
    return _scalar_or_array(out)


# ---------------------------------------------------------------------------------------
# Incomplete gamma and chi-square
# ---------------------------------------------------------------------------------------

_GAMMA_EPS = 1e-15
_GAMMA_MAX_ITER = 100_000
_TINY = 1e-300


def _gammaincc_scalar(a: float, x: float) -> float:
    """Regularised upper incomplete gamma Q(a, x) for one pair (see :func:`gammaincc`)."""
    if math.isnan(a) or math.isnan(x) or a <= 0.0 or x < 0.0:
        return math.nan
    if x == 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    # log of the common prefactor x^a e^-x / Γ(a), kept in log space: for a ~ 1e3 both
    # x^a and Γ(a) overflow on their own.
    log_pref = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        # Series for P(a, x) = pref/a · Σ x^n / ((a+1)...(a+n)); Q = 1 − P has no
        # cancellation here because P(a, x) < ~0.6 for x < a + 1.
        ap = a
        term = 1.0 / a
        total = term
        for _ in range(_GAMMA_MAX_ITER):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * _GAMMA_EPS:
                break
        else:  # pragma: no cover - a safety net; convergence takes O(sqrt(a)) terms
            raise ArithmeticError(f"gammaincc: series did not converge for a={a}, x={x}")
        return max(0.0, 1.0 - math.exp(log_pref + math.log(total)))
    # Continued fraction for Q(a, x) (modified Lentz), converges fast for x >= a + 1.
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, _GAMMA_MAX_ITER):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        if abs(d) < _TINY:
            d = _TINY
        c = b + an / c
        if abs(c) < _TINY:
            c = _TINY
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _GAMMA_EPS:
            break
    else:  # pragma: no cover
        raise ArithmeticError(f"gammaincc: continued fraction did not converge for a={a}, x={x}")
    return math.exp(log_pref + math.log(h))


_gammaincc_vec = np.vectorize(_gammaincc_scalar, otypes=[np.float64])


def gammaincc(a: ArrayLike, x: ArrayLike) -> FloatArray | float:
    """Regularised upper incomplete gamma function Q(a, x) = Γ(a, x) / Γ(a).

    Numerical Recipes' method: the power series for P(a, x) when x < a + 1 (then
    Q = 1 − P) and the Lentz continued fraction for Q directly otherwise, with the
    prefactor x^a e^(−x) / Γ(a) formed in log space so that large shapes (a in the
    thousands, a chi-square with thousands of degrees of freedom) neither overflow
    nor underflow prematurely. The relative error is about 1e-14 for a of order 1 and
    grows to about 1e-12 for a in the thousands (the rounding of the log-space
    prefactor, whose terms are then ~1e4); in the upper tail Q keeps that relative
    precision down to the float64 underflow limit, below which it returns 0. Where
    x < a + 1, Q = 1 − P and the absolute error is about 1e-15.

    Parameters
    ----------
    a : array_like
        Shape, > 0.
    x : array_like
        Argument, >= 0.

    Returns
    -------
    float or ndarray
        Q(a, x), broadcast over `a` and `x`; NaN for invalid input. A float for
        scalar input.
    """
    return _scalar_or_array(_gammaincc_vec(np.asarray(a, np.float64), np.asarray(x, np.float64)))


def chi2_sf(x: ArrayLike, dof: ArrayLike) -> FloatArray | float:
    """Survival function of the chi-square distribution, P(X > x) = Q(dof/2, x/2).

    Parameters
    ----------
    x : array_like
        Statistic values.
    dof : array_like
        Degrees of freedom, > 0.

    Returns
    -------
    float or ndarray
        The upper-tail probability (1 for x <= 0). A float for scalar input.
    """
    x = np.asarray(x, dtype=np.float64)
    dof = np.asarray(dof, dtype=np.float64)
    return gammaincc(0.5 * dof, 0.5 * np.maximum(x, 0.0))


# ---------------------------------------------------------------------------------------
# Variance of M trials
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VarianceEstimate:
    """Mean and variance of M trials, with a confidence interval for the true variance.

    Every array has the shape of the input with the trial axis removed.

    Attributes
    ----------
    mean : ndarray
        Sample mean x̄.
    mean_stderr : ndarray
        Standard error of the mean, sqrt(s² / M).
    variance : ndarray
        Unbiased sample variance s² = Σ(x − x̄)² / (M − 1).
    variance_stderr : ndarray
        Estimated standard error of s² from the fourth central moment.
    lo, hi : ndarray
        Interval s² ∓ z·se for the true variance; `lo` clipped at 0.
    trials : int
        M, the number of trials.
    level : float
        Two-sided confidence level of [lo, hi].
    """

    mean: FloatArray
    mean_stderr: FloatArray
    variance: FloatArray
    variance_stderr: FloatArray
    lo: FloatArray
    hi: FloatArray
    trials: int
    level: float


def variance_interval(estimates: ArrayLike, axis: int = -1, level: float = 0.95) -> VarianceEstimate:
    """Sample variance of M trials and an asymptotic interval for the true variance.

    For x_1..x_M independent with variance σ² and fourth central moment μ4, the
    unbiased sample variance s² has

        Var(s²) = (μ4 − σ⁴ (M − 3)/(M − 1)) / M.

    Here μ4 is estimated by the plug-in fourth central moment m4 = mean((x − x̄)⁴) and
    σ⁴ by s⁴, so se(s²) = sqrt(max((m4 − s⁴ (M − 3)/(M − 1)) / M, 0)), and the
    interval is s² ± z·se with z = Φ⁻¹((1 + level)/2), `lo` clipped at 0. The interval
    makes no normality assumption (a normal-theory chi-square interval silently
    assumes μ4 = 3σ⁴ and under-covers badly for heavy-tailed estimators); it is
    asymptotic in M, and for strongly heavy-tailed data it still under-covers somewhat
    because m4 itself is then noisy and skewed low.

    The computation is in float64 and two-pass: the mean is subtracted first (with the
    usual correction term, the mean of the residuals, subtracted again), so data with a
    large mean and a tiny spread (estimates ~1e3, variance ~1e-6) lose no precision.

    Parameters
    ----------
    estimates : array_like
        Independent estimates; the trials run along `axis`. An (R, M) array of R
        receivers × M trials gives per-receiver results of shape (R,).
    axis : int, optional
        The trial axis. Default: the last.
    level : float, optional
        Two-sided confidence level, in (0, 1). Default 0.95.

    Returns
    -------
    VarianceEstimate
        Mean, its standard error, s², se(s²), the interval [lo, hi], M and the level.

    Raises
    ------
    ValueError
        When there are fewer than 2 trials or `level` is not in (0, 1).
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    x = np.moveaxis(np.asarray(estimates, dtype=np.float64), axis, -1)
    m = x.shape[-1]
    if m < 2:
        raise ValueError(f"variance_interval needs at least 2 trials, got {m}")
    mean = np.mean(x, axis=-1)
    dev = x - mean[..., None]
    corr = np.mean(dev, axis=-1)  # rounding left in the first pass (corrected two-pass)
    dev -= corr[..., None]
    mean = mean + corr
    dev2 = dev * dev
    s2 = np.sum(dev2, axis=-1) / (m - 1)
    m4 = np.mean(dev2 * dev2, axis=-1)
    var_s2 = (m4 - s2 * s2 * (m - 3) / (m - 1)) / m
    se = np.sqrt(np.maximum(var_s2, 0.0))
    z = float(normal_quantile(0.5 * (1.0 + level)))
    return VarianceEstimate(
        mean=mean,
        mean_stderr=np.sqrt(s2 / m),
        variance=s2,
        variance_stderr=se,
        lo=np.maximum(s2 - z * se, 0.0),
        hi=s2 + z * se,
        trials=m,
        level=float(level),
    )


def zscore(measured: ArrayLike, stderr: ArrayLike, predicted: ArrayLike) -> FloatArray | float:
    """Standardised difference (measured − predicted) / stderr.

    Infinity-safe and warning-free: with stderr = 0 the result is 0 where measured
    equals predicted and ±inf otherwise; NaN in any input gives NaN.

    Parameters
    ----------
    measured, stderr, predicted : array_like
        Broadcast together. `stderr` must be >= 0.

    Returns
    -------
    float or ndarray
        The z-scores; a float when all inputs are scalars.
    """
    measured = np.asarray(measured, dtype=np.float64)
    stderr = np.asarray(stderr, dtype=np.float64)
    predicted = np.asarray(predicted, dtype=np.float64)
    diff = measured - predicted
    with np.errstate(divide="ignore", invalid="ignore"):
        z = diff / stderr
    z = np.where((stderr == 0.0) & (diff == 0.0), 0.0, z)
    return _scalar_or_array(np.asarray(z, dtype=np.float64))


# ---------------------------------------------------------------------------------------
# Convergence-rate fits
# ---------------------------------------------------------------------------------------


class SlopeFit(NamedTuple):
    """Result of :func:`fit_slope`: log(variance) ≈ intercept + slope · log(n).

    Attributes
    ----------
    slope, intercept : float
        The fitted line in natural-log coordinates.
    slope_lo, slope_hi : float
        Two-sided confidence interval for the slope.
    slope_stderr : float
        Standard error of the slope.
    dof : int
        Residual degrees of freedom (points − 2).
    weighted : bool
        Whether the fit used the given standard errors.
    chi2 : float
        Weighted residual sum of squares Σ w r² (with known standard errors it is
        chi-square with `dof` degrees of freedom when the power law holds); the plain
        residual sum of squares for an unweighted fit.
    """

    slope: float
    intercept: float
    slope_lo: float
    slope_hi: float
    slope_stderr: float = math.nan
    dof: int = 0
    weighted: bool = False
    chi2: float = math.nan


def fit_slope(n: ArrayLike, variance: ArrayLike, variance_stderr: ArrayLike | None = None,
              level: float = 0.95) -> SlopeFit:
    """Fit a power law variance ∝ n^slope by least squares in log–log coordinates.

    Unweighted (``variance_stderr is None``): ordinary least squares of log(variance)
    on log(n); the slope's standard error comes from the residual variance
    RSS / (k − 2), and the interval uses Student's t quantile with k − 2 degrees of
    freedom (k points, k >= 3).

    Weighted: weighted least squares with weights 1/se(log v)², where by the delta
    method se(log v) = se(v)/v; the standard errors are taken as known, so the slope's
    standard error is sqrt(1/Σw(x − x̄_w)²) and the interval uses the normal quantile
    (k >= 2). The weighted residual sum of squares is returned as `chi2` for a
    goodness-of-fit check.

    Parameters
    ----------
    n : array_like
        Sample counts, > 0, at least two distinct values.
    variance : array_like
        Measured variances, > 0.
    variance_stderr : array_like, optional
        Standard errors of `variance`, > 0.
    level : float, optional
        Two-sided confidence level of the slope interval. Default 0.95.

    Returns
    -------
    SlopeFit
        slope, intercept, slope_lo, slope_hi and diagnostics.

    Raises
    ------
    ValueError
        On shape mismatch, non-positive or non-finite inputs, too few points or fewer
        than two distinct n.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    n = np.asarray(n, dtype=np.float64).ravel()
    v = np.asarray(variance, dtype=np.float64).ravel()
    if n.shape != v.shape:
        raise ValueError(f"n and variance differ in length: {n.size} vs {v.size}")
    if not (np.all(np.isfinite(n)) and np.all(n > 0)):
        raise ValueError("n must be finite and > 0")
    if not (np.all(np.isfinite(v)) and np.all(v > 0)):
        raise ValueError("variance must be finite and > 0 to take its logarithm")
    x = np.log(n)
    y = np.log(v)
    k = x.size
    q = 0.5 * (1.0 + level)
    if variance_stderr is None:
        if k < 3:
            raise ValueError(f"an unweighted slope interval needs at least 3 points, got {k}")
        w = np.ones(k)
    else:
        se = np.asarray(variance_stderr, dtype=np.float64).ravel()
        if se.shape != v.shape:
            raise ValueError(f"variance_stderr has {se.size} entries, variance {v.size}")
        if not (np.all(np.isfinite(se)) and np.all(se > 0)):
            raise ValueError("variance_stderr must be finite and > 0")
        if k < 2:
            raise ValueError(f"a slope needs at least 2 points, got {k}")
        w = (v / se) ** 2  # 1 / se(log v)^2
    sw = np.sum(w)
    xm = np.sum(w * x) / sw
    ym = np.sum(w * y) / sw
    dx = x - xm
    sxx = np.sum(w * dx * dx)
    if not sxx > 0.0:
        raise ValueError("n needs at least two distinct values")
    slope = float(np.sum(w * dx * (y - ym)) / sxx)
    intercept = float(ym - slope * xm)
    resid = y - (intercept + slope * x)
    rss = float(np.sum(w * resid * resid))
    dof = k - 2
    if variance_stderr is None:
        slope_se = math.sqrt(rss / dof / sxx)
        crit = float(t_quantile(q, dof))
    else:
        slope_se = math.sqrt(1.0 / sxx)
        crit = float(normal_quantile(q))
    return SlopeFit(slope=slope, intercept=intercept,
                    slope_lo=slope - crit * slope_se, slope_hi=slope + crit * slope_se,
                    slope_stderr=slope_se, dof=dof, weighted=variance_stderr is not None,
                    chi2=rss)


def sidak_threshold(alpha: float, runs: int) -> float:
    """Per-test significance that keeps the family-wise error at `alpha` over `runs` tests.

    Šidák's correction, 1 − (1 − alpha)^(1/runs), computed as
    −expm1(log1p(−alpha)/runs) so that tiny alphas keep their precision.

    Parameters
    ----------
    alpha : float
        Family-wise significance, in [0, 1].
    runs : int
        Number of independent tests, >= 1.

    Returns
    -------
    float
        The per-test threshold.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    if alpha == 1.0:
        return 1.0
    return -math.expm1(math.log1p(-alpha) / runs)
