"""A 4-wide BVH over a scene's triangles and its ray queries, written in Warp.

Warp's own ``wp.mesh_query_ray`` walks a binary BVH one box pair at a time; on the CPU a
4-wide tree whose nodes keep their children's boxes axis by axis (structure of arrays)
tests four boxes per node and four triangles per leaf at once, and halves the depth.
``closest_hit`` returns what ``wp.mesh_query_ray`` returns for the integrand's purpose
(the face hit first and the sign of its facing), ``any_hit`` what
``wp.mesh_query_ray_anyhit`` returns (a shadow ray); both fall back to Warp's query where
their fixed stack would overflow, so no ray is ever dropped.  Every device uses the tree:
rays that leave or reach a surface ignore hits on that surface's own plane (``Planes``),
which only a leaf test of warpis's own can do.

Layout (one :class:`WideBvh` per scene upload):

* ``bounds``: 6 ``vec4`` per node, the lower x, upper x, lower y, upper y, lower z and
  upper z bounds of its four children.  A ray picks near and far planes once from the
  signs of its direction: ``bounds[6·node + 2·axis + s]`` is the near plane for s = 1 if
  the direction is negative along ``axis`` (else 0), the far plane at the other index.
  Empty child slots have lower = +inf, upper = −inf, which every ray misses.
* ``children``: one ``vec4i`` per node; a child ≥ 0 is a node, < 0 is leaf −(child + 1).
  The root is node 0.
* ``corners``: 9 ``vec4`` per leaf: coordinate c (0..2) of vertex v (0..2) of its four
  triangles at ``corners[9·leaf + 3·v + c]``; ``faces``: one ``vec4i`` per leaf, the
  triangles' indices in the mesh, −1 for an empty slot.

The triangle test is Woop, Benthin and Wald's watertight test (JCGT 2013), as in Warp's
query: edge functions in float32, recomputed in float64 (where products of float32
values are exact) for a triangle where one is 0, so two triangles sharing an edge see
exactly opposite values on it and no ray slips between them.  The tree is built on the
host with a binned surface-area heuristic (:func:`build_wide_bvh`), level by level in
numpy, then collapsed from binary to 4-wide, and kept on disk by content
(:func:`cached_wide_bvh`); :mod:`warpis.kernels.device` uploads it once per scene
content.  Derivations and measurements: docs/theory.md, "Ray queries".
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from .. import files

__all__ = ["LEAF_SIZE", "PLANE_TOL", "SELF_HIT", "RayHit", "WideBvh", "WideBvhArrays", "any_hit", "any_hit_between", "build_wide_bvh",
           "cache_dir", "cached_wide_bvh", "closest_hit", "closest_hit_from", "coplanar", "magnitude", "upload_wide_bvh", "vec64"]

LEAF_SIZE = 4  # triangles per leaf, tested together
WIDTH = 4  # children per node
SAH_BINS = 16
# A node test costs about one leaf test (both are a few vec4 operations): the surface-area
# heuristic keeps a group of ≤ LEAF_SIZE triangles as a leaf unless splitting it saves more.
TRAVERSAL_COST = 1.0
LEAF_COST = 1.5
STACK_SIZE = wp.constant(64)
# How far float32 rounding can move a triangle's plane, relative to the magnitude of its
# corners' coordinates: 2^-16 is 128 ulps, far above the rounding of the watertight
# test.  The self-hit slabs of device.py are this factor × local magnitudes.
SELF_HIT = wp.constant(2.0**-16)
# A triangle is in the plane of a ray's end point when that point is within this height
# of its plane, relative to the same magnitudes: 16 ulps.  Rounding puts a point that
# lies on the triangle within 2 ulps of its float32 plane, and Warp's watertight test
# reports no hit from 1 ulp above it (measured on triangles of size 1 to 1e6), so the
# ignored planes are the point's own, and a parallel surface 16 ulps away is not one.
PLANE_TOL = wp.constant(2.0**-19)
# Two unit normals are parallel when |n·m| is at least this: float32 rounding of a
# triangle's corners tilts its normal by ~1e-7; a bend of 0.1° is not parallel.
PARALLEL = wp.constant(1.0 - 1.0e-6)
INFINITY = wp.constant(float("inf"))
NO_NODE = wp.constant(-2147483647)  # an empty stack: no node or leaf has this code
OVERFLOW = wp.constant(-2)  # a query's answer when its stack would overflow
NodeStack = wp.types.vector(length=64, dtype=wp.int32)
DistanceStack = wp.types.vector(length=64, dtype=wp.float32)
# pbrt's robust slab test: widen each box's far distance by 2γ₃ so that rounding never
# culls a box the ray touches (Ize 2013).
FAR_WIDEN = wp.constant(1.0 + 2.0 * 3.0 * 2.0**-24 / (1.0 - 3.0 * 2.0**-24))


@wp.struct
class WideBvh:
    bounds: wp.array(dtype=wp.vec4)  # 6 per node (see the module docstring)
    children: wp.array(dtype=wp.vec4i)  # 1 per node
    corners: wp.array(dtype=wp.vec4)  # 9 per leaf
    faces: wp.array(dtype=wp.vec4i)  # 1 per leaf
    enabled: wp.int32  # 0: the kernels use wp.mesh_query_ray (a tree uploaded empty, for tests)


@wp.struct
class RayHit:
    face: wp.int32  # −1: no hit
    t: wp.float32
    sign: wp.float32  # Warp's convention: the watertight test's determinant; ≤ 0 is a back face
    slot: wp.int32  # within a leaf test: the leaf slot of the hit, −1 if the leaf found none


# --------------------------------------------------------------------------- query


@wp.struct
class Ray:
    """A ray's constants for the box and triangle tests, computed once per query."""

    o: wp.vec3
    inv: wp.vec3  # 1/d, a zero component made tiny (as Warp's query does): no 0 × inf NaN
    o_inv: wp.vec3  # o / d: a box plane's distance is plane × inv − o_inv, one FMA
    near_x: wp.int32  # bounds row of each axis's near plane (2·axis + 1 for d < 0), far = the other
    near_y: wp.int32
    near_z: wp.int32
    kx: wp.int32  # the watertight test's axes: kz the dominant axis of d (Woop et al. 2013)
    ky: wp.int32
    kz: wp.int32
    sx: float  # its shear constants
    sy: float
    sz: float


