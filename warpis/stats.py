"""Statistics for variance measurements: intervals, mergeable moments, z-scores and slope fits.

Everything here is numpy and :mod:`scipy.special`, in float64.

The central object is :func:`variance_interval`: from M independent estimates of one
quantity it returns the sample mean, the unbiased sample variance s² and a confidence
interval for the true variance that uses the fourth central moment of the sample.
Estimators of rendering are heavy-tailed, so the normal-theory (chi-square) interval,
which assumes a kurtosis of 3, is wrong for them; the fourth-moment interval is only
asymptotic but holds whatever the distribution, provided its fourth moment exists.

Quantiles come from :mod:`scipy.special` (``ndtri`` for the normal, ``stdtrit`` for
Student's t), exact to rounding.  Not :mod:`scipy.stats`: trimesh already loads
scipy.special, while scipy.stats would add about 0.4 s to every CLI start.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtri, stdtrit

from .errors import WarpisError

__all__ = [
    "VarianceEstimate",
    "SampleMoments",
    "SlopeFit",
    "variance_interval",
    "zscore",
    "fit_slope",
    "sidak_threshold",
]

FloatArray = NDArray[np.float64]

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
    It is ``SampleMoments.of(estimates, axis).interval(level)``: the streaming path of
    :func:`warpis.kernels.engine.run_moments` ends in the same formula.

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
    WarpisError
        One line naming the argument: `estimates` that are not an array of real numbers,
        hold a NaN or an infinity (its index is named) or fewer than 2 trials along
        `axis`; an `axis` the array lacks; a `level` outside (0, 1).
    """
    _check_level(level)
    try:
        raw = np.asarray(estimates, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise WarpisError(f"estimates: expected an array of real numbers ({str(exc).splitlines()[0]})") from None
    if raw.ndim == 0:
        raise WarpisError(f"estimates: expected an array of trials, got one value ({estimates!r})")
    finite = np.isfinite(raw)
    if not finite.all():
        bad = tuple(int(i) for i in np.argwhere(~finite)[0])
        where = ", ".join(map(str, bad))
        raise WarpisError(f"estimates[{where}]: {raw[bad]} is not a finite number; nothing is computed from it")
    if isinstance(axis, bool) or not isinstance(axis, (int, np.integer)) or not -raw.ndim <= axis < raw.ndim:
        raise WarpisError(f"axis: the estimates have {raw.ndim} dimension(s), so axis {axis!r} does not exist")
    x = np.moveaxis(raw, axis, -1)
    if x.shape[-1] < 2:
        raise WarpisError(f"estimates: a variance interval needs at least 2 trials along axis {axis}, "
                          f"got {x.shape[-1]}")
    return SampleMoments.of(x).interval(level)


def _check_level(level: float) -> None:
    """A two-sided confidence level in (0, 1), else a one-line error."""
    if isinstance(level, bool) or not isinstance(level, (int, float, np.integer, np.floating)) \
            or not 0.0 < level < 1.0:
        raise WarpisError(f"level: a two-sided confidence level must be a number in (0, 1), got {level!r}")


def _interval(mean: FloatArray, s2: FloatArray, m4: FloatArray, m: int, level: float) -> VarianceEstimate:
    """The fourth-moment interval from x̄, s², the plug-in m4 = mean((x − x̄)⁴) and M.

    The one definition behind :func:`variance_interval` and :meth:`SampleMoments.interval`.
    """
    _check_level(level)
    if m < 2:
        raise WarpisError(f"a variance interval needs at least 2 trials, got {m}")
    var_s2 = (m4 - s2 * s2 * (m - 3) / (m - 1)) / m
    se = np.sqrt(np.maximum(var_s2, 0.0))
    z = float(ndtri(0.5 * (1.0 + level)))
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


@dataclass(frozen=True)
class SampleMoments:
    """Count, mean and central moment sums of a sample, mergeable without losing precision.

    For each row (receiver) of n values x_i with mean x̄: ``m2`` = Σ(x_i − x̄)²,
    ``m3`` = Σ(x_i − x̄)³ and ``m4`` = Σ(x_i − x̄)⁴ (sums, not means).  Blocks of trials
    are reduced with :meth:`of` and combined with :meth:`merge`, so M trials can be
    summarised in memory that does not grow with M; :meth:`interval` then gives the same
    :class:`VarianceEstimate` as :func:`variance_interval` on all M values at once.

    Central sums rather than raw power sums Σx^k: with estimates ~1e3 and a variance
    ~1e-6, Σx² − (Σx)²/n cancels all but three or four digits, while central sums keep
    the data's precision.

    Attributes
    ----------
    count : ndarray of int64
        Values per row.
    mean, m2, m3, m4 : ndarray of float64
        Mean and central moment sums per row (shape of the input less the trial axis).
    """

    count: NDArray[np.int64]
    mean: FloatArray
    m2: FloatArray
    m3: FloatArray
    m4: FloatArray

    @classmethod
    def of(cls, values: ArrayLike, axis: int = -1) -> SampleMoments:
        """Moments of one block of values along ``axis``, two-pass in float64.

        The mean is subtracted first, with the usual correction term (the mean of the
        residuals) subtracted again, so the deviations carry the data's full precision.
        """
        x = np.moveaxis(np.asarray(values, dtype=np.float64), axis, -1)
        m = x.shape[-1]
        if m < 1:
            raise ValueError("SampleMoments.of needs at least 1 value, got 0")
        mean = np.mean(x, axis=-1)
        dev = x - mean[..., None]
        corr = np.mean(dev, axis=-1)  # rounding left in the first pass (corrected two-pass)
        dev -= corr[..., None]
        dev2 = dev * dev
        return cls(count=np.full(np.shape(mean), m, dtype=np.int64), mean=mean + corr,
                   m2=np.sum(dev2, axis=-1), m3=np.sum(dev2 * dev, axis=-1), m4=np.sum(dev2 * dev2, axis=-1))

    def merge(self, other: SampleMoments) -> SampleMoments:
        """The moments of both samples together: Pébay's (2008) pairwise update.

        P. Pébay, "Formulas for robust, one-pass parallel computation of covariances and
        arbitrary-order statistical moments", Sandia report SAND2008-6212, for orders
        2–4.  Only the difference of the two means, δ, enters the correction terms, so a
        large common mean cancels before anything is squared.  An empty side (count 0)
        leaves the other unchanged.
        """
        if not np.any(other.count):
            return self
        if not np.any(self.count):
            return other
        na, nb = self.count.astype(np.float64), other.count.astype(np.float64)
        n = na + nb
        d = other.mean - self.mean
        dn = d / n
        t = d * dn * na * nb  # δ² na nb / n, the between-blocks sum of squares
        m2 = self.m2 + other.m2 + t
        m3 = (self.m3 + other.m3 + t * dn * (na - nb)
              + 3.0 * dn * (na * other.m2 - nb * self.m2))
        m4 = (self.m4 + other.m4 + t * dn * dn * (na * na - na * nb + nb * nb)
              + 6.0 * dn * dn * (na * na * other.m2 + nb * nb * self.m2)
              + 4.0 * dn * (na * other.m3 - nb * self.m3))
        return SampleMoments(count=self.count + other.count, mean=self.mean + nb * dn, m2=m2, m3=m3, m4=m4)

    @staticmethod
    def merged(blocks: Sequence[SampleMoments]) -> SampleMoments:
        """Consecutive blocks merged left to right, ((b0 + b1) + b2) + …: the order
        :func:`warpis.kernels.engine.run_moments` merges in, so the same blocks give the
        same bits wherever they were computed."""
        if not blocks:
            raise ValueError("no blocks to merge")
        total = blocks[0]
        for block in blocks[1:]:
            total = total.merge(block)
        return total

    def interval(self, level: float = 0.95) -> VarianceEstimate:
        """Mean, stderr, s², se(s²) and the fourth-moment interval, as :func:`variance_interval`.

        Raises
        ------
        ValueError
            When rows hold different counts.
        WarpisError
            When rows hold fewer than 2 values, or `level` is not in (0, 1).
        """
        counts = np.unique(self.count)
        if counts.size != 1:
            raise ValueError(f"rows hold different numbers of values: {counts.tolist()}")
        m = int(counts[0])
        return _interval(self.mean, self.m2 / max(m - 1, 1), self.m4 / max(m, 1), m, level)


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
    z = np.asarray(np.where((stderr == 0.0) & (diff == 0.0), 0.0, z), dtype=np.float64)
    return float(z) if z.ndim == 0 else z


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
    """Fit a power law variance ∝ n^slope by least squares (:func:`numpy.polyfit`) in log–log coordinates.

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
    weighted = variance_stderr is not None
    if not weighted:
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
        w = v / se  # 1 / se(log v): polyfit weights the unsquared residuals
    if not np.ptp(x) > 0.0:
        raise ValueError("n needs at least two distinct values")
    # Known stderrs give the unscaled covariance; otherwise polyfit scales it by RSS/(k − 2).
    (slope, intercept), cov = np.polyfit(x, y, 1, w=w, cov="unscaled" if weighted else True)
    slope, intercept = float(slope), float(intercept)
    rss = float(np.sum((w * (y - (intercept + slope * x))) ** 2))
    slope_se = math.sqrt(cov[0, 0])
    q = 0.5 * (1.0 + level)
    crit = float(ndtri(q)) if weighted else float(stdtrit(k - 2, q))
    return SlopeFit(slope=slope, intercept=intercept,
                    slope_lo=slope - crit * slope_se, slope_hi=slope + crit * slope_se,
                    slope_stderr=slope_se, dof=k - 2, weighted=weighted, chi2=rss)


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
