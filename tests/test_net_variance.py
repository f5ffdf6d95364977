"""The exact-variance forms of ``sobol`` and ``halton`` (warpis.point_sets.nets).

*The pair classes.*  The counts N(a, b) of pairs whose unscrambled coordinates share ≥ a
and ≥ b leading digits equal those read off the kernel's own scrambled points (nested
scrambling keeps the number of shared digits), pair by pair.  The gains have Owen's
properties: with levels counted as box widths b^-j, Γ(j) = 0 whenever 0 < j1 + j2 ≤ k
for the Sobol' (0,k,2)-net m = 2^k, Γ = 2 on j1 + j2 = k + 1 (j1, j2 ≥ 1), 1 beyond; Γ = 0
on [0,a]×[0,b] for Halton at m = 2^a·3^b; Γ ≥ 0 always.  And m·Σ Γ(j)·Δ(j) equals, to
rounding, the variance over *every* nested scramble of the leading digits (enumerated
exhaustively: 2^7 per base-2 coordinate with 3 digits, 6^4 per base-3 one with 2) of a
random ψ constant on the level-3 boxes, at several m that are not nets.

*Exact to rounding.*  For a product of Walsh functions of single digits (ψ = r_{j1}(x)
r_{j2}(y), Δ = ‖ψ‖² at j alone) the estimator has no noise where the design cancels
every other level: the prediction is exactly 0 at the coarse levels of a net (and every
trial's Σψ is exactly 0 on the kernel's points), exactly 2m on the diagonal j1 + j2 = k + 1
of the Sobol' net, and m·Γ(j)·‖ψ‖² at levels of non-nets listed below.

*Against the kernel's own points.*  For sobol at m ∈ {1, 4, 12, 16, 64} and halton at
m ∈ {1, 6, 12, 18, 27}, a smooth ψ, a straight edge (indicator of y < 0.3 + 0.4x) and
x·y; a mixture (a technique picked at random per sample, so E[ψ²|u] ≠ E[ψ|u]²) simulated
with its random picks; the exact nonzero Walsh cases: the prediction is held against the
sample variance of Σψ over ``TRIALS`` trials of ``pattern_points`` (a fourth-moment
interval), the gap divided by both standard errors together.  Against closed forms: m = 1
gives Var ψ (smooth: Gauss–Legendre; edge: 1/4), and ψ = x on the Sobol' net m = 2^k gives
the stratified m·(4^-k − 4^-24)/12 (the points lie on the 2^-24 grid).

Every statistical comparison of this file (``RUNS`` of them) uses the Šidák threshold of
``ALPHA`` = 1e-3, so the file fails by chance with probability ≤ 1e-3 (asymptotically in
the trial and draw counts).  ``test_a_wrong_law_is_rejected`` shows the comparison has
power: the Sobol' prediction is rejected for Halton points, and independent points'
m·Var ψ for Sobol' points, at the same threshold.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.special import ndtri

from conftest import mixture, one_technique

from warpis.point_sets import MAX_POINTS_PER_CALL
from warpis.point_sets.nets import (gains, halton_sum_variance, pair_counts,
                                              sobol_sum_variance)
from warpis.stats import sidak_threshold, variance_interval
from warpis.kernels.patterns import pattern_points

FORMS = {"sobol": sobol_sum_variance, "halton": halton_sum_variance}
COUNTS = {"sobol": (1, 4, 12, 16, 64), "halton": (1, 6, 12, 18, 27)}
MIXTURE_COUNTS = {"sobol": (12, 64), "halton": (18, 27)}
TRIALS = 1 << 15
BUDGET = 1 << 18  # dense points per prediction (the caller starts at 2^17 and goes up to 2^20)
ALPHA = 1e-3
BASES = {"sobol": (2, 2), "halton": (2, 3)}

# (pattern, m, j1, j2, Γ): Walsh products whose prediction is exact and nonzero.
EXACT = [("sobol", 16, j1, 5 - j1, 2.0) for j1 in range(1, 5)] + [
    ("sobol", 12, 0, 3, 1 / 3), ("sobol", 12, 3, 0, 1 / 3), ("halton", 18, 2, 0, 1 / 9), ("halton", 18, 0, 3, 1 / 2)]
X_NETS = range(0, 7)  # ψ = x on the Sobol' net of 2^k points


def smooth(x, y):
    return np.exp(x) * np.sin(3 * y) + x * y


def edge(x, y):
    return (y < 0.3 + 0.4 * x).astype(np.float64)


def product(x, y):
    return x * y


INTEGRANDS = (smooth, edge, product)
RUNS = (sum(len(c) for c in COUNTS.values()) * len(INTEGRANDS)  # test_matches_kernel_points
        + sum(len(c) for c in MIXTURE_COUNTS.values())  # test_mixture_matches_kernel_points
        + 2 * 2  # test_one_point_is_var_psi
        + len(X_NETS)  # test_x_on_a_net_is_stratified
        + 2 * len(EXACT))  # test_exact_walsh_levels: closed form and kernel points
Z = float(ndtri(1 - sidak_threshold(ALPHA, RUNS) / 2))


# --------------------------------------------------------------------------- helpers


def digit(v: np.ndarray, base: int, j: int) -> np.ndarray:
    """The j-th base-``base`` digit of v (j ≥ 1)."""
    return np.floor(v * float(base) ** j).astype(np.int64) % base


def walsh(base: int, j: int):
    """A function of the j-th digit alone with mean 0 over the next digit: (−1)^digit in
    base 2, (1, −1, 0)[digit] in base 3; the constant 1 at j = 0.  Returns (g, ‖g‖²)."""
    if j == 0:
        return (lambda v: np.ones_like(v)), 1.0
    if base == 2:
        return (lambda v: 1.0 - 2.0 * digit(v, 2, j)), 1.0
    return (lambda v: np.array([1.0, -1.0, 0.0])[digit(v, 3, j)]), 2.0 / 3.0


def walsh_product(pattern: str, j1: int, j2: int):
    (gx, nx), (gy, ny) = walsh(BASES[pattern][0], j1), walsh(BASES[pattern][1], j2)
    return (lambda x, y: gx(x) * gy(y)), nx * ny


def sums(pattern: str, m: int, funcs, seed: int) -> np.ndarray:
    """(len(funcs), TRIALS) sums Σψ over the kernel's points."""
    u = pattern_points(pattern, m, TRIALS, seed=seed).astype(np.float64)
    return np.stack([fn(u[..., 0], u[..., 1]).sum(axis=1) for fn in funcs])


