"""Mitsuba 3's ``roughconductor`` and ``roughplastic`` BSDFs (isotropic α) as Warp functions.

warpis follows Mitsuba 3 (``include/mitsuba/render/microfacet.h``, ``fresnel.h`` and the
two plugins) formula for formula, so that a warpis variance is the variance of the
estimator that Mitsuba itself would run; the one deliberate exception is the pdf of
Beckmann's visible normals (below), which is the density that the sampler draws:

* **Distributions** (``MicrofacetDistribution::eval``).  GGX (Trowbridge–Reitz; Walter
  et al. 2007, "Microfacet Models for Refraction through Rough Surfaces", eq. 33)
  D(m) = 1 / (π α² (tan²θm/α² + 1)² cos⁴θm), written as 1/(π α² ((x²+y²)/α² + z²)²);
  Beckmann (Walter et al. eq. 25) D(m) = exp(−tan²θm/α²) / (π α² cos⁴θm).  As in
  Mitsuba, D is set to 0 where D·cos θm ≤ 1e-20, and α is clamped to ≥ 1e-4.
* **Masking** (``smith_g1``, ``G``).  Smith's G1 for GGX, 2/(1 + sqrt(1 + α² tan²θ))
  (Walter et al. eq. 34); for Beckmann, Walter et al.'s rational approximation (eq. 27)
  of the erf form, as Mitsuba uses it (relative error < 0.35 %, exactly 1 for
  a = 1/(α tan θ) ≥ 1.6).  G1 = 0 when v·m and v·n differ in sign; G = G1(wi) G1(wo)
  (separable).
* **Sampling the normal** (``sample``).  Visible normals (Heitz & d'Eon 2014, "Importance
  Sampling Microfacet-Based BSDFs using the Distribution of Visible Normals"): stretch
  wi by α, sample slopes for α = 1, rotate and unstretch.  The α = 1 slopes are Heitz's
  projection of a disk onto the visible hemisphere for GGX ("A Simpler and Exact
  Sampling Routine for the GGX Distribution of Visible Normals", 2017; Heitz 2018,
  "Sampling the GGX Distribution of Visible Normals", JCGT 7(4)) and Jakob's numerical
  inversion for Beckmann (three Newton steps in the erf domain, "An Improved Visible
  Normal Sampling Routine for the Beckmann Distribution", 2014).  The normal's density is
  the one the sampler draws, D(m) G1(wi, m) |wi·m| / cos θi with Smith's exact
  G1(wi) = 1/(1 + Λ(wi)) (:func:`visible_g1`).  For GGX that is Mitsuba's pdf.  For
  Beckmann the sampler inverts the exact (erf) distribution of visible normals,
  Λ(a) = (erf(a) − 1)/2 + exp(−a²)/(2a√π), a = 1/(α tan θi), while Mitsuba's pdf carries
  the rational G1 in place of 1/(1 + Λ); so warpis's pdf differs from Mitsuba's, on
  purpose, by the constant factor exact/fit G1(wi) per view, between 0.99688
  (a ≈ 1.34) and 1.00296 (a ≈ 0.56), 1 at normal incidence and within 1e-6 of 1 for
  a ≥ 3.  With Mitsuba's pdf, f/pdf would be biased by the inverse factor (up to
  0.31 %) and ∫pdf could reach 1.003.  The sampler's three Newton steps draw that exact
  density to within 3e-6 in the CDF of the slope (in float64 and in float32; the local
  density is off by more than 1e-4 only in the tail of slopes near cot θi, under 0.6 %
  of the samples).  f keeps Mitsuba's rational G1, in G = G1(wi) G1(wo): f is
  Mitsuba's integrand, the pdf is the sampler's.  Full distribution: the inverse CDF of
  D(m) cos θm, whose density is D(m) cos θm.
* **Reflection** (the plugins).  wo = 2 (wi·m) m − wi, of solid-angle density
  p(m) / (4 wo·m).  Mitsuba's ``pdf`` writes the visible-normal case as
  D(h) G1(wi, h) / (4 cos θi), the same value since wi·h = wo·h for h = (wi+wo)/|wi+wo|
  (warpis: with the G1 of :func:`visible_g1`).
  A sample with wo below the horizon, or with density 0, is a failed sample; the pdf of
  the valid directions is *not* renormalised, so it integrates to the probability of a
  valid sample.  (Mitsuba's roughconductor tests the density of the sampled normal;
  warpis tests the pdf at the returned direction, so that a direction it returns never
  has pdf 0.  The two differ only where rounding puts them on either side of 0.)
* **Fresnel** (``fresnel.h``).  ``fresnel_conductor`` (after K. D. Moeller, "Optics",
  1988) with complex index eta + i k, per colour channel; ``fresnel`` (dielectric,
  unpolarised) for roughplastic.

warpis's ρ is Mitsuba's ``eval`` divided by cos θo (Mitsuba's eval includes the cosine
factor).  Colour (see :mod:`.shading`): the conductor's specular term is
Σ_c specular_c F(wi·h; eta_c, k_c) D G / (4 cos θi cos θo); roughplastic's Fresnel term
is the same in every channel, so it carries specular_0 + specular_1 + specular_2.

**roughplastic** (Mitsuba 3's ``roughplastic.cpp``): a rough dielectric interface of
relative index η = int_ior/ext_ior over a Lambertian base of reflectance d.  Per
(η, α, distribution) it precomputes, by Gauss–Legendre quadrature over the visible
normals (``eval_transmittance``/``eval_reflectance`` of microfacet.h), the table
T(μ_j) of the interface's transmittance at μ_j = max(1e-6, j/(RES−1)), j < RES, and the
internal diffuse reflectance R_int = 2 · mean_j(R(μ_j; 1/η) μ_j): a plain mean over the
same μ grid (not a cosine-weighted quadrature), R the rough reflectance seen from inside
(relative index 1/η).  Res 32 × 32 Gauss–Legendre nodes when the relative index is > 1,
else 128 × 128.  :func:`plastic_table` repeats this in float64; for η > 1 it matches
Mitsuba's float32 table to 1e-5 relative at every node but μ_0 = 1e-6 (1e-4 there for
α ≥ 0.01); for η < 1 total internal reflection cuts the integrand and the two agree to
about 1e-4 of the table's largest value.  It evaluates all nodes of a batch of views as
numpy arrays (the Beckmann slopes are separable: the x slope depends on u.x only) and
caches rows by their float32 parameters.  Then

    eval = F(wi·h; η) D G / (4 cos θi) (s_0+s_1+s_2)
           + d / (1 − R_int) · (1/π) · (1/η²) · cos θo · T(cos θi) · T(cos θo),

T interpolated linearly between table nodes (Mitsuba's ``lerp_gather``: index
min(⌊μ (RES−1)⌋, RES−2)).  Sampling picks the specular lobe with probability
P_s = (1 − T(cos θi)) w / ((1 − T(cos θi)) w + T(cos θi)(1 − w)), w = the specular
sampling weight, else a cosine-weighted direction; pdf = P_s p_spec + (1 − P_s) cos θo/π.
Mitsuba draws the lobe from a separate 1D sample; warpis draws it from u.x and rescales
u.x within the chosen interval, which leaves the density unchanged and keeps strata of u
as strata of each lobe's square.  The ``nonlinear`` option is not modelled.

The functions take directions in world space (``sp.n``, ``sp.wi`` and ``wo`` unit
vectors) and work in the shading point's frame (``sp.t``, ``sp.b``, ``sp.n``, with the
view ``sp.wi_local`` in it: :func:`.shading.with_frame`, once per shading point); the
BSDFs are isotropic, so the choice of tangents does not matter.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import warp as wp
from scipy.special import erf, erfinv

from .shading import BECKMANN, ShadingPoint, from_shading, to_shading
from .warps import INV_PI, PI, square_to_concentric_disk, square_to_cosine_hemisphere

__all__ = [
    "PLASTIC_TABLE_WIDTH", "ROUGH_TRANSMITTANCE_RES", "conductor_brdf", "conductor_pdf", "conductor_sample",
    "plastic_brdf", "plastic_pdf", "plastic_sample", "plastic_table",
]

ROUGH_TRANSMITTANCE_RES = 64  # Mitsuba's MI_ROUGH_TRANSMITTANCE_RES
PLASTIC_TABLE_WIDTH = ROUGH_TRANSMITTANCE_RES + 1  # T(μ_0..μ_63), then R_int

ALPHA_MIN = 1.0e-4  # MicrofacetDistribution::configure() clamps α to this
D_FLOOR = 1.0e-20  # MicrofacetDistribution::eval returns 0 where D cos θm ≤ this

_TABLE_CHUNK = 32768  # quadrature points per numpy batch of the plastic table

_RES = wp.constant(ROUGH_TRANSMITTANCE_RES)
_ALPHA_MIN = wp.constant(ALPHA_MIN)
_D_FLOOR = wp.constant(D_FLOOR)
_INV_SQRT_PI = wp.constant(0.56418958354775628695)
_ONE_MINUS_ULP = wp.constant(0.99999994)  # largest float32 below 1
_FOUR_EPS = wp.constant(4.0 * 5.9604645e-8)  # Frame3f's threshold on sin²θ: 4 × float32 ε (2⁻²⁴)


@wp.func
def reflect(wi: wp.vec3, m: wp.vec3) -> wp.vec3:
    """Mirror ``wi`` about the microfacet normal ``m`` (Mitsuba's ``reflect(wi, m)``)."""
    return 2.0 * wp.dot(wi, m) * m - wi


# --------------------------------------------------------------------------- distribution


@wp.func
def distribution_d(distribution: wp.int32, alpha: float, m: wp.vec3) -> float:
    """D(m) of a local normal ``m``: Mitsuba's ``MicrofacetDistribution::eval`` (isotropic)."""
    cos_t = m[2]
    cos_t2 = cos_t * cos_t
    # The tangential part from x and y, not 1 − z², which cancels when m ≈ n and α is small.
    xy = (m[0] / alpha) * (m[0] / alpha) + (m[1] / alpha) * (m[1] / alpha)
    result = float(0.0)
    if distribution == BECKMANN:
        result = wp.exp(-xy / cos_t2) / (PI * alpha * alpha * cos_t2 * cos_t2)
    else:
        s = xy + cos_t2
        result = 1.0 / (PI * alpha * alpha * s * s)
    # Mitsuba's guard; it also maps a NaN (0/0 at cos θm = 0) and normals below the
    # horizon to 0.
    if result * cos_t > _D_FLOOR:
        return result
    return 0.0


@wp.func
def smith_g1(distribution: wp.int32, alpha: float, v: wp.vec3, m: wp.vec3) -> float:
    """Smith's masking G1(v, m) of local ``v`` for the microfacet normal ``m`` (Mitsuba's)."""
    xy_alpha2 = (alpha * v[0]) * (alpha * v[0]) + (alpha * v[1]) * (alpha * v[1])
    tan_alpha2 = xy_alpha2 / (v[2] * v[2])  # α² tan²θ; +inf for a grazing v
    result = float(0.0)
    if distribution == BECKMANN:
        a = 1.0 / wp.sqrt(tan_alpha2)
        a2 = a * a
        if a >= 1.6:
            result = 1.0
        else:
            result = (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2)
    else:
        result = 2.0 / (1.0 + wp.sqrt(1.0 + tan_alpha2))
    if xy_alpha2 == 0.0:  # perpendicular incidence: no masking
        result = 1.0
    # The back of a microfacet cannot be seen from the front, nor the reverse.
    if wp.dot(v, m) * v[2] <= 0.0:
        result = 0.0
    return result


@wp.func
def visible_g1(distribution: wp.int32, alpha: float, v: wp.vec3, m: wp.vec3) -> float:
    """G1(v, m) in the density of visible normals that :func:`sample_normal` draws.

    Smith's exact G1 = 1/(1 + Λ(v)).  For GGX that is :func:`smith_g1`.  For Beckmann
    Λ(a) = (erf(a) − 1)/2 + exp(−a²)/(2a√π), a = 1/(α tan θ), written with erfc, where
    Mitsuba (and :func:`smith_g1`) use Walter's rational fit.  1 at perpendicular
    incidence; 0 where v·m and v·n differ in sign.
    """
    if distribution != BECKMANN:
        return smith_g1(distribution, alpha, v, m)
    if wp.dot(v, m) * v[2] <= 0.0:
        return 0.0
    xy_alpha2 = (alpha * v[0]) * (alpha * v[0]) + (alpha * v[1]) * (alpha * v[1])
    if xy_alpha2 == 0.0:
        return 1.0
    a = wp.abs(v[2]) / wp.sqrt(xy_alpha2)  # 0 for a grazing v: Λ = +inf, G1 = 0
    lam = 0.5 * (_INV_SQRT_PI * wp.exp(-a * a) / a - wp.erfc(a))
    return 1.0 / (1.0 + lam)


@wp.func
def ggx_visible_slopes(cos_i: float, u: wp.vec2) -> wp.vec2:
    """Slopes of a visible GGX normal for α = 1 seen from cos θ = ``cos_i`` (Heitz 2018).

    A uniform point on the disk, shifted onto the part of the hemisphere that the
    view sees, projected along the view: Mitsuba's ``sample_visible_11`` for GGX.
    """
    p = square_to_concentric_disk(u)
    s = 0.5 * (1.0 + cos_i)
    py = wp.lerp(wp.sqrt(wp.max(0.0, 1.0 - p[0] * p[0])), p[1], s)
    px = p[0]
    z = wp.sqrt(wp.max(0.0, 1.0 - px * px - py * py))
    sin_i = wp.sqrt(wp.max(0.0, 1.0 - cos_i * cos_i))
    norm = 1.0 / (sin_i * py + cos_i * z)
    return wp.vec2((cos_i * py - sin_i * z) * norm, px * norm)


@wp.func
def beckmann_visible_slopes(cos_i: float, u: wp.vec2) -> wp.vec2:
    """Slopes of a visible Beckmann normal for α = 1 (Jakob 2014), as Mitsuba computes them.

    The x slope inverts the CDF of the visible slopes numerically in the erf domain,
    from the closed-form solution at θi = π/2, with exactly three Newton steps (so the
    map is continuous in u and identical to Mitsuba's); the y slope is Gaussian.
    """
    tan_i = wp.sqrt(wp.max(0.0, 1.0 - cos_i * cos_i)) / cos_i
    cot_i = 1.0 / tan_i
    maxval = wp.erf(cot_i)
    ux = wp.clamp(u[0], 1.0e-6, 1.0 - 1.0e-6)
    uy = wp.clamp(u[1], 1.0e-6, 1.0 - 1.0e-6)
    x = maxval - (maxval + 1.0) * wp.erf(wp.sqrt(-wp.log(ux)))
    ux = ux * (1.0 + maxval + _INV_SQRT_PI * tan_i * wp.exp(-cot_i * cot_i))
    for _step in range(3):
        slope = wp.erfinv(x)
        value = 1.0 + x + _INV_SQRT_PI * tan_i * wp.exp(-slope * slope) - ux
        derivative = 1.0 - slope * tan_i
        x = x - value / derivative
    return wp.vec2(wp.erfinv(x), wp.erfinv(2.0 * uy - 1.0))


@wp.func
def sample_normal(distribution: wp.int32, alpha: float, visible: wp.int32, wi: wp.vec3, u: wp.vec2) -> wp.vec3:
    """A local microfacet normal for the local view ``wi`` (Mitsuba's ``sample``).

    Its density is :func:`normal_pdf`.
    """
    if visible == 0:
        # Inverse CDF of D(m) cos θm: φ uniform, tan²θm from the marginal in θm.
        # Mitsuba's map; sin θm is taken as tan θm cos θm rather than sqrt(1 − cos²θm),
        # which in float32 leaves only a handful of distinct θm below 1e-3 (α = 0.01).
        phi = 2.0 * PI * u[1]
        tan2 = float(0.0)
        if distribution == BECKMANN:
            tan2 = -alpha * alpha * wp.log(1.0 - u[0])
        else:
            tan2 = alpha * alpha * u[0] / (1.0 - u[0])
        cos_t = 1.0 / wp.sqrt(1.0 + tan2)
        sin_t = wp.sqrt(tan2) * cos_t
        return wp.vec3(wp.cos(phi) * sin_t, wp.sin(phi) * sin_t, cos_t)
    # Visible normals (Heitz & d'Eon 2014): 1. stretch the view to the α = 1 configuration.
    wi_s = wp.normalize(wp.vec3(alpha * wi[0], alpha * wi[1], wi[2]))
    sin2 = wi_s[0] * wi_s[0] + wi_s[1] * wi_s[1]
    cos_phi = float(1.0)
    sin_phi = float(0.0)
    if sin2 > _FOUR_EPS:
        inv = 1.0 / wp.sqrt(sin2)
        cos_phi = wp.clamp(wi_s[0] * inv, -1.0, 1.0)
        sin_phi = wp.clamp(wi_s[1] * inv, -1.0, 1.0)
    # 2. slopes of a visible normal for α = 1 and a view in the xz plane;
    slope = wp.vec2(0.0, 0.0)
    if distribution == BECKMANN:
        slope = beckmann_visible_slopes(wi_s[2], u)
    else:
        slope = ggx_visible_slopes(wi_s[2], u)
    # 3. rotate to the view's azimuth and unstretch; 4. the normal of those slopes.
    sx = (cos_phi * slope[0] - sin_phi * slope[1]) * alpha
    sy = (sin_phi * slope[0] + cos_phi * slope[1]) * alpha
    return wp.normalize(wp.vec3(-sx, -sy, 1.0))


@wp.func
def normal_pdf(distribution: wp.int32, alpha: float, visible: wp.int32, wi: wp.vec3, m: wp.vec3) -> float:
    """Density of :func:`sample_normal` at ``m``: D(m) G1(wi, m) |wi·m| / cos θi with the
    exact G1 of :func:`visible_g1` for visible normals (for Beckmann not quite Mitsuba's
    ``MicrofacetDistribution::pdf``, which has the rational G1), else D(m) cos θm."""
    d = distribution_d(distribution, alpha, m)
    if visible != 0:
        return d * visible_g1(distribution, alpha, wi, m) * wp.abs(wp.dot(wi, m)) / wi[2]
    return d * m[2]


# --------------------------------------------------------------------------- Fresnel


@wp.func
def fresnel_dielectric(cos_i: float, eta: float) -> float:
    """Unpolarised Fresnel reflectance of a dielectric interface (Mitsuba's ``fresnel``).

    ``eta`` is the relative index; ``cos_i`` < 0 means the light arrives from inside.
    Total internal reflection gives 1.
    """
    eta_it = wp.where(cos_i >= 0.0, eta, 1.0 / eta)
    eta_ti = wp.where(cos_i >= 0.0, 1.0 / eta, eta)
    cos_t2 = 1.0 - (1.0 - cos_i * cos_i) * eta_ti * eta_ti
    ci = wp.abs(cos_i)
    ct = wp.sqrt(wp.max(0.0, cos_t2))
    if eta == 1.0:
        return 0.0
    if ci == 0.0:
        return 1.0
    a_s = (ci - eta_it * ct) / (ci + eta_it * ct)
    a_p = (ct - eta_it * ci) / (ct + eta_it * ci)
    return 0.5 * (a_s * a_s + a_p * a_p)


@wp.func
def fresnel_conductor(cos_i: float, eta: float, k: float) -> float:
    """Unpolarised Fresnel reflectance of a conductor of complex index eta + i k.

    Mitsuba's ``fresnel_conductor`` (after Moeller, "Optics", 1988), for cos θi > 0.
    """
    c2 = cos_i * cos_i
    s2 = 1.0 - c2
    s4 = s2 * s2
    temp1 = eta * eta - k * k - s2
    a2pb2 = wp.sqrt(wp.max(0.0, temp1 * temp1 + 4.0 * k * k * eta * eta))
    a = wp.sqrt(wp.max(0.0, 0.5 * (a2pb2 + temp1)))
    term1 = a2pb2 + c2
    term2 = 2.0 * cos_i * a
    r_s = (term1 - term2) / (term1 + term2)
    term3 = a2pb2 * c2 + s4
    term4 = term2 * s2
    r_p = r_s * (term3 - term4) / (term3 + term4)
    return 0.5 * (r_s + r_p)


# --------------------------------------------------------------------------- the specular lobe


@wp.func
def microfacet_dg(distribution: wp.int32, alpha: float, wi: wp.vec3, wo: wp.vec3, h: wp.vec3) -> float:
    """D(h) G(wi, wo, h) / (4 cos θi cos θo): the specular lobe without its Fresnel term."""
    d = distribution_d(distribution, alpha, h)
    if d == 0.0:
        return 0.0
    g = smith_g1(distribution, alpha, wi, h) * smith_g1(distribution, alpha, wo, h)
    return d * g / (4.0 * wi[2] * wo[2])


@wp.func
def specular_pdf(distribution: wp.int32, alpha: float, visible: wp.int32, wi: wp.vec3, wo: wp.vec3,
                 h: wp.vec3) -> float:
    """Solid-angle density of wo = reflect(wi, m), m from :func:`sample_normal`; cos θi, cos θo > 0.

    The Jacobian of the reflection is 1/(4 wo·h).  With visible normals Mitsuba writes
    D G1(wi) |wi·h| / cos θi / (4 wo·h) as D G1(wi) / (4 cos θi); G1 is that of
    :func:`visible_g1`.
    """
    if wp.dot(wi, h) <= 0.0 or wp.dot(wo, h) <= 0.0:
        return 0.0
    if visible != 0:
        return distribution_d(distribution, alpha, h) * visible_g1(distribution, alpha, wi, h) / (4.0 * wi[2])
    return normal_pdf(distribution, alpha, 0, wi, h) / (4.0 * wp.dot(wo, h))


@wp.func
def clamped_alpha(sp: ShadingPoint) -> float:
    """α as Mitsuba uses it: at least 1e-4."""
    return wp.max(sp.alpha, _ALPHA_MIN)


# --------------------------------------------------------------------------- roughconductor


@wp.func
def conductor_brdf(sp: ShadingPoint, wo: wp.vec3) -> float:
    """ρ(wo) of roughconductor: Σ_c specular_c F_c(wi·h) D G / (4 cos θi cos θo).

    Reads sp.n, sp.wi, sp.alpha, sp.distribution, sp.eta, sp.k, sp.specular.
    """
    wi_l = sp.wi_local
    wo_l = to_shading(sp, wo)
    if wi_l[2] <= 0.0 or wo_l[2] <= 0.0:
        return 0.0
    alpha = clamped_alpha(sp)
    h = wp.normalize(wi_l + wo_l)
    dg = microfacet_dg(sp.distribution, alpha, wi_l, wo_l, h)
    if dg == 0.0:
        return 0.0
    c = wp.dot(wi_l, h)
    f = (sp.specular[0] * fresnel_conductor(c, sp.eta[0], sp.k[0])
         + sp.specular[1] * fresnel_conductor(c, sp.eta[1], sp.k[1])
         + sp.specular[2] * fresnel_conductor(c, sp.eta[2], sp.k[2]))
    return f * dg


@wp.func
def conductor_pdf(sp: ShadingPoint, wo: wp.vec3) -> float:
    """Solid-angle density of :func:`conductor_sample` at wo: Mitsuba's roughconductor
    ``pdf``, save the exact G1 of :func:`visible_g1` for Beckmann's visible normals.

    Reads sp.n, sp.wi, sp.alpha, sp.distribution, sp.sample_visible.
    """
    wi_l = sp.wi_local
    wo_l = to_shading(sp, wo)
    if wi_l[2] <= 0.0 or wo_l[2] <= 0.0:
        return 0.0
    h = wp.normalize(wi_l + wo_l)
    return specular_pdf(sp.distribution, clamped_alpha(sp), sp.sample_visible, wi_l, wo_l, h)


@wp.func
def conductor_sample(sp: ShadingPoint, u: wp.vec2) -> wp.vec3:
    """A direction from roughconductor's sampler, or the zero vector for a failed sample.

    The sample fails where Mitsuba's does: the view is at or below the horizon, the
    reflected direction is, or its density is 0 (the 1e-20 floor of D).  That last test
    is left to the caller, which evaluates :func:`conductor_pdf` at the returned
    direction anyway (``techniques.sample_technique``: pdf 0 is a failed sample), so the
    density is computed once per sample (Mitsuba tests the density of the sampled
    normal, which rounding can leave positive where its ``pdf`` at wo is 0).  Reads
    sp.n, sp.wi, sp.alpha, sp.distribution, sp.sample_visible.
    """
    wi_l = sp.wi_local
    if wi_l[2] <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    m = sample_normal(sp.distribution, clamped_alpha(sp), sp.sample_visible, wi_l, u)
    wo_l = reflect(wi_l, m)
    if wo_l[2] <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    # Where rounding leaves the density at wo 0 (the 1e-20 floor of D), the caller's pdf
    # (techniques.sample_technique evaluates it once) is 0, which fails the sample.
    return wp.normalize(from_shading(sp, wo_l))


# --------------------------------------------------------------------------- roughplastic


@wp.func
def plastic_transmittance(table: wp.array2d(dtype=wp.float32), row: wp.int32, cos_t: float) -> float:
    """T(cos θ) from row ``row`` of the table: Mitsuba's ``lerp_gather`` on the μ grid."""
    x = cos_t * float(_RES - 1)
    i = wp.min(wp.int32(x), _RES - 2)
    w1 = x - float(i)
    return (1.0 - w1) * table[row, i] + w1 * table[row, i + 1]


@wp.func
def plastic_specular_probability(table: wp.array2d(dtype=wp.float32), sp: ShadingPoint, cos_i: float) -> float:
    """Probability that roughplastic's sampler picks the specular lobe (Mitsuba's rule)."""
    t_i = plastic_transmittance(table, sp.plastic_row, cos_i)
    p_spec = (1.0 - t_i) * sp.specular_weight
    p_diff = t_i * (1.0 - sp.specular_weight)
    total = p_spec + p_diff
    if total <= 0.0:
        return 0.0
    return p_spec / total


@wp.func
def plastic_brdf(table: wp.array2d(dtype=wp.float32), sp: ShadingPoint, wo: wp.vec3) -> float:
    """ρ(wo) of roughplastic: the coating's specular lobe plus the diffuse base seen through it.

    Reads sp.n, sp.wi, sp.alpha, sp.distribution, sp.eta[0], sp.specular, sp.albedo,
    sp.plastic_row.
    """
    wi_l = sp.wi_local
    wo_l = to_shading(sp, wo)
    if wi_l[2] <= 0.0 or wo_l[2] <= 0.0:
        return 0.0
    eta = sp.eta[0]
    h = wp.normalize(wi_l + wo_l)
    spec = microfacet_dg(sp.distribution, clamped_alpha(sp), wi_l, wo_l, h)
    if spec != 0.0:
        spec = spec * fresnel_dielectric(wp.dot(wi_l, h), eta) * (sp.specular[0] + sp.specular[1] + sp.specular[2])
    row = sp.plastic_row
    t_i = plastic_transmittance(table, row, wi_l[2])
    t_o = plastic_transmittance(table, row, wo_l[2])
    internal = table[row, _RES]
    diffuse = sp.albedo / (1.0 - internal) * INV_PI / (eta * eta) * t_i * t_o
    return spec + diffuse


@wp.func
def plastic_pdf(table: wp.array2d(dtype=wp.float32), sp: ShadingPoint, wo: wp.vec3) -> float:
    """Solid-angle density of :func:`plastic_sample` at wo, both lobes together.

    Reads sp.n, sp.wi, sp.alpha, sp.distribution, sp.sample_visible, sp.specular_weight,
    sp.plastic_row.
    """
    wi_l = sp.wi_local
    wo_l = to_shading(sp, wo)
    if wi_l[2] <= 0.0 or wo_l[2] <= 0.0:
        return 0.0
    p_spec = plastic_specular_probability(table, sp, wi_l[2])
    h = wp.normalize(wi_l + wo_l)
    spec = specular_pdf(sp.distribution, clamped_alpha(sp), sp.sample_visible, wi_l, wo_l, h)
    return p_spec * spec + (1.0 - p_spec) * wo_l[2] * INV_PI


@wp.func
def plastic_sample(table: wp.array2d(dtype=wp.float32), sp: ShadingPoint, u: wp.vec2) -> wp.vec3:
    """A direction from roughplastic's sampler, or the zero vector for a failed sample.

    u.x < P_s picks the specular lobe and u.x/P_s becomes its first coordinate, else the
    cosine lobe gets (u.x − P_s)/(1 − P_s): each lobe sees a uniform u on its own square.
    The sample fails where Mitsuba's does: the view or wo at or below the horizon, or a
    direction where :func:`plastic_pdf` is 0 (that test through the caller's pdf, as for
    the conductor).  Reads what :func:`plastic_pdf` reads.
    """
    wi_l = sp.wi_local
    if wi_l[2] <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    p_spec = plastic_specular_probability(table, sp, wi_l[2])
    wo_l = wp.vec3(0.0, 0.0, 0.0)
    if u[0] < p_spec:
        ux = wp.min(u[0] / p_spec, _ONE_MINUS_ULP)
        m = sample_normal(sp.distribution, clamped_alpha(sp), sp.sample_visible, wi_l, wp.vec2(ux, u[1]))
        wo_l = reflect(wi_l, m)
    else:
        ux = wp.min((u[0] - p_spec) / (1.0 - p_spec), _ONE_MINUS_ULP)
        wo_l = square_to_cosine_hemisphere(wp.vec2(ux, u[1]))
    if wo_l[2] <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    # A density of 0 at wo fails the sample through the caller's pdf, as for the conductor.
    return wp.normalize(from_shading(sp, wo_l))


# --------------------------------------------------------------------------- the plastic table (numpy)


@functools.lru_cache(maxsize=None)
def _gauss_legendre(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's Gauss–Legendre rule on [0, 1]: nodes and weights stored as float32, the
    nodes mapped to [0, 1] in float32; returned as read-only float64 arrays."""
    nodes, weights = np.polynomial.legendre.leggauss(res)
    nodes = (nodes.astype(np.float32) * np.float32(0.5) + np.float32(0.5)).astype(np.float64)
    weights = weights.astype(np.float32).astype(np.float64)
    nodes.flags.writeable = False
    weights.flags.writeable = False
    return nodes, weights


@functools.lru_cache(maxsize=None)
def _concentric_disk(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Shirley's concentric map of the points (node_i, node_j) of :func:`_gauss_legendre`:
    (px, py), each (res, res), read-only."""
    nodes, _ = _gauss_legendre(res)
    a = (2.0 * nodes - 1.0)[:, None]
    b = (2.0 * nodes - 1.0)[None, :]
    first = np.abs(a) > np.abs(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(first, a, b)
        theta = np.where(first, (math.pi / 4.0) * (b / a), math.pi / 2.0 - (math.pi / 4.0) * (a / b))
    theta = np.where((a == 0.0) & (b == 0.0), 0.0, theta)
    px, py = r * np.cos(theta), r * np.sin(theta)
    px.flags.writeable = False
    py.flags.writeable = False
    return px, py


def _visible_slopes(distribution: int, alpha: float, vx: np.ndarray, vz: np.ndarray,
                    res: int) -> tuple[np.ndarray, np.ndarray]:
    """Slopes (sx, sy) of the visible normals that :func:`sample_normal` maps the points
    (node_i, node_j) of :func:`_gauss_legendre` to, float64, for local views (vx, 0, vz)
    (k,) with vx ≥ 0 (their azimuth needs no rotation).  For Beckmann sx depends on
    node_i only and sy on node_j only: shapes (k, res, 1) and (1, 1, res); for GGX both
    (k, res, res)."""
    nodes, _ = _gauss_legendre(res)
    sx_s = alpha * vx
    c = (vz / np.sqrt(sx_s * sx_s + vz * vz))[:, None]  # cos θ of the stretched view, (k, 1)
    sin_i = np.sqrt(np.maximum(0.0, 1.0 - c * c))
    if distribution == 0:
        u = np.clip(nodes, 1e-6, 1.0 - 1e-6)
        tan_i = sin_i / c
        with np.errstate(divide="ignore"):
            cot_i = np.where(tan_i > 0.0, 1.0 / np.where(tan_i > 0.0, tan_i, 1.0), np.inf)
        maxval = erf(cot_i)
        tail = tan_i * np.exp(-cot_i * cot_i) / math.sqrt(math.pi)
        x = maxval - (maxval + 1.0) * erf(np.sqrt(-np.log(u)))[None, :]
        target = u[None, :] * (1.0 + maxval + tail)
        for _step in range(3):
            slope = erfinv(x)
            value = 1.0 + x + tan_i * np.exp(-slope * slope) / math.sqrt(math.pi) - target
            x = x - value / (1.0 - slope * tan_i)
        return erfinv(x)[:, :, None], erfinv(2.0 * u - 1.0)[None, None, :]
    px, py = _concentric_disk(res)
    c, sin_i = c[:, :, None], sin_i[:, :, None]
    h = np.sqrt(np.maximum(0.0, 1.0 - px * px))
    py = h + (0.5 * (1.0 + c)) * (py - h)
    z = np.sqrt(np.maximum(0.0, 1.0 - px * px - py * py))
    norm = 1.0 / (sin_i * py + c * z)
    return (c * py - sin_i * z) * norm, px * norm


def _quadrature(distribution: int, alpha: float, eta: float, mu: np.ndarray, transmit: bool) -> np.ndarray:
    """Mitsuba's ``eval_transmittance`` (``transmit``) or ``eval_reflectance`` at views
    (sqrt(1−μ²), 0, μ): Gauss–Legendre over the unit square of the visible-normal map,
    vectorised over views and nodes in batches of about _TABLE_CHUNK points."""
    res = 32 if eta > 1.0 else 128
    mu32 = mu.astype(np.float32)
    vx = np.sqrt(np.float32(1.0) - mu32 * mu32).astype(np.float64)
    vz = mu32.astype(np.float64)
    step = max(1, _TABLE_CHUNK // (res * res))
    return np.concatenate([_quadrature_views(distribution, alpha, eta, vx[i:i + step], vz[i:i + step], res, transmit)
                           for i in range(0, len(mu), step)])


def _quadrature_views(distribution: int, alpha: float, eta: float, vx: np.ndarray, vz: np.ndarray, res: int,
                      transmit: bool) -> np.ndarray:
    """:func:`_quadrature` for the views (vx, 0, vz), vx ≥ 0, vz > 0 (k,): all nodes at once.

    Per node, with m the visible normal and c = wi·m: Mitsuba's ``fresnel(c, eta)``; wo
    the refraction (``transmit``, weight 1 − F) or the reflection (weight F) of wi at m;
    the value is weight × G1(wo, m) where wo lies on the side of the interface it should
    (below it for a transmission, above for a reflection), else 0.  Where c ≤ 0 (the rim
    of the visible hemisphere, by rounding) Mitsuba's value is 0 as well: the refracted
    wo of the inside branch, and a reflection with wo·m = c ≤ 0 above the surface, are
    masked by G1.  float64, in place where it can be.
    """
    k = len(vz)
    sx, sy = _visible_slopes(distribution, alpha, vx, vz, res)
    mx = -alpha * sx  # the unnormalised normal (−α sx, −α sy, 1)
    my = -alpha * sy
    mz = np.empty((k, res, res))
    np.add(mx * mx, my * my, out=mz)
    mz += 1.0
    np.sqrt(mz, out=mz)
    np.divide(1.0, mz, out=mz)
    mx = mx * mz
    my = my * mz
    vx, vz = vx[:, None, None], vz[:, None, None]
    c = vx * mx
    tmp = vz * mz
    c += tmp
    keep = c > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        # Fresnel from outside (c > 0): ct = |cos θt|, 0 under total internal reflection.
        eta_ti = 1.0 / eta
        ct = np.multiply(c, c, out=tmp)
        ct -= 1.0
        ct *= eta_ti * eta_ti
        ct += 1.0
        np.maximum(ct, 0.0, out=ct)
        np.sqrt(ct, out=ct)
        e_ct = eta * ct
        f = (c - e_ct) / (c + e_ct)
        f *= f
        e_c = np.multiply(eta, c, out=e_ct)
        a_p = (ct - e_c) / (ct + e_c)
        a_p *= a_p
        f += a_p
        f *= 0.5
        if transmit:
            kk = c * eta_ti
            kk -= ct  # c η_ti + cos θt, with cos θt = −ct
            wx = mx * kk - vx * eta_ti
            wy = np.multiply(my, kk, out=my)
            wz = np.multiply(mz, kk, out=kk)
            wz -= vz * eta_ti
            keep &= wz < 0.0
            np.subtract(1.0, f, out=f)
        else:
            kk = np.add(c, c, out=c)
            wx = kk * mx - vx
            wy = np.multiply(kk, my, out=my)
            wz = np.multiply(kk, mz, out=kk)
            wz -= vz
            keep &= wz > 0.0
        # Smith's G1(wo, m) as in smith_g1: α² tan²θo = q / wz².
        q = np.multiply(wx, wx, out=wx)
        q += np.multiply(wy, wy, out=wy)
        q *= alpha * alpha
        z2 = np.multiply(wz, wz, out=wz)
        if distribution == 0:
            a = np.divide(z2, q, out=z2)
            np.sqrt(a, out=a)  # 1/(α tan θo)
            num = 2.181 * a
            num += 3.535
            num *= a
            den = 2.577 * a
            den += 2.276
            den *= a
            den += 1.0
            g = np.divide(num, den, out=num)
            g[a >= 1.6] = 1.0
        else:
            t2 = np.divide(q, z2, out=q)
            t2 += 1.0
            np.sqrt(t2, out=t2)
            t2 += 1.0
            g = np.divide(2.0, t2, out=t2)
    g *= f
    g[~keep] = 0.0
    return np.einsum("kq,q->k", g.reshape(k, res * res), _node_weights(res))


@functools.lru_cache(maxsize=None)
def _node_weights(res: int) -> np.ndarray:
    """Weights of the res × res points of :func:`_gauss_legendre` on the unit square
    (flattened, node_i major), read-only."""
    _, weights = _gauss_legendre(res)
    w = (np.outer(weights, weights) * 0.25).ravel()
    w.flags.writeable = False
    return w


@functools.lru_cache(maxsize=256)
def _plastic_row(distribution: int, alpha: np.float32, eta: np.float32) -> np.ndarray:
    """:func:`plastic_table` for float32 parameters already checked and clamped; read-only."""
    res = ROUGH_TRANSMITTANCE_RES
    # Mitsuba's grid: linspace in float32, then max(1e-6, ·).
    mu = np.maximum(np.float32(1e-6), np.arange(res, dtype=np.float32) * np.float32(1.0 / (res - 1)))
    out = np.empty(PLASTIC_TABLE_WIDTH, dtype=np.float32)
    out[:res] = _quadrature(distribution, float(alpha), float(eta), mu, transmit=True)
    inv_eta = float(np.float32(1.0) / eta)
    reflect = _quadrature(distribution, float(alpha), inv_eta, mu, transmit=False)
    out[res] = 2.0 * float(np.mean(reflect * mu.astype(np.float64)))
    out.flags.writeable = False
    return out


def plastic_table(distribution: int, alpha: float, eta: float) -> np.ndarray:
    """One row of roughplastic's precomputed table, as Mitsuba computes it.

    Parameters
    ----------
    distribution : int
        0 (Beckmann) or 1 (GGX), as :data:`.shading.DISTRIBUTIONS`.
    alpha : float
        Roughness (clamped to ≥ 1e-4 as Mitsuba does).
    eta : float
        int_ior / ext_ior, > 0 and ≠ 1.

    Returns
    -------
    ndarray, shape (PLASTIC_TABLE_WIDTH,), float32
        T(μ_j) for μ_j = max(1e-6, j/(RES−1)), j < RES (the interface's transmittance
        from outside at cos θ = μ_j), then R_int = 2 · mean_j(R(μ_j; 1/η) μ_j) (the
        internal reflectance of diffuse light).  Parameters are rounded to float32 as
        in Mitsuba; the quadrature runs in float64.  Rows are cached by the rounded
        parameters; each call returns a new (writeable) copy.
    """
    if distribution not in (0, 1):
        raise ValueError(f"distribution must be 0 (beckmann) or 1 (ggx), got {distribution!r}")
    eta32 = np.float32(eta)
    alpha32 = np.float32(alpha)
    if not (np.isfinite(eta32) and eta32 > 0.0 and eta32 != 1.0):
        raise ValueError(f"eta must be a positive number other than 1, got {eta!r}")
    if not np.isfinite(alpha32):
        raise ValueError(f"alpha must be finite, got {alpha!r}")
    return _plastic_row(int(distribution), max(alpha32, np.float32(ALPHA_MIN)), eta32).copy()
