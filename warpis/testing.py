"""Test helpers: a chi-square goodness-of-fit test for direction samplers.

:class:`ChiSquareTest` checks that a sampling routine draws directions with the density
that its pdf routine claims. Both are given as vectorised callables, so a Warp-backed
technique is tested through thin wrappers that launch a kernel over many directions.

The test, in outline:

1. Draw ``sample_count`` directions; each sample also reports its pdf, which must agree
   with ``pdf_func`` at the same direction.
2. Bin the directions on a grid over the *whole* sphere, uniform in cos θ ∈ [−1, 1] and
   φ ∈ [0, 2π), θ measured from ``axis``. Every cell has the same solid angle
   Δcosθ·Δφ, and the probability of a cell is ∫∫ pdf d(cosθ) dφ over it.
3. Integrate ``pdf_func`` over every cell by jittered (stratified) quadrature to get the
   expected counts.
4. Pool the cells whose expected count is small, form Pearson's statistic, and compare
   its chi-square p-value with a (Šidák-corrected) significance level.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import chdtrc

from .stats import sidak_threshold

__all__ = ["ChiSquareTest", "orthonormal_frame"]

SampleFunc = Callable[[int, int], tuple[NDArray, NDArray]]
PdfFunc = Callable[[NDArray], NDArray]


def orthonormal_frame(axis: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
    """Orthonormal basis (b1, b2, n) with n = the normalised `axis`.

    Duff et al., "Building an orthonormal basis, revisited", JCGT 6(1), 2017: branch
    on the sign of n.z, so that the frame is continuous and accurate for every axis,
    including ±z.

    Parameters
    ----------
    axis : ndarray, shape (3,)
        Any non-zero vector.

    Returns
    -------
    tuple of ndarray
        b1, b2, n, each shape (3,) float64; (b1, b2, n) is right-handed.
    """
    n = np.asarray(axis, dtype=np.float64).reshape(3)
    length = float(np.linalg.norm(n))
    if not (math.isfinite(length) and length > 0.0):
        raise ValueError(f"axis must be a finite non-zero 3-vector, got {axis!r}")
    n = n / length
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    b1 = np.array([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    b2 = np.array([b, sign + n[1] * n[1] * a, -n[1]])
    return b1, b2, n


class ChiSquareTest:
    """Pearson chi-square test that a direction sampler draws from its claimed pdf.

    Parameters
    ----------
    sample_func : callable
        ``sample_func(count, seed) -> (dirs, pdf)``: `dirs` an array (count, 3) of unit
        directions, `pdf` an array (count,) holding the solid-angle density that the
        sampler reports for each. A sample with pdf 0, or with any NaN/inf, is
        *invalid* (a sampler may signal failure this way, e.g. a light sampler with no
        emitter in view).
    pdf_func : callable
        ``pdf_func(dirs) -> pdf``: the solid-angle density at each of `dirs`
        (float64 array (k, 3)); called with large batches of at most `max_batch`
        directions.
    axis : array_like, shape (3,)
        Pole of the (cosθ, φ) grid. Pick it so the pdf's features are resolved,
        e.g. the surface normal.
    sample_count : int, optional
        Number of samples drawn.
    res : tuple of int, optional
        Grid resolution (cells in cosθ, cells in φ).
    ires : int, optional
        Quadrature points per cell and dimension (ires × ires jittered points).
    seed : int, optional
        Seed passed to `sample_func`; the quadrature jitter uses its own stream derived
        from it.
    min_expected : float, optional
        Cells whose expected count is below this are pooled into one bin.
    allow_invalid : bool, optional
        If False (default), any invalid sample fails the test. If True, invalid samples
        are allowed: the pdf is then the density of the *valid* samples and must
        integrate to the valid fraction, and the invalid samples form one more bin
        whose expected count is ``sample_count · (1 − ∫pdf)``.
    pdf_rtol : float, optional
        Relative tolerance of the check of reported pdf against `pdf_func`.
    pdf_mismatch_fraction : float, optional
        Largest fraction of valid samples that may exceed `pdf_rtol` (samples exactly
        on a discontinuity of the pdf may legitimately disagree).
    max_batch : int, optional
        Largest number of directions passed to `pdf_func` in one call.
    refine_factor : int, optional
        Cells whose quadrature looks noisy are integrated again with
        ``refine_factor · ires`` points per dimension (1 turns this off).
    refine_inflation : float, optional
        A cell is noisy when its estimated quadrature variance, in counts², over its
        expected count exceeds this (its expected addition to the statistic).

    Notes
    -----
    *Quadrature.* Each cell's probability is estimated from ires² points, one uniform
    point in each cell of an ires × ires sub-grid in (cosθ, φ). The estimate is
    unbiased for any integrable pdf, discontinuous ones included. Its error is
    O(ires⁻²) relative for a smooth pdf and O(ires^(−3/2)) times the size of the jump
    for a cell crossed by a discontinuity (only the ~ires sub-cells that the edge cuts
    contribute variance). The error inflates the statistic by about
    Σ E_cell · (relative error)² over the cells, which must stay small against the
    statistic's spread sqrt(2·dof). For a spherical cap sampled with 1e6 samples
    (~900 per cell), ires = 16 alone inflates the statistic by about 20 over ~125 edge
    cells (0.16 each), against a spread of ~50. Hence the refinement: the quadrature
    variance of each cell is estimated (collapsed strata, an estimate that errs high),
    and cells whose expected addition to the statistic exceeds `refine_inflation` are
    integrated again with `refine_factor`× the points per dimension, which divides an
    edge cell's variance by about refine_factor³ (64). For that cap the inflation left
    is about 0.35 (the report's estimate: about 0.9). The report gives the estimated
    remaining inflation; raise `ires` when `sample_count` grows a lot.

    *Pooling.* Cells with expected count below `min_expected` are pooled into one bin
    (more cells are added, smallest first, until the pool reaches `min_expected`);
    dof = bins − 1. A cell with observed samples whose expected count stays below
    1e-6 after re-integrating it at 8× the quadrature resolution fails the test: the
    pdf says those directions are impossible.

    Attributes
    ----------
    After :meth:`run`:

    p_value : float
        Upper-tail chi-square probability of the statistic.
    statistic : float
        Pearson's statistic Σ (O − E)² / E over the bins.
    dof : int
        Degrees of freedom, bins − 1.
    histogram : ndarray, shape res
        Observed counts of the valid samples per cell (index [i_cos, i_phi]).
    expected : ndarray, shape res
        Expected counts per cell.
    pdf_integral : float
        ∫ pdf over the sphere, by the quadrature.
    valid_fraction : float
        Fraction of samples that were valid.
    passed : bool
        The result of the last :meth:`run`.
    messages : str
        A readable report.
    """

    def __init__(self, sample_func: SampleFunc, pdf_func: PdfFunc, axis: ArrayLike, sample_count: int = 1_000_000,
                 res: tuple[int, int] = (40, 80), ires: int = 16, seed: int = 0,
                 min_expected: float = 5.0, allow_invalid: bool = False, pdf_rtol: float = 1e-3,
                 pdf_mismatch_fraction: float = 1e-4, max_batch: int = 4_000_000,
                 refine_factor: int = 4, refine_inflation: float = 0.01) -> None:
        self.sample_func = sample_func
        self.pdf_func = pdf_func
        self.frame = orthonormal_frame(np.asarray(axis, dtype=np.float64))
        self.axis = self.frame[2]
        self.sample_count = int(sample_count)
        if self.sample_count < 1:
            raise ValueError(f"sample_count must be >= 1, got {sample_count}")
        self.res = (int(res[0]), int(res[1]))
        if min(self.res) < 1:
            raise ValueError(f"res must be two positive integers, got {res!r}")
        self.ires = int(ires)
        if self.ires < 1:
            raise ValueError(f"ires must be >= 1, got {ires}")
        self.seed = int(seed)
        self.min_expected = float(min_expected)
        self.allow_invalid = bool(allow_invalid)
        self.pdf_rtol = float(pdf_rtol)
        self.pdf_mismatch_fraction = float(pdf_mismatch_fraction)
        self.max_batch = int(max_batch)
        self.refine_factor = int(refine_factor)
        self.refine_inflation = float(refine_inflation)
        self.refined_cells = 0

        self.histogram: NDArray | None = None
        self.expected: NDArray | None = None
        self.p_value = math.nan
        self.statistic = math.nan
        self.dof = 0
        self.pdf_integral = math.nan
        self.valid_fraction = math.nan
        self.invalid_count = 0
        self.passed = False
        self.messages = ""
        self._sample_problems: list[str] = []
        self._sample_notes: list[str] = []
        self._pdf_problems: list[str] = []
        self._cell_problems: list[str] = []
        self._quad_var: NDArray | None = None
        self._impossible_cells = 0
        self._cells_checked = False

    # -- geometry ------------------------------------------------------------------------

    def to_grid(self, dirs: NDArray) -> tuple[NDArray, NDArray]:
        """(cos θ, φ ∈ [0, 2π)) of unit directions in this test's frame."""
        b1, b2, n = self.frame
        cos_t = np.clip(dirs @ n, -1.0, 1.0)
        phi = np.arctan2(dirs @ b2, dirs @ b1)
        phi = np.where(phi < 0.0, phi + 2.0 * math.pi, phi)
        return cos_t, phi

    def from_grid(self, cos_t: NDArray, phi: NDArray) -> NDArray:
        """Unit directions (k, 3) for (cos θ, φ) in this test's frame."""
        b1, b2, n = self.frame
        sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
        x, y = sin_t * np.cos(phi), sin_t * np.sin(phi)
        out = np.empty((len(cos_t), 3))
        for j in range(3):  # a column at a time: no (k, 3) temporaries, the same sums in the same order
            out[:, j] = x * b1[j] + y * b2[j] + cos_t * n[j]
        return out

    def _cell_index(self, cos_t: NDArray, phi: NDArray) -> tuple[NDArray, NDArray]:
        nc, nphi = self.res
        i = np.clip(np.floor((cos_t + 1.0) * (0.5 * nc)).astype(np.int64), 0, nc - 1)
        j = np.floor(phi * (nphi / (2.0 * math.pi))).astype(np.int64) % nphi
        return i, j

    def _pdf(self, dirs: NDArray) -> NDArray:
        """`pdf_func` over `dirs` in batches of at most `max_batch`, as float64."""
        out = np.empty(dirs.shape[0], dtype=np.float64)
        for start in range(0, dirs.shape[0], self.max_batch):
            stop = min(start + self.max_batch, dirs.shape[0])
            vals = np.asarray(self.pdf_func(np.ascontiguousarray(dirs[start:stop])), dtype=np.float64)
            if vals.shape != (stop - start,):
                raise ValueError(f"pdf_func returned shape {vals.shape} for {stop - start} directions")
            out[start:stop] = vals
        return out

    # -- tabulation -----------------------------------------------------------------------

    def tabulate_histogram(self) -> None:
        """Draw the samples, check their pdfs, and bin the valid ones.

        :meth:`run` calls this once; call it again to draw afresh.
        """
        self._sample_problems = []
        self._sample_notes = []
        self._cells_checked = False
        out = self.sample_func(self.sample_count, self.seed)
        dirs = np.asarray(out[0], dtype=np.float64)
        pdf = np.asarray(out[1], dtype=np.float64)
        if dirs.shape != (self.sample_count, 3) or pdf.shape != (self.sample_count,):
            raise ValueError(f"sample_func returned shapes {dirs.shape} and {pdf.shape}, "
                             f"expected ({self.sample_count}, 3) and ({self.sample_count},)")
        valid = np.all(np.isfinite(dirs), axis=1) & np.isfinite(pdf) & (pdf != 0.0)
        self.invalid_count = int(self.sample_count - np.count_nonzero(valid))
        self.valid_fraction = 1.0 - self.invalid_count / self.sample_count
        if self.invalid_count and not self.allow_invalid:
            self._sample_problems.append(
                f"{self.invalid_count} invalid samples (pdf 0 or NaN) of {self.sample_count}; "
                "pass allow_invalid=True if the sampler may fail")
        dirs = dirs[valid]
        pdf = pdf[valid]
        negative = int(np.count_nonzero(pdf < 0.0))
        if negative:
            self._sample_problems.append(f"{negative} samples report a negative pdf")

        norms = np.linalg.norm(dirs, axis=1)
        off_unit = int(np.count_nonzero(np.abs(norms - 1.0) > 1e-4))
        if off_unit:
            self._sample_problems.append(f"{off_unit} valid samples are not unit vectors "
                                         f"(|norm − 1| up to {np.max(np.abs(norms - 1.0)):.3g})")

        if dirs.shape[0]:
            claimed = self._pdf(dirs)
            scale = np.maximum(np.abs(pdf), np.abs(claimed))
            with np.errstate(invalid="ignore", divide="ignore"):
                rel = np.where(scale > 0.0, np.abs(pdf - claimed) / scale, 0.0)
            rel = np.where(np.isfinite(rel), rel, np.inf)
            bad = int(np.count_nonzero(rel > self.pdf_rtol))
            frac = bad / dirs.shape[0]
            if bad:
                worst = int(np.argmax(rel))
                note = (f"{bad} samples ({frac:.3g} of the valid ones) report a pdf that differs from "
                        f"pdf_func by more than {self.pdf_rtol:g} relative; worst: sampler "
                        f"{pdf[worst]:.6g} vs pdf_func {claimed[worst]:.6g} at direction "
                        f"{np.array2string(dirs[worst], precision=5)}")
                if frac > self.pdf_mismatch_fraction:
                    self._sample_problems.append(note)
                else:
                    self._sample_notes.append(note + f" (tolerated, below {self.pdf_mismatch_fraction:g})")
            safe = dirs / np.where(norms > 0.0, norms, 1.0)[:, None]
        else:
            safe = dirs
        cos_t, phi = self.to_grid(safe)
        i, j = self._cell_index(cos_t, phi)
        nc, nphi = self.res
        self.histogram = np.bincount(i * nphi + j, minlength=nc * nphi).reshape(nc, nphi).astype(np.float64)

    def _integrate_cells(self, cells: NDArray, ires: int, rng: np.random.Generator) -> tuple[NDArray, NDArray]:
        """Jittered-quadrature integral of the pdf over `cells` (flat indices).

        Returns the integrals and, per cell, an estimate of the quadrature variance
        that errs high: collapsed strata (:meth:`_collapsed_strata_variance`) for
        even `ires` >= 4, the plain Monte Carlo variance of the points otherwise.
        """
        nc, nphi = self.res
        dc = 2.0 / nc
        dphi = 2.0 * math.pi / nphi
        area = dc * dphi
        per_cell = ires * ires
        # Cells per pdf_func call, so that a call holds at most max_batch points.
        chunk = max(1, self.max_batch // per_cell)
        sub = (np.arange(per_cell) // ires).astype(np.float64), (np.arange(per_cell) % ires).astype(np.float64)
        integrals = np.empty(cells.size)
        variances = np.empty(cells.size)
        for start in range(0, cells.size, chunk):
            batch = cells[start:start + chunk]
            ci = (batch // nphi).astype(np.float64)[:, None]
            cj = (batch % nphi).astype(np.float64)[:, None]
            ju = rng.random((batch.size, per_cell))
            jv = rng.random((batch.size, per_cell))
            cos_t = -1.0 + dc * (ci + (sub[0][None, :] + ju) / ires)
            phi = dphi * (cj + (sub[1][None, :] + jv) / ires)
            vals = self._pdf(self.from_grid(cos_t.ravel(), phi.ravel())).reshape(batch.size, per_cell)
            integrals[start:start + batch.size] = area * np.mean(vals, axis=1)
            if ires % 2 == 0 and ires >= 4:
                var = self._collapsed_strata_variance(vals.reshape(batch.size, ires, ires))
            elif per_cell > 1:
                var = np.var(vals, axis=1, ddof=1) / per_cell  # plain Monte Carlo bound
            else:
                var = np.full(batch.size, np.inf)
            variances[start:start + batch.size] = area * area * var
        return integrals, variances

    @staticmethod
    def _collapsed_strata_variance(grid: NDArray) -> NDArray:
        """Variance of the mean of one-point-per-stratum samples, by collapsed strata.

        `grid` is (cells, ires, ires), one value per sub-cell. Neighbouring sub-cells are
        paired and each pair taken as one stratum of two points, which gives an
        upward-biased estimate Σ (f_a − f_b)² / S² (S = ires²). One pairing is blind to
        some edges (an edge along φ does not separate φ-pairs; a corner of the support
        that covers exactly an aligned 2 × 2 block separates no pair), so four pairings
        are formed (along each axis, aligned and shifted by one sub-cell) and the
        largest estimate kept.
        """
        ires = grid.shape[1]
        half = ires // 2
        s = float(ires * ires) ** 2
        estimates = []
        for g in (grid, np.swapaxes(grid, 1, 2)):
            d = g[:, :, 0::2] - g[:, :, 1::2]
            estimates.append(np.sum(d * d, axis=(1, 2)) / s)
            d = g[:, :, 1:-1:2] - g[:, :, 2::2]  # shifted: half − 1 pairs per row
            estimates.append(np.sum(d * d, axis=(1, 2)) * (half / (half - 1)) / s)
        return np.max(estimates, axis=0)

    def tabulate_pdf(self) -> None:
        """Expected counts per cell by jittered quadrature of `pdf_func`.

        :meth:`run` calls this once; call it again to integrate afresh.
        """
        self._pdf_problems = []
        self._cells_checked = False
        nc, nphi = self.res
        rng = np.random.default_rng([self.seed, 0x5C2])
        integrals, variances = self._integrate_cells(np.arange(nc * nphi), self.ires, rng)
        # Cells whose quadrature noise would add more than `refine_inflation` to the
        # statistic (typically those a discontinuity crosses) are integrated again,
        # independently, with `refine_factor`× the points per dimension.
        with np.errstate(invalid="ignore"):
            counts = self.sample_count * integrals
            inflation = self.sample_count ** 2 * variances / np.maximum(counts, self.min_expected)
        rough = np.flatnonzero(np.isfinite(inflation) & (inflation > self.refine_inflation))
        self.refined_cells = int(rough.size)
        if rough.size and self.refine_factor > 1:
            fine, fine_var = self._integrate_cells(rough, self.refine_factor * self.ires, rng)
            integrals[rough] = fine
            variances[rough] = fine_var
        bad = ~np.isfinite(integrals)
        if np.any(bad):
            self._pdf_problems.append(f"pdf_func is not finite in {int(np.count_nonzero(bad))} cells")
            integrals = np.where(bad, 0.0, integrals)
        if np.any(integrals < 0.0):
            self._pdf_problems.append("pdf_func is negative somewhere")
        self.expected = (self.sample_count * integrals).reshape(nc, nphi)
        self._quad_var = (self.sample_count ** 2 * variances).reshape(nc, nphi)
        self.pdf_integral = float(np.sum(integrals))

    def _refine_impossible(self) -> None:
        """Re-integrate cells with samples but (almost) no expected mass at 8× resolution."""
        assert self.histogram is not None and self.expected is not None
        self._cell_problems = []
        self._cells_checked = True
        flat_obs = self.histogram.ravel()
        flat_exp = self.expected.ravel()
        suspects = np.flatnonzero((flat_obs > 0) & (flat_exp < 1e-6))
        self._impossible_cells = 0
        if suspects.size == 0:
            return
        rng = np.random.default_rng([self.seed, 0x5C3])
        integrals, _ = self._integrate_cells(suspects, 8 * self.ires, rng)
        refined = self.sample_count * np.where(np.isfinite(integrals), integrals, 0.0)
        flat_exp[suspects] = np.maximum(flat_exp[suspects], refined)
        still = suspects[flat_exp[suspects] < 1e-6]
        self._impossible_cells = int(still.size)
        if still.size:
            nc, nphi = self.res
            lines = []
            for c in still[np.argsort(-flat_obs[still])][:5]:
                ci, cj = divmod(int(c), nphi)
                lines.append(f"cos θ {(-1.0 + (ci + 0.5) * 2.0 / nc):+.4f}, "
                             f"φ {((cj + 0.5) * 2.0 * math.pi / nphi):.4f}: observed {int(flat_obs[c])}, "
                             f"expected {flat_exp[c]:.3g}")
            self._cell_problems.append(
                f"{still.size} cells hold samples where the pdf says they are impossible "
                f"(expected < 1e-6), e.g. " + "; ".join(lines))
        self.expected = flat_exp.reshape(self.res)

    # -- the test -------------------------------------------------------------------------

    def run(self, significance: float = 0.01, test_count: int = 1) -> bool:
        """Run the test.

        The samples and the expected counts are tabulated on the first call and kept;
        later calls only redo the statistic (e.g. at another significance).

        Parameters
        ----------
        significance : float, optional
            Family-wise significance level.
        test_count : int, optional
            Number of tests in the family; the per-test threshold is
            ``sidak_threshold(significance, test_count)``.

        Returns
        -------
        bool
            True when the sampler passes: no sample or pdf problem and
            p-value >= threshold.
        """
        if self.histogram is None:
            self.tabulate_histogram()
        if self.expected is None:
            self.tabulate_pdf()
        if not self._cells_checked:
            self._refine_impossible()
        assert self.histogram is not None and self.expected is not None
        problems = self._sample_problems + self._pdf_problems + self._cell_problems
        threshold = sidak_threshold(significance, test_count)

        obs = self.histogram.ravel()
        exp = self.expected.ravel()
        labels = np.arange(obs.size)
        if self.allow_invalid:
            # The invalid samples are one more bin of the multinomial.
            exp_invalid = max(0.0, self.sample_count * (1.0 - self.pdf_integral))
            obs = np.append(obs, float(self.invalid_count))
            exp = np.append(exp, exp_invalid)
            labels = np.append(labels, -1)

        order = np.argsort(exp, kind="stable")
        exp_sorted = exp[order]
        small = int(np.searchsorted(exp_sorted, self.min_expected, side="left"))
        pooled = small
        if small:
            cum = np.cumsum(exp_sorted)
            if 0.0 < cum[small - 1] < self.min_expected:
                # Grow the pool, smallest cells first, until it reaches min_expected.
                pooled = min(int(np.searchsorted(cum, self.min_expected, side="left")) + 1, exp.size)
        pool_idx = order[:pooled]
        keep_idx = order[pooled:]
        pool_obs = float(np.sum(obs[pool_idx]))
        pool_exp = float(np.sum(exp[pool_idx]))

        contrib = (obs[keep_idx] - exp[keep_idx]) ** 2 / exp[keep_idx]
        statistic = float(np.sum(contrib))
        bins = keep_idx.size
        if pool_exp > 0.0:
            statistic += (pool_obs - pool_exp) ** 2 / pool_exp
            bins += 1
        elif pool_obs > 0.0 and not self._impossible_cells:
            # Cells with samples but no expected mass were reported above; what is left
            # is the invalid-sample bin: the sampler failed although the pdf integrates to 1.
            problems.append(f"{int(pool_obs)} samples were pooled where the pdf integrates to 0 "
                            f"(invalid samples although the pdf integrates to {self.pdf_integral:.6f})")
        self.statistic = statistic
        self.dof = bins - 1
        if self.dof < 1:
            problems.append(f"only {bins} bin(s) after pooling: too few samples for a test")
            self.p_value = math.nan
        else:
            self.p_value = float(chdtrc(self.dof, statistic))  # chi-square survival function

        self.passed = (not problems) and self.p_value >= threshold
        self.messages = self._report(threshold, significance, test_count, keep_idx, contrib, labels,
                                     pooled, pool_obs, pool_exp, problems)
        return self.passed

    def _report(self, threshold: float, significance: float, test_count: int, keep_idx: NDArray,
                contrib: NDArray, labels: NDArray, pooled: int, pool_obs: float, pool_exp: float,
                problems: list[str]) -> str:
        assert self.histogram is not None and self.expected is not None and self._quad_var is not None
        nc, nphi = self.res
        lines = [
            f"chi-square test: {'PASSED' if self.passed else 'FAILED'}",
            f"  samples {self.sample_count}, valid fraction {self.valid_fraction:.6f}, "
            f"grid {nc} (cos θ) × {nphi} (φ), quadrature {self.ires}² points per cell "
            f"({self.refined_cells} cells refined to {self.refine_factor * self.ires}²)",
            f"  integral of pdf over the sphere {self.pdf_integral:.6f} "
            f"(should be {'the valid fraction' if self.allow_invalid else '1'}: "
            f"{self.valid_fraction if self.allow_invalid else 1.0:.6f})",
            f"  statistic {self.statistic:.2f}, dof {self.dof}, p-value {self.p_value:.4g}, "
            f"threshold {threshold:.4g} (significance {significance:g} over {test_count} test(s), Šidák)",
            f"  pooled {pooled} cells (expected < {self.min_expected:g}) into one bin: observed {pool_obs:.0f}, "
            f"expected {pool_exp:.2f}",
        ]
        exp = self.expected.ravel()
        qv = self._quad_var.ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            inflation = np.where(exp >= self.min_expected, qv / exp, 0.0)
        bound = float(np.sum(inflation))
        if self.allow_invalid:
            exp_invalid = self.sample_count * (1.0 - self.pdf_integral)
            if exp_invalid >= self.min_expected:
                bound += float(np.sum(qv)) / exp_invalid
        lines.append(f"  quadrature: estimated inflation of the statistic (errs high) {bound:.3g} "
                     f"(against its spread sqrt(2·dof) = {math.sqrt(2.0 * max(self.dof, 0)):.1f})")
        for p in problems:
            lines.append(f"  problem: {p}")
        for note in self._sample_notes:
            lines.append(f"  note: {note}")
        if contrib.size:
            top = np.argsort(-contrib)[:5]
            lines.append("  largest contributions (O − E)²/E:")
            for t in top:
                lab = int(labels[keep_idx[t]])
                if lab < 0:
                    where = "invalid samples"
                    o = float(self.invalid_count)
                    e = max(0.0, self.sample_count * (1.0 - self.pdf_integral))
                else:
                    ci, cj = divmod(lab, nphi)
                    where = (f"cos θ {(-1.0 + (ci + 0.5) * 2.0 / nc):+.4f}, "
                             f"φ {((cj + 0.5) * 2.0 * math.pi / nphi):.4f}")
                    o = float(self.histogram[ci, cj])
                    e = float(self.expected[ci, cj])
                lines.append(f"    {where}: observed {o:.0f}, expected {e:.2f}, contribution {contrib[t]:.2f}")
        return "\n".join(lines)
