"""The emitter triangles as Warp functions: corners, ray crossings, the nearest crossing.

Light sampling needs every crossing of a ray with the emitters (the pdf is a sum over
them, :func:`warpis.kernels.techniques.light_pdf`); the integrand needs the nearest one
(what a ray sees first, if it sees an emitter at all, :mod:`warpis.kernels.integrand`).
Both walk the emitter triangles alone: a loop over them when there are at most
``FEW_EMITTERS`` (a quad light is two), else a traversal of their own BVH.
"""

from __future__ import annotations

import warp as wp

from .device import SceneData

__all__ = ["CROSSING_TOLERANCE", "EDGE_SLACK", "EmitterHit", "FEW_EMITTERS", "emitter_corner", "emitter_corner64",
           "emitter_faces", "nearest_emitter", "ray_triangle", "to64"]

# Up to this many emitter triangles, a loop over all of them is cheaper than a BVH query.
FEW_EMITTERS = wp.constant(8)
# Barycentric widening of the emitter triangles for light pdfs (see ray_triangle).
EDGE_SLACK = wp.constant(1.0e-6)
# Two emitter crossings of one ray closer than this fraction of their distance are one
# crossing seen through two triangles (a shared edge): relative, so no scene size enters.
CROSSING_TOLERANCE = wp.constant(1.0e-5)
# The float32 pre-test of ``crossing`` rejects only rays this far outside a triangle
# (in barycentric terms): 100× its worst error seen on small grazing triangles.
PREFILTER_MARGIN = wp.constant(0.1)


@wp.struct
class EmitterHit:
    """The nearest crossing of a ray with an emitter triangle."""

    k: wp.int32  # emitter index (into scene.emitter_tri), −1: the ray crosses none
    t: float  # distance from the ray's origin
    front: wp.int32  # 1 if the ray meets the triangle's front (emitting) face


@wp.func
def emitter_corner(scene: SceneData, k: wp.int32, c: wp.int32) -> wp.vec3:
    """Corner ``c`` of emitter triangle ``k``."""
    t = scene.emitter_tri[k]
    return scene.points[scene.indices[3 * t + c]]


@wp.func
def emitter_corner64(scene: SceneData, k: wp.int32, c: wp.int32) -> wp.vec3d:
    v = emitter_corner(scene, k, c)
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def emitter_faces(scene: SceneData, k: wp.int32, p: wp.vec3) -> bool:
    """Whether the front face of emitter triangle ``k`` faces point ``p``."""
    a = emitter_corner(scene, k, 0)
    nrm = wp.cross(emitter_corner(scene, k, 1) - a, emitter_corner(scene, k, 2) - a)
    return wp.dot(nrm, p - a) > 0.0


@wp.func
def to64(v: wp.vec3) -> wp.vec3d:
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def crossing(o: wp.vec3, w: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, slack: wp.float64) -> float:
    """Distance t > 0 at which the ray (o, ω) crosses triangle abc widened by ``slack`` in
    barycentric terms, or −1 (Möller–Trumbore in float64).

    In float64: for a small emitter triangle seen from afar at a grazing angle, float32
    Möller–Trumbore misplaces the crossing by 1e-3 of the triangle (its determinant is
    tiny) and loses crossings of directions the light technique itself produced.
    """
    # A float32 pass first rejects what is far outside (most directions miss a light by
    # far); its barycentrics can be off by 1e-3 of the triangle, so the margin is wide.
    e1f = b - a
    e2f = c - a
    pvf = wp.cross(w, e2f)
    detf = wp.dot(e1f, pvf)
    if detf != 0.0:
        tvf = o - a
        buf = wp.dot(tvf, pvf) / detf
        bvf = wp.dot(w, wp.cross(tvf, e1f)) / detf
        if buf < -PREFILTER_MARGIN or bvf < -PREFILTER_MARGIN or buf + bvf > 1.0 + PREFILTER_MARGIN:
            return -1.0
    o64 = to64(o)
    w64 = to64(w)
    a64 = to64(a)
    e1 = to64(b) - a64
    e2 = to64(c) - a64
    pv = wp.cross(w64, e2)
    det = wp.dot(e1, pv)
    if det == wp.float64(0.0):
        return -1.0
    inv = wp.float64(1.0) / det
    tv = o64 - a64
    bu = wp.dot(tv, pv) * inv
    if bu < -slack or bu > wp.float64(1.0) + slack:
        return -1.0
    qv = wp.cross(tv, e1)
    bv = wp.dot(w64, qv) * inv
    if bv < -slack or bu + bv > wp.float64(1.0) + slack:
        return -1.0
    t = float(wp.dot(e2, qv) * inv)
    return wp.where(t > 0.0, t, -1.0)


@wp.func
def ray_triangle(o: wp.vec3, w: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """:func:`crossing` with edges widened by ``EDGE_SLACK``: the light pdf never loses a
    crossing of a direction a light technique produced through a shared edge (the test
    is not watertight); the duplicate a widened edge can cause is removed by ``light_pdf``."""
    return crossing(o, w, a, b, c, wp.float64(EDGE_SLACK))


@wp.func
def _nearer(best: EmitterHit, scene: SceneData, k: wp.int32, o: wp.vec3, w: wp.vec3, t_min: float) -> EmitterHit:
    """``best``, or emitter k's crossing beyond t_min if it is nearer."""
    a = emitter_corner(scene, k, 0)
    b = emitter_corner(scene, k, 1)
    c = emitter_corner(scene, k, 2)
    t = crossing(o, w, a, b, c, wp.float64(0.0))
    out = best
    if t > t_min and (out.k < 0 or t < out.t):
        out.k = k
        out.t = t
        out.front = wp.where(wp.dot(scene.emitter_normal[k], w) < 0.0, 1, 0)
    return out


@wp.func
def meets_box(lower: wp.vec3, upper: wp.vec3, o: wp.vec3, w: wp.vec3) -> bool:
    """Whether the ray (o, ω), t ≥ 0, meets the box (a slab test, widened like pbrt's)."""
    t_near = float(0.0)
    t_far = float(1.0e30)
    for i in range(3):
        if w[i] == 0.0:
            if o[i] < lower[i] or o[i] > upper[i]:
                return False
        else:
            inv = 1.0 / w[i]
            t0 = (lower[i] - o[i]) * inv
            t1 = (upper[i] - o[i]) * inv
            t_near = wp.max(t_near, wp.min(t0, t1))
            t_far = wp.min(t_far, wp.max(t0, t1))
    return t_near <= t_far * 1.0000004


@wp.func
def nearest_emitter(scene: SceneData, o: wp.vec3, w: wp.vec3, t_min: float) -> EmitterHit:
    """The nearest crossing beyond ``t_min`` of the ray (o, ω) with an emitter triangle.

    Unwidened (slack 0): the integrand counts light only where the ray truly crosses an
    emitter, up to float64 rounding at the edges.
    """
    best = EmitterHit()
    best.k = -1
    best.t = 0.0
    best.front = 0
    if scene.emitter_count <= FEW_EMITTERS:
        if meets_box(scene.emitter_lower, scene.emitter_upper, o, w):
            for k in range(scene.emitter_count):
                best = _nearer(best, scene, k, o, w, t_min)
        return best
    query = wp.bvh_query_ray(scene.emitter_bvh, o, w)
    k = wp.int32(0)
    while wp.bvh_query_next(query, k):
        best = _nearer(best, scene, k, o, w, t_min)
    return best
