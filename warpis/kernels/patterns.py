"""Primary-sample patterns: where the points u ∈ [0,1)² of one technique in one trial fall.

Each pattern places the ``m`` samples of one technique: ``independent`` (uniform, iid),
``jittered`` (one uniform point in each cell of a rows × cols grid, rows × cols = m, as
square as m allows), ``antithetic`` (pairs u and (1,1) − u) and ``jittered-antithetic``
(jittered points in the first half of the cells, their reflections through the centre
of the square in the mirrored cells).  Points are computed from their index alone, so a
kernel needs no per-trial arrays.  What the rest of warpis knows about each pattern (its
constraints on m, its independent blocks for the theory) is its entry in ``PATTERNS``
below: adding a pattern is its entry, its constant and its branch in :func:`pattern_point`.

User patterns (:func:`register_pattern`): a Warp ``point(s, i, m) -> vec2`` function gets
the next free code and the trial kernels are rebuilt with a dispatch that knows it
(:func:`point_dispatch`), as for user techniques.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import warp as wp

from ..errors import WarpisError
from ..vocabulary import (IID_SLOPE, STRATIFIED_SLOPE, Blocks, Pattern, Registry, Slope, UserEntries, UserEntry,
                          grid_shape)
from .rng import stream, uniform


def _whole_square(m: int) -> Blocks:
    return Blocks(1, m, (1, 1), False)


def _pairs_on_square(m: int) -> Blocks:
    return Blocks(1, m // 2, (1, 1), True)


def _cells(m: int) -> Blocks:
    return Blocks(m, 1, grid_shape(m), False)


def _pairs_of_cells(m: int) -> Blocks:
    """Cell i < m/2 and its mirror m−1−i form one block (see patterns.pattern_point)."""
    return Blocks(m // 2, 1, grid_shape(m), True)


PATTERNS: Registry[Pattern] = Registry("pattern", [
    Pattern(name="independent", code=0, description="uniform independent points", blocks=_whole_square,
            slope=IID_SLOPE),
    Pattern(name="jittered", code=1, description="one uniform point per cell of a rows × cols = m grid, as square "
                                                 "as m allows",
            grid=True, blocks=_cells, slope=STRATIFIED_SLOPE),
    Pattern(name="antithetic", code=2, description="pairs u and (1,1) − u", paired=True, blocks=_pairs_on_square,
            slope=IID_SLOPE),
    Pattern(name="jittered-antithetic", code=3, description="jittered points in half the cells, reflected through "
                                                            "the centre into the mirrored cells",
            paired=True, grid=True, blocks=_pairs_of_cells, slope=STRATIFIED_SLOPE),
])


# The kernels' codes, from the registry (PATTERNS above describes each pattern).
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


# --------------------------------------------------------------------------- user patterns


USER_PATTERNS = UserEntries(PATTERNS, "register_pattern")  # functions: (point,)

# The sample counts and seeds at which register_pattern checks that every point lies in [0,1)².
_CHECK_COUNTS = (1, 2, 3, 4, 5, 16, 17, 64, 256)
_CHECK_STREAMS = 64


def register_pattern(name: str, point: Any, *, description: str = "a user-defined pattern", paired: bool = False,
                     blocks: Callable[[int], Blocks] | None = None, slope: Slope | None = None) -> Pattern:
    """Add a pattern written as a Warp function to ``PATTERNS``.

    ``point(s: wp.uint32, i: wp.int32, m: wp.int32) -> wp.vec2`` is sample ``i`` of the
    ``m`` that one technique places in one trial; ``s`` is that technique's random stream
    in that trial (draw from it with :func:`warpis.kernels.rng.uniform` ``(s, index, dim)``).
    Every point must lie in [0,1)²: the function is run at several m and streams when it
    is registered, and a point outside (or not finite) is a WarpisError.

    ``paired=True`` makes m odd an error; ``blocks`` (m → :class:`~warpis.vocabulary.Blocks`)
    states the independent blocks the exact-variance theory needs, and ``slope`` the
    expected convergence; without them the predictions say why they are absent.
    """
    code = USER_PATTERNS.next_code(name, {"point": point})
    _check_points(name, point)
    entry = Pattern(name=name, code=code, description=description, paired=paired, blocks=blocks, slope=slope)
    return USER_PATTERNS.add(entry, (point,))


def unregister_pattern(name: str) -> None:
    """Remove a pattern added by :func:`register_pattern`."""
    USER_PATTERNS.remove(name)


def user_patterns() -> tuple[UserEntry, ...]:
    """The registered user patterns still in the registry, in registration order."""
    return USER_PATTERNS.active()


def _check_points(name: str, point: Any) -> None:
    """A WarpisError naming the first (m, stream, i) whose point is outside [0,1)² or not finite."""

    @wp.kernel(module="unique")
    def points_kernel(m: wp.int32, out: wp.array2d(dtype=wp.vec2)):
        k, i = wp.tid()
        out[k, i] = point(stream(wp.uint32(0), 0, k, 0), i, m)

    for m in _CHECK_COUNTS:
        out = wp.empty((_CHECK_STREAMS, m), dtype=wp.vec2, device="cpu")
        wp.launch(points_kernel, dim=(_CHECK_STREAMS, m), inputs=[m, out], device="cpu")
        u = out.numpy()
        bad = ~(np.isfinite(u) & (u >= 0.0) & (u < 1.0)).all(axis=2)
        if bad.any():
            k, i = np.argwhere(bad)[0]
            raise WarpisError(f"pattern {name!r}: point {i} of m = {m} is {tuple(float(x) for x in u[k, i])}, "
                              f"outside [0,1)²")


def _with_user_point(inner: Any, code: int, user_point: Any) -> Any:
    @wp.func(module="unique")
    def point_dispatch(pattern: wp.int32, s: wp.uint32, i: wp.int32, m: wp.int32, rows: wp.int32,
                       cols: wp.int32) -> wp.vec2:
        if pattern == wp.static(code):
            return user_point(s, i, m)
        return inner(pattern, s, i, m, rows, cols)

    return point_dispatch


@functools.lru_cache(maxsize=None)
def point_dispatch(user: tuple[UserEntry, ...]) -> Any:
    """``pattern_point`` that also knows the user patterns ``user`` (itself when none)."""
    point = pattern_point
    for p in user:
        point = _with_user_point(point, p.code, *p.functions)
    return point
