"""Primary-sample patterns: where the points u ∈ [0,1)² of one technique in one trial fall.

Each pattern places the ``m`` samples of one technique: ``independent`` (uniform, iid),
``jittered`` (one uniform point in each cell of a rows × cols grid, rows × cols = m, as
square as m allows), ``antithetic`` (pairs u and (1,1) − u), ``jittered-antithetic``
(jittered points in the first half of the cells, their reflections through the centre
of the square in the mirrored cells), and the point sets renderers use today: ``lhs``
(Latin hypercube), ``cmj`` (Kensler's correlated multi-jitter), ``sobol`` and ``halton``
(Owen-scrambled), ``lattice`` (a rank-1 lattice with a random shift), whose exact
variances are pair forms (``sum_variance``, point_sets) where they have one.
Every pattern is randomised per technique and trial, so trials stay independent and each point is
uniform on [0,1)² (every estimator stays unbiased).  Points are computed from their index
alone, so a kernel needs no per-trial arrays.  What the rest of warpis knows about each pattern (its
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

from ..point_sets.lattice import lattice_sum_variance
from ..point_sets.lhs import lhs_sum_variance
from ..point_sets.nets import halton_sum_variance, sobol_sum_variance
from ..errors import WarpisError
from ..vocabulary import (IID_SLOPE, SCRAMBLED_NET_SLOPE, STRATIFIED_SLOPE, Blocks, Pattern, Registry, Slope,
                          UserEntries, UserEntry, every_sample, grid_shape, grid_side)
from .rng import chain, mix32, stream, uniform


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
            strata=grid_side, blocks=_cells, slope=STRATIFIED_SLOPE),
    Pattern(name="antithetic", code=2, description="pairs u and (1,1) − u", paired=True, blocks=_pairs_on_square,
            slope=IID_SLOPE),
    Pattern(name="jittered-antithetic", code=3, description="jittered points in half the cells, reflected through "
                                                            "the centre into the mirrored cells",
            paired=True, strata=grid_side, blocks=_pairs_of_cells, slope=STRATIFIED_SLOPE),
    # The point sets below are not independent blocks: their exact variances are pair
    # forms (point_sets), except cmj's, whose correlated permutations have no
    # simple pair law (its predictions say "no exact form").  LHS keeps the rate of
    # independent points (it removes the additive part of the variance, not its order).
    Pattern(name="lhs", code=4, description="Latin hypercube: one point in each of m columns and m rows, "
                                            "randomly paired", strata=every_sample, slope=IID_SLOPE,
            sum_variance=lhs_sum_variance),
    Pattern(name="cmj", code=5, description="correlated multi-jittered (Kensler 2013): jittered on the rows × cols "
                                            "grid and a Latin hypercube at once",
            strata=every_sample, slope=STRATIFIED_SLOPE),
    Pattern(name="sobol", code=6, description="Sobol' (0,2)-sequence, Owen-scrambled by hashing; a (0,m,2)-net "
                                              "when m is a power of two",
            strata=every_sample, slope=SCRAMBLED_NET_SLOPE, sum_variance=sobol_sum_variance),
    Pattern(name="halton", code=7, description="Halton (bases 2 and 3), Owen-scrambled digit by digit",
            strata=every_sample, slope=STRATIFIED_SLOPE, sum_variance=halton_sum_variance),
    Pattern(name="lattice", code=8, description="rank-1 lattice (i/m, i·g/m), g the integer nearest m/φ coprime "
                                                "with m (Fibonacci), with a random Cranley–Patterson shift",
            strata=every_sample, slope=STRATIFIED_SLOPE, sum_variance=lattice_sum_variance),
])


# The kernels' codes, from the registry (PATTERNS above describes each pattern).
INDEPENDENT = wp.constant(PATTERNS["independent"].code)
JITTERED = wp.constant(PATTERNS["jittered"].code)
ANTITHETIC = wp.constant(PATTERNS["antithetic"].code)
JITTERED_ANTITHETIC = wp.constant(PATTERNS["jittered-antithetic"].code)
LHS = wp.constant(PATTERNS["lhs"].code)
CMJ = wp.constant(PATTERNS["cmj"].code)
SOBOL = wp.constant(PATTERNS["sobol"].code)
HALTON = wp.constant(PATTERNS["halton"].code)
LATTICE = wp.constant(PATTERNS["lattice"].code)

_BELOW_ONE = wp.constant(0.99999994)  # the largest float32 below 1
SHUFFLE_ROUNDS = wp.constant(24)  # rounds of shuffle_index
_TO_UNIT = wp.constant(1.0 / 16777216.0)
_TOP_BIT = wp.constant(wp.uint32(0x80000000))
_INV_GOLDEN = wp.constant(0.6180339887498949)  # 1/φ
# The multipliers of Kensler's permutation hash.
_K1 = wp.constant(wp.uint32(0xE170893D))
_K2 = wp.constant(wp.uint32(0x0929EB3F))
_K3 = wp.constant(wp.uint32(0x6935FA69))
_K4 = wp.constant(wp.uint32(0x74DCB303))
_K5 = wp.constant(wp.uint32(0x9E501CC3))
_K6 = wp.constant(wp.uint32(0xC860A3DF))


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
def pattern_hash(s: wp.uint32, purpose: wp.int32) -> wp.uint32:
    """A random 32-bit word per technique and trial, one per ``purpose`` (≥ 1); sample
    indices are ≥ 0, so ``chain(s, -purpose)`` never repeats ``uniform``'s words."""
    return chain(s, -purpose)


