"""Sampling techniques: ``sample(u) → (ω, pdf)`` and ``pdf(ω)`` pairs, as Warp functions.

Techniques (entries of ``TECHNIQUES`` (below)):

``uniform``            uniform over the receiver's hemisphere, 1/(2π).
``cosine``             cosine-weighted hemisphere, cos θ/π (BSDF sampling for irradiance
                       and lambert).
``phong``              the lobe (e+1)/(2π) cos^e α about the view's mirror direction, on the
                       whole sphere: directions below the horizon are produced with that
                       density and carry f = 0, so the estimate stays unbiased.
``light-area``         an emitter triangle or sphere light picked by its share of the total
                       emitter area (u.x through the area CDF, then rescaled within the
                       chosen interval so that strata of u stay strata), a uniform point on
                       it; a uniform area density 1/A over all emitters, in solid angle
                       A⁻¹ r²/|cos θ_y|.
``light-power``        the same with lights picked in proportion to radiance × area.
``light-solid-angle``  a light picked in proportion to solid angle × radiance among those
                       whose front faces the receiver, then a uniform direction within its
                       spherical triangle (Arvo 1995), or within the cone a sphere light
                       subtends (uniform over the whole sphere of directions inside an
                       inward-emitting sphere).
``bsdf``               the receiver material's own sampling, as Mitsuba 3 samples it: cosine
                       for irradiance and lambert, the lobe for phong, visible normals (Heitz
                       2018) or the whole distribution for roughconductor, and for
                       roughplastic a choice between its specular and diffuse lobes (weight
                       from its transmittance at the view) followed by either; the pdf sums
                       both lobes' densities.
``envmap``             the environment light's cells picked by their energy ∫ L dω, then a
                       direction uniform in solid angle within the cell (environment.py);
                       on the whole sphere, like phong.  Area emitters are the light
                       techniques' and the environment is this one's: a scene lit by both
                       combines them as separate techniques (MIS or a mixture), whose
                       weights are explicit, rather than as one technique of hidden pick
                       probabilities.

The pdf convention, relied on by MIS and by the theory: ``technique_pdf(ω)`` is the density
of the direction ω that ``sample_technique`` produces, whatever ω hits first.  For light
techniques a direction crossing several emitter triangles (the near and far side of a
sphere light, an emitter behind an occluder) carries the *sum* of their densities: the
pdf visits every crossing (a loop over a few emitter triangles, else a BVH of them).  The
pdf a sample reports is computed by that same function, so the two cannot disagree;
the one exception is a light-area or light-power sample on a planar emitter set
(``sample_light_point``), whose ray crosses the emitters only at its own point: it
reports that point's density, the single term of the sum (docs/theory.md, "The
integrand at a receiver"; tests/test_light_paths.py holds the two against each other).

User techniques (:func:`register_technique`): a ``sample``/``pdf`` pair of ``@wp.func`` s
on a ``ShadingPoint``.  :func:`dispatch` wraps the built-in dispatch in one branch per user
technique (its code a ``wp.static`` constant), and the kernels that dispatch on codes
(the sample and pdf kernels here, the trial and pilot kernels, the quadrature's evaluate
kernel) are built from it together, in one Warp module per registered set
(:mod:`warpis.kernels.registered`); with no user technique they are the built-in kernels
themselves.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from ..errors import WarpisError
from ..vocabulary import Registry, Technique, UserEntries, UserEntry
from .device import DeviceScene, ReceiverData, SceneData, upload
from .emitters import (CROSSING_TOLERANCE, FEW_EMITTERS, emitter_corner, emitter_corner64, emitter_faces, meets_box,
                       ray_triangle)
from .environment import environment_pdf, sample_environment
from .integrand import PHONG as PHONG_MATERIAL
from .integrand import ROUGHCONDUCTOR, ROUGHPLASTIC, ShadingPoint, shading_point
from .microfacet import conductor_pdf, conductor_sample, plastic_pdf, plastic_sample
from .precompiled import compile_portably
from .spheres import cone_sample, into_sphere, one_minus_cos_max, sphere_area_point, sphere_roots
from .warps import (PI64, cosine_hemisphere_pdf, phong_lobe_pdf, square_to_cosine_hemisphere, square_to_phong_lobe,
                    square_to_spherical_triangle, square_to_triangle, square_to_uniform_hemisphere, to_world,
                    triangle_solid_angle, uniform_hemisphere_pdf)

compile_portably(__name__)  # shipped compiled: precompiled.py says why portably

if TYPE_CHECKING:  # annotations only: scenes import the kernels' registries
    from ..scenes import Scene


TECHNIQUES: Registry[Technique] = Registry("technique", [
    # ∫ 1/g dω is 2π · 2π for uniform; for cosine ∫ π/cos θ dω diverges (logarithmically)
    # at the horizon; the lobe and the light techniques vanish on part of the hemisphere.
    Technique(name="uniform", code=0, description="uniform over the receiver's hemisphere, 1/(2π)",
              inverse_pdf_integral=4 * math.pi**2),
    Technique(name="cosine", code=1, description="cosine-weighted hemisphere, cos θ/π",
              inverse_pdf_integral=math.inf),
    Technique(name="phong", code=2, description="the Phong lobe (e+1)/(2π) cos^e α about the view's mirror direction",
              inverse_pdf_integral=math.inf),
    # Costs measured on the bundled scenes: a light-solid-angle sample costs 1.5–2
    # light-area or 4–7 phong samples.  A fixed table keeps references reproducible.
    Technique(name="light-area", code=3, description="a uniform point on the emitters (triangle picked by area)",
              light=True, inverse_pdf_integral=math.inf, cost=2.0),
    Technique(name="light-power", code=4, description="a uniform point on an emitter triangle picked by "
                                                      "radiance × area",
              light=True, inverse_pdf_integral=math.inf, cost=2.0),
    Technique(name="light-solid-angle", code=5, description="a uniform direction in a spherical triangle, picked by "
                                                            "solid angle × radiance (Arvo 1995)",
              light=True, inverse_pdf_integral=math.inf, cost=5.0),
    Technique(name="bsdf", code=6, description="the receiver material's own BSDF sampling, as Mitsuba 3 does it: "
                                               "cosine (irradiance, lambert), the lobe (phong), visible or all "
                                               "microfacet normals (roughconductor), a lobe choice then either "
                                               "(roughplastic)",
              inverse_pdf_integral=math.inf),
    # Its pdf vanishes in cells of zero radiance, so ∫ 1/g dω is infinite in general.
    Technique(name="envmap", code=7, description="the environment light's cells by their energy, then uniform in "
                                                 "solid angle within the cell",
              environment=True, inverse_pdf_integral=math.inf, cost=2.0),
])


# The kernels' codes, from the registry.
UNIFORM = wp.constant(TECHNIQUES["uniform"].code)
COSINE = wp.constant(TECHNIQUES["cosine"].code)
PHONG = wp.constant(TECHNIQUES["phong"].code)
LIGHT_AREA = wp.constant(TECHNIQUES["light-area"].code)
LIGHT_POWER = wp.constant(TECHNIQUES["light-power"].code)
LIGHT_SOLID_ANGLE = wp.constant(TECHNIQUES["light-solid-angle"].code)
BSDF = wp.constant(TECHNIQUES["bsdf"].code)
ENVMAP = wp.constant(TECHNIQUES["envmap"].code)

# Crossings a pdf evaluation remembers, so that a ray through an edge (or corner) shared
# by several emitter triangles, which each of them reports, counts that crossing once.
MAX_CROSSINGS = wp.constant(16)
Crossings = wp.types.vector(length=MAX_CROSSINGS, dtype=wp.float32)


@wp.struct
class LightTable:
    """Per-receiver selection of lights (emitter triangles, then sphere lights) for
    ``light-solid-angle``."""

    cdf: wp.array2d(dtype=wp.float64)  # (R, E + L + 1): Σ Ω_k L_k over front-facing k, normalised
    total: wp.array(dtype=wp.float64)  # (R,): Σ Ω_k L_k; 0 when no emitter faces the receiver


# --------------------------------------------------------------------------- emitters


@wp.func
def search_cdf(cdf: wp.array(dtype=wp.float32), count: wp.int32, x: float) -> wp.int32:
    """The interval k with cdf[k] ≤ x < cdf[k+1] (cdf has count + 1 entries)."""
    lo = wp.int32(0)
    hi = count
    while hi - lo > 1:
        mid = (lo + hi) / 2
        if cdf[mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def search_cdf_row(cdf: wp.array2d(dtype=wp.float64), r: wp.int32, count: wp.int32, x: wp.float64) -> wp.int32:
    lo = wp.int32(0)
    hi = count
    while hi - lo > 1:
        mid = (lo + hi) / 2
        if cdf[r, mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def rescale(x: float, lo: float, hi: float) -> float:
    """Map x ∈ [lo, hi) to [0, 1): the chosen interval of u.x becomes a fresh u.x."""
    return wp.clamp((x - lo) / wp.max(hi - lo, 1.0e-30), 0.0, 0.99999994)


@wp.struct
class CrossingSum:
    """A light pdf being summed over a ray's emitter crossings."""

    pdf: float
    seen: Crossings  # distances of the crossings counted, negated for back-facing ones
    count: wp.int32


