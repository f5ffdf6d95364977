"""The direct-illumination integrand f(ω) at a receiver, as a Warp function.

``f(ω) = Le(ω) · ρ(ω) · max(0, n·ω)``, where Le is the radiance of the front face of
the first surface the ray (p, ω) hits, a triangle or an analytic sphere (:mod:`.spheres`)
(0 for a non-emitter or a back face: one-sided
emission, which is also how visibility V enters), and ρ is 1 (irradiance), albedo/π
(lambert), the energy-normalised Phong lobe albedo·(e+2)/(2π)·max(0, cos α)^e about
the mirror direction of the view, or one of Mitsuba 3's microfacet BSDFs (roughconductor,
roughplastic; :mod:`.microfacet`) divided by its cosine factor.

A ray that hits nothing sees the scene's environment light, if it has one (Mitsuba's
envmap lookup, :mod:`.environment`), else nothing.

How a value is found: only emitters have Le > 0, so the first triangle the ray hits
matters only if it is an emitter, and then it is the nearest emitter the ray crosses.
With an environment every ray that crosses no emitter may still bring light, so f asks
one closest-hit query instead.
f therefore takes the nearest crossing with an emitter triangle (a loop over them, or
their own small BVH: :mod:`.emitters`), and f = 0 at once when there is none or it is a
back face; else one shadow ray, an any-hit query (:mod:`.bvh`) over the segment up to
that crossing, says whether anything blocks it.  Most BSDF samples miss every emitter
and cast no ray at all; a light sample on a planar emitter set knows its crossing (the
point it sampled) and casts only the shadow ray.

Ray ends: warpis integrates F at the receiver x itself.  Sampling, pdfs and f all
refer to directions from x.  Receivers sit exactly on their surface, and a ray from x
could hit the surface it starts on.  Two rules keep it off:

* A hit on a triangle whose plane holds x (to float32 rounding) is ignored (bvh.py): a
  ray that starts on a plane crosses it nowhere else, so such a hit is always rounding.
  The receiver's own triangle, its coplanar neighbours and a huge floor under it are
  never hit, however large their coordinates.
* The segment starts at x + (δ / n·ω)·ω: the part below height δ over the receiver's
  tangent plane is skipped, δ = the receiver's self-hit slab, ``SELF_HIT_SLAB`` × the
  float32 magnitude of x and of the triangles that touch x but bend away from its plane
  (device.py).  Emitter crossings within that slab are not seen either.  Where a huge
  bent surface would make δ hide real geometry, the upload refuses the receiver.

At the other end the same two rules hold for the emitter point y: hits in a plane
through y are ignored, and the segment stops δ_y / |cos θ_y| before y, δ_y from the
magnitudes of y and of the emitter's bent neighbours, so the emitter cannot block its
own light.  Nothing depends on the scene's size: scaling a scene, or adding a huge
floor beneath, leaves F unchanged.  Only geometry inside those slabs is ignored, which
changes F by a second-order amount (docs/theory.md, "The integrand at a receiver").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from ..vocabulary import MATERIALS
from .bvh import SELF_HIT, any_hit_between, closest_hit_from
from .device import ReceiverData, SceneData, upload
from .emitters import nearest_emitter
from .spheres import nearest_sphere, spheres_block
from .environment import environment_radiance
from .microfacet import conductor_brdf, plastic_brdf
from .precompiled import compile_portably
from .shading import ShadingPoint, with_frame
from .warps import INV_2PI, INV_PI

compile_portably(__name__)  # shipped compiled: precompiled.py says why portably

if TYPE_CHECKING:  # annotations only: scenes import the kernels' registries
    from ..scenes import Scene

__all__ = ["MATERIALS", "ShadingPoint", "brdf", "delta_terms", "evaluate_integrand", "integrand", "shading_point"]


# The kernels' material codes, from the registry (vocabulary.MATERIALS).
IRRADIANCE = wp.constant(MATERIALS["irradiance"].code)
LAMBERT = wp.constant(MATERIALS["lambert"].code)
PHONG = wp.constant(MATERIALS["phong"].code)
ROUGHCONDUCTOR = wp.constant(MATERIALS["roughconductor"].code)
ROUGHPLASTIC = wp.constant(MATERIALS["roughplastic"].code)
FAR = wp.constant(1.0e30)


@wp.func
def shading_point(scene: SceneData, recv: ReceiverData, r: wp.int32) -> ShadingPoint:
    """The shading point of receiver ``r``."""
    sp = ShadingPoint()
    n = recv.normal[r]
    v = recv.view[r]
    sp.receiver = r
    sp.p = recv.position[r]
    sp.n = n
    sp.ng = recv.geometric[r]
    sp.slab = recv.slab[r]
    sp.material = recv.material[r]
    sp.albedo = recv.albedo[r]
    sp.exponent = recv.exponent[r]
    sp.wi = v
    sp.lobe_axis = wp.normalize(2.0 * wp.dot(n, v) * n - v)
    sp.alpha = recv.alpha[r]
    sp.distribution = recv.distribution[r]
    sp.sample_visible = recv.sample_visible[r]
    sp.eta = recv.eta[r]
    sp.k = recv.k[r]
    sp.specular = recv.specular[r]
    sp.specular_weight = recv.specular_weight[r]
    sp.plastic_row = recv.plastic_row[r]
    return with_frame(sp)


@wp.func
def brdf(scene: SceneData, sp: ShadingPoint, w: wp.vec3) -> float:
    """ρ(ω) of the receiver's material (1 for irradiance)."""
    if sp.material == LAMBERT:
        return sp.albedo * INV_PI
    if sp.material == PHONG:
        c = wp.dot(w, sp.lobe_axis)
        if c <= 0.0:
            return 0.0
        return sp.albedo * (sp.exponent + 2.0) * INV_2PI * wp.pow(c, sp.exponent)
    if sp.material == ROUGHCONDUCTOR:
        return conductor_brdf(sp, w)
    if sp.material == ROUGHPLASTIC:
        return plastic_brdf(scene.plastic_table, sp, w)
    return 1.0