def gap(pred_value, pred_stderr, emp) -> np.ndarray:
    """|prediction − sample variance| in units of both standard errors together."""
    return np.abs(pred_value - emp.variance) / np.hypot(pred_stderr, emp.variance_stderr)


# --------------------------------------------------------------------------- pair classes


def shared_digits(v: np.ndarray, base: int, most: int) -> np.ndarray:
    """(m, m) leading base-``base`` digits each pair of coordinates shares (up to ``most``)."""
    k = np.zeros((len(v), len(v)), np.int64)
    for j in range(1, most + 1):
        cell = np.floor(v * float(base) ** j).astype(np.int64)
        k += (cell[:, None] == cell[None, :]) & (k == j - 1)
    return k


@pytest.mark.parametrize("pattern, m", [("sobol", m) for m in (1, 2, 3, 5, 12, 16, 27, 64, 100)]
                         + [("halton", m) for m in (1, 2, 5, 6, 12, 18, 27, 64)])
def test_pair_counts_match_the_kernels_points(pattern, m):
    n = pair_counts(pattern, m)
    b1, b2 = BASES[pattern]
    for trial in pattern_points(pattern, m, 3, seed=21).astype(np.float64):
        k1 = shared_digits(trial[:, 0], b1, n.shape[0] + 1)
        k2 = shared_digits(trial[:, 1], b2, n.shape[1] + 1)
        off = ~np.eye(m, dtype=bool)
        brute = np.array([[int(((k1 >= a) & (k2 >= b) & off).sum()) for b in range(n.shape[1] + 1)]
                          for a in range(n.shape[0] + 1)])
        assert (brute[:-1, :-1] == n).all() and not brute[-1].any() and not brute[:, -1].any(), (pattern, m)