@wp.func
def add_crossing(acc: CrossingSum, tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint,
                 w: wp.vec3, k: wp.int32) -> CrossingSum:
    """``acc`` plus emitter triangle k's density at ω, if the ray crosses it at a point
    not already counted."""
    a = emitter_corner(scene, k, 0)
    b = emitter_corner(scene, k, 1)
    c = emitter_corner(scene, k, 2)
    t = ray_triangle(sp.p, w, a, b, c)
    if t <= 0.0:
        return acc
    nrm = wp.cross(b - a, c - a)
    front = wp.dot(nrm, w) < 0.0
    signed = wp.where(front, t, -t)
    for i in range(acc.count):
        if wp.abs(acc.seen[i] - signed) <= CROSSING_TOLERANCE * t:
            return acc
    out = acc
    if out.count < MAX_CROSSINGS:
        out.seen[out.count] = signed
        out.count += 1
    radiance = scene.tri_emission[scene.emitter_tri[k]]
    if tech == LIGHT_SOLID_ANGLE:
        # Only triangles whose front faces the receiver can be chosen.
        if front and table.total[sp.receiver] > wp.float64(0.0):
            out.pdf = out.pdf + radiance / float(table.total[sp.receiver])
    else:
        out.pdf = out.pdf + area_to_solid_angle(light_density(tech, scene, radiance), t, nrm, w)
    return out


