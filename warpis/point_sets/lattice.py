"""Exact Var(Σψ) of a randomly shifted rank-1 lattice (the ``lattice`` pattern).

Law assumed (``kernels.patterns.lattice_point``): the points are p_i + Δ mod 1, i < m,
p_i = (i/m, (i·g mod m)/m), g = :func:`lattice_generator` (m), with one shift Δ uniform on
[0,1)² per trial.  (The kernel draws Δ on the 2⁻²⁴ grid of float32: the form assumes the
continuous law.)

With f = E[ψ|u], s = E[ψ²|u] (s ≠ f² for a random technique pick) and
Q(Δ) = Σ_i f(p_i + Δ), conditioning on Δ gives

    Var(Σψ) = m·E[s − f²] + Var_Δ Q(Δ).

Q is periodic with the lattice L = {p_i} + Z², so Var_Δ Q is the variance of Q over one
cell of L, estimated from K independent *sets* of n shifts each.  A set is a coset
decomposition: the rank-1 lattice L' = {(k/N, k·G/N)} + Z² of N = m·n points, with
G ≡ g (mod m) so that L' ⊃ L (its points k = n·i are the p_i), splits into the n cosets
L + δ_j, δ_j = (j/N, j·G/N); with one uniform r per set the shifts are Δ_j = r + δ_j, each
uniform (so the estimate stays unbiased), while together they cover the cell of L evenly:
the set's mean of Q and of Q² are lattice-rule averages, whose error involves only the
Fourier modes of Q and Q² on the dual lattice of L'.  G is the candidate whose dual has
the longest shortest vector (the spectral test), so the low modes, where the variance of
Q lives, are averaged out.  With Q̄_k and v_k = mean_j (Q_kj − Q̄_k)² the mean and spread
of set k,

    V̂ = mean_k (w_k + v_k) + S²(Q̄₁, …, Q̄_K),    w_k = m · mean over set k of (s − f²),

is unbiased: E v_k = Var Q − Var Q̄_k and the sample variance S² of the K i.i.d. set means
has expectation Var Q̄_k.  It is the average of (Q − Q')²/2 over all pairs of shifts from
different sets, written without any difference of large sums.  Its stderr is the
jackknife over sets.  Derivation: docs/theory.md, "Exact variance of the point sets".
"""

from __future__ import annotations

import functools
import math

import numpy as np

from . import MAX_POINTS_PER_CALL, SumVariance, Values

BELOW_ONE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))  # the largest float32 below 1
INV_GOLDEN = 0.6180339887498949  # 1/φ, as in kernels.patterns
SETS = 16  # independent sets of shifts: the jackknife's replicas
MIN_SHIFTS_PER_SET = 4
UNION_CANDIDATES = 48  # generators G of L' tried on each side of N/φ


def lattice_generator(m: int) -> int:
    """g of the rank-1 lattice {(i/m, i·g/m)}: the integer nearest m/φ that is coprime with
    m, searched outwards from round(m/φ), the larger candidate first, exactly as the Warp
    ``kernels.patterns.lattice_generator`` (whose m/φ + 0.5 is float32 arithmetic)."""
    scaled = np.float32(np.float32(m) * np.float32(INV_GOLDEN)) + np.float32(0.5)
    g0 = int(np.floor(np.float32(scaled)))
    for d in range(m + 1):
        if g0 + d <= m and math.gcd(g0 + d, m) == 1:
            return g0 + d
        if g0 - d >= 1 and math.gcd(g0 - d, m) == 1:
            return g0 - d
    return 1


def shortest_dual_sq(count: int, g: int) -> int:
    """|h|² of the shortest h ≠ 0 with h₁ + h₂·g ≡ 0 (mod count): the spectral test of the
    rank-1 lattice {(k/count, k·g/count)}, by Lagrange reduction of the basis (count, 0),
    (−g, 1) of its dual."""
    a, b = (count, 0), (-g % count, 1)
    while True:
        if _norm_sq(a) < _norm_sq(b):
            a, b = b, a  # b is the shorter
        q = round((a[0] * b[0] + a[1] * b[1]) / _norm_sq(b))
        if q == 0:
            return _norm_sq(b)
        a = (a[0] - q * b[0], a[1] - q * b[1])


