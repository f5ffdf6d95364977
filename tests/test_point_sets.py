"""The point sets themselves, as the trial kernel places them (``patterns.pattern_points``).

*Every point is uniform where it may fall.*  An estimator stays unbiased under a pattern
when its points' laws average to the uniform law on [0,1)².  Randomised sets (lhs, cmj,
sobol, halton, lattice, independent, antithetic) make each point uniform on the square;
the jittered ones make point i uniform in cell i of their grid (the cells the registry's
``blocks`` names).  For every registered pattern, at several m, the first, middle and
last point of 4096 trials — relative to its cell where it has one — is binned 4 × 4 and
held to the uniform by a chi-square test (15 degrees of freedom); all the runs of the
module together fail by chance with probability ≤ 1e-3 (Šidák over the runs).

*The structure that defines each set* (deterministic: no threshold), in every trial:
jittered — one point per cell of its rows × cols grid; lhs, cmj, lattice — one point in
each of the m columns and each of the m rows; cmj — also one per coarse cell; sobol —
at m = 2^k one point in every elementary interval 2^-a × 2^-b with a + b = k (a
(0,k,2)-net); halton — at m = 2^a·3^b one point in every box 2^-a × 3^-b; lattice — the
points minus the first are the lattice (i/m, i·g/m) mod 1, g coprime with m.

*The kernel runs them.*  On a smooth integrand (light-area sampling at the lit receiver 0
of occluded-quad, N = 64) every stratifying set must beat independent points: the upper
end of its 99.9% variance interval below the lower end of independent's (measured ratios
are 6× for lhs to over 100× for sobol, so a chance failure needs both fourth-moment
intervals to miss by factors far beyond their 1e-3 miss rates).  Unbiasedness of every
pattern × combiner is in tests/test_estimators.py, which loops over the registry.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.stats import chi2

import warpis
from warpis.stats import sidak_threshold
from warpis.kernels.patterns import PATTERNS, pattern_points
from warpis.vocabulary import grid_shape

TRIALS = 4096
COUNTS = (1, 2, 3, 7, 12, 16, 36, 64)
CASES = [(p, m) for p in PATTERNS for m in COUNTS if PATTERNS[p].problem(m) is None]
RUNS = 3 * len(CASES)  # first, middle and last point of each case
ALPHA = 1e-3


def _cells(u: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """The cell index of each point on an nx × ny grid (trials, m)."""
    return np.floor(u[..., 0] * nx).astype(int) * ny + np.floor(u[..., 1] * ny).astype(int)


def _one_per_cell(u: np.ndarray, nx: int, ny: int) -> bool:
    """Each trial's points fill the nx × ny cells once each."""
    cells = np.sort(_cells(u, nx, ny), axis=1)
    return bool((cells == np.arange(nx * ny)).all())