@wp.func
def light_density(tech: wp.int32, scene: SceneData, radiance: float) -> float:
    """Area density of light-area (1/A) or light-power (L_k/P) on a triangle of radiance L_k."""
    if tech == LIGHT_POWER:
        return radiance / scene.total_power
    return 1.0 / scene.total_area


@wp.func
def area_to_solid_angle(density: float, t: float, nrm: wp.vec3, w: wp.vec3) -> float:
    """An area density at distance t on a surface of (unnormalised) normal nrm, per unit
    solid angle about ω."""
    cos_y = wp.max(wp.abs(wp.dot(wp.normalize(nrm), w)), 1.0e-12)
    return density * t * t / cos_y


@wp.func
def light_pdf(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, w: wp.vec3) -> float:
    """Solid-angle density of a light technique at ω: a sum over every emitter crossing.

    Every emitter triangle the ray crosses adds its density: a loop over all of them when
    there are few, else one traversal of the emitter triangles' BVH.  Crossings within
    ``CROSSING_TOLERANCE`` × t of one already counted *through a face of the same
    facing* are the same crossing (a ray through an edge shared by two triangles meets
    both at one point) and add nothing.  The facing matters: at a sphere light's
    silhouette the ray enters through a front face and leaves through a back face at
    almost the same t, two crossings that both count.
    """
    acc = CrossingSum()
    acc.pdf = 0.0
    acc.count = 0
    spheres = float(0.0)
    for j in range(scene.light_count - scene.emitter_count):
        spheres = spheres + sphere_light_pdf(tech, scene, table, sp, w, j)
    if scene.emitter_count <= FEW_EMITTERS:
        if scene.emitter_count > 0 and meets_box(scene.emitter_lower, scene.emitter_upper, sp.p, w):
            for k in range(scene.emitter_count):
                acc = add_crossing(acc, tech, scene, table, sp, w, k)
        return acc.pdf + spheres
    query = wp.bvh_query_ray(scene.emitter_bvh, sp.p, w)
    k = wp.int32(0)
    while wp.bvh_query_next(query, k):
        acc = add_crossing(acc, tech, scene, table, sp, w, k)
    return acc.pdf + spheres