@pytest.mark.parametrize("k", range(0, 11))
def test_sobol_nets_have_owens_gains(k):
    """Γ(j) = 0 for 0 < j1 + j2 ≤ k, 2 on j1 + j2 = k + 1 off the axes, 1 on the axes there
    and beyond (the table stops where every further gain is 1)."""
    g = gains("sobol", 1 << k)
    j1, j2 = np.indices(g.shape)
    s = j1 + j2
    assert g[0, 0] == 1 << k
    assert (g[(s <= k) & (s > 0)] == 0).all()
    assert (g[(s == k + 1) & (j1 > 0) & (j2 > 0)] == 2).all()
    assert (g[(s == k + 1) & ((j1 == 0) | (j2 == 0))] == 1).all()
    assert (g[s > k + 1] == 1).all()


@pytest.mark.parametrize("a, b", [(0, 1), (1, 0), (1, 1), (2, 1), (1, 2), (3, 2)])
def test_halton_at_2a_3b_has_zero_gains_on_its_boxes(a, b):
    g = gains("halton", 2**a * 3**b)
    block = g[:a + 1, :b + 1].copy()
    block[0, 0] = 0
    assert (block == 0).all()
    assert (g != 0).sum() > 1  # gains beyond the boxes are not zero


def test_gains_are_never_negative():
    """Γ(j) < 0 would give a negative variance to a Walsh function of level j."""
    for pattern in FORMS:
        for m in range(1, 300):
            assert (gains(pattern, m) >= -1e-12).all(), (pattern, m)