def _within_cell(pattern: str, u: np.ndarray, m: int) -> np.ndarray:
    """Points relative to their cell (point i in row-major cell i) for a pattern whose
    blocks are grid cells; the points themselves otherwise."""
    blocks = PATTERNS[pattern].blocks
    if blocks is None or blocks(m).cells == (1, 1):
        return u
    rows, cols = blocks(m).cells
    i = np.arange(m)
    return np.stack([u[..., 0] * cols - i % cols, u[..., 1] * rows - i // cols], axis=-1)


@pytest.mark.parametrize("pattern, m", CASES)
def test_every_point_of_every_pattern_is_uniform(pattern, m):
    u = pattern_points(pattern, m, TRIALS, seed=11)
    assert u.shape == (TRIALS, m, 2) and (u >= 0).all() and (u < 1).all()
    u = _within_cell(pattern, u.astype(np.float64), m)
    assert (u >= 0).all() and (u < 1).all(), pattern  # point i lies in cell i
    for i in sorted({0, m // 2, m - 1}):
        counts = np.bincount(_cells(u[:, i], 4, 4), minlength=16)
        stat = float(((counts - TRIALS / 16) ** 2).sum() / (TRIALS / 16))
        p = float(chi2.sf(stat, 15))
        assert p >= sidak_threshold(ALPHA, RUNS), (pattern, m, i, p, counts)


@pytest.mark.parametrize("m", [1, 2, 3, 7, 12, 16, 17, 64])
def test_jittered_and_cmj_fill_their_grid(m):
    rows, cols = grid_shape(m)
    for pattern in ("jittered", "cmj"):
        assert _one_per_cell(pattern_points(pattern, m, 64, seed=2), cols, rows), pattern


@pytest.mark.parametrize("pattern", ["lhs", "cmj", "lattice"])
@pytest.mark.parametrize("m", [1, 2, 3, 7, 12, 16, 17, 64, 100])
def test_latin_sets_hold_one_point_per_row_and_column(pattern, m):
    u = pattern_points(pattern, m, 64, seed=3)
    assert _one_per_cell(u, m, 1) and _one_per_cell(u, 1, m)


def _pairings(m: int, trials: int) -> np.ndarray:
    """The row of each column, (trials, m), of the lhs points of each trial."""
    u = pattern_points("lhs", m, trials, seed=6)
    cols, rows = np.floor(u[..., 0] * m).astype(int), np.floor(u[..., 1] * m).astype(int)
    return np.take_along_axis(rows, np.argsort(cols, axis=1), axis=1)


def test_lhs_pairs_columns_with_rows_uniformly():
    """The law the exact variance of lhs needs (docs/theory.md): the pairing of columns
    with rows is a uniform permutation.  At m = 4 all 24 pairings, and at m = 7 the row
    pair of columns 0 and 1 (42 values), are held to uniform by chi-square over 24,000
    trials, each at 5e-4 (false failure ≤ 1e-3).  Kensler's hashed permutation, which
    dealt the rows before, gave 8 of the 24 pairings at m = 4 (χ² ≈ 48,000)."""
    trials = 24000
    four = _pairings(4, trials)
    codes = (four * np.array([64, 16, 4, 1])).sum(axis=1)
    counts = np.bincount(codes, minlength=256)[np.unique(
        (np.array(list(itertools.permutations(range(4)))) * np.array([64, 16, 4, 1])).sum(axis=1))]
    assert counts.sum() == trials
    expected = trials / 24
    assert ((counts - expected) ** 2 / expected).sum() < chi2.ppf(1 - 5e-4, 23)
    seven = _pairings(7, trials)
    pair = seven[:, 0] * 7 + seven[:, 1]
    counts = np.bincount(pair, minlength=49)[[a * 7 + b for a in range(7) for b in range(7) if a != b]]
    assert counts.sum() == trials
    expected = trials / 42
    assert ((counts - expected) ** 2 / expected).sum() < chi2.ppf(1 - 5e-4, 41)


@pytest.mark.parametrize("k", range(0, 9))
def test_sobol_is_a_net_at_powers_of_two(k):
    m = 1 << k
    u = pattern_points("sobol", m, 64, seed=4)
    for a in range(k + 1):
        assert _one_per_cell(u, 1 << a, 1 << (k - a)), (m, a)


def test_sobol_prefixes_that_are_not_powers_of_two_are_not_nets_but_stay_uniform():
    """At m = 12 no elementary-interval property is promised (docs/estimators.md): the points are the
    first 12 of a scrambled sequence, so every point is still uniform (tested above)."""
    u = pattern_points("sobol", 16, 8, seed=5)
    first12 = pattern_points("sobol", 12, 8, seed=5)
    np.testing.assert_array_equal(u[:, :12], first12)


@pytest.mark.parametrize("a, b", [(0, 0), (1, 0), (0, 1), (2, 1), (1, 2), (3, 2), (2, 3)])
def test_halton_fills_its_boxes(a, b):
    m = 2**a * 3**b
    assert _one_per_cell(pattern_points("halton", m, 64, seed=6), 2**a, 3**b)


@pytest.mark.parametrize("m", [1, 2, 5, 8, 13, 21, 34, 36, 89, 100])
def test_lattice_is_a_shifted_rank_1_lattice(m):
    u = pattern_points("lattice", m, 16, seed=7).astype(np.float64)
    g = next(g for d in range(m + 1) for g in (round(m / ((1 + 5**0.5) / 2)) + d, round(m / ((1 + 5**0.5) / 2)) - d)
             if 1 <= g <= max(m, 1) and math.gcd(g, m) == 1)
    i = np.arange(m)
    for trial in u:
        shift = trial[0]
        expected = np.stack([i / m, (i * g % m) / m], axis=1)
        offset = (trial - shift - expected) % 1.0
        assert np.minimum(offset, 1 - offset).max() < 1e-5, (m, g)
    if m in (13, 21, 34, 89):  # Fibonacci m: g is the previous Fibonacci number
        assert g == {13: 8, 21: 13, 34: 21, 89: 55}[m]


@pytest.fixture(scope="module")
def quad():
    return warpis.load_scene("occluded-quad")


@pytest.mark.parametrize("pattern", ["jittered", "cmj", "sobol", "halton", "lattice", "lhs"])
def test_the_kernel_runs_each_set(quad, pattern):
    z = 3.29  # two-sided 99.9%
    iid = warpis.variance_interval(warpis.run_trials(quad, "independent:single:light-area", 64, 2000, seed=1,
                                                     receivers=[0])[0], level=0.999)
    got = warpis.variance_interval(warpis.run_trials(quad, f"{pattern}:single:light-area", 64, 2000, seed=1,
                                                     receivers=[0])[0], level=0.999)
    assert got.variance + z * got.variance_stderr < iid.variance - z * iid.variance_stderr, (got, iid)


@pytest.mark.parametrize("pattern", ["lhs", "cmj", "sobol", "halton", "lattice"])
def test_a_set_larger_than_float32_can_stratify_is_refused(pattern):
    with pytest.raises(warpis.WarpisError, match="float32"):
        pattern_points(pattern, (1 << 24) + 1, 1)