@wp.func
def sphere_light_pdf(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, w: wp.vec3,
                     j: wp.int32) -> float:
    """Sphere light j's share of a light technique's density at ω.

    light-solid-angle: L_j / Σ Ω_k L_k where ω lies in the sphere's cone (a ray that
    meets it ahead, its front facing the receiver); light-area and light-power: its
    area density at each of the ray's crossings, t²/|cos θ_y| per unit solid angle."""
    s = scene.sphere_light[j]
    c = scene.sphere_center[s]
    r = scene.sphere_radius[s]
    roots = sphere_roots(sp.p, w, c, r)
    if roots[1] <= wp.float64(0.0):  # a miss (NO_ROOT) or a sphere behind
        return 0.0
    radiance = scene.sphere_emission[s]
    if tech == LIGHT_SOLID_ANGLE:
        inside = roots[0] <= wp.float64(0.0)
        faces = (inside and scene.sphere_inward[s] != 0) or (not inside and scene.sphere_inward[s] == 0)
        if faces and table.total[sp.receiver] > wp.float64(0.0):
            return radiance / float(table.total[sp.receiver])
        return 0.0
    density = light_density(tech, scene, radiance)
    out = float(0.0)
    p64 = wp.vec3d(wp.float64(sp.p[0]), wp.float64(sp.p[1]), wp.float64(sp.p[2]))
    w64 = wp.vec3d(wp.float64(w[0]), wp.float64(w[1]), wp.float64(w[2]))
    for i in range(2):
        t = roots[i]
        if t > wp.float64(0.0):
            n = (p64 + t * w64 - c) / r
            cos_y = wp.max(wp.abs(float(wp.dot(n, w64))), 1.0e-12)
            out = out + density * float(t * t) / cos_y
    return out


@wp.struct
class DirectionSample:
    """A sampled direction with what its technique knows of it."""

    w: wp.vec3  # zero vector: a failed sample
    pdf: float  # the technique's density at ω; < 0: not known here (technique_pdf gives it)
    emitter: wp.int32  # the emitter triangle the ray from x crosses first, −1: not known
    t: float  # distance from x to that crossing


@wp.func
def unknown_sample(w: wp.vec3) -> DirectionSample:
    """A direction and nothing more: its pdf and what it sees are looked up."""
    s = DirectionSample()
    s.w = w
    s.pdf = -1.0
    s.emitter = -1
    s.t = 0.0
    return s


@wp.func
def pick_light(tech: wp.int32, scene: SceneData, u: wp.vec2):
    """light-area / light-power: (k, u') the light k (an emitter triangle, or sphere light
    k − E) that u.x picks, and u with u.x rescaled within k's interval."""
    k = wp.int32(0)
    ux = float(0.0)
    if tech == LIGHT_POWER:
        k = search_cdf(scene.power_cdf, scene.light_count, u[0])
        ux = rescale(u[0], scene.power_cdf[k], scene.power_cdf[k + 1])
    else:
        k = search_cdf(scene.area_cdf, scene.light_count, u[0])
        ux = rescale(u[0], scene.area_cdf[k], scene.area_cdf[k + 1])
    return k, wp.vec2(ux, u[1])


@wp.func
def pick_light_point(tech: wp.int32, scene: SceneData, u: wp.vec2):
    """light-area / light-power on emitter triangles alone: (y, k), the point y of emitter
    triangle k that u maps to."""
    n_e = scene.emitter_count
    k = wp.int32(0)
    ux = float(0.0)
    if tech == LIGHT_POWER:
        k = search_cdf(scene.power_cdf, n_e, u[0])
        ux = rescale(u[0], scene.power_cdf[k], scene.power_cdf[k + 1])
    else:
        k = search_cdf(scene.area_cdf, n_e, u[0])
        ux = rescale(u[0], scene.area_cdf[k], scene.area_cdf[k + 1])
    y = square_to_triangle(wp.vec2(ux, u[1]), emitter_corner(scene, k, 0), emitter_corner(scene, k, 1),
                           emitter_corner(scene, k, 2))
    return y, k


@wp.func
def sample_light_point(tech: wp.int32, scene: SceneData, sp: ShadingPoint, u: wp.vec2) -> DirectionSample:
    """light-area / light-power on a planar emitter set (``scene.planar_emitters``): the ray
    from x crosses the emitters only at the sampled point y, so the sample knows its pdf
    (y's density, the single term of light_pdf's sum) and that y is what it sees first
    among the emitters."""
    y, k = pick_light_point(tech, scene, u)
    d = y - sp.p
    t = wp.length(d)
    s = unknown_sample(wp.vec3(0.0, 0.0, 0.0))
    if t == 0.0:
        return s
    s.w = d / t
    cos_y = wp.max(wp.abs(wp.dot(scene.emitter_normal[k], s.w)), 1.0e-12)
    s.pdf = light_density(tech, scene, scene.tri_emission[scene.emitter_tri[k]]) * t * t / cos_y
    s.emitter = k
    s.t = t
    return s