@wp.func
def unit_float(x: wp.uint32) -> float:
    """The top 24 bits of x as a float in [0, 1) (exact in float32)."""
    return float(x >> wp.uint32(8)) * _TO_UNIT


@wp.func
def permute(i: wp.uint32, count: wp.uint32, p: wp.uint32) -> wp.uint32:
    """Element i of a pseudo-random permutation of 0..count−1 keyed by p (Kensler 2013,
    "Correlated Multi-Jittered Sampling": a hash bijective on the next power of two,
    cycle-walked back into range)."""
    w = count - wp.uint32(1)
    w = w | (w >> wp.uint32(1))
    w = w | (w >> wp.uint32(2))
    w = w | (w >> wp.uint32(4))
    w = w | (w >> wp.uint32(8))
    w = w | (w >> wp.uint32(16))
    x = i
    first = bool(True)
    while first or x >= count:
        first = False
        x = x ^ p
        x = x * _K1
        x = x ^ (p >> wp.uint32(16))
        x = x ^ ((x & w) >> wp.uint32(4))
        x = x ^ (p >> wp.uint32(8))
        x = x * _K2
        x = x ^ (p >> wp.uint32(23))
        x = x ^ ((x & w) >> wp.uint32(1))
        x = x * (wp.uint32(1) | (p >> wp.uint32(27)))
        x = x * _K3
        x = x ^ ((x & w) >> wp.uint32(11))
        x = x * _K4
        x = x ^ ((x & w) >> wp.uint32(2))
        x = x * _K5
        x = x ^ ((x & w) >> wp.uint32(2))
        x = x * _K6
        x = x & w
        x = x ^ (x >> wp.uint32(5))
    return (x + p) % count


@wp.func
def shuffle_index(i: wp.uint32, count: wp.uint32, key: wp.uint32) -> wp.uint32:
    """Element i of a pseudo-random permutation of 0..count−1 keyed by ``key``: the
    swap-or-not shuffle (Hoang, Morris, Rogaway 2012).  Each round draws K and pairs x
    with K − x (mod count); a hash of the round and the pair's larger member decides
    whether the pair swaps, so every round is a permutation of any domain size, with no
    cycle walking.  With ideal hashes the law of the images of two distinct points is
    uniform over distinct pairs to 1.3e-5 relative after ``SHUFFLE_ROUNDS`` = 24 rounds
    for every count up to 32 (docs/theory.md, "Exact variance of the point sets"), which
    is the law the Latin hypercube's exact variance needs; Kensler's hash (``permute``)
    is far from it (at count = 4 it deals 8 of the 24 permutations).  K is the round's
    hash scaled to [0, count) by a multiply (no division), and K − x wraps by one add."""
    x = i
    for r in range(SHUFFLE_ROUNDS):
        h = chain(key, r)
        k = wp.uint32((wp.uint64(h) * wp.uint64(count)) >> wp.uint64(32))
        partner = k - x
        if k < x:
            partner = k + (count - x)
        if chain(h, wp.int32(wp.max(x, partner))) & wp.uint32(1) != wp.uint32(0):
            x = partner
    return x