def nested_scrambles(base: int, depth: int) -> np.ndarray:
    """(S, base^depth): every nested scramble of ``depth`` digits as a map of cells (cell
    index = the digits as an integer, most significant first): a permutation of the
    digit values at every node (prefix) of the digit tree, all combinations."""
    nodes = [(k, prefix) for k in range(depth) for prefix in range(base**k)]
    perms = list(itertools.permutations(range(base)))
    cells = np.arange(base**depth)
    digits = [(cells // base ** (depth - 1 - k)) % base for k in range(depth)]
    maps = []
    for choice in itertools.product(range(len(perms)), repeat=len(nodes)):
        table = dict(zip(nodes, choice))
        out = np.zeros_like(cells)
        for k in range(depth):
            prefix = cells // base ** (depth - k)
            perm = np.array([perms[table[(k, p)]] for p in prefix])
            out = out * base + perm[cells, digits[k]]
        maps.append(out)
    return np.array(maps)


def unscrambled_cells(pattern: str, m: int, d1: int, d2: int) -> tuple[np.ndarray, np.ndarray]:
    """The level-(d1, d2) cell of each of the first m unscrambled points (an independent
    implementation: bit reversal; the Pascal matrix mod 2 for Sobol' y; base-3 digit
    reversal for Halton y)."""
    i = np.arange(m)
    x = sum(((i >> k) & 1) << (d1 - 1 - k) for k in range(d1))
    if pattern == "sobol":
        bits = [(i >> s) & 1 for s in range(12)]
        ydig = [sum(bits[s] * (1 if (s & r) == r else 0) for s in range(12)) % 2 for r in range(d2)]  # C(s, r) odd
        y = sum(ydig[r] << (d2 - 1 - r) for r in range(d2))
    else:
        y = sum(((i // 3**k) % 3) * 3 ** (d2 - 1 - k) for k in range(d2))
    return x, y


def exact_components(grid: np.ndarray, b1: int, b2: int) -> np.ndarray:
    """Δ(j1, j2) of a function constant on the cells of ``grid`` (x along axis 0)."""
    d1, d2 = round(np.log(grid.shape[0]) / np.log(b1)), round(np.log(grid.shape[1]) / np.log(b2))
    rho = np.zeros((d1 + 1, d2 + 1))
    for j1 in range(d1 + 1):
        for j2 in range(d2 + 1):
            means = grid.reshape(b1**j1, -1, b2**j2, grid.shape[1] // b2**j2).mean(axis=(1, 3))
            rho[j1, j2] = means.var()
    padded = np.pad(rho, ((1, 0), (1, 0)))
    return padded[1:, 1:] - padded[:-1, 1:] - padded[1:, :-1] + padded[:-1, :-1]


@pytest.mark.parametrize("pattern, m",
                         [("sobol", m) for m in (2, 3, 5, 6, 7, 8)] + [("halton", m) for m in (2, 4, 5, 7)])
def test_gain_form_equals_every_nested_scramble(pattern, m):
    """Var over all nested scrambles of the leading digits of Σψ, ψ constant on the
    level-(3, 3) boxes (level (3, 2) for Halton), equals m·Σ Γ(j)·Δ(j) to rounding."""
    b1, b2 = BASES[pattern]
    d1, d2 = 3, (3 if b2 == 2 else 2)
    grid = np.random.default_rng(m).normal(size=(b1**d1, b2**d2))
    sx, sy = nested_scrambles(b1, d1), nested_scrambles(b2, d2)
    cx, cy = unscrambled_cells(pattern, m, d1, d2)
    total = sum(grid[sx[:, cx[i]][:, None], sy[:, cy[i]][None, :]] for i in range(m))
    brute = total.var()
    g = np.ones((d1 + 1, d2 + 1))
    table = gains(pattern, m)
    g[:min(d1 + 1, table.shape[0]), :min(d2 + 1, table.shape[1])] = table[:d1 + 1, :d2 + 1]
    delta = exact_components(grid, b1, b2)
    delta[0, 0] = 0.0
    assert m * (g * delta).sum() == pytest.approx(brute, rel=1e-10)


# --------------------------------------------------------------------------- exact cases


@pytest.mark.parametrize("pattern, m, a, b", [("sobol", 16, 4, 4), ("halton", 18, 1, 2)])
def test_walsh_functions_at_coarse_levels_of_a_net_have_no_variance(pattern, m, a, b):
    """Levels where Γ = 0: prediction 0 with stderr 0, and Σψ = 0 in every trial."""
    levels = [(j1, j2) for j1 in range(a + 1) for j2 in range(b + 1)
              if (j1, j2) != (0, 0) and (pattern == "halton" or j1 + j2 <= a)]
    funcs = [walsh_product(pattern, j1, j2)[0] for j1, j2 in levels]
    pred = FORMS[pattern](one_technique(funcs), m, 1 << 14, np.random.default_rng(1))
    assert np.abs(pred.value).max() < 1e-9 and pred.stderr.max() < 1e-9
    assert np.abs(sums(pattern, m, funcs, seed=31)).max() < 1e-9


@pytest.mark.parametrize("pattern, m, j1, j2, gain", EXACT)
def test_exact_walsh_levels(pattern, m, j1, j2, gain):
    """Where the design cancels every other level the prediction is m·Γ(j)·‖ψ‖² to
    rounding (2m on the diagonal of the Sobol' net), and it matches the kernel's points."""
    fn, norm = walsh_product(pattern, j1, j2)
    assert gains(pattern, m)[j1, j2] == pytest.approx(gain, rel=1e-12)
    pred = FORMS[pattern](one_technique([fn]), m, 1 << 14, np.random.default_rng(2))
    assert pred.value[0] == pytest.approx(m * gain * norm, rel=1e-12) and pred.stderr[0] < 1e-9
    emp = variance_interval(sums(pattern, m, [fn], seed=41 + j1 + 7 * j2), level=0.99)
    assert gap(pred.value, pred.stderr, emp)[0] <= Z, (pred, emp)


@pytest.mark.parametrize("pattern", list(FORMS))
def test_one_point_is_var_psi(pattern):
    nodes, weights = np.polynomial.legendre.leggauss(64)
    x, w = (nodes + 1) / 2, weights / 2
    f = smooth(x[:, None], x[None, :])
    ww = w[:, None] * w[None, :]
    var_smooth = (ww * f * f).sum() - (ww * f).sum() ** 2
    pred = FORMS[pattern](one_technique([smooth, edge]), 1, BUDGET, np.random.default_rng(3))
    z = np.abs(pred.value - [var_smooth, 0.25]) / pred.stderr
    assert (z <= Z).all(), (pred, var_smooth)


@pytest.mark.parametrize("k", X_NETS)
def test_x_on_a_net_is_stratified(k):
    """ψ = x: m strata of 2^(24−k) grid points each, Var = m·(4^-k − 4^-24)/12."""
    m = 1 << k
    pred = sobol_sum_variance(one_technique([lambda x, y: x]), m, 1 << 16, np.random.default_rng(4))
    exact = m * (4.0**-k - 4.0**-24) / 12
    assert abs(pred.value[0] - exact) <= Z * pred.stderr[0], (pred, exact)
    assert pred.stderr[0] < 0.05 * exact


# --------------------------------------------------------------------------- kernel points


@pytest.mark.parametrize("pattern, m", [(p, m) for p in FORMS for m in COUNTS[p]])
def test_matches_kernel_points(pattern, m):
    pred = FORMS[pattern](one_technique(INTEGRANDS), m, BUDGET, np.random.default_rng(5))
    emp = variance_interval(sums(pattern, m, INTEGRANDS, seed=51), level=0.99)
    assert (gap(pred.value, pred.stderr, emp) <= Z).all(), (pred, emp.variance, emp.variance_stderr)


@pytest.mark.parametrize("pattern, m", [(p, m) for p in FORMS for m in MIXTURE_COUNTS[p]])
def test_mixture_matches_kernel_points(pattern, m):
    pred = FORMS[pattern](mixture(smooth, edge), m, BUDGET, np.random.default_rng(6))
    u = pattern_points(pattern, m, TRIALS, seed=61).astype(np.float64)
    pick = np.random.default_rng(62).random(u.shape[:2]) < 0.5
    psi = np.where(pick, smooth(u[..., 0], u[..., 1]), edge(u[..., 0], u[..., 1]))
    emp = variance_interval(psi.sum(axis=1)[None], level=0.99)
    assert gap(pred.value, pred.stderr, emp)[0] <= Z, (pred, emp)


def test_a_wrong_law_is_rejected():
    """The comparison has power: Sobol's prediction for Halton's points, and independent
    points' m·Var ψ for Sobol's, both miss by more than Z."""
    emp = variance_interval(sums("halton", 12, [smooth], seed=71), level=0.99)
    wrong = sobol_sum_variance(one_technique([smooth]), 12, BUDGET, np.random.default_rng(7))
    assert gap(wrong.value, wrong.stderr, emp)[0] > Z
    emp = variance_interval(sums("sobol", 16, [smooth], seed=72), level=0.99)
    iid = sobol_sum_variance(one_technique([smooth]), 1, BUDGET, np.random.default_rng(8))
    assert gap(16 * iid.value, 16 * iid.stderr, emp)[0] > Z


# --------------------------------------------------------------------------- the interface


def test_points_are_shared_by_receivers_and_counted():
    """Every call holds at most MAX_POINTS_PER_CALL points inside [0,1)² after the float32
    cast; the points reported are the points evaluated; a receiver's result is the same
    whatever other receivers are asked for (the points depend on m, budget and rng alone)."""
    seen = []

    def counting(funcs):
        inner = one_technique(funcs)

        def values(u):
            seen.append(len(u))
            return inner(u)
        return values

    both = sobol_sum_variance(counting([smooth, edge]), 100, 1 << 17, np.random.default_rng(9))
    assert sum(seen) == both.points and max(seen) <= MAX_POINTS_PER_CALL
    alone = sobol_sum_variance(counting([edge]), 100, 1 << 17, np.random.default_rng(9))
    assert alone.value[0] == pytest.approx(both.value[1], rel=1e-12)
    assert alone.stderr[0] == pytest.approx(both.stderr[1], rel=1e-12)


@pytest.mark.parametrize("pattern", list(FORMS))
def test_a_tiny_budget_still_gives_an_estimate_with_an_error(pattern):
    pred = FORMS[pattern](one_technique([smooth]), 64, 1, np.random.default_rng(10))
    assert pred.points > 1 and np.isfinite(pred.value).all() and (pred.stderr > 0).all()


def test_sets_the_kernels_refuse_are_refused():
    with pytest.raises(ValueError):
        pair_counts("sobol", (1 << 24) + 1)