@wp.struct
class Planes:
    """The surfaces a ray leaves and reaches (``on`` = 1): the point ``a`` with its surface
    normal ``na`` (the receiver), ``b`` with ``nb`` (the emitter point).  A hit on a
    triangle of either plane is rounding, never a real crossing (a ray that starts on a
    plane meets it nowhere else), and is ignored; so no slab as tall as the rounding of a
    huge own triangle is needed.  Apart from :class:`Ray`, which every node test reads:
    only a hit reads these."""

    a: wp.vec3
    na: wp.vec3
    b: wp.vec3
    nb: wp.vec3
    on: wp.int32


@wp.func
def _nonzero(x: float) -> float:
    return wp.where(x == 0.0, 1.0e-20, x)


@wp.func
def make_ray(o: wp.vec3, d: wp.vec3) -> Ray:
    r = Ray()
    r.o = o
    r.inv = wp.vec3(1.0 / _nonzero(d[0]), 1.0 / _nonzero(d[1]), 1.0 / _nonzero(d[2]))
    r.o_inv = wp.cw_mul(o, r.inv)
    r.near_x = wp.where(r.inv[0] < 0.0, 1, 0)
    r.near_y = wp.where(r.inv[1] < 0.0, 3, 2)
    r.near_z = wp.where(r.inv[2] < 0.0, 5, 4)
    kz = wp.int32(0)
    if wp.abs(d[1]) > wp.abs(d[kz]):
        kz = 1
    if wp.abs(d[2]) > wp.abs(d[kz]):
        kz = 2
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    if d[kz] < 0.0:  # keep the winding, so the sign of the determinant tells the facing
        swap = kx
        kx = ky
        ky = swap
    r.kx = kx
    r.ky = ky
    r.kz = kz
    r.sx = d[kx] / d[kz]
    r.sy = d[ky] / d[kz]
    r.sz = 1.0 / d[kz]
    return r


@wp.func
def _smax(a: float, b: float) -> float:
    # wp.max is fmaxf (NaN-aware), which LLVM keeps scalar and slow; a compare and select
    # is cheaper, and no operand here is NaN.
    return wp.where(a > b, a, b)


@wp.func
def _smin(a: float, b: float) -> float:
    return wp.where(a < b, a, b)


@wp.func
def _entries(bvh: WideBvh, node: wp.int32, r: Ray, t_max: float) -> wp.vec4:
    """Where the ray enters each of the node's four child boxes, +inf where it misses one
    or enters it beyond t_max (Williams' slab test, the far distance widened by 2γ₃)."""
    base = node * 6
    lx = bvh.bounds[base + r.near_x]
    ly = bvh.bounds[base + r.near_y]
    lz = bvh.bounds[base + r.near_z]
    hx = bvh.bounds[base + 1 - r.near_x]
    hy = bvh.bounds[base + 5 - r.near_y]
    hz = bvh.bounds[base + 9 - r.near_z]
    out = wp.vec4()
    for i in range(4):
        t_near = _smax(_smax(lx[i] * r.inv[0] - r.o_inv[0], ly[i] * r.inv[1] - r.o_inv[1]),
                       _smax(lz[i] * r.inv[2] - r.o_inv[2], 0.0))
        t_far = _smin(_smin(hx[i] * r.inv[0] - r.o_inv[0], hy[i] * r.inv[1] - r.o_inv[1]),
                      _smin(hz[i] * r.inv[2] - r.o_inv[2], t_max))
        out[i] = wp.where(t_near <= t_far * FAR_WIDEN, t_near, INFINITY)
    return out


@wp.func
def _sheared(bvh: WideBvh, leaf: wp.int32, r: Ray):
    """The leaf's four triangles in the ray's sheared frame (Woop et al., section 3):
    x and y of each corner (the ray runs along +z from the origin) and z before scaling."""
    base = leaf * 9
    ox = wp.vec4(r.o[r.kx])
    oy = wp.vec4(r.o[r.ky])
    oz = wp.vec4(r.o[r.kz])
    a_z = bvh.corners[base + r.kz] - oz
    b_z = bvh.corners[base + 3 + r.kz] - oz
    c_z = bvh.corners[base + 6 + r.kz] - oz
    ax = bvh.corners[base + r.kx] - ox - r.sx * a_z
    ay = bvh.corners[base + r.ky] - oy - r.sy * a_z
    bx = bvh.corners[base + 3 + r.kx] - ox - r.sx * b_z
    by = bvh.corners[base + 3 + r.ky] - oy - r.sy * b_z
    cx = bvh.corners[base + 6 + r.kx] - ox - r.sx * c_z
    cy = bvh.corners[base + 6 + r.ky] - oy - r.sy * c_z
    return ax, ay, a_z, bx, by, b_z, cx, cy, c_z