@wp.func
def owen_scramble_base2(x: wp.uint32, seed: wp.uint32) -> wp.uint32:
    """Owen's nested uniform scramble of the 24 leading bits of x (a binary fraction):
    bit k is flipped by a hash of the seed and the k bits above it, so every point of a
    scrambled set is uniform and a (0,m,2)-net stays one."""
    out = wp.uint32(0)
    prefix = wp.uint32(1)  # a leading 1 marks the prefix length
    for k in range(24):
        bit = (x >> wp.uint32(31 - k)) & wp.uint32(1)
        flip = mix32(seed ^ mix32(prefix)) & wp.uint32(1)
        out = out | ((bit ^ flip) << wp.uint32(31 - k))
        prefix = (prefix << wp.uint32(1)) | bit
    return out


@wp.func
def sobol_2d(i: wp.uint32) -> wp.vec2ui:
    """The first two Sobol' coordinates of point i as 32-bit binary fractions: the van der
    Corput sequence and the x + 1 (Pascal) direction numbers."""
    x = wp.uint32(0)
    y = wp.uint32(0)
    v = _TOP_BIT
    for bit in range(32):
        if (i >> wp.uint32(bit)) & wp.uint32(1) != wp.uint32(0):
            x = x ^ (_TOP_BIT >> wp.uint32(bit))
            y = y ^ v
        v = v ^ (v >> wp.uint32(1))
    return wp.vec2ui(x, y)


@wp.func
def owen_radical_inverse_base3(i: wp.uint32, seed: wp.uint32) -> float:
    """The base-3 radical inverse of i with Owen's nested scramble of its first 20 digits
    (3^-20 < 2^-31: the rest is below float32's resolution): digit k is permuted by one of
    the six permutations of {0, 1, 2}, chosen by a hash of the seed and the k digits above."""
    value = float(0.0)
    scale = float(1.0 / 3.0)
    prefix = wp.uint32(1)
    n = i
    for k in range(20):
        d = n % wp.uint32(3)
        n = n / wp.uint32(3)
        h = mix32(seed ^ mix32(prefix)) % wp.uint32(6)
        # the six permutations of {0,1,2}: a rotation by h % 3, mirrored when h ≥ 3
        e = (d + h) % wp.uint32(3)
        if h >= wp.uint32(3):
            e = (wp.uint32(2) * (h % wp.uint32(3)) + wp.uint32(3) - d) % wp.uint32(3)
        value = value + float(e) * scale
        scale = scale / 3.0
        prefix = prefix * wp.uint32(3) + d
    return wp.min(value, _BELOW_ONE)


@wp.func
def gcd(a: wp.int32, b: wp.int32) -> wp.int32:
    while b != 0:
        t = a % b
        a = b
        b = t
    return a


@wp.func
def lattice_generator(m: wp.int32) -> wp.int32:
    """g of the rank-1 lattice {(i/m, i·g/m)}: the integer nearest m/φ that is coprime with
    m (m/φ rounded is the Fibonacci lattice's generator when m is a Fibonacci number)."""
    g0 = wp.int32(wp.floor(float(m) * _INV_GOLDEN + 0.5))
    for d in range(m + 1):
        if g0 + d <= m and gcd(g0 + d, m) == 1:
            return g0 + d
        if g0 - d >= 1 and gcd(g0 - d, m) == 1:
            return g0 - d
    return 1


@wp.func
def lhs_point(s: wp.uint32, i: wp.int32, m: wp.int32) -> wp.vec2:
    """Point i of a Latin hypercube: column and row from two independent random
    permutations of 0..m−1.  The cells the points occupy depend on the pairing of columns
    with rows, whose law is that of the row permutation alone: it is the swap-or-not
    shuffle, whose pair law is uniform (what the exact variance needs); the column
    permutation only relabels points."""
    cx = permute(wp.uint32(i), wp.uint32(m), pattern_hash(s, 1))
    cy = shuffle_index(wp.uint32(i), wp.uint32(m), pattern_hash(s, 2))
    x = (float(cx) + uniform(s, i, 0)) / float(m)
    y = (float(cy) + uniform(s, i, 1)) / float(m)
    return wp.vec2(wp.min(x, _BELOW_ONE), wp.min(y, _BELOW_ONE))


