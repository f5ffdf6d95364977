"""Exact Var(Σψ) of a Latin hypercube (the ``lhs`` pattern).

Law assumed (``kernels.patterns.lhs_point``): the m columns [c/m, (c+1)/m) and the m rows
are dealt to the m points by two independent uniformly random permutations, and each point
is uniform in its (column, row) cell, independently of the others.  So every point is
uniform on [0,1)², and two distinct points lie in distinct columns and distinct rows, the
two pairs of strata uniform and independent.

With f = E[ψ|u], s = E[ψ²|u] (a random technique pick makes s ≠ f²), μ = E f, and X, Y
i.i.d. uniform, conditioning on whether X and Y share a column (C) and a row (R):

    Var(Σψ) = m·W + m/(m−1) · (m·K − D)          (m ≥ 2);    Var(Σψ) = W + Var f   (m = 1)

    W = E[s − f²]                                   (the technique pick's own noise)
    K = E[(f(X₁₁) − f(X₁₂) − f(X₂₁) + f(X₂₂))²] / 4  (= Var f − Var col-means − Var row-means)
    D = E[(f(X₁₁) − f(X₁₁'))²] / 2                   (= the mean within-cell variance)

where X_ab is uniform in cell (column c_a, row r_b) with c₁, c₂, r₁, r₂ i.i.d. uniform on
0..m−1 and X₁₁' a second point of cell (c₁, r₁).  K is an interaction contrast: the
additive part of f cancels between points of the same strip, so neither K nor D carries
the O(1) variance that the Latin hypercube removes, and no large terms cancel.  One
replica (five points) gives one term T = m·w + m/(m−1)·(m·k − d) whose mean is the
variance; T is i.i.d. over replicas, so the estimate is their mean and its stderr their
sample standard error.  Derivation: docs/theory.md, "Exact variance of the point sets".
"""

from __future__ import annotations

import numpy as np

from . import MAX_POINTS_PER_CALL, SumVariance, Values, add_draws, mean_variance

BELOW_ONE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))  # the largest float32 below 1
POINTS_PER_REPLICA = 5
MIN_REPLICAS = 256


def lhs_sum_variance(values: Values, m: int, points: int, rng: np.random.Generator) -> SumVariance:
    """Var(Σ_{i<m} ψ(u_i)) of an m-point Latin hypercube at every receiver of ``values``.

    Uses ``points`` // 5 replicas of five points (at least ``MIN_REPLICAS``), drawn in
    chunks of at most ``MAX_POINTS_PER_CALL`` points per call of ``values``.
    """
    if m < 1:
        raise ValueError(f"m must be >= 1, got {m}")
    replicas = max(MIN_REPLICAS, points // POINTS_PER_REPLICA)
    per_call = MAX_POINTS_PER_CALL // POINTS_PER_REPLICA
    moments = None
    done = 0
    while done < replicas:
        count = min(per_call, replicas - done)
        moments = add_draws(moments, _replica_terms(values, m, _replica_points(m, count, rng)))
        done += count
    assert moments is not None
    return SumVariance(moments.mean, np.sqrt(mean_variance(moments)), replicas * POINTS_PER_REPLICA)


def _replica_points(m: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """(5, count, 2) points: X₁₁, X₁₂, X₂₁, X₂₂, X₁₁' of ``count`` replicas."""
    col = rng.integers(0, m, size=(2, count))
    row = rng.integers(0, m, size=(2, count))
    # The cell of each of the five points: (column index a, row index b) into col, row.
    which = np.array([(0, 0), (0, 1), (1, 0), (1, 1), (0, 0)])
    cells = np.stack([col[which[:, 0]], row[which[:, 1]]], axis=-1)  # (5, count, 2)
    u = (cells + rng.random((POINTS_PER_REPLICA, count, 2))) / m
    return np.minimum(u, BELOW_ONE)  # stays below 1 when the caller casts to float32


def _replica_terms(values: Values, m: int, u: np.ndarray) -> np.ndarray:
    """The unbiased term T of each replica, (R, count)."""
    count = u.shape[1]
    first, second = values(u.reshape(-1, 2))
    first = np.asarray(first, np.float64).reshape(-1, POINTS_PER_REPLICA, count)
    second = np.asarray(second, np.float64).reshape(first.shape)
    # Each of the five points is uniform on the square, so each estimates W.
    w = (second - first * first).mean(axis=1)
    f11, f12, f21, f22, f11b = (first[:, k] for k in range(POINTS_PER_REPLICA))
    k = 0.25 * ((f11 - f12) - (f21 - f22)) ** 2
    if m == 1:
        return w + k  # the four points are i.i.d. uniform: k estimates Var f
    d = 0.5 * (f11 - f11b) ** 2
    return m * w + m / (m - 1) * (m * k - d)