@wp.func
def _edge64(ax: float, ay: float, bx: float, by: float) -> float:
    """ax·by − ay·bx with one rounding (a product of float32s is exact in float64)."""
    return float(wp.float64(ax) * wp.float64(by) - wp.float64(ay) * wp.float64(bx))


@wp.func
def _edges(ax: wp.vec4, ay: wp.vec4, bx: wp.vec4, by: wp.vec4, cx: wp.vec4, cy: wp.vec4, i: wp.int32) -> wp.vec3:
    """The edge functions (U, V, W) of triangle i: in float32, as Warp's own test, and
    again in float64 where one is 0 (the ray through an edge or a vertex, where float32
    rounding could let it slip between the two triangles that share it)."""
    u = cx[i] * by[i] - cy[i] * bx[i]
    v = ax[i] * cy[i] - ay[i] * cx[i]
    w = bx[i] * ay[i] - by[i] * ax[i]
    if u == 0.0 or v == 0.0 or w == 0.0:
        u = _edge64(cx[i], cy[i], bx[i], by[i])
        v = _edge64(ax[i], ay[i], cx[i], cy[i])
        w = _edge64(bx[i], by[i], ax[i], ay[i])
    return wp.vec3(u, v, w)


@wp.func
def magnitude(v: wp.vec3) -> float:
    """The largest coordinate magnitude |v|∞: what float32 rounding of v scales with."""
    return wp.max(wp.max(wp.abs(v[0]), wp.abs(v[1])), wp.abs(v[2]))


@wp.func
def vec64(v: wp.vec3) -> wp.vec3d:
    """v in float64 (exactly)."""
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def coplanar(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3, q: wp.vec3, m: wp.vec3) -> bool:
    """Whether the triangle (p0, p1, p2) lies in the plane through ``q`` with unit normal
    ``m``, to within float32's rounding: its normal parallel to m (``PARALLEL``) and
    |n̂·(q − p0)| ≤ PLANE_TOL × the largest coordinate magnitude of the corners and of q
    (in float64, where the differences of float32 values are exact)."""
    a = vec64(p0)
    n = wp.cross(vec64(p1) - a, vec64(p2) - a)
    nn = wp.dot(n, n)
    along = wp.dot(n, vec64(m))
    if along * along < wp.float64(PARALLEL * PARALLEL) * nn:
        return False
    h = wp.dot(n, vec64(q) - a)
    mag = wp.max(wp.max(magnitude(p0), magnitude(p1)), wp.max(magnitude(p2), magnitude(q)))
    tol = wp.float64(mag) * wp.float64(PLANE_TOL)
    return h * h <= tol * tol * nn


@wp.func
def _ignored(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3, planes: Planes) -> bool:
    """Whether a hit on the triangle is one the ray ignores (see :class:`Planes`)."""
    if planes.on == 0:
        return False
    return coplanar(p0, p1, p2, planes.a, planes.na) or coplanar(p0, p1, p2, planes.b, planes.nb)


@wp.func
def _leaf_ignores(bvh: WideBvh, leaf: wp.int32, i: wp.int32, planes: Planes) -> bool:
    """_ignored for triangle ``i`` of a leaf."""
    base = leaf * 9
    p0 = wp.vec3(bvh.corners[base][i], bvh.corners[base + 1][i], bvh.corners[base + 2][i])
    p1 = wp.vec3(bvh.corners[base + 3][i], bvh.corners[base + 4][i], bvh.corners[base + 5][i])
    p2 = wp.vec3(bvh.corners[base + 6][i], bvh.corners[base + 7][i], bvh.corners[base + 8][i])
    return _ignored(p0, p1, p2, planes)


@wp.func
def _face_ignored(mesh: wp.uint64, face: wp.int32, planes: Planes) -> bool:
    """_ignored for a mesh face (a hit of Warp's own query): its corners from the mesh."""
    if planes.on == 0:
        return False
    return _ignored(wp.mesh_eval_position(mesh, face, 1.0, 0.0), wp.mesh_eval_position(mesh, face, 0.0, 1.0),
                    wp.mesh_eval_position(mesh, face, 0.0, 0.0), planes)


@wp.func
def _leaf_hit(bvh: WideBvh, leaf: wp.int32, r: Ray, best: RayHit, skip: wp.int32) -> RayHit:
    """``best``, replaced by the nearest of the leaf's triangles the ray hits before it
    (its ``slot`` set, −1 if none), leaving out the slots of the bit mask ``skip``."""
    ax, ay, az, bx, by, bz, cx, cy, cz = _sheared(bvh, leaf, r)
    faces = bvh.faces[leaf]
    out = best
    out.slot = -1
    for i in range(4):
        e = _edges(ax, ay, bx, by, cx, cy, i)
        inside = (e[0] >= 0.0 and e[1] >= 0.0 and e[2] >= 0.0) or (e[0] <= 0.0 and e[1] <= 0.0 and e[2] <= 0.0)
        det = e[0] + e[1] + e[2]
        if inside and det != 0.0 and faces[i] >= 0:
            t = r.sz * (e[0] * az[i] + e[1] * bz[i] + e[2] * cz[i]) / det
            if t >= 0.0 and t < out.t and (skip & (1 << i)) == 0:
                out.face = faces[i]
                out.t = t
                out.sign = det
                out.slot = i
    return out