@wp.func
def radiance_unless_blocked(scene: SceneData, p: wp.vec3, n: wp.vec3, w: wp.vec3, lead: float, k: wp.int32,
                            t: float) -> float:
    """Le of emitter triangle k, which the ray (p, ω) crosses at distance t before any other
    emitter, unless another triangle blocks the way: one shadow ray (an any-hit query)
    from where the ray leaves the receiver's slab (``lead``) to where it enters the
    emitter's own slab (see the module docstring)."""
    cos_y = wp.abs(wp.dot(scene.emitter_normal[k], w))
    y = p + t * w
    y_slab = SELF_HIT * wp.max(wp.max(wp.abs(y[0]), wp.abs(y[1])), wp.abs(y[2]))
    tail = wp.max(scene.emitter_slab[k], y_slab) / wp.max(cos_y, 1.0e-12)
    length = t - lead - tail
    # Hits in a plane through p or y (the receiver's own surface, the emitter's) are rounding.
    if length > 0.0 and any_hit_between(scene.bvh, scene.mesh, p, n, y, scene.emitter_normal[k], p + lead * w, w,
                                         length):
        return 0.0
    if length > 0.0 and spheres_block(scene, p, w, lead, t - tail, -1):
        return 0.0
    return scene.tri_emission[scene.emitter_tri[k]]


@wp.func
def radiance_beyond(scene: SceneData, p: wp.vec3, n: wp.vec3, w: wp.vec3, lead: float) -> float:
    """Le of the first surface the ray (p, ω) hits beyond distance ``lead``: the front-face
    radiance of the nearest emitter it crosses there, unless something blocks the way;
    0 when it crosses no emitter or the nearest one's back face (emission is one-sided)."""
    hit = nearest_emitter(scene, p, w, lead)
    if hit.k < 0 or hit.front == 0:
        return 0.0
    return radiance_unless_blocked(scene, p, n, w, lead, hit.k, hit.t)


@wp.func
def incident_radiance(scene: SceneData, p: wp.vec3, w: wp.vec3) -> float:
    """Le of the first surface the ray (p, ω) hits: its front-face radiance, else 0.

    On a planar emitter set the nearest emitter crossing and a shadow ray answer (most
    directions cross no emitter and cast no ray); elsewhere one closest-hit query, which
    for sphere lights and emitters in several planes costs less than finding the nearest
    crossing among many emitter triangles first."""
    if scene.planar_emitters != 0 and scene.environment.present == 0:
        return radiance_beyond(scene, p, wp.vec3(0.0), w, 0.0)  # p is on no surface: no plane of its own
    return closest_radiance(scene, p, wp.vec3(0.0), w, 0.0)


