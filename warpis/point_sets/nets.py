"""Exact Var(Σψ) of Owen-scrambled digital sequences (the ``sobol`` and ``halton`` patterns).

Law assumed (``kernels.patterns.pattern_point``): point i < m is (x_i, y_i) with x_i the
base-2 van der Corput point of i and y_i either the second Sobol' coordinate of i (Pascal
direction numbers, ``sobol_2d``; base 2) or the base-3 radical inverse of i (``halton``),
each coordinate scrambled by Owen's nested uniform scramble (a random permutation of the
digit values at every node of the digit tree, independent across nodes and across the two
coordinates).  Base 2 scrambles the leading 24 bits and places the point on the 2^-24 grid
(``owen_scramble_base2``, ``unit_float``); base 3 scrambles 20 digits (3^-20 < 2^-31).  So
every point is uniform, and for two distinct points whose *unscrambled* coordinate d
shares exactly k_d leading base-b_d digits (Owen 1997), after scrambling coordinate d
shares exactly k_d digits (a uniform random prefix), the next digits are a uniform ordered
pair of distinct digits and the later digits are independent uniform; the coordinates
are independent.  The hash that stands in for the random permutations is taken as ideal.
Base-2 coordinates are drawn on the kernel's 2^-24 grid, so their digit law holds exactly;
base-3 ones are drawn continuous and the caller rounds them to float32 as the kernel
rounds its points (the two can differ only for features finer than float32 resolves).

Formula (derivation: docs/theory.md, "Exact variance of the point sets").  With f = E[ψ|u], s = E[ψ²|u], E_j the
conditional mean on the base-b elementary cells of level j (width b^-j) and D_j = E_j −
E_{j−1} (D_0 = E_0), the variance components Δ(j) = ‖(D_{j1} ⊗ D_{j2}) f‖² ≥ 0 sum to
Var f, and a pair sharing exactly (k1, k2) digits has covariance Σ_j Δ(j) c1(j1,k1)
c2(j2,k2), c(j,k) = 1 if k ≥ j, −1/(b−1) if k = j−1, else 0.  Hence Owen's gain form

    Var(Σψ) = m·E[s − f²] + m·Σ_{j≠0} Γ(j)·Δ(j),
    Γ(j) = 1 + (1/m)·Σ_{pairs i≠i'} c1(j1,k1(i,i'))·c2(j2,k2(i,i')),

with the gains Γ ≥ 0 counted exactly from N(a, b), the ordered pairs whose unscrambled
coordinates share ≥ a and ≥ b digits, i.e. Σ c(c−1) over the elementary boxes of level
(a, b) holding c points, which both sequences give in closed form for any m, not only
for nets (``_counts``).  Γ = 1 at every level finer than all pairs' shared digits, so
with h(j1) the highest j2 where Γ(j1, j2) ≠ 1 (−1 where none) and J1 the last column
with one, every other level folds into local tail terms (T_h = I − E_h, T_{−1} = I):

    Var(Σψ)/m = Σ_{j1≤J1} Σ_{0<j, j2≤h(j1)} Γ(j)·‖(D_{j1}⊗D_{j2})f‖²
                + Σ_{j1≤J1} ‖(D_{j1}⊗T_{h(j1)})f‖² + ‖(T_{J1}⊗I)f‖² + E[s − f²].

Each term is the mean of i.i.d. draws of an unbiased quadratic form in f on a small
product grid of random points inside one random parent cell (centred over the sub-cells
for D, half a squared difference of two points of one cell for T; a point paired with
itself contributes s, which gives the last term its E[s − f²]), so its noise scales with
the variation of f inside that cell at that level, never with m²·E[ψ]², and a constant
shift of ψ cancels exactly.  The stderr is the sample standard error of the draws.  Only
levels with Γ ≠ 0 get points: for the (0,k,2)-net of Sobol' at m = 2^k, Γ(j) = 0
whenever 0 < j1 + j2 ≤ k (levels counted as box widths b^-j), which is why nets converge
fast.  The split of the budget over the terms depends on m and the budget alone (every
receiver sees the same points), so only efficiency depends on it.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from . import MAX_POINTS_PER_CALL, SumVariance, Values, add_draws, mean_variance

BELOW_ONE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))  # the largest float32 below 1
BITS = 24  # base-2 digits the kernel scrambles: its points lie on the 2^-BITS grid
MAX_M = 1 << BITS  # the kernels refuse larger sets (float32 resolves 2^24 strata per side)
BASES = {"sobol": (2, 2), "halton": (2, 3)}
MIN_DRAWS = 8  # per term, whatever the budget, so every term has a sample variance


# --------------------------------------------------------------------------- pair counts


def _counts(m: int, b1: int, b2: int, a_max: int, b_max: int) -> np.ndarray:
    """N[a, b] for the first m points of either sequence.

    Both are (0,2)-sequences in the sense that matters here: any M = b1^a·b2^b consecutive
    indices starting at a multiple of M put one point in every box of level (a, b) (Sobol':
    a block of 2^(a+b) is a (0, a+b, 2)-net; Halton: M consecutive integers hit every
    residue mod 2^a·3^b, and x, y share a, b digits exactly when the indices agree mod 2^a,
    3^b); so fewer than M of them, part of such a block, fall in distinct boxes.  With
    m = qM + r every box holds q or q + 1 points, r of them q + 1: N = Σ c(c−1) over the
    boxes = M·q(q−1) + 2qr.  (tests/test_net_variance.py counts the kernel's points.)
    """
    n = np.zeros((a_max + 1, b_max + 1), np.int64)
    for a in range(a_max + 1):
        for b in range(b_max + 1):
            boxes = b1**a * b2**b
            q, r = divmod(m, boxes)
            n[a, b] = boxes * q * (q - 1) + 2 * q * r
    return n


def _digits_needed(m: int, base: int) -> int:
    """The least L with base^L ≥ m: no two of m points share L digits of a coordinate."""
    level = 0
    while base**level < m:
        level += 1
    return level


@functools.lru_cache(maxsize=64)
def pair_counts(pattern: str, m: int) -> np.ndarray:
    """N[a, b]: ordered pairs i ≠ i' < m whose unscrambled coordinates share ≥ a leading
    base-b1 digits in x and ≥ b base-b2 digits in y; shape (A+1, B+1) with A, B the
    digits no pair shares (N[A, :] = N[:, B] = 0).  Read-only."""
    if not 1 <= m <= MAX_M:
        raise ValueError(f"m must be in [1, {MAX_M}], got {m}")
    b1, b2 = BASES[pattern]
    a_max, b_max = _digits_needed(m, b1), _digits_needed(m, b2)
    n = _counts(m, b1, b2, a_max, b_max)
    n.flags.writeable = False
    return n


# --------------------------------------------------------------------------- gains


def _exactly(n: np.ndarray, base: int, axis: int) -> np.ndarray:
    """(b−1)·Σ_k n(k)·c(j, k) along ``axis`` from the ≥-counts: b·N(j) − N(j−1), and N(0)
    at j = 0 (c(0, k) = 1: the whole interval is shared by every pair)."""
    n = np.moveaxis(n, axis, 0)
    out = n.copy()
    out[1:] = base * n[1:] - n[:-1]
    return np.moveaxis(out, 0, axis)


@functools.lru_cache(maxsize=64)
def _gain_parts(pattern: str, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer numerator and denominator of Γ(j) − 1 on the table of pair_counts (exact:
    Γ(j) = 1 exactly when the numerator is 0, and 0 when it is −den)."""
    b1, b2 = BASES[pattern]
    n = pair_counts(pattern, m)
    num = _exactly(_exactly(n, b1, 0), b2, 1)
    j1, j2 = np.indices(n.shape)
    den = m * np.where(j1 > 0, b1 - 1, 1) * np.where(j2 > 0, b2 - 1, 1)
    num.flags.writeable = den.flags.writeable = False  # cached: shared by every caller
    return num, den


def gains(pattern: str, m: int) -> np.ndarray:
    """Owen's gain Γ(j1, j2) of the m-point scrambled ``pattern`` at the level of boxes
    b1^-j1 × b2^-j2, on the (A+1, B+1) table of :func:`pair_counts` (Γ = 1 beyond it):
    Var(Σψ) = m·E[s − f²] + m·Σ_{j≠0} Γ(j)·Δ(j).  (Γ(0,0) = m multiplies Δ(0,0) = μ², which
    the variance omits.)"""
    num, den = _gain_parts(pattern, m)
    return 1.0 + num / den


# --------------------------------------------------------------------------- the terms


class _Axis:
    """The points one coordinate of a term's grid takes, and the quadratic form W over them.

    ``kind`` D (level j ≥ 1): a random parent cell of level j−1, two independent points
    (copies) in each of its b sub-cells, W = [[0, C], [C, 0]]/(2b) with C the centring
    over the sub-cells (only pairs of different copies, which are independent); D at j = 0:
    two independent uniform points, W = [[0, 1], [1, 0]]/2; T (level h): two independent
    points of one random cell of level h, W = [[1, −1], [−1, 1]]/2 (half the squared
    difference); I: one uniform point, W = [[1]].  E[Σ W φ(x_p)φ(x_p')] = ‖A φ‖² for every φ.
    """

    def __init__(self, kind: str, level: int, base: int) -> None:
        self.kind, self.level, self.base = kind, level, base
        if kind == "D" and level > 0:
            centre = np.eye(base) - 1.0 / base
            self.parent_level, self.cell_level = level - 1, level
            self.subs = np.tile(np.arange(base), 2)
            self.w = np.block([[np.zeros((base, base)), centre], [centre, np.zeros((base, base))]]) / (2 * base)
        elif kind == "D":
            self.parent_level = self.cell_level = 0
            self.subs = np.zeros(2, np.int64)
            self.w = np.array([[0.0, 0.5], [0.5, 0.0]])
        elif kind == "T":
            self.parent_level = self.cell_level = level
            self.subs = np.zeros(2, np.int64)
            self.w = np.array([[0.5, -0.5], [-0.5, 0.5]])
        else:
            self.parent_level = self.cell_level = 0
            self.subs = np.zeros(1, np.int64)
            self.w = np.ones((1, 1))

    @property
    def size(self) -> int:
        return len(self.subs)

    def positions(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, size) coordinates of n independent draws."""
        parent = rng.integers(0, self.base**self.parent_level, size=(n, 1))
        cells = parent * self.base ** (self.cell_level - self.parent_level) + self.subs
        return _uniform_in(cells, self.cell_level, self.base, rng)


def _uniform_in(cells: np.ndarray, level: int, base: int, rng: np.random.Generator) -> np.ndarray:
    """A uniform point in each cell of ``level``: base 2 on the kernel's 2^-24 grid (where
    its points lie, so the digit law holds exactly), base 3 continuous."""
    if base == 2:
        fine = 1 << (BITS - level)
        return (cells * fine + rng.integers(0, fine, size=cells.shape)) / float(1 << BITS)
    return np.minimum((cells + rng.random(cells.shape)) / float(base**level), BELOW_ONE)


class _Term:
    """coef · ‖(A_x ⊗ A_y) f‖², estimated on the product grid of the two axes' points."""

    def __init__(self, coef: float, x: _Axis, y: _Axis, scale: float) -> None:
        self.coef, self.x, self.y = coef, x, y
        self.scale = scale  # the heuristic size of the term, for splitting the budget
        # A point paired with itself (on both diagonals) contributes E[ψ²|u] = s, not f².
        self.diag = np.outer(np.diag(x.w), np.diag(y.w))

    @property
    def size(self) -> int:
        return self.x.size * self.y.size

    def points(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, size, 2) points of n draws: the product grid of both axes' coordinates."""
        px, py = self.x.positions(n, rng), self.y.positions(n, rng)
        grid = np.broadcast_arrays(px[:, :, None], py[:, None, :])
        return np.stack(grid, axis=-1).reshape(n, self.size, 2)

    def estimates(self, first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """(R, n) unbiased estimates of ‖(A_x ⊗ A_y) f‖² (plus E[s − f²] where the form has
        a diagonal) from the (R, n, size) values at n draws."""
        shape = first.shape[:2] + (self.x.size, self.y.size)
        f, s = first.reshape(shape), second.reshape(shape)
        out = (f * (self.x.w @ f @ self.y.w)).sum(axis=(2, 3))  # Σ W_x ⊗ W_y · f ⊗ f (W symmetric)
        if self.diag.any():
            out += ((s - f * f) * self.diag).sum(axis=(2, 3))
        return out


def _smooth_size(b1: int, b2: int, j1s: range, j2s: range) -> float:
    """Σ over the levels a term covers of (b1^-j1·b2^-j2)^1.5: the spread of a term's
    draws for a smooth ψ (its components fall like the box area squared), for splitting the
    budget only; every term stays unbiased whatever it says."""
    return sum((float(b1) ** -j1 * float(b2) ** -j2) ** 1.5 for j1 in j1s for j2 in j2s)


@functools.lru_cache(maxsize=64)
def _terms(pattern: str, m: int) -> tuple[_Term, ...]:
    """The terms of Var(Σψ)/m: Γ(j)·Δ(j) on R, the levels j2 ≤ h(j1) of each column j1 ≤ J1
    below its highest Γ ≠ 1 (those with Γ = 0 need no points), the tail of each column
    beyond R (T_{-1} = I where a column has none) and the columns beyond J1."""
    b1, b2 = BASES[pattern]
    num, den = _gain_parts(pattern, m)
    differs = num != 0  # Γ ≠ 1
    differs[0, 0] = True  # column 0 always holds the level of the mean
    height = [int(np.flatnonzero(col).max()) if col.any() else -1 for col in differs]
    last = max(j1 for j1, h in enumerate(height) if h >= 0)
    terms = []
    for j1 in range(last + 1):
        h = height[j1]
        for j2 in range(h + 1):
            if (j1, j2) != (0, 0) and num[j1, j2] != -den[j1, j2]:  # Γ = 0 needs no points
                gain = 1.0 + num[j1, j2] / den[j1, j2]
                terms.append(_Term(gain, _Axis("D", j1, b1), _Axis("D", j2, b2),
                                   _smooth_size(b1, b2, range(j1, j1 + 1), range(j2, j2 + 1))))
        tail = _Axis("T", h, b2) if h >= 0 else _Axis("I", 0, b2)
        terms.append(_Term(1.0, _Axis("D", j1, b1), tail,
                           _smooth_size(b1, b2, range(j1, j1 + 1), range(h + 1, h + 40))))
    terms.append(_Term(1.0, _Axis("T", last, b1), _Axis("I", 0, b2),
                       _smooth_size(b1, b2, range(last + 1, last + 40), range(0, 40))))
    return tuple(terms)


# --------------------------------------------------------------------------- estimation


def _allocate(terms: tuple[_Term, ...], points: int) -> list[int]:
    """Draws per term, the same for every ψ (every receiver sees the same points): half the
    budget spread evenly over the terms (a discontinuity's noise is set by how often a draw
    straddles it, much the same at every level) and half by Neyman's rule for a smooth ψ
    (n_t ∝ |coef_t|·size_t/√cost_t); at least ``MIN_DRAWS`` each.  Measured against the
    best split for each ψ this costs at most ~6× in variance (~2× typically)."""
    even = 0.5 * points / len(terms)
    weight = [abs(t.coef) * t.scale / math.sqrt(t.size) for t in terms]
    total = sum(w * t.size for w, t in zip(weight, terms))
    return [max(MIN_DRAWS, int((even + 0.5 * points * w / total * t.size) / t.size)) for w, t in zip(weight, terms)]


def _calls(sizes: list[int], draws: list[int]) -> list[list[tuple[int, int, int]]]:
    """Pack (term, first draw, end draw) pieces into calls of at most MAX_POINTS_PER_CALL
    points, a draw never split between calls (few calls for many small terms)."""
    calls: list[list[tuple[int, int, int]]] = [[]]
    room = MAX_POINTS_PER_CALL
    for t, (size, n) in enumerate(zip(sizes, draws)):
        lo = 0
        while lo < n:
            take = min(n - lo, room // size)
            if take == 0:
                calls.append([])
                room = MAX_POINTS_PER_CALL
                continue
            calls[-1].append((t, lo, lo + take))
            room -= take * size
            lo += take
    return [c for c in calls if c]


def _net_sum_variance(pattern: str, values: Values, m: int, points: int, rng: np.random.Generator) -> SumVariance:
    """Var(Σψ) = m·Σ_t coef_t·E_t, each E_t the mean of its i.i.d. draws."""
    terms = _terms(pattern, m)
    draws = _allocate(terms, points)
    grids = [t.points(n, rng) for t, n in zip(terms, draws)]  # every point from rng, in a fixed order
    moments: list = [None] * len(terms)
    for call in _calls([t.size for t in terms], draws):
        u = np.concatenate([grids[t][lo:hi].reshape(-1, 2) for t, lo, hi in call])
        first, second = (np.asarray(v, np.float64) for v in values(u))
        start = 0
        for t, lo, hi in call:
            stop = start + (hi - lo) * terms[t].size
            shape = (first.shape[0], hi - lo, terms[t].size)
            moments[t] = add_draws(moments[t], terms[t].estimates(first[:, start:stop].reshape(shape),
                                                                  second[:, start:stop].reshape(shape)))
            start = stop
    value = m * sum(t.coef * mo.mean for t, mo in zip(terms, moments))
    var = m * m * sum(t.coef**2 * mean_variance(mo) for t, mo in zip(terms, moments))
    used = sum(n * t.size for t, n in zip(terms, draws))
    return SumVariance(np.asarray(value, np.float64), np.sqrt(var), used)


def sobol_sum_variance(values: Values, m: int, points: int, rng: np.random.Generator) -> SumVariance:
    """Var(Σ_{i<m} ψ(u_i)) over the first m points (any m ≥ 1) of the Owen-scrambled 2D
    Sobol' sequence, at every receiver of ``values``: about ``points`` dense points per
    receiver (at least ``MIN_DRAWS`` draws of every term)."""
    return _net_sum_variance("sobol", values, m, points, rng)


def halton_sum_variance(values: Values, m: int, points: int, rng: np.random.Generator) -> SumVariance:
    """Var(Σ_{i<m} ψ(u_i)) over the first m points of the Owen-scrambled Halton sequence
    (bases 2 and 3), at every receiver of ``values``, as :func:`sobol_sum_variance`."""
    return _net_sum_variance("halton", values, m, points, rng)