@wp.func
def sample_sphere_light(tech: wp.int32, scene: SceneData, sp: ShadingPoint, u: wp.vec2, j: wp.int32) -> wp.vec3:
    """A direction towards sphere light j: uniform in the cone it subtends
    (light-solid-angle; uniform over all directions from inside an inward sphere), or
    towards a uniform point of its surface (light-area, light-power)."""
    s = scene.sphere_light[j]
    c = scene.sphere_center[s]
    r = scene.sphere_radius[s]
    p64 = wp.vec3d(wp.float64(sp.p[0]), wp.float64(sp.p[1]), wp.float64(sp.p[2]))
    to_c = c - p64
    inside = wp.dot(to_c, to_c) <= r * r
    d = wp.vec3d(0.0, 0.0, 0.0)
    if tech == LIGHT_SOLID_ANGLE:
        if inside:
            d = sphere_area_point(u, wp.vec3d(0.0, 0.0, 0.0), wp.float64(1.0))  # uniform on the unit sphere
        else:
            d = cone_sample(u, wp.normalize(to_c), one_minus_cos_max(p64, c, r))
    else:
        d = sphere_area_point(u, c, r) - p64
    if wp.length_sq(d) == wp.float64(0.0):
        return wp.vec3(0.0, 0.0, 0.0)
    return into_sphere(sp.p, wp.normalize(d), c, r)


@wp.func
def sample_light(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, u: wp.vec2) -> wp.vec3:
    """A direction from a light technique (zero vector when there is nothing to sample)."""
    n_e = scene.emitter_count
    if tech == LIGHT_SOLID_ANGLE:
        total = table.total[sp.receiver]
        if total <= wp.float64(0.0):
            return wp.vec3(0.0, 0.0, 0.0)
        x = wp.float64(u[0])
        k = search_cdf_row(table.cdf, sp.receiver, scene.light_count, x)
        lo = table.cdf[sp.receiver, k]
        hi = table.cdf[sp.receiver, k + 1]
        ux = float(wp.clamp((x - lo) / wp.max(hi - lo, wp.float64(1.0e-300)), wp.float64(0.0), wp.float64(0.99999994)))
        if k >= n_e:
            return sample_sphere_light(tech, scene, sp, wp.vec2(ux, u[1]), k - n_e)
        p64 = wp.vec3d(wp.float64(sp.p[0]), wp.float64(sp.p[1]), wp.float64(sp.p[2]))
        d = square_to_spherical_triangle(wp.vec2(ux, u[1]), p64, emitter_corner64(scene, k, 0),
                                         emitter_corner64(scene, k, 1), emitter_corner64(scene, k, 2))
        return wp.normalize(wp.vec3(float(d[0]), float(d[1]), float(d[2])))
    k, uk = pick_light(tech, scene, u)
    if k >= n_e:
        return sample_sphere_light(tech, scene, sp, uk, k - n_e)
    y = square_to_triangle(uk, emitter_corner(scene, k, 0), emitter_corner(scene, k, 1), emitter_corner(scene, k, 2))
    return wp.normalize(y - sp.p)


# --------------------------------------------------------------------------- dispatch


@wp.func
def bsdf_pdf(scene: SceneData, sp: ShadingPoint, w: wp.vec3) -> float:
    """Solid-angle density of the receiver material's own BSDF sampling at ω."""
    if sp.material == PHONG_MATERIAL:
        return phong_lobe_pdf(wp.dot(w, sp.lobe_axis), sp.exponent)
    if sp.material == ROUGHCONDUCTOR:
        return conductor_pdf(sp, w)
    if sp.material == ROUGHPLASTIC:
        return plastic_pdf(scene.plastic_table, sp, w)
    return cosine_hemisphere_pdf(wp.dot(w, sp.n))


@wp.func
def sample_bsdf(scene: SceneData, sp: ShadingPoint, u: wp.vec2) -> wp.vec3:
    """The direction the receiver material's own BSDF sampling maps u to (zero if none)."""
    if sp.material == PHONG_MATERIAL:
        return to_world(square_to_phong_lobe(u, sp.exponent), sp.lobe_axis)
    if sp.material == ROUGHCONDUCTOR:
        return conductor_sample(sp, u)
    if sp.material == ROUGHPLASTIC:
        return plastic_sample(scene.plastic_table, sp, u)
    return to_world(square_to_cosine_hemisphere(u), sp.n)


