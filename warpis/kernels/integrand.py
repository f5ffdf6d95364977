"""The direct-illumination integrand f(ω) at a receiver, as a Warp function.

``f(ω) = Le(ω) · ρ(ω) · max(0, n·ω)``, where Le is the radiance of the front face of
the first triangle the ray (p, ω) hits (0 for a non-emitter or a back face: one-sided
emission, which is also how visibility V enters), and ρ is 1 (irradiance), albedo/π
(lambert) or the energy-normalised Phong lobe albedo·(e+2)/(2π)·max(0, cos α)^e about
the mirror direction of the view.

Ray origin: warpis integrates F at the receiver x itself.  Sampling, pdfs and f all
refer to directions from x.  Receivers sit exactly on their surface, and Warp's mesh
query accepts hits at t ≥ 0 with no t_min, so a ray from x could hit the surface it
starts on.  The ray along ω therefore starts at x + (δ / n·ω)·ω: the same ray, with the
part below height δ over the receiver's tangent plane skipped, δ = the receiver's
self-hit slab (``SELF_HIT_SLAB`` × the float32 magnitude of the coordinates around x,
see device.py).  Nothing depends on the scene's size: scaling a scene, or adding a huge
floor far away, leaves F unchanged.  Only geometry inside that slab is ignored, which
changes F by a second-order amount (docs/theory.md, "The integrand at a receiver").
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ..vocabulary import Material, Registry
from .device import ReceiverData, SceneData, upload
from .warps import INV_2PI, INV_PI

if TYPE_CHECKING:  # annotations only: scenes import the kernels' registries
    from ..scenes import Scene


def _unit_rho(albedo: np.ndarray) -> np.ndarray:
    return np.ones_like(albedo)


def _albedo_over_pi(albedo: np.ndarray) -> np.ndarray:
    return albedo / np.pi



MATERIALS: Registry[Material] = Registry("material", [
    Material(name="irradiance", code=0, description="ρ = 1: F is the irradiance", diffuse=True,
             lambert_scale=_unit_rho, bsdf_technique="cosine"),
    Material(name="lambert", code=1, description="diffuse, ρ = albedo/π", keys=("albedo",), diffuse=True,
             lambert_scale=_albedo_over_pi, bsdf_technique="cosine"),
    # A Phong lobe is normalised so that ∫ ρ cos θ dω ≈ albedo: albedo/π × Lambert's value
    # gives F's scale (reference.py's floor), though not F.
    Material(name="phong", code=2, description="energy-normalised Phong lobe albedo·(e+2)/(2π)·cos^e α about the "
                                               "view's mirror direction",
             keys=("albedo", "exponent", "view"), required=("exponent", "view"), diffuse=False,
             lambert_scale=_albedo_over_pi, bsdf_technique="phong"),
])


# The kernels' material codes, from the registry (vocabulary.MATERIALS).
IRRADIANCE = wp.constant(MATERIALS["irradiance"].code)
LAMBERT = wp.constant(MATERIALS["lambert"].code)
PHONG = wp.constant(MATERIALS["phong"].code)
FAR = wp.constant(1.0e30)


@wp.struct
class ShadingPoint:
    """A receiver as the techniques and the integrand see it."""

    receiver: wp.int32
    p: wp.vec3  # the receiver x: every direction is from here
    n: wp.vec3
    slab: float  # self-hit slab height above the tangent plane
    material: wp.int32
    albedo: float
    exponent: float
    lobe_axis: wp.vec3  # mirror direction of the view about n (Phong)


@wp.func
def shading_point(scene: SceneData, recv: ReceiverData, r: wp.int32) -> ShadingPoint:
    """The shading point of receiver ``r``."""
    sp = ShadingPoint()
    n = recv.normal[r]
    v = recv.view[r]
    sp.receiver = r
    sp.p = recv.position[r]
    sp.n = n
    sp.slab = recv.slab[r]
    sp.material = recv.material[r]
    sp.albedo = recv.albedo[r]
    sp.exponent = recv.exponent[r]
    sp.lobe_axis = wp.normalize(2.0 * wp.dot(n, v) * n - v)
    return sp


@wp.func
def brdf(sp: ShadingPoint, w: wp.vec3) -> float:
    """ρ(ω) of the receiver's material (1 for irradiance)."""
    if sp.material == LAMBERT:
        return sp.albedo * INV_PI
    if sp.material == PHONG:
        c = wp.dot(w, sp.lobe_axis)
        if c <= 0.0:
            return 0.0
        return sp.albedo * (sp.exponent + 2.0) * INV_2PI * wp.pow(c, sp.exponent)
    return 1.0


@wp.func
def incident_radiance(scene: SceneData, p: wp.vec3, w: wp.vec3) -> float:
    """Le of the first surface the ray (p, ω) hits: its front-face radiance, else 0."""
    q = wp.mesh_query_ray(scene.mesh, p, w, FAR)
    if not q.result:
        return 0.0
    if q.sign <= 0.0:  # back face: emission is one-sided
        return 0.0
    return scene.tri_emission[q.face]


@wp.func
def integrand(scene: SceneData, sp: ShadingPoint, w: wp.vec3) -> float:
    """f(ω) = Le(ω) · ρ(ω) · max(0, n·ω) at the shading point (one shadow ray)."""
    cos_n = wp.dot(sp.n, w)
    if cos_n <= 0.0:
        return 0.0
    rho = brdf(sp, w)
    if rho == 0.0:
        return 0.0
    # Start the ray where it leaves the self-hit slab: the same ray from x, so no
    # direction, pdf or solid angle moves (see the module docstring).
    return incident_radiance(scene, sp.p + w * (sp.slab / cos_n), w) * rho * cos_n


@wp.kernel
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
