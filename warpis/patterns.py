"""Primary-sample patterns: where the points u ∈ [0,1)² of one technique in one trial fall.

Each pattern places the ``m`` samples of one technique: ``independent`` (uniform, iid),
``jittered`` (one uniform point in each cell of a rows × cols grid, rows × cols = m, as
square as m allows), ``antithetic`` (pairs u and (1,1) − u) and ``jittered-antithetic``
(jittered points in the first half of the cells, their reflections through the centre
of the square in the mirrored cells).  Points are computed from their index alone, so a
kernel needs no per-trial arrays.
"""

from __future__ import annotations

import math

import warp as wp

from .rng import uniform

INDEPENDENT = wp.constant(0)
JITTERED = wp.constant(1)
ANTITHETIC = wp.constant(2)
JITTERED_ANTITHETIC = wp.constant(3)

# float32 holds every integer up to 2^24 exactly: a jittered cell index beyond it (and a
# cell narrower than the generator's 2^-24 lattice) would no longer be placed exactly.
MAX_CELLS_PER_SIDE = 1 << 24

PATTERNS = {
    "independent": 0,
    "jittered": 1,
    "antithetic": 2,
    "jittered-antithetic": 3,
}


def grid_shape(m: int) -> tuple[int, int]:
    """(rows, cols) with rows × cols = m and rows the largest divisor of m ≤ √m.

    Searches down from ⌊√m⌋ and stops at the first divisor: at most √m steps, i.e.
    46,341 for the largest N the kernels take (limits.MAX_COUNT).
    """
    rows = next(d for d in range(math.isqrt(m), 0, -1) if m % d == 0)
    return rows, m // rows


def pattern_problem(pattern: str, m: int) -> str | None:
    """Why ``pattern`` cannot place ``m`` samples per technique, or None when it can."""
    if m < 1:
        return "needs at least one sample per technique"
    if pattern in ("antithetic", "jittered-antithetic") and m % 2:
        return f"pairs samples, so it needs an even number of samples per technique (got {m})"
    if pattern in ("jittered", "jittered-antithetic") and max(grid_shape(m)) > MAX_CELLS_PER_SIDE:
        rows, cols = grid_shape(m)
        return (f"lays {m} samples per technique on a {rows} × {cols} grid, and float32 cannot place points "
                f"inside more than {MAX_CELLS_PER_SIDE} cells per side")
    return None


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