@wp.func
def cmj_point(s: wp.uint32, i: wp.int32, m: wp.int32, rows: wp.int32, cols: wp.int32) -> wp.vec2:
    """Point i of a correlated multi-jittered set on the rows × cols grid (Kensler 2013):
    sample j (a random permutation of i) in coarse cell (j mod cols, j div cols); its fine
    column within the cell is a permutation of its coarse row, its fine row a permutation
    of its coarse column, so each of the m fine columns and rows holds one point."""
    j = permute(wp.uint32(i), wp.uint32(m), pattern_hash(s, 1))
    cx = j % wp.uint32(cols)
    cy = j / wp.uint32(cols)
    sx = permute(cx, wp.uint32(cols), pattern_hash(s, 2))
    sy = permute(cy, wp.uint32(rows), pattern_hash(s, 3))
    x = (float(cx) + (float(sy) + uniform(s, i, 0)) / float(rows)) / float(cols)
    y = (float(cy) + (float(sx) + uniform(s, i, 1)) / float(cols)) / float(rows)
    return wp.vec2(wp.min(x, _BELOW_ONE), wp.min(y, _BELOW_ONE))


@wp.func
def lattice_point(s: wp.uint32, i: wp.int32, m: wp.int32) -> wp.vec2:
    """Point i of the rank-1 lattice (i/m, i·g/m) shifted by one uniform vector per trial, mod 1."""
    g = lattice_generator(m)
    x = float(i) / float(m) + unit_float(pattern_hash(s, 1))
    y = float((wp.int64(i) * wp.int64(g)) % wp.int64(m)) / float(m) + unit_float(pattern_hash(s, 2))
    return wp.vec2(wp.min(x - wp.floor(x), _BELOW_ONE), wp.min(y - wp.floor(y), _BELOW_ONE))


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
    if pattern == LHS:
        return lhs_point(s, i, m)
    if pattern == CMJ:
        return cmj_point(s, i, m, rows, cols)
    if pattern == SOBOL:
        bits = sobol_2d(wp.uint32(i))
        return wp.vec2(unit_float(owen_scramble_base2(bits[0], pattern_hash(s, 1))),
                       unit_float(owen_scramble_base2(bits[1], pattern_hash(s, 2))))
    if pattern == HALTON:
        return wp.vec2(unit_float(owen_scramble_base2(sobol_2d(wp.uint32(i))[0], pattern_hash(s, 1))),
                       owen_radical_inverse_base3(wp.uint32(i), pattern_hash(s, 2)))
    if pattern == LATTICE:
        return lattice_point(s, i, m)
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

    @wp.kernel(module="unique", enable_backward=False)
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


# --------------------------------------------------------------------------- points on the host


@functools.lru_cache(maxsize=None)
def _points_kernel(point: Any) -> Any:
    @wp.kernel(module="unique", enable_backward=False)
    def points_kernel(pattern: wp.int32, seed: wp.uint32, m: wp.int32, rows: wp.int32, cols: wp.int32,
                      out: wp.array2d(dtype=wp.vec2)):
        trial, i = wp.tid()
        out[trial, i] = point(pattern, stream(seed, 0, trial, 0), i, m, rows, cols)

    return points_kernel


def pattern_points(pattern: str, m: int, trials: int, seed: int = 0) -> np.ndarray:
    """The m points ``pattern`` places for technique 0 at receiver 0 in trials
    0..trials−1, exactly as the trial kernel places them: a (trials, m, 2) float32 array
    (for figures and for tests of the point sets)."""
    from .. import limits

    entry = PATTERNS.lookup(pattern)
    m, trials = limits.count(m, "m"), limits.count(trials, "trials")
    problem = entry.problem(m)
    if problem:
        raise WarpisError(f"pattern {pattern!r} {problem}")
    rows, cols = grid_shape(m)
    limits.memory(trials * m * 8, "points")
    out = wp.empty((trials, m), dtype=wp.vec2, device="cpu")
    wp.launch(_points_kernel(point_dispatch(user_patterns())), dim=(trials, m), device="cpu",
              inputs=[entry.code, wp.uint32(limits.seed(seed)), m, rows, cols, out])
    return out.numpy()
