"""Analytic spheres in Warp: exact ray crossings, the cone a sphere subtends, its sampling.

A sphere is intersected in float64 from the float32 ray (o, ω), after moving the origin
to the ray's closest approach to the centre (Mitsuba's robust form): the discriminant
r² − |q|² is then a product (r − |q|)(r + |q|) of well-conditioned terms however far
the sphere is.  The root nearer the origin meets the sphere's outside, the farther one
its inside, so whether a crossing sees the *front* (the emitting side: the outside, or
the inside of an ``inward`` sphere) follows from which root it is, never from a rounded
dot product at the silhouette.

Every test of "does ω cross sphere s" — the integrand's nearest crossing, a shadow
ray's, the light pdf's — is the same discriminant on the same float32 ω, so a light
sample the pdf counts is a ray the integrand sees reach the light, and vice versa.
Light samples are drawn in float64 and rounded to a float32 ω; the few that rounding
carries out of the sphere's silhouette (a 10⁻⁷-radian rim) are moved back inside
(:func:`into_sphere`), so no sample is lost to rounding (docs/theory.md, "Sphere
lights").
"""

from __future__ import annotations

import warp as wp

from .device import SceneData
from .warps import PI

__all__ = ["SphereCrossing", "FEW_SPHERES", "cone_sample", "into_sphere", "nearest_sphere", "one_minus_cos_max",
           "sphere_area_point", "sphere_roots", "spheres_block"]

# Up to this many spheres a loop over them is cheaper than a BVH query.
FEW_SPHERES = wp.constant(8)
NO_ROOT = wp.constant(-1.0e30)


@wp.struct
class SphereCrossing:
    """The nearest crossing of a ray with a sphere in a range of distances."""

    s: wp.int32  # sphere index, −1: none
    t: float
    front: wp.int32  # 1 if the ray meets the sphere's front (emitting) side there


@wp.func
def sphere_roots(o: wp.vec3, w: wp.vec3, c: wp.vec3d, r: wp.float64) -> wp.vec2d:
    """The distances (t0 ≤ t1) at which the ray o + t·ω meets the sphere (c, r), in
    float64; (NO_ROOT, NO_ROOT) when it misses."""
    o64 = wp.vec3d(wp.float64(o[0]), wp.float64(o[1]), wp.float64(o[2]))
    w64 = wp.vec3d(wp.float64(w[0]), wp.float64(w[1]), wp.float64(w[2]))
    a = wp.dot(w64, w64)
    oc = c - o64
    tc = wp.dot(oc, w64) / a  # the ray's closest approach to the centre
    q = tc * w64 - oc  # from the centre to that point
    ql = wp.length(q)
    h2 = (r - ql) * (r + ql)
    if h2 < wp.float64(0.0):
        return wp.vec2d(wp.float64(NO_ROOT), wp.float64(NO_ROOT))
    h = wp.sqrt(h2 / a)
    return wp.vec2d(tc - h, tc + h)


@wp.func
def _nearer_sphere(best: SphereCrossing, scene: SceneData, s: wp.int32, o: wp.vec3, w: wp.vec3, t_min: float,
                   t_max: float) -> SphereCrossing:
    roots = sphere_roots(o, w, scene.sphere_center[s], scene.sphere_radius[s])
    if roots[1] == wp.float64(NO_ROOT):
        return best
    out = best
    t0 = float(roots[0])
    t1 = float(roots[1])
    limit = wp.where(out.s >= 0, out.t, t_max)
    # The near root meets the outside, the far one the inside.
    if t0 > t_min and t0 < limit:
        out.s = s
        out.t = t0
        out.front = 1 - scene.sphere_inward[s]
    elif t1 > t_min and t1 < limit:
        out.s = s
        out.t = t1
        out.front = scene.sphere_inward[s]
    return out


@wp.func
def nearest_sphere(scene: SceneData, o: wp.vec3, w: wp.vec3, t_min: float, t_max: float) -> SphereCrossing:
    """The nearest crossing of the ray (o, ω) with any sphere at t_min < t < t_max."""
    best = SphereCrossing()
    best.s = -1
    best.t = t_max
    best.front = 0
    if scene.sphere_count <= FEW_SPHERES:
        for s in range(scene.sphere_count):
            best = _nearer_sphere(best, scene, s, o, w, t_min, t_max)
        return best
    query = wp.bvh_query_ray(scene.sphere_bvh, o, w)
    s = wp.int32(0)
    while wp.bvh_query_next(query, s):
        best = _nearer_sphere(best, scene, s, o, w, t_min, t_max)
    return best