@wp.func
def closest_radiance(scene: SceneData, p: wp.vec3, n: wp.vec3, w: wp.vec3, lead: float) -> float:
    """Le of the first surface the ray (p, ω) hits beyond distance ``lead``, from one
    closest-hit query (hits on the plane through p of normal n are rounding, and are
    ignored; n = 0 for a p on no surface); the environment's radiance if it hits none."""
    # The nearest sphere crossing first: it bounds the triangle query, and it is what the
    # ray sees unless a triangle comes before it: its emission if the ray meets the
    # sphere's front (the near root meets the outside, spheres.py), else 0.
    ball = nearest_sphere(scene, p, w, lead, FAR)
    hit = closest_hit_from(scene.bvh, scene.mesh, p, n, p + lead * w, w, wp.where(ball.s >= 0, ball.t - lead, FAR))
    if hit.face < 0 and ball.s >= 0:
        if ball.front == 0:
            return 0.0
        return scene.sphere_emission[ball.s]
    if hit.face < 0:  # the ray leaves the scene
        return environment_radiance(scene.environment, w)
    if hit.sign <= 0.0:  # a back face: emission is one-sided
        return 0.0
    return scene.tri_emission[hit.face]


@wp.func
def integrand_via(scene: SceneData, sp: ShadingPoint, w: wp.vec3, known: wp.int32, known_t: float) -> float:
    """f(ω) = Le(ω) · ρ(ω) · max(0, n·ω), where the ray from the receiver is known to cross
    emitter triangle ``known`` at distance ``known_t`` before any other emitter (a light
    sample on a planar emitter set), or ``known`` = −1: the nearest emitter crossing is
    looked up.  One shadow ray at most, and none when the ray crosses no emitter."""
    cos_n = wp.dot(sp.n, w)
    if cos_n <= 0.0:
        return 0.0
    # Geometry within the receiver's slab is not seen (see the module docstring).  The slab
    # lies along the surface's own normal, which a shading normal may tilt from: a ray may
    # leave through the back of the surface, as in Mitsuba, and its height is |ng·ω|.
    lead = sp.slab / wp.max(wp.abs(wp.dot(sp.ng, w)), 1.0e-12)
    microfacet = sp.material == ROUGHCONDUCTOR or sp.material == ROUGHPLASTIC
    rho = float(1.0)
    if not microfacet:
        # Phong's ρ is cheap and often 0 (outside its lobe): it goes first and saves the ray.
        rho = brdf(scene, sp, w)
        if rho == 0.0:
            return 0.0
    # One call site per query: each is inlined wherever f is, and the trial kernel has f
    # in several places.
    le = float(0.0)
    # With an environment, a ray that crosses no emitter may still bring light: one
    # closest-hit query says what it sees.
    if known < 0 and (scene.planar_emitters == 0 or scene.environment.present != 0):
        le = closest_radiance(scene, sp.p, sp.ng, w, lead)
    else:
        k = known
        t = known_t
        if k < 0:
            hit = nearest_emitter(scene, sp.p, w, lead)
            k = hit.k
            t = hit.t
        # Light arrives from the front face of an emitter beyond the slab: one-sided emission.
        if k >= 0 and t > lead and wp.dot(scene.emitter_normal[k], w) < 0.0:
            le = radiance_unless_blocked(scene, sp.p, sp.ng, w, lead, k, t)
    if le == 0.0:
        return 0.0
    if microfacet:
        # A microfacet ρ costs more than finding the emitter and casting the shadow ray,
        # and most of its own samples see no emitter: it comes last.
        rho = brdf(scene, sp, w)
    return le * rho * cos_n


@wp.func
def integrand(scene: SceneData, sp: ShadingPoint, w: wp.vec3) -> float:
    """f(ω) = Le(ω) · ρ(ω) · max(0, n·ω) at the shading point."""
    return integrand_via(scene, sp, w, -1, 0.0)