@wp.func
def technique_pdf(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, w: wp.vec3) -> float:
    """Solid-angle density with which technique ``tech`` produces direction ω."""
    if tech == BSDF:
        return bsdf_pdf(scene, sp, w)
    if tech == UNIFORM:
        return uniform_hemisphere_pdf(wp.dot(w, sp.n))
    if tech == COSINE:
        return cosine_hemisphere_pdf(wp.dot(w, sp.n))
    if tech == PHONG:
        return phong_lobe_pdf(wp.dot(w, sp.lobe_axis), sp.exponent)
    if tech == ENVMAP:
        return environment_pdf(scene.environment, w)
    return light_pdf(tech, scene, table, sp, w)


@wp.func
def sample_direction(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, u: wp.vec2) -> wp.vec3:
    """The direction that technique ``tech`` maps primary sample u to (zero if none)."""
    if tech == BSDF:
        return sample_bsdf(scene, sp, u)
    if tech == UNIFORM:
        return to_world(square_to_uniform_hemisphere(u), sp.n)
    if tech == COSINE:
        return to_world(square_to_cosine_hemisphere(u), sp.n)
    if tech == PHONG:
        return to_world(square_to_phong_lobe(u, sp.exponent), sp.lobe_axis)
    if tech == ENVMAP:
        return sample_environment(scene.environment, u)
    return sample_light(tech, scene, table, sp, u)


@wp.func
def sample_technique(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, u: wp.vec2):
    """``(ω, pdf)`` for primary sample u; pdf = 0 marks a failed sample (contributes 0)."""
    w = sample_direction(tech, scene, table, sp, u)
    if wp.length_sq(w) == 0.0:
        return w, float(0.0)
    return w, technique_pdf(tech, scene, table, sp, w)


# --------------------------------------------------------------------------- light table


@wp.func
def sphere_solid_angle(scene: SceneData, p: wp.vec3d, s: wp.int32) -> wp.float64:
    """The solid angle of sphere s's front as seen from p: its cone 2π(1 − cos θmax) from
    outside an outward sphere, 4π from inside an inward one, else 0."""
    c = scene.sphere_center[s]
    r = scene.sphere_radius[s]
    to_c = c - p
    inside = wp.dot(to_c, to_c) <= r * r
    if inside and scene.sphere_inward[s] != 0:
        return wp.float64(4.0) * wp.float64(PI64)
    if not inside and scene.sphere_inward[s] == 0:
        return wp.float64(2.0) * wp.float64(PI64) * one_minus_cos_max(p, c, r)
    return wp.float64(0.0)


@wp.kernel(enable_backward=False)
def _light_table_kernel(scene: SceneData, recv: ReceiverData, cdf: wp.array2d(dtype=wp.float64),
                        total: wp.array(dtype=wp.float64)):
    r = wp.tid()
    sp = shading_point(scene, recv, r)
    p64 = wp.vec3d(wp.float64(sp.p[0]), wp.float64(sp.p[1]), wp.float64(sp.p[2]))
    acc = wp.float64(0.0)
    cdf[r, 0] = acc
    for k in range(scene.emitter_count):
        if emitter_faces(scene, k, sp.p):
            omega = triangle_solid_angle(p64, emitter_corner64(scene, k, 0), emitter_corner64(scene, k, 1),
                                         emitter_corner64(scene, k, 2))
            acc = acc + omega * wp.float64(scene.tri_emission[scene.emitter_tri[k]])
        cdf[r, k + 1] = acc
    for j in range(scene.light_count - scene.emitter_count):
        acc = acc + sphere_solid_angle(scene, p64, scene.sphere_light[j]) * wp.float64(
            scene.sphere_emission[scene.sphere_light[j]])
        cdf[r, scene.emitter_count + j + 1] = acc
    total[r] = acc
    if acc > wp.float64(0.0):
        for k in range(scene.light_count + 1):
            cdf[r, k] = cdf[r, k] / acc
        cdf[r, scene.light_count] = wp.float64(1.0)


def light_table(scene: Scene) -> LightTable:
    """The solid-angle selection table of every receiver of ``scene``, built once per
    content and device (kept with its upload, :meth:`warpis.kernels.device.DeviceScene.cached`)."""
    dev = upload(scene)
    return dev.cached("light_table", lambda: _build_light_table(dev, len(scene.receivers), scene.light_count))


def _build_light_table(dev: DeviceScene, receivers: int, emitters: int) -> LightTable:
    table = LightTable()
    table.cdf = wp.zeros((receivers, emitters + 1), dtype=wp.float64, device=dev.device)
    table.total = wp.zeros(receivers, dtype=wp.float64, device=dev.device)
    wp.launch(_light_table_kernel, dim=receivers, inputs=[dev.data, dev.receiver_data, table.cdf, table.total],
              device=dev.device)
    return table