@wp.func
def _leaf_blocks(bvh: WideBvh, leaf: wp.int32, r: Ray, t_max: float, skip: wp.int32) -> wp.int32:
    """The first slot of the leaf whose triangle the ray meets at 0 ≤ t < t_max (no
    division), leaving out the slots of the bit mask ``skip``; −1 if none."""
    ax, ay, az, bx, by, bz, cx, cy, cz = _sheared(bvh, leaf, r)
    faces = bvh.faces[leaf]
    for i in range(4):
        e = _edges(ax, ay, bx, by, cx, cy, i)
        inside = (e[0] >= 0.0 and e[1] >= 0.0 and e[2] >= 0.0) or (e[0] <= 0.0 and e[1] <= 0.0 and e[2] <= 0.0)
        det = e[0] + e[1] + e[2]
        big_t = r.sz * (e[0] * az[i] + e[1] * bz[i] + e[2] * cz[i])
        # 0 ≤ t = T/det < t_max: T and det of one sign, |T| < t_max·|det|.
        signed_t = wp.where(det < 0.0, -big_t, big_t)
        if inside and det != 0.0 and faces[i] >= 0 and signed_t >= 0.0 and signed_t < t_max * wp.abs(det):
            if (skip & (1 << i)) == 0:
                return i
    return -1


@wp.func
def _far_first(da: float, ka: wp.int32, db: float, kb: wp.int32):
    """A compare-exchange of the sorting network: the farther pair first."""
    swap = db > da
    return wp.where(swap, db, da), wp.where(swap, kb, ka), wp.where(swap, da, db), wp.where(swap, ka, kb)


@wp.func
def _wide_closest(bvh: WideBvh, r: Ray, t_max: float, planes: Planes) -> RayHit:
    """closest_hit through the wide BVH; face ``OVERFLOW`` if the stack would overflow."""
    best = RayHit()
    best.slot = -1
    best.face = -1
    best.t = t_max
    best.sign = 0.0
    nodes = NodeStack()
    near = DistanceStack()
    top = wp.int32(0)
    node = wp.int32(0)
    while True:
        # Descend: go on to the nearest child the ray meets, push the others far → near.
        while node >= 0:
            if top > STACK_SIZE - 6:  # no room for three more entries and three discarded
                best.face = OVERFLOW
                return best
            d = _entries(bvh, node, r, best.t)
            kids = bvh.children[node]
            d0, k0, d1, k1 = _far_first(d[0], kids[0], d[1], kids[1])
            d2, k2, d3, k3 = _far_first(d[2], kids[2], d[3], kids[3])
            d0, k0, d2, k2 = _far_first(d0, k0, d2, k2)
            d1, k1, d3, k3 = _far_first(d1, k1, d3, k3)
            d1, k1, d2, k2 = _far_first(d1, k1, d2, k2)
            node = wp.where(d3 == INFINITY, NO_NODE, k3)
            # The other hits land on the stack nearest on top; misses (sorted first) above
            # the new top, where they are never read.
            misses = wp.where(d0 == INFINITY, 1, 0) + wp.where(d1 == INFINITY, 1, 0) + wp.where(d2 == INFINITY, 1, 0)
            start = top - misses
            i0 = wp.where(d0 == INFINITY, top + 3, start)
            i1 = wp.where(d1 == INFINITY, top + 4, start + 1)
            i2 = wp.where(d2 == INFINITY, top + 5, start + 2)
            nodes[i0] = k0
            near[i0] = d0
            nodes[i1] = k1
            near[i1] = d1
            nodes[i2] = k2
            near[i2] = d2
            top = wp.where(d3 == INFINITY, top, start + 3)
        if node != NO_NODE:
            leaf = -node - 1
            hit = _leaf_hit(bvh, leaf, r, best, 0)
            if planes.on != 0:
                skip = wp.int32(0)
                while hit.slot >= 0 and _leaf_ignores(bvh, leaf, hit.slot, planes):
                    skip = skip | (1 << hit.slot)
                    hit = _leaf_hit(bvh, leaf, r, best, skip)
            best = hit
        # Pop the nearest entry the current hit does not already hide.
        node = NO_NODE
        while top > 0:
            top -= 1
            if near[top] <= best.t:
                node = nodes[top]
                break
        if node == NO_NODE:
            return best
    return best


@wp.func
def _wide_any(bvh: WideBvh, r: Ray, t_max: float, planes: Planes) -> wp.int32:
    """any_hit through the wide BVH: 1 hit, 0 none, ``OVERFLOW`` if the stack would overflow."""
    nodes = NodeStack()
    top = wp.int32(1)
    nodes[0] = 0
    while top > 0:
        top -= 1
        node = nodes[top]
        if node < 0:
            leaf = -node - 1
            slot = _leaf_blocks(bvh, leaf, r, t_max, 0)
            if planes.on != 0:
                skip = wp.int32(0)
                while slot >= 0 and _leaf_ignores(bvh, leaf, slot, planes):
                    skip = skip | (1 << slot)
                    slot = _leaf_blocks(bvh, leaf, r, t_max, skip)
            if slot >= 0:
                return 1
        else:
            if top > STACK_SIZE - 4:
                return OVERFLOW
            d = _entries(bvh, node, r, t_max)
            kids = bvh.children[node]
            # Any order finds a blocker: the children met go on the stack unsorted.
            for i in range(4):
                if d[i] < INFINITY:
                    nodes[top] = kids[i]
                    top += 1
    return 0


# Steps of the fallback past hits the ray ignores (see _warp_closest).
IGNORED_STEPS = 64


