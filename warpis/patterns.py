"""Primary-sample patterns: where the points u ∈ [0,1)² of one technique in one trial fall.

Each pattern places the ``m`` samples of one technique: ``independent`` (uniform, iid),
``jittered`` (one uniform point in each cell of a rows × cols grid, rows × cols = m, as
square as m allows), ``antithetic`` (pairs u and (1,1) − u) and ``jittered-antithetic``
(jittered points in the first half of the cells, their reflections through the centre
of the square in the mirrored cells).  Points are computed from their index alone, so a
kernel needs no per-trial arrays.  What the rest of warpis knows about each pattern (its
constraints on m, its independent blocks for the theory) is its entry in
``vocabulary.PATTERNS``.
"""

from __future__ import annotations

import warp as wp

from .rng import uniform
from .vocabulary import PATTERNS

# The kernels' codes, from the registry (vocabulary.PATTERNS describes each pattern).
INDEPENDENT = wp.constant(PATTERNS["independent"].code)
JITTERED = wp.constant(PATTERNS["jittered"].code)
ANTITHETIC = wp.constant(PATTERNS["antithetic"].code)
JITTERED_ANTITHETIC = wp.constant(PATTERNS["jittered-antithetic"].code)


@wp.func
def jittered_point(s: wp.uint32, cell: wp.int32, rows: wp.int32, cols: wp.int32) -> wp.vec2:
    """A uniform point in cell ``cell`` (row-major) of a rows × cols grid on [0,1)²."""
    r = cell / cols
    c = cell - r * cols
    x = (float(c) + uniform(s, cell, 0)) / float(cols)
    y = (float(r) + uniform(s, cell, 1)) / float(rows)
    # Rounding can land exactly on the cell's far edge; keep u inside [0,1).
    return wp.vec2(wp.min(x, 0.99999994), wp.min(y, 0.99999994))


@wp.func
def reflect(u: wp.vec2) -> wp.vec2:
    """The point reflection through the centre of the unit square, kept inside [0,1)²."""
    return wp.vec2(wp.min(1.0 - u[0], 0.99999994), wp.min(1.0 - u[1], 0.99999994))


@wp.func
def pattern_point(pattern: wp.int32, s: wp.uint32, i: wp.int32, m: wp.int32, rows: wp.int32, cols: wp.int32) -> wp.vec2:
    """Sample ``i`` of ``m`` of one technique's stream ``s`` under ``pattern``."""
    if pattern == JITTERED:
        return jittered_point(s, i, rows, cols)
    if pattern == ANTITHETIC:
        j = i / 2
        u = wp.vec2(uniform(s, j, 0), uniform(s, j, 1))
        if i - 2 * j == 1:
            return reflect(u)
        return u
    if pattern == JITTERED_ANTITHETIC:
        half = m / 2
        if i < half:
            return jittered_point(s, i, rows, cols)
        # Reflecting cell (r, c) through the centre gives cell (rows-1-r, cols-1-c),
        # whose row-major index is m-1-(r*cols+c): the point of cell m-1-i lands in i.
        return reflect(jittered_point(s, m - 1 - i, rows, cols))
    return wp.vec2(uniform(s, i, 0), uniform(s, i, 1))