# --------------------------------------------------------------------------- user techniques


USER_TECHNIQUES = UserEntries(TECHNIQUES, "register_technique")  # functions: (sample, pdf)


def register_technique(name: str, sample: Any, pdf: Any, *, description: str = "a user-defined technique",
                       light: bool = False, cost: float = 1.0) -> Technique:
    """Add a technique written as a Warp ``sample``/``pdf`` pair to ``TECHNIQUES`` (below).

    ``sample(sp: ShadingPoint, u: wp.vec2) -> wp.vec3`` maps a primary sample to a unit
    direction (the zero vector for no sample); ``pdf(sp: ShadingPoint, w: wp.vec3) -> float``
    is the solid-angle density with which ``sample`` produces ω, whatever ω hits.  The entry
    gets the next free code and no theory (``inverse_pdf_integral=None``).  The kernels
    that dispatch on technique codes are rebuilt for the registered set (once per set).
    """
    code = USER_TECHNIQUES.next_code(name, {"sample": sample, "pdf": pdf})
    entry = Technique(name=name, code=code, description=description, light=light,
                      inverse_pdf_integral=None, cost=cost)
    return USER_TECHNIQUES.add(entry, (sample, pdf))


def unregister_technique(name: str) -> None:
    """Remove a technique added by :func:`register_technique`."""
    USER_TECHNIQUES.remove(name)


def user_techniques() -> tuple[UserEntry, ...]:
    """The registered user techniques still in the registry, in registration order."""
    return USER_TECHNIQUES.active()


def _with_user_pdf(inner: Any, code: int, user_pdf: Any) -> Any:
    @wp.func(module="unique")
    def pdf_dispatch(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, w: wp.vec3) -> float:
        if tech == wp.static(code):
            return user_pdf(sp, w)
        return inner(tech, scene, table, sp, w)

    return pdf_dispatch


def _with_user_sample(inner: Any, code: int, user_sample: Any) -> Any:
    @wp.func(module="unique")
    def sample_dispatch(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint,
                        u: wp.vec2) -> wp.vec3:
        if tech == wp.static(code):
            return user_sample(sp, u)
        return inner(tech, scene, table, sp, u)

    return sample_dispatch


@functools.lru_cache(maxsize=None)
def dispatch(user: tuple[UserEntry, ...]) -> tuple[Any, Any]:
    """``(sample_direction, technique_pdf)`` that also know the user techniques ``user``
    (the built-in functions themselves when there are none)."""
    sample, pdf = sample_direction, technique_pdf
    for t in user:
        user_sample, user_pdf = t.functions
        sample = _with_user_sample(sample, t.code, user_sample)
        pdf = _with_user_pdf(pdf, t.code, user_pdf)
    return sample, pdf


@functools.lru_cache(maxsize=None)
def sampler(user: tuple[UserEntry, ...]) -> Any:
    """``sample_technique`` that also knows the user techniques ``user`` (itself when none)."""
    if not user:
        return sample_technique
    sample_direction, technique_pdf = dispatch(user)

    @wp.func(module="unique")
    def sample_user(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, u: wp.vec2):
        w = sample_direction(tech, scene, table, sp, u)
        if wp.length_sq(w) == 0.0:
            return w, float(0.0)
        return w, technique_pdf(tech, scene, table, sp, w)

    return sample_user


def make_numpy_kernels(sample_technique: Any, technique_pdf: Any, module: Any) -> tuple[Any, Any]:
    """The kernels behind :func:`sample_directions` and :func:`direction_pdf` over the
    dispatch ``sample_technique``/``technique_pdf``, in the Warp module ``module`` (None: this one)."""

    @wp.kernel(module=module, enable_backward=False)
    def sample_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, tech: wp.int32, r: wp.int32,
                      u: wp.array(dtype=wp.vec2), dirs: wp.array(dtype=wp.vec3), pdf: wp.array(dtype=wp.float64)):
        i = wp.tid()
        sp = shading_point(scene, recv, r)
        w, p = sample_technique(tech, scene, table, sp, u[i])
        dirs[i] = w
        pdf[i] = wp.float64(p)

    @wp.kernel(module=module, enable_backward=False)
    def pdf_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, tech: wp.int32, r: wp.int32,
                   dirs: wp.array(dtype=wp.vec3), pdf: wp.array(dtype=wp.float64)):
        i = wp.tid()
        sp = shading_point(scene, recv, r)
        pdf[i] = wp.float64(technique_pdf(tech, scene, table, sp, wp.normalize(dirs[i])))

    return sample_kernel, pdf_kernel


