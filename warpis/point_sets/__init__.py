"""Exact variances of point sets that are not independent blocks.

``jittered`` and its kin split a technique's m samples into independent blocks
(``Pattern.blocks``); the point sets renderers use today do not: every pair of points of a
Latin hypercube, a scrambled net or a shifted lattice is dependent.  Their exact variance
is a sum over pairs of points, grouped into classes whose joint law the randomisation
fixes:

* ``lhs`` — a Latin hypercube: two distinct points never share a row or a column stratum;
* ``lattice`` — a rank-1 lattice with a uniform Cranley–Patterson shift: the variance over
  the shift of the sum at the m points;
* ``nets`` — Owen-scrambled digital sequences (``sobol``, ``halton``): the law of a pair
  depends only on how many leading digits its coordinates share (Owen 1997), so the
  variance is a sum of gain coefficients, counted from the unscrambled points, times
  variance components at each level of elementary boxes.

Each form is a :data:`SumVarianceForm`, the ``sum_variance`` of its entry in
``kernels.patterns.PATTERNS``: given the weighted values ψ of one technique stream at
any points it asks for (``quadrature.py`` supplies them from the Warp integrand), it returns
Var(Σ_{i<m} ψ(u_i)) at every receiver with a standard error.  docs/theory.md derives each.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..stats import SampleMoments

# (P, 2) points in [0,1)² → (E[ψ|u], E[ψ²|u]), each (R, P), at the R receivers being
# predicted.  For a stream of one technique the second is the first squared; for the
# mixture (a technique picked at random per sample) they are the means over techniques.
Values = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

# Most points a form passes to ``values`` in one call (quadrature.py sizes its receiver
# chunks by it).
MAX_POINTS_PER_CALL = 1 << 16


@dataclass(frozen=True)
class SumVariance:
    """Var(Σ_{i<m} ψ(u_i)) of one technique stream at each receiver."""

    value: np.ndarray  # (R,)
    stderr: np.ndarray  # (R,) standard error of ``value``
    points: int  # dense points evaluated per receiver


def add_draws(moments: SampleMoments | None, draws: np.ndarray) -> SampleMoments:
    """Running moments per receiver of i.i.d. draws (R, n) added chunk by chunk: the
    engine's SampleMoments and its pairwise merge, so a small spread around a large mean
    keeps its digits."""
    part = SampleMoments.of(draws)
    return part if moments is None else moments.merge(part)


def mean_variance(moments: SampleMoments) -> np.ndarray:
    """The squared standard error of the mean of the draws, per receiver."""
    return moments.m2 / (moments.count - 1) / moments.count


# (values, m, points, rng) → SumVariance: ``points`` is the budget of dense points per
# receiver (a form may use fewer, or more where it needs a minimum); ``rng`` draws them,
# so the same rng state gives the same points for every receiver.
SumVarianceForm = Callable[[Values, int, int, np.random.Generator], SumVariance]