@wp.func
def _warp_closest(mesh: wp.uint64, r: Ray, d: wp.vec3, t_max: float, planes: Planes) -> RayHit:
    """Warp's ``mesh_query_ray``, stepped past the hits the ray ignores: after an ignored
    hit at distance t it starts again at t·(1 + 2^-10), at most IGNORED_STEPS times.

    Only a tree deeper than the stack comes here (the wide BVH filters in its leaf test,
    exactly).  Warp's query cannot skip a face, so this is exact where the ignored plane's
    rounding zone is thin beside the distances to other geometry; it is not for a
    receiver on a 1e6-sized tilted triangle under a light 0.05 away."""
    hit = RayHit()
    hit.face = -1
    hit.t = t_max
    hit.sign = 0.0
    hit.slot = -1
    start = float(0.0)
    for _step in range(IGNORED_STEPS):
        q = wp.mesh_query_ray(mesh, r.o + start * d, d, t_max - start)
        if not q.result:
            return hit
        if not _face_ignored(mesh, q.face, planes):
            hit.face = q.face
            hit.t = start + q.t
            hit.sign = q.sign
            return hit
        start = (start + q.t) * (1.0 + 1.0 / 1024.0) + 1.0e-30
        if start >= t_max:
            return hit
    return hit


@wp.func
def _planes(a: wp.vec3, na: wp.vec3, b: wp.vec3, nb: wp.vec3, on: wp.int32) -> Planes:
    p = Planes()
    p.a = a
    p.na = na
    p.b = b
    p.nb = nb
    p.on = on
    return p


@wp.func
def _closest(bvh: WideBvh, mesh: wp.uint64, r: Ray, d: wp.vec3, t_max: float, planes: Planes) -> RayHit:
    if bvh.enabled != 0:
        hit = _wide_closest(bvh, r, t_max, planes)
        if hit.face != OVERFLOW:
            return hit
    return _warp_closest(mesh, r, d, t_max, planes)


@wp.func
def _any(bvh: WideBvh, mesh: wp.uint64, r: Ray, d: wp.vec3, t_max: float, planes: Planes) -> bool:
    if bvh.enabled != 0:
        found = _wide_any(bvh, r, t_max, planes)
        if found != OVERFLOW:
            return found == 1
    if not wp.mesh_query_ray_anyhit(mesh, r.o, d, t_max):
        return False
    if planes.on == 0:
        return True
    return _warp_closest(mesh, r, d, t_max, planes).face >= 0  # the hit may be an ignored one


@wp.func
def closest_hit(bvh: WideBvh, mesh: wp.uint64, o: wp.vec3, d: wp.vec3, t_max: float) -> RayHit:
    """The first triangle the ray o + t·d, 0 ≤ t < t_max, hits (face −1 if none): through
    the wide BVH, or Warp's ``mesh_query_ray`` where it is disabled or too deep."""
    return _closest(bvh, mesh, make_ray(o, d), d, t_max, _planes(o, d, o, d, 0))


@wp.func
def any_hit(bvh: WideBvh, mesh: wp.uint64, o: wp.vec3, d: wp.vec3, t_max: float) -> bool:
    """Whether the ray o + t·d meets any triangle at 0 ≤ t < t_max (a shadow ray): through
    the wide BVH, or Warp's ``mesh_query_ray_anyhit`` where it is disabled or too deep."""
    return _any(bvh, mesh, make_ray(o, d), d, t_max, _planes(o, d, o, d, 0))


@wp.func
def closest_hit_from(bvh: WideBvh, mesh: wp.uint64, x: wp.vec3, nx: wp.vec3, o: wp.vec3, d: wp.vec3,
                     t_max: float) -> RayHit:
    """closest_hit for a ray that leaves the surface point ``x`` of unit normal ``nx`` (o
    is on the ray beyond x): hits on triangles of x's plane are rounding, and are ignored."""
    return _closest(bvh, mesh, make_ray(o, d), d, t_max, _planes(x, nx, x, nx, 1))


@wp.func
def any_hit_between(bvh: WideBvh, mesh: wp.uint64, x: wp.vec3, nx: wp.vec3, y: wp.vec3, ny: wp.vec3, o: wp.vec3,
                    d: wp.vec3, t_max: float) -> bool:
    """any_hit for a shadow ray from the surface point ``x`` (unit normal ``nx``) to the
    surface point ``y`` (unit normal ``ny``), along o + t·d, 0 ≤ t < t_max, between them:
    hits on triangles of x's plane or of y's are rounding, and are ignored."""
    return _any(bvh, mesh, make_ray(o, d), d, t_max, _planes(x, nx, y, ny, 1))


# --------------------------------------------------------------------------- build


@dataclass
class WideBvhArrays:
    """A built 4-wide BVH as numpy arrays, in :class:`WideBvh`'s layout."""

    bounds: np.ndarray  # (nodes · 6, 4) float32
    children: np.ndarray  # (nodes, 4) int32
    corners: np.ndarray  # (leaves · 9, 4) float32
    faces: np.ndarray  # (leaves, 4) int32
    depth: int  # nodes on the longest root-to-leaf path


@dataclass
class _Binary:
    """A binary BVH: node k covers order[start[k] : start[k] + count[k]]."""

    order: np.ndarray
    start: np.ndarray
    count: np.ndarray
    left: np.ndarray  # child node, −1 for a leaf (right = left + 1)
    lower: np.ndarray  # (nodes, 3)
    upper: np.ndarray