# The built-in pair: the same factory over the built-in dispatch, in this module.
sample_kernel, pdf_kernel = make_numpy_kernels(sample_technique, technique_pdf, None)

# With user techniques registered, the pair that knows them is built together with the
# registry's other kernels (trial, pilot, evaluate) in one Warp module, so that one
# compile serves them all; that is warpis.kernels.registered's work, a module above this
# one (it builds the trial kernel too), which hands its pair over here on import.
_registered_pair: list[Callable[[], tuple[Any, Any]]] = []


def register_numpy_kernels(pair: Callable[[], tuple[Any, Any]]) -> None:
    """Set the function ``pair() → (sample kernel, pdf kernel)`` that knows the registered
    user techniques (:mod:`warpis.kernels.registered` sets it on import)."""
    _registered_pair[:] = [pair]


def _numpy_kernels() -> tuple[Any, Any]:
    if not user_techniques():
        return sample_kernel, pdf_kernel
    if not _registered_pair:
        raise WarpisError("user techniques: the kernels that know them are built by warpis.kernels.registered, "
                          "which is not imported (import warpis)")
    return _registered_pair[0]()


def check_lights(scene: Scene, techniques: Sequence[str], estimates_f: bool = True) -> None:
    """A one-line error unless ``scene`` has what each technique samples (emitter triangles
    for the light techniques, an environment for ``envmap``) and, for an estimator of F
    (``estimates_f``), the set reaches all of its light: light techniques alone never see
    an environment, nor envmap alone the emitter triangles (where the map is dark behind
    them), so either alone would estimate part of F and print it as F."""
    entries = [TECHNIQUES.lookup(name) for name in techniques]
    for tech in entries:
        if tech.light and scene.light_count == 0:
            raise WarpisError(f"technique {tech.name}: scene {scene.name!r} has no emitter triangle or sphere light "
                              f"(it is lit by its environment alone): sample it with envmap or a BSDF technique")
        if tech.environment and scene.environment is None:
            raise WarpisError(f"technique {tech.name}: scene {scene.name!r} has no environment light")
    names = "+".join(techniques)
    if not estimates_f:
        return
    if scene.environment is not None and entries and all(t.light for t in entries):
        raise WarpisError(f"techniques {names} sample the emitter triangles only and miss the environment light of "
                          f"scene {scene.name!r}: add envmap or a BSDF technique")
    if scene.light_count and entries and all(t.environment for t in entries):
        raise WarpisError(f"technique {names} samples the environment only and misses the emitter triangles of "
                          f"scene {scene.name!r}: add a light or a BSDF technique")


def sample_directions(scene: Scene, receiver: int, technique: str, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map primary samples ``u`` (K, 2) through a technique at one receiver.

    Returns
    -------
    directions : (K, 3) float32 unit vectors (zero rows where the technique had nothing to sample)
    pdf : (K,) float64 solid-angle densities (0 for failed samples)
    """
    check_lights(scene, [technique], estimates_f=False)
    up = upload(scene)  # held until the launch is done: the struct knows its mesh by id only
    dev = up.device
    uu = wp.array(np.ascontiguousarray(u, dtype=np.float32), dtype=wp.vec2, device=dev)
    dirs = wp.zeros(len(u), dtype=wp.vec3, device=dev)
    pdf = wp.zeros(len(u), dtype=wp.float64, device=dev)
    wp.launch(_numpy_kernels()[0], dim=len(u), device=dev,
              inputs=[up.data, up.receiver_data, light_table(scene), TECHNIQUES.lookup(technique).code, receiver,
                      uu, dirs, pdf])
    return dirs.numpy(), pdf.numpy()


def direction_pdf(scene: Scene, receiver: int, technique: str, directions: np.ndarray) -> np.ndarray:
    """Solid-angle density of ``technique`` at each of ``directions`` (K, 3) → (K,)."""
    check_lights(scene, [technique], estimates_f=False)
    up = upload(scene)
    dev = up.device
    dirs = wp.array(np.ascontiguousarray(directions, dtype=np.float32), dtype=wp.vec3, device=dev)
    pdf = wp.zeros(len(directions), dtype=wp.float64, device=dev)
    wp.launch(_numpy_kernels()[1], dim=len(directions), device=dev,
              inputs=[up.data, up.receiver_data, light_table(scene), TECHNIQUES.lookup(technique).code, receiver,
                      dirs, pdf])
    return pdf.numpy()