@wp.func
def delta_term(scene: SceneData, sp: ShadingPoint, w: wp.vec3, t: float, e: float) -> float:
    """One delta light's term E · ρ(ω) · max(0, n·ω) · V at the shading point: the light is
    at distance t along ω (t ≥ FAR: a directional light, the ray must leave the scene)
    and casts irradiance E on a surface facing it (scenes/delta.py).  The shadow ray
    follows f's rules: it leaves the receiver's slab and ignores its plane; a point
    light lies on no surface, so its end keeps only the slab of its own magnitude."""
    cos_n = wp.dot(sp.n, w)
    if cos_n <= 0.0 or e <= 0.0:
        return 0.0
    rho = brdf(scene, sp, w)
    if rho == 0.0:
        return 0.0
    lead = sp.slab / wp.max(wp.abs(wp.dot(sp.ng, w)), 1.0e-12)
    length = FAR
    if t < FAR:
        y = sp.p + t * w
        length = t - lead - SELF_HIT * wp.max(wp.max(wp.abs(y[0]), wp.abs(y[1])), wp.abs(y[2]))
    if length > 0.0 and any_hit_between(scene.bvh, scene.mesh, sp.p, sp.ng, sp.p, sp.ng, sp.p + lead * w, w, length):
        return 0.0
    if length > 0.0 and spheres_block(scene, sp.p, w, lead, lead + length, -1):
        return 0.0
    return e * rho * cos_n


@wp.kernel(enable_backward=False)
def _delta_kernel(scene: SceneData, recv: ReceiverData, dirs: wp.array2d(dtype=wp.vec3),
                  dist: wp.array2d(dtype=wp.float32), irr: wp.array2d(dtype=wp.float32),
                  out: wp.array(dtype=wp.float64)):
    r = wp.tid()
    sp = shading_point(scene, recv, r)
    total = wp.float64(0.0)
    for k in range(dirs.shape[1]):
        total += wp.float64(delta_term(scene, sp, wp.normalize(dirs[r, k]), dist[r, k], irr[r, k]))
    out[r] = total


def delta_terms(scene: Scene) -> np.ndarray:
    """(R,) the exact term of the scene's delta lights at each receiver, Σ_l E_l ρ cos V
    (zeros without delta lights); computed once per upload, read-only."""
    up = upload(scene)
    return up.cached("delta_terms", lambda: _delta_terms(scene, up))


def _delta_terms(scene: Scene, up: Any) -> np.ndarray:
    delta = scene.delta_lights
    count = len(scene.receivers)
    if delta is None or len(delta) == 0:
        out = np.zeros(count)
    else:
        dev = up.device
        dist = np.where(np.isinf(delta.distances), 2.0 * float(FAR), delta.distances)
        dirs = wp.array(delta.directions.astype(np.float32), dtype=wp.vec3, device=dev)
        d = wp.array(dist.astype(np.float32), dtype=wp.float32, device=dev)
        e = wp.array(delta.irradiance.astype(np.float32), dtype=wp.float32, device=dev)
        res = wp.zeros(count, dtype=wp.float64, device=dev)
        wp.launch(_delta_kernel, dim=count, inputs=[up.data, up.receiver_data, dirs, d, e, res], device=dev)
        out = res.numpy()
    out.flags.writeable = False
    return out


@wp.kernel(enable_backward=False)
def _integrand_kernel(scene: SceneData, recv: ReceiverData, r: wp.int32,
                      dirs: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    sp = shading_point(scene, recv, r)
    out[i] = wp.float64(integrand(scene, sp, wp.normalize(dirs[i])))


def evaluate_integrand(scene: Scene, receiver: int, directions: np.ndarray) -> np.ndarray:
    """f at receiver ``receiver`` for each row of ``directions`` (K, 3) → (K,) float64."""
    up = upload(scene)  # held until the launch is done: the struct knows its mesh by id only
    dirs = wp.array(np.ascontiguousarray(directions, dtype=np.float32), dtype=wp.vec3, device=up.device)
    out = wp.zeros(len(directions), dtype=wp.float64, device=up.device)
    wp.launch(_integrand_kernel, dim=len(directions), inputs=[up.data, up.receiver_data, receiver, dirs, out],
              device=up.device)
    return out.numpy()
