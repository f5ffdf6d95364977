"""The shading point: a receiver as the techniques, the materials and the integrand see it.

Its own module because both the integrand (:mod:`.integrand`) and the material models
(:mod:`.microfacet`) read it, and the integrand calls the material models.

Colour: warpis is monochrome, but a conductor's Fresnel term differs per colour channel
and is not linear in its parameters, so a microfacet receiver keeps three channels of
``eta``, ``k`` and ``specular``: the specular term is Σ_c specular_c · F(cos; eta_c, k_c)
× D G / (4 cos θi cos θo), where ``specular_c`` already holds the channel's weight in the
chosen output (luminance weights for Y; (1, 0, 0) for r; …).  A scene without colour
splits its scalar specular reflectance evenly over the three equal channels.
"""

from __future__ import annotations

import warp as wp

from ..vocabulary import DISTRIBUTIONS
from .warps import frame

# Microfacet distributions, numbered as Mitsuba 3 numbers them (MicrofacetType).
BECKMANN = wp.constant(DISTRIBUTIONS["beckmann"])
GGX = wp.constant(DISTRIBUTIONS["ggx"])


@wp.struct
class ShadingPoint:
    """A receiver as the techniques and the integrand see it."""

    receiver: wp.int32
    p: wp.vec3  # the receiver x: every direction is from here
    n: wp.vec3  # the shading normal: the BSDF's frame and its cosine
    ng: wp.vec3  # the surface's own normal: the side rays leave from, its plane, the slab
    slab: float  # self-hit slab height above the tangent plane
    material: wp.int32
    albedo: float  # lambert/phong albedo; roughplastic's diffuse reflectance
    exponent: float  # phong
    wi: wp.vec3  # unit direction towards the viewer
    t: wp.vec3  # tangent frame (t, b, n) of warps.frame: set by with_frame
    b: wp.vec3
    wi_local: wp.vec3  # wi in that frame
    lobe_axis: wp.vec3  # mirror direction of the view about n (Phong)
    # Microfacet materials (roughconductor, roughplastic).
    alpha: float  # isotropic roughness
    distribution: wp.int32  # BECKMANN or GGX
    sample_visible: wp.int32  # 1: sample visible normals (Heitz 2018), 0: the full distribution
    eta: wp.vec3  # conductor: per channel; roughplastic: int_ior / ext_ior in every channel
    k: wp.vec3  # conductor's extinction per channel (0 for roughplastic)
    specular: wp.vec3  # specular reflectance × the channel's output weight
    specular_weight: float  # roughplastic: Mitsuba's specular_sampling_weight
    plastic_row: wp.int32  # roughplastic: row of SceneData.plastic_table, else -1


@wp.func
def with_frame(sp: ShadingPoint) -> ShadingPoint:
    """``sp`` with its tangent frame about n and the view in it: computed once per shading
    point (a trial), not in every sample and pdf of a microfacet material."""
    t, b = frame(sp.n)
    sp.t = t
    sp.b = b
    sp.wi_local = wp.vec3(wp.dot(sp.wi, t), wp.dot(sp.wi, b), wp.dot(sp.wi, sp.n))
    return sp


@wp.func
def to_shading(sp: ShadingPoint, v: wp.vec3) -> wp.vec3:
    """World ``v`` in the shading point's frame (z along n)."""
    return wp.vec3(wp.dot(v, sp.t), wp.dot(v, sp.b), wp.dot(v, sp.n))


@wp.func
def from_shading(sp: ShadingPoint, v: wp.vec3) -> wp.vec3:
    """Inverse of :func:`to_shading`."""
    return v[0] * sp.t + v[1] * sp.b + v[2] * sp.n