def _norm_sq(v: tuple[int, int]) -> int:
    return v[0] * v[0] + v[1] * v[1]


@functools.lru_cache(maxsize=256)
def union_generator(m: int, n: int) -> int:
    """G of the N = m·n point rank-1 lattice L' ⊃ L that the shifts of one set tile: among
    the G ≡ g (mod m) nearest N/φ (``UNION_CANDIDATES`` each side), the one with the best
    spectral test, the nearest N/φ among equals."""
    g, count = lattice_generator(m), m * n
    centre = round((count * INV_GOLDEN - g) / m)
    candidates = {(g + m * (t % n)) % count for t in range(centre - UNION_CANDIDATES, centre + UNION_CANDIDATES + 1)}
    return max(sorted(candidates), key=lambda c: (shortest_dual_sq(count, c), -abs(c - count * INV_GOLDEN)))


def lattice_sum_variance(values: Values, m: int, points: int, rng: np.random.Generator) -> SumVariance:
    """Var(Σ_{i<m} ψ(u_i)) of the shifted rank-1 lattice at every receiver of ``values``.

    Uses ``SETS`` sets of n shifts, n = (points // m) // SETS but at least
    ``MIN_SHIFTS_PER_SET``; each shift costs m points.
    """
    if m < 1:
        raise ValueError(f"m must be >= 1, got {m}")
    n = max(MIN_SHIFTS_PER_SET, points // m // SETS)
    big_g = union_generator(m, n)
    per_set = [_set_moments(values, m, n, big_g, rng.random(2)) for _ in range(SETS)]
    w, qbar, v = (np.stack(x, axis=-1) for x in zip(*per_set))  # each (R, SETS)
    value, stderr = _jackknife(w + v, qbar)
    return SumVariance(value, stderr, SETS * n * m)


def _set_moments(values: Values, m: int, n: int, big_g: int, r: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """w (m · mean of s − f²), Q̄ and the spread v = mean (Q − Q̄)² of one set (the lattice
    L' shifted by r), each (R,)."""
    total = n * m
    q, w = None, None
    for lo in range(0, total, MAX_POINTS_PER_CALL):
        # Shift-major order: point i of shift j is point k = j + n·i of L'.
        idx = np.arange(lo, min(lo + MAX_POINTS_PER_CALL, total))
        shift = idx // m
        k = shift + n * (idx % m)
        u = np.stack([k / total + r[0], (k * big_g % total) / total + r[1]], axis=-1)
        first, second = values(np.minimum(u % 1.0, BELOW_ONE))
        first, second = np.asarray(first, np.float64), np.asarray(second, np.float64)
        if q is None:
            q, w = np.zeros((len(first), n)), np.zeros(len(first))
        # The chunk holds a run of whole or partial shifts: sum each run into its Q.
        starts = np.flatnonzero(np.r_[True, shift[1:] != shift[:-1]])
        q[:, shift[starts]] += np.add.reduceat(first, starts, axis=1)
        w += (second - first * first).sum(axis=1)
    qbar = q.mean(axis=1)
    return w / n, qbar, ((q - qbar[:, None]) ** 2).mean(axis=1)


def _jackknife(a: np.ndarray, qbar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """mean(a) + S²(qbar) over the K sets (last axis) and its jackknife stderr.

    Leave-one-out values come from deviations from the mean (never from raw sums of
    squares): with d = qbar − mean(qbar) and D = Σd², S² without set k is
    (D − d_k²·K/(K−1)) / (K−2).
    """
    k = a.shape[-1]
    d = qbar - qbar.mean(axis=-1, keepdims=True)
    big_d = (d * d).sum(axis=-1, keepdims=True)
    value = a.mean(axis=-1) + big_d[..., 0] / (k - 1)
    loo = (a.sum(axis=-1, keepdims=True) - a) / (k - 1) + (big_d - d * d * k / (k - 1)) / (k - 2)
    spread = ((loo - loo.mean(axis=-1, keepdims=True)) ** 2).sum(axis=-1)
    return value, np.sqrt(spread * (k - 1) / k)