@wp.func
def _crosses(scene: SceneData, s: wp.int32, o: wp.vec3, w: wp.vec3, t_min: float, t_max: float,
             skip: wp.int32) -> bool:
    if s == skip:
        return False
    roots = sphere_roots(o, w, scene.sphere_center[s], scene.sphere_radius[s])
    if roots[1] == wp.float64(NO_ROOT):
        return False
    t0 = float(roots[0])
    t1 = float(roots[1])
    return (t0 > t_min and t0 < t_max) or (t1 > t_min and t1 < t_max)


@wp.func
def spheres_block(scene: SceneData, o: wp.vec3, w: wp.vec3, t_min: float, t_max: float, skip: wp.int32) -> bool:
    """Whether any sphere but ``skip`` crosses the segment t_min < t < t_max of the ray (o, ω)."""
    if scene.sphere_count <= FEW_SPHERES:
        for s in range(scene.sphere_count):
            if _crosses(scene, s, o, w, t_min, t_max, skip):
                return True
        return False
    query = wp.bvh_query_ray(scene.sphere_bvh, o, w)
    s = wp.int32(0)
    while wp.bvh_query_next(query, s):
        if _crosses(scene, s, o, w, t_min, t_max, skip):
            return True
    return False


# --------------------------------------------------------------------------- sampling


@wp.func
def one_minus_cos_max(p: wp.vec3d, c: wp.vec3d, r: wp.float64) -> wp.float64:
    """1 − cos θmax of the cone the sphere (c, r) subtends at p outside it: sin²θmax / (1 +
    cos θmax), with cos θmax = √((d − r)(d + r))/d, which stays exact near the sphere
    (d → r) and far from it (where 1 − cos θmax ≈ r²/2d² would cancel)."""
    d = wp.length(c - p)
    sin2 = (r / d) * (r / d)
    cos_max = wp.sqrt(wp.max((d - r) * (d + r), wp.float64(0.0))) / d
    return sin2 / (wp.float64(1.0) + cos_max)


@wp.func
def frame_to_world(local: wp.vec3d, n: wp.vec3d) -> wp.vec3d:
    """``local`` (z along n) in world space (Duff et al. 2017's frame about n)."""
    sign = wp.where(n[2] >= wp.float64(0.0), wp.float64(1.0), wp.float64(-1.0))
    a = wp.float64(-1.0) / (sign + n[2])
    b = n[0] * n[1] * a
    b1 = wp.vec3d(wp.float64(1.0) + sign * n[0] * n[0] * a, sign * b, -sign * n[0])
    b2 = wp.vec3d(b, sign + n[1] * n[1] * a, -n[1])
    return local[0] * b1 + local[1] * b2 + local[2] * n


@wp.func
def cone_sample(u: wp.vec2, axis: wp.vec3d, one_minus_cos: wp.float64) -> wp.vec3d:
    """A direction uniform in solid angle within the cone about the unit ``axis`` of
    1 − cos θmax = ``one_minus_cos``: 1 − cos θ = u.x (1 − cos θmax), so sin²θ = s(2 − s)
    from s = 1 − cos θ without cancellation; φ = 2π u.y."""
    s = wp.float64(u[0]) * one_minus_cos
    sin_t = wp.sqrt(wp.max(s * (wp.float64(2.0) - s), wp.float64(0.0)))
    phi = wp.float64(2.0 * PI) * wp.float64(u[1])
    local = wp.vec3d(sin_t * wp.cos(phi), sin_t * wp.sin(phi), wp.float64(1.0) - s)
    return frame_to_world(local, axis)


@wp.func
def sphere_area_point(u: wp.vec2, c: wp.vec3d, r: wp.float64) -> wp.vec3d:
    """A point uniform on the sphere's surface: z = 1 − 2u.x, φ = 2π u.y."""
    z = wp.float64(1.0) - wp.float64(2.0) * wp.float64(u[0])
    rho = wp.sqrt(wp.max(wp.float64(1.0) - z * z, wp.float64(0.0)))
    phi = wp.float64(2.0 * PI) * wp.float64(u[1])
    return c + r * wp.vec3d(rho * wp.cos(phi), rho * wp.sin(phi), z)


@wp.func
def into_sphere(p: wp.vec3, d: wp.vec3d, c: wp.vec3d, r: wp.float64) -> wp.vec3:
    """The float32 unit direction of ``d`` (a float64 direction from p that meets the
    sphere), moved towards the centre by a few float32 ulps if rounding carried it off
    the silhouette, so that :func:`sphere_roots` (every test of the kernels) sees it
    meet the sphere ahead of p."""
    w = wp.normalize(wp.vec3(float(d[0]), float(d[1]), float(d[2])))
    p64 = wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))
    to_c = wp.normalize(c - p64)
    axis = wp.vec3(float(to_c[0]), float(to_c[1]), float(to_c[2]))
    step = float(1.0e-7)
    for _ in range(24):
        roots = sphere_roots(p, w, c, r)
        if roots[1] > wp.float64(0.0):
            return w
        w = wp.normalize(w + step * axis)
        step = step * 2.0
    return axis