def _half_area(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    e = np.maximum(upper - lower, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _segment_bounds(values: np.ndarray, starts: np.ndarray, reduce: np.ufunc) -> np.ndarray:
    return reduce.reduceat(values, starts, axis=0)


def _best_splits(tri_lo, tri_hi, centroid, seg_of, seg_starts, seg_count):
    """Binned SAH over every segment at once: (cost, area, axis, bin) of each segment's
    best split into bins ≤ bin | > bin, and each item's bin along every axis.  A level of
    small segments gets as many bins as its largest segment has triangles: more could
    not separate more, and the per-bin arrays would dwarf the level itself."""
    s = len(seg_starts)
    n_bins = int(min(SAH_BINS, max(2, seg_count.max())))
    c_lo = _segment_bounds(centroid, seg_starts, np.minimum)
    c_hi = _segment_bounds(centroid, seg_starts, np.maximum)
    extent = c_hi - c_lo
    scale = np.where(extent > 0, n_bins * (1 - 1e-9) / np.where(extent > 0, extent, 1.0), 0.0)
    bins = np.clip(((centroid - c_lo[seg_of]) * scale[seg_of]).astype(np.int64), 0, n_bins - 1)  # (n, 3)
    best_cost = np.full(s, np.inf)
    best_axis = np.zeros(s, np.int64)
    best_bin = np.zeros(s, np.int64)
    best_area = np.zeros(s)
    for axis in range(3):
        key = seg_of * n_bins + bins[:, axis]
        lo = np.full((s * n_bins, 3), np.inf)
        hi = np.full((s * n_bins, 3), -np.inf)
        # Bounds per (segment, bin): sort by bin, then one reduceat over each run.
        by_key = np.argsort(key, kind="stable")
        sorted_key = key[by_key]
        first = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
        lo[sorted_key[first]] = np.minimum.reduceat(tri_lo[by_key], first, axis=0)
        hi[sorted_key[first]] = np.maximum.reduceat(tri_hi[by_key], first, axis=0)
        n = np.bincount(key, minlength=s * n_bins).reshape(s, n_bins)
        lo, hi = lo.reshape(s, n_bins, 3), hi.reshape(s, n_bins, 3)
        left_area = _half_area(np.minimum.accumulate(lo, axis=1), np.maximum.accumulate(hi, axis=1))[:, :-1]
        right_area = _half_area(np.minimum.accumulate(lo[:, ::-1], axis=1),
                                np.maximum.accumulate(hi[:, ::-1], axis=1))[:, ::-1][:, 1:]
        left_n = np.cumsum(n, axis=1)[:, :-1]
        right_n = seg_count[:, None] - left_n
        # A leaf tests LEAF_SIZE triangles at once: the cost of n triangles is that of
        # ⌈n / LEAF_SIZE⌉ leaf tests (Wald et al., "Getting rid of packets", 2008).
        cost = left_area * -(-left_n // LEAF_SIZE) + right_area * -(-right_n // LEAF_SIZE)
        cost[(left_n == 0) | (right_n == 0)] = np.inf
        j = np.argmin(cost, axis=1)
        c = cost[np.arange(s), j]
        better = c < best_cost
        best_cost[better], best_axis[better], best_bin[better] = c[better], axis, j[better]
        best_area[better] = (left_area + right_area)[np.arange(s), j][better]
    return best_cost, best_area, best_axis, best_bin, bins


def _build_binary(tri_lo: np.ndarray, tri_hi: np.ndarray) -> _Binary:
    """Top-down binned-SAH BVH, all segments of one level split together."""
    n_tri = len(tri_lo)
    centroid = 0.5 * (tri_lo + tri_hi)
    order = np.arange(n_tri)
    start, count = [np.array([0])], [np.array([n_tri])]
    lower, upper = [tri_lo.min(axis=0)[None]], [tri_hi.max(axis=0)[None]]
    level = np.array([0])  # nodes still to decide, numbered in creation order
    level_lower, level_upper = lower[0], upper[0]
    seg_start, seg_count = start[0], count[0]
    created = 1
    left_of = np.full(2 * n_tri, -1, np.int64)
    while len(level):
        offsets = np.concatenate([[0], np.cumsum(seg_count)[:-1]])
        seg_of = np.repeat(np.arange(len(level)), seg_count)
        rank = np.arange(len(seg_of)) - offsets[seg_of]
        items = order[seg_start[seg_of] + rank]
        cost, area, axis, split, bins = _best_splits(tri_lo[items], tri_hi[items], centroid[items], seg_of, offsets,
                                               seg_count)
        node_area = _half_area(level_lower, level_upper)
        # A small group stays a leaf unless the split is cheaper than testing it whole.
        # A leaf's ≤ LEAF_SIZE triangles are tested at once, so a leaf costs LEAF_COST
        # whatever it holds; splitting one costs a node test plus two such leaves.
        leaf = (seg_count <= LEAF_SIZE) & (LEAF_COST * node_area <= TRAVERSAL_COST * node_area + LEAF_COST * cost)
        leaf |= seg_count == 1
        goes_right = bins[np.arange(len(items)), axis[seg_of]] > split[seg_of]
        # Identical centroids along every axis leave no SAH split: halve by position.
        degenerate = ~np.isfinite(cost) & ~leaf
        goes_right = np.where(degenerate[seg_of], rank >= seg_count[seg_of] // 2, goes_right)
        keep = ~leaf[seg_of]
        # Sorting by (segment, side) keeps every segment in its place: position p of the
        # sorted list is position p of the level, now holding its left items first.
        moved = np.argsort(seg_of * 2 + goes_right, kind="stable")
        p = np.flatnonzero(keep)
        order[seg_start[seg_of[p]] + rank[p]] = items[moved[p]]
        splitting = np.flatnonzero(~leaf)
        n_right = np.bincount(seg_of, weights=goes_right, minlength=len(level)).astype(np.int64)[splitting]
        n_left = seg_count[splitting] - n_right
        child_start = np.stack([seg_start[splitting], seg_start[splitting] + n_left], axis=1).reshape(-1)
        child_count = np.stack([n_left, n_right], axis=1).reshape(-1)
        left_of[level[splitting]] = created + 2 * np.arange(len(splitting))
        level = created + np.arange(len(child_start))
        created += len(child_start)
        if len(child_start) == 0:
            break
        sorted_lo, sorted_hi = tri_lo[order], tri_hi[order]
        level_lower = np.minimum.reduceat(sorted_lo, child_start, axis=0)
        level_upper = np.maximum.reduceat(sorted_hi, child_start, axis=0)
        seg_start, seg_count = child_start, child_count
        start.append(child_start)
        count.append(child_count)
        lower.append(level_lower)
        upper.append(level_upper)
    return _Binary(order, np.concatenate(start), np.concatenate(count), left_of[:created],
                   np.concatenate(lower), np.concatenate(upper))


def _collapse(tree: _Binary) -> tuple[list[int], list[list[int]], int]:
    """The binary tree as 4-wide nodes: each node's children are binary nodes, opened
    largest surface area first until there are four (or only leaves).  Returns each wide
    node's binary root, its children and the depth."""
    area = _half_area(tree.lower, tree.upper)
    left = tree.left.tolist()
    roots: list[int] = []
    groups: list[list[int]] = []
    depth = 0
    todo = [(0, 1)]
    while todo:
        root, d = todo.pop()
        depth = max(depth, d)
        group = [root]
        while len(group) < WIDTH:
            inner = [k for k in group if left[k] >= 0]
            if not inner:
                break
            k = max(inner, key=lambda c: area[c])
            group.remove(k)
            group += [left[k], left[k] + 1]
        roots.append(root)
        groups.append(group)
        todo += [(k, d + 1) for k in group if left[k] >= 0]
    return roots, groups, depth


def _join(first: _Binary, first_ids: np.ndarray, second: _Binary, second_ids: np.ndarray) -> _Binary:
    """One binary tree whose root's children are the roots of ``first`` and ``second``
    (trees over the triangle subsets ``first_ids`` and ``second_ids``)."""
    f = len(first.start)

    def renumber(left: np.ndarray, shift: int) -> np.ndarray:
        # A child k > 0 of either tree becomes node k + shift (their roots become 1 and 2).
        return np.where(left < 0, -1, left + shift)

    start = np.concatenate([[0], [first.start[0]], [second.start[0] + len(first_ids)], first.start[1:],
                            second.start[1:] + len(first_ids)])
    count = np.concatenate([[len(first_ids) + len(second_ids)], [first.count[0]], [second.count[0]], first.count[1:],
                            second.count[1:]])
    left = np.concatenate([[1], renumber(first.left[:1], 2), renumber(second.left[:1], f + 1),
                           renumber(first.left[1:], 2), renumber(second.left[1:], f + 1)])
    lower = np.concatenate([np.minimum(first.lower[:1], second.lower[:1]), first.lower[:1], second.lower[:1],
                            first.lower[1:], second.lower[1:]])
    upper = np.concatenate([np.maximum(first.upper[:1], second.upper[:1]), first.upper[:1], second.upper[:1],
                            first.upper[1:], second.upper[1:]])
    order = np.concatenate([first_ids[first.order], second_ids[second.order]])
    return _Binary(order, start, count, left, lower, upper)


def build_wide_bvh(vertices: np.ndarray, triangles: np.ndarray, apart: np.ndarray | None = None) -> WideBvhArrays:
    """The 4-wide BVH of the float32 triangles ``vertices[triangles]``.

    ``apart`` (triangle indices, e.g. the emitters) gets its own subtree under the root:
    nearly every light-sampling ray ends on an emitter, and a tree built for all
    triangles alike can file a small light with the nearest part of a large occluder,
    which every such ray would then have to search.
    """
    corners = np.asarray(vertices, dtype=np.float32)[np.asarray(triangles)]  # (T, 3, 3)
    tri_lo = corners.min(axis=1).astype(np.float64)
    tri_hi = corners.max(axis=1).astype(np.float64)
    chosen = np.zeros(len(corners), bool)
    if apart is not None:
        chosen[np.asarray(apart, dtype=np.int64)] = True
    if chosen.any() and not chosen.all():
        ids, rest = np.flatnonzero(chosen), np.flatnonzero(~chosen)
        tree = _join(_build_binary(tri_lo[ids], tri_hi[ids]), ids, _build_binary(tri_lo[rest], tri_hi[rest]), rest)
    else:
        tree = _build_binary(tri_lo, tri_hi)
    roots, groups, depth = _collapse(tree)
    node_of = np.full(len(tree.start), -1, np.int64)
    node_of[roots] = np.arange(len(roots))
    slots = [(i, slot, k) for i, group in enumerate(groups) for slot, k in enumerate(group)]
    node_i, slot_i, binary = (np.array(x, dtype=np.int64) for x in zip(*slots))
    is_leaf = tree.left[binary] < 0
    leaves = binary[is_leaf]
    bounds = np.empty((len(groups), 6, 4), np.float32)
    bounds[:, 0::2, :] = np.inf
    bounds[:, 1::2, :] = -np.inf
    for axis in range(3):
        bounds[node_i, 2 * axis, slot_i] = tree.lower[binary, axis].astype(np.float32)
        bounds[node_i, 2 * axis + 1, slot_i] = tree.upper[binary, axis].astype(np.float32)
    children = np.zeros((len(groups), 4), np.int32)
    children[node_i[~is_leaf], slot_i[~is_leaf]] = node_of[binary[~is_leaf]]
    children[node_i[is_leaf], slot_i[is_leaf]] = -(np.arange(len(leaves)) + 1)
    faces = np.full((len(leaves), 4), -1, np.int32)
    leaf_corners = np.zeros((len(leaves), 3, 3, 4), np.float32)  # leaf, vertex, coordinate, slot
    for j in range(LEAF_SIZE):
        has = tree.count[leaves] > j
        tris = tree.order[tree.start[leaves[has]] + j]
        faces[has, j] = tris
        leaf_corners[has, :, :, j] = corners[tris]
    return WideBvhArrays(bounds=bounds.reshape(-1, 4), children=children,
                         corners=leaf_corners.reshape(-1, 4), faces=faces, depth=depth)


# Meshes smaller than this are built in milliseconds: not worth a file.
CACHE_MIN_TRIANGLES = 4096
_CACHE_FORMAT = b"warpis wide bvh 1\0"  # a new layout or builder gets a new number
_CACHE_FIELDS = ("bounds", "children", "corners", "faces", "depth")


def cache_dir() -> Path:
    """Where built BVHs are kept: ``WARPIS_CACHE_DIR``, else ``$XDG_CACHE_HOME/warpis``
    (``~/.cache/warpis``)."""
    explicit = os.environ.get("WARPIS_CACHE_DIR")
    if explicit:
        return Path(explicit)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "warpis"


def cached_wide_bvh(vertices: np.ndarray, triangles: np.ndarray, apart: np.ndarray) -> WideBvhArrays:
    """:func:`build_wide_bvh`, kept on disk by the geometry's content (the float32
    vertices, the triangles and ``apart``) so that another process with the same mesh,
    a cluster worker or the next command, loads it instead (82k triangles take about a
    second to build in numpy).  A file that cannot be read or does not fit the mesh is
    rebuilt and replaced; one that cannot be written only costs the next build."""
    verts = np.ascontiguousarray(vertices, dtype=np.float32)
    tris = np.ascontiguousarray(triangles, dtype=np.int32)
    chosen = np.ascontiguousarray(apart, dtype=np.int32)
    if len(tris) < CACHE_MIN_TRIANGLES:
        return build_wide_bvh(verts, tris, chosen)
    key = hashlib.sha256(_CACHE_FORMAT)
    for part in (verts, tris, chosen):
        key.update(np.asarray(part.shape, np.int64).tobytes())
        key.update(part.tobytes())
    path = cache_dir() / f"bvh-{key.hexdigest()[:32]}.npz"
    try:
        with np.load(path, allow_pickle=False) as f:
            built = WideBvhArrays(**{name: f[name] for name in _CACHE_FIELDS[:-1]}, depth=int(f["depth"]))
        if _fits(built, verts[tris]):
            return built
    except (OSError, ValueError, KeyError, TypeError):
        pass
    built = build_wide_bvh(verts, tris, chosen)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with files.replacing(path, durable=False) as fh:  # a reader sees the old file or the whole new one
            np.savez(fh, **{name: getattr(built, name) for name in _CACHE_FIELDS})
    except OSError:
        pass
    return built


def _fits(built: WideBvhArrays, corners: np.ndarray) -> bool:
    """Whether a loaded BVH has the layout's shapes, holds each triangle (T, 3, 3 corners)
    once, and holds its very corners: a file that passes cannot give another mesh's hits."""
    nodes, leaves = len(built.children), len(built.faces)
    if built.bounds.shape != (6 * nodes, 4) or built.corners.shape != (9 * leaves, 4) \
            or built.children.shape != (nodes, 4) or built.faces.shape != (leaves, 4):
        return False
    used = built.faces >= 0
    faces = built.faces[used]
    if len(faces) != len(corners) or not np.array_equal(np.sort(faces), np.arange(len(corners))):
        return False
    stored = built.corners.reshape(leaves, 3, 3, 4).transpose(0, 3, 1, 2)[used]  # (T, vertex, coordinate)
    return bool(np.array_equal(stored, corners[faces])) and bool(np.all(built.children < nodes)) \
        and bool(np.all(built.children >= -leaves))


def upload_wide_bvh(built: WideBvhArrays | None) -> WideBvh:
    """The :class:`WideBvh` struct of ``built`` on the current device; ``None`` gives a
    disabled one (the kernels then use ``wp.mesh_query_ray``)."""
    b = WideBvh()
    if built is None:
        built = WideBvhArrays(np.zeros((6, 4), np.float32), np.zeros((1, 4), np.int32),
                              np.zeros((9, 4), np.float32), np.full((1, 4), -1, np.int32), 0)
    b.bounds = wp.array(built.bounds, dtype=wp.vec4)
    b.children = wp.array(built.children, dtype=wp.vec4i)
    b.corners = wp.array(built.corners, dtype=wp.vec4)
    b.faces = wp.array(built.faces, dtype=wp.vec4i)
    b.enabled = 0 if built.depth == 0 else 1
    return b
