"""The direct-illumination integrand f(ω) at a receiver, as a Warp function.

``f(ω) = Le(ω) · ρ(ω) · max(0, n·ω)``, where Le is the radiance of the front face of
the first triangle the ray (p, ω) hits (0 for a non-emitter or a back face: one-sided
emission, which is also how visibility V enters), and ρ is 1 (irradiance), albedo/π
(lambert), the energy-normalised Phong lobe albedo·(e+2)/(2π)·max(0, cos α)^e about
the mirror direction of the view, or one of Mitsuba 3's microfacet BSDFs (roughconductor,
roughplastic; :mod:`.microfacet`) divided by its cosine factor.

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
from .microfacet import conductor_brdf, plastic_brdf
from .shading import ShadingPoint, with_frame
from .warps import INV_2PI, INV_PI

if TYPE_CHECKING:  # annotations only: scenes import the kernels' registries
    from ..scenes import Scene
    from ..scenes.description import Receivers

__all__ = ["MATERIALS", "ShadingPoint", "brdf", "evaluate_integrand", "integrand", "shading_point"]


def _unit_rho(rx: Receivers, rows: np.ndarray) -> np.ndarray:
    return np.ones(len(rows))


def _albedo_over_pi(rx: Receivers, rows: np.ndarray) -> np.ndarray:
    return rx.albedo[rows] / np.pi


def _specular_over_pi(rx: Receivers, rows: np.ndarray) -> np.ndarray:
    return rx.specular[rows].sum(axis=1) / np.pi


def _diffuse_and_specular_over_pi(rx: Receivers, rows: np.ndarray) -> np.ndarray:
    return (rx.albedo[rows] + rx.specular[rows].sum(axis=1)) / np.pi


MICROFACET_KEYS = ("alpha", "distribution", "sample_visible", "eta", "specular", "view")

MATERIALS: Registry[Material] = Registry("material", [
    Material(name="irradiance", code=0, description="ρ = 1: F is the irradiance", diffuse=True,
             lambert_scale=_unit_rho, bsdf_technique="cosine"),
    Material(name="lambert", code=1, description="diffuse, ρ = albedo/π", keys=("albedo",), diffuse=True,
             lambert_scale=_albedo_over_pi, bsdf_technique="cosine"),
    # A Phong lobe is normalised so that ∫ ρ cos θ dω ≈ albedo: albedo/π × Lambert's value
    # gives F's scale (reference.py's floor), though not F.  Likewise the microfacet
    # materials' reflectances over π.
    Material(name="phong", code=2, description="energy-normalised Phong lobe albedo·(e+2)/(2π)·cos^e α about the "
                                               "view's mirror direction",
             keys=("albedo", "exponent", "view"), required=("exponent", "view"), diffuse=False,
             lambert_scale=_albedo_over_pi, bsdf_technique="phong"),
    Material(name="roughconductor", code=3, description="Mitsuba 3's roughconductor: a GGX or Beckmann microfacet "
                                                        "lobe with the conductor's Fresnel term",
             keys=(*MICROFACET_KEYS, "k"), required=("alpha", "eta", "k", "view"), diffuse=False,
             lambert_scale=_specular_over_pi, bsdf_technique="bsdf"),
    Material(name="roughplastic", code=4, description="Mitsuba 3's roughplastic: a dielectric microfacet coating over "
                                                      "a diffuse base, with its internal scattering",
             keys=(*MICROFACET_KEYS, "albedo"), required=("alpha", "view"), diffuse=False,
             lambert_scale=_diffuse_and_specular_over_pi, bsdf_technique="bsdf"),
])


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
    # Start the ray where it leaves the self-hit slab: the same ray from x, so no
    # direction, pdf or solid angle moves (see the module docstring).
    origin = sp.p + w * (sp.slab / cos_n)
    if sp.material == ROUGHCONDUCTOR or sp.material == ROUGHPLASTIC:
        # A microfacet ρ costs more than the ray, and most of its own samples see no
        # emitter: cast first, evaluate ρ only where light arrives.
        le = incident_radiance(scene, origin, w)
        if le == 0.0:
            return 0.0
        return le * brdf(scene, sp, w) * cos_n
    # Phong's ρ is cheap and often 0 (outside its lobe): it goes first and saves the ray.
    rho = brdf(scene, sp, w)
    if rho == 0.0:
        return 0.0
    return incident_radiance(scene, origin, w) * rho * cos_n


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
