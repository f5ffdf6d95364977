"""Mitsuba 3's roughconductor and roughplastic in warpis (``warpis.kernels.microfacet``).

*Against Mitsuba* (each such test skips when Mitsuba is not installed; nothing else here
needs it).  ρ and pdf at 2000 (wi, wo) pairs per configuration — roughconductor and
roughplastic × {GGX, Beckmann} × visible/full normal sampling × α ∈ {0.01, 0.1, 0.3, 1} —
against ``bsdf.eval / cos θo`` and ``bsdf.pdf`` of Mitsuba's ``scalar_rgb`` variant at the
same float32 directions (normal +z, so warpis's local frame is the identity): relative
error ≤ 1e-4, ≤ 1e-3 where cos θi or cos θo < 0.1 (measured: ≤ 4e-5).  The one deliberate
difference: the pdf of Beckmann's visible normals has the exact Smith G1(wi) of the density
that the sampler draws, where Mitsuba's has Walter's rational fit (≤ 0.35 % apart; ρ keeps
the fit, as Mitsuba's does).  Half the pairs are
reflections of wi about normals drawn near the lobe, so the small-α lobes are probed where
they are not 0.  Conductors: scalar (eta, k) = (1.5, 2) split evenly over the channels,
and Mitsuba's "Au" with luminance weights (warpis's Σ_c specular_c F_c against the same
weighted sum of Mitsuba's RGB).  The samplers map u to Mitsuba's directions (roughplastic's
lobe from u.x, then the rescaled u.x, as Mitsuba's (sample1, sample2)), and roughplastic's
table reproduces Mitsuba's diffuse component.  All deterministic.

*Without Mitsuba.*  Chi-square goodness of fit of every sampler against its own pdf
(``warpis.testing.ChiSquareTest``, 5·10⁵ samples each).  The lobes of small α would fall
into a cell or two of the harness's 40 × 80 grid, so each run bins the sphere after a
magnification about the lobe's axis (the mirror direction of the view), θ' = π log(1 +
θ/θc) / log(1 + π/θc) with θc = 2α cos θi (:class:`Magnifier`): a bijection of the sphere
that keeps φ and divides the solid-angle density by its Jacobian.  Failed samples (below
the horizon) are one more bin, expected N (1 − ∫pdf).  All ``CHI2_RUNS`` runs form one
family at family-wise level 1e-3 (Šidák): the probability that a correct implementation
fails this module's chi-square tests by chance is ≤ 1e-3 (fixed seeds, so every run
draws the same numbers); Beckmann's visible normals included, with no correction: the
pdf is the density the sampler draws.  Also: samples and pdfs are finite, pdf > 0 at
every sample, ∫pdf by quadrature equals the probability of a valid sample, no NaN at
grazing views and α = 1e-4; the mean of ρ cos θo / pdf equals the quadrature of ρ cos θo
(an unbiased pair) for Beckmann's visible normals; the conductor's albedo with F ≡ 1, by
quadrature of ρ cos θo, matches a 1-D integral at normal incidence and the mean of
ρ cos θo / pdf under visible-normal sampling.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import warp as wp
from scipy.special import erf

from warpis.kernels import microfacet as mf
from warpis.kernels.shading import ShadingPoint, with_frame
from warpis.testing import ChiSquareTest, orthonormal_frame

CONDUCTOR = wp.constant(3)  # material codes of integrand.MATERIALS
PLASTIC = wp.constant(4)
DIST = {"beckmann": 0, "ggx": 1}
ALPHAS = (0.01, 0.1, 0.3, 1.0)
LUMINANCE = (0.2126, 0.7152, 0.0722)
PLASTIC_ETA = 1.5
PLASTIC_ALBEDO = 0.5

# --------------------------------------------------------------------------- kernels


@wp.struct
class Params:
    """The material fields of a ShadingPoint."""

    alpha: float
    distribution: wp.int32
    sample_visible: wp.int32
    eta: wp.vec3
    k: wp.vec3
    specular: wp.vec3
    specular_weight: float
    albedo: float
    plastic_row: wp.int32


@wp.func
def build_sp(material: wp.int32, prm: Params, n: wp.vec3, wi: wp.vec3) -> ShadingPoint:
    sp = ShadingPoint()
    sp.receiver = 0
    sp.p = wp.vec3(0.0, 0.0, 0.0)
    sp.n = n
    sp.slab = 0.0
    sp.material = material
    sp.albedo = prm.albedo
    sp.exponent = 0.0
    sp.wi = wi
    sp.lobe_axis = wp.normalize(2.0 * wp.dot(n, wi) * n - wi)
    sp.alpha = prm.alpha
    sp.distribution = prm.distribution
    sp.sample_visible = prm.sample_visible
    sp.eta = prm.eta
    sp.k = prm.k
    sp.specular = prm.specular
    sp.specular_weight = prm.specular_weight
    sp.plastic_row = prm.plastic_row
    return with_frame(sp)


@wp.func
def rho_of(material: wp.int32, table: wp.array2d(dtype=wp.float32), sp: ShadingPoint, wo: wp.vec3) -> float:
    if material == CONDUCTOR:
        return mf.conductor_brdf(sp, wo)
    return mf.plastic_brdf(table, sp, wo)


@wp.func
def pdf_of(material: wp.int32, table: wp.array2d(dtype=wp.float32), sp: ShadingPoint, wo: wp.vec3) -> float:
    if material == CONDUCTOR:
        return mf.conductor_pdf(sp, wo)
    return mf.plastic_pdf(table, sp, wo)


@wp.kernel(enable_backward=False)
def eval_kernel(material: wp.int32, prm: Params, table: wp.array2d(dtype=wp.float32), n: wp.array(dtype=wp.vec3),
                wi: wp.array(dtype=wp.vec3), wo: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                pdf: wp.array(dtype=float)):
    i = wp.tid()
    sp = build_sp(material, prm, n[i], wi[i])
    rho[i] = rho_of(material, table, sp, wo[i])
    pdf[i] = pdf_of(material, table, sp, wo[i])


@wp.kernel(enable_backward=False)
def sample_kernel(material: wp.int32, prm: Params, table: wp.array2d(dtype=wp.float32), n: wp.vec3, wi: wp.vec3,
                  u: wp.array(dtype=wp.vec2), dirs: wp.array(dtype=wp.vec3), pdf: wp.array(dtype=float)):
    """Samples and the pdf at each (0 for a failed sample)."""
    i = wp.tid()
    sp = build_sp(material, prm, n, wi)
    d = wp.vec3(0.0, 0.0, 0.0)
    if material == CONDUCTOR:
        d = mf.conductor_sample(sp, u[i])
    else:
        d = mf.plastic_sample(table, sp, u[i])
    dirs[i] = d
    p = float(0.0)
    if wp.length_sq(d) > 0.0:
        p = pdf_of(material, table, sp, d)
    pdf[i] = p


@wp.kernel(enable_backward=False)
def view_kernel(material: wp.int32, prm: Params, table: wp.array2d(dtype=wp.float32), n: wp.vec3, wi: wp.vec3,
                wo: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), pdf: wp.array(dtype=float)):
    """ρ and pdf at each wo for one view."""
    i = wp.tid()
    sp = build_sp(material, prm, n, wi)
    rho[i] = rho_of(material, table, sp, wo[i])
    pdf[i] = pdf_of(material, table, sp, wo[i])


@wp.kernel(enable_backward=False)
def pdf_kernel(material: wp.int32, prm: Params, table: wp.array2d(dtype=wp.float32), n: wp.vec3, wi: wp.vec3,
               wo: wp.array(dtype=wp.vec3), pdf: wp.array(dtype=float)):
    """pdf at each wo for one view."""
    i = wp.tid()
    sp = build_sp(material, prm, n, wi)
    pdf[i] = pdf_of(material, table, sp, wo[i])


# --------------------------------------------------------------------------- helpers


TILTED = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
Z = np.array([0.0, 0.0, 1.0])
NO_TABLE = np.zeros((1, mf.PLASTIC_TABLE_WIDTH), dtype=np.float32)


def conductor_params(dist: str, alpha: float, visible: bool, eta=(1.5, 1.5, 1.5), k=(2.0, 2.0, 2.0),
                     specular=(1.0 / 3.0,) * 3) -> Params:
    prm = Params()
    prm.alpha = alpha
    prm.distribution = DIST[dist]
    prm.sample_visible = int(visible)
    prm.eta = wp.vec3(*eta)
    prm.k = wp.vec3(*k)
    prm.specular = wp.vec3(*specular)
    prm.specular_weight = 0.0
    prm.albedo = 0.0
    prm.plastic_row = -1
    return prm


@functools.lru_cache(maxsize=None)
def one_row_table(dist: str, alpha: float, eta: float) -> np.ndarray:
    table = mf.plastic_table(DIST[dist], alpha, eta)[None, :]
    table.flags.writeable = False
    return table


def plastic_params(dist: str, alpha: float, visible: bool, eta: float = PLASTIC_ETA,
                   albedo: float = PLASTIC_ALBEDO, specular: float = 1.0) -> tuple[Params, np.ndarray]:
    """Params and the one-row table of a roughplastic (int_ior = eta, ext_ior = 1)."""
    prm = Params()
    prm.alpha = alpha
    prm.distribution = DIST[dist]
    prm.sample_visible = int(visible)
    prm.eta = wp.vec3(eta, eta, eta)
    prm.k = wp.vec3(0.0, 0.0, 0.0)
    prm.specular = wp.vec3(specular / 3.0, specular / 3.0, specular / 3.0)
    prm.specular_weight = specular / (albedo + specular)  # Mitsuba: s_mean / (d_mean + s_mean)
    prm.albedo = albedo
    prm.plastic_row = 0
    return prm, one_row_table(dist, alpha, eta)


def evaluate(material: int, prm: Params, table: np.ndarray, n, wi, wo) -> tuple[np.ndarray, np.ndarray]:
    """(ρ, pdf) at rows of wi, wo (k, 3) for normals n ((3,) or (k, 3)), as float64."""
    wi = np.asarray(wi, dtype=np.float32).reshape(-1, 3)
    count = wi.shape[0]
    n = np.broadcast_to(np.asarray(n, dtype=np.float32), (count, 3))
    rho = wp.zeros(count, dtype=float, device="cpu")
    pdf = wp.zeros(count, dtype=float, device="cpu")
    wp.launch(eval_kernel, dim=count, device="cpu",
              inputs=[material, prm, wp.array(table, dtype=wp.float32, device="cpu"),
                      wp.array(np.ascontiguousarray(n), dtype=wp.vec3, device="cpu"),
                      wp.array(wi, dtype=wp.vec3, device="cpu"),
                      wp.array(np.asarray(wo, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device="cpu"),
                      rho, pdf])
    return rho.numpy().astype(np.float64), pdf.numpy().astype(np.float64)


def sample(material: int, prm: Params, table: np.ndarray, n, wi, u) -> tuple[np.ndarray, np.ndarray]:
    """(directions (k, 3), pdf at each; 0 and the zero vector for a failed sample) for u (k, 2)."""
    u = np.asarray(u, dtype=np.float32)
    dirs = wp.zeros(len(u), dtype=wp.vec3, device="cpu")
    pdf = wp.zeros(len(u), dtype=float, device="cpu")
    wp.launch(sample_kernel, dim=len(u), device="cpu",
              inputs=[material, prm, wp.array(table, dtype=wp.float32, device="cpu"), wp.vec3(*map(float, n)),
                      wp.vec3(*map(float, wi)), wp.array(u, dtype=wp.vec2, device="cpu"), dirs, pdf])
    return dirs.numpy().astype(np.float64), pdf.numpy().astype(np.float64)


def view_eval(material: int, prm: Params, table: np.ndarray, n, wi, wo) -> tuple[np.ndarray, np.ndarray]:
    """(ρ, pdf) at directions wo (k, 3) for one normal and view, as float64."""
    wo = np.asarray(wo, dtype=np.float32).reshape(-1, 3)
    rho = wp.zeros(len(wo), dtype=float, device="cpu")
    pdf = wp.zeros(len(wo), dtype=float, device="cpu")
    wp.launch(view_kernel, dim=len(wo), device="cpu",
              inputs=[material, prm, wp.array(table, dtype=wp.float32, device="cpu"), wp.vec3(*map(float, n)),
                      wp.vec3(*map(float, wi)), wp.array(wo, dtype=wp.vec3, device="cpu"), rho, pdf])
    return rho.numpy().astype(np.float64), pdf.numpy().astype(np.float64)


def view_pdf(material: int, prm: Params, table: np.ndarray, n, wi, wo) -> np.ndarray:
    """pdf at directions wo (k, 3) for one normal and view, as float64."""
    wo = np.asarray(wo, dtype=np.float32).reshape(-1, 3)
    pdf = wp.zeros(len(wo), dtype=float, device="cpu")
    wp.launch(pdf_kernel, dim=len(wo), device="cpu",
              inputs=[material, prm, wp.array(table, dtype=wp.float32, device="cpu"), wp.vec3(*map(float, n)),
                      wp.vec3(*map(float, wi)), wp.array(wo, dtype=wp.vec3, device="cpu"), pdf])
    return pdf.numpy().astype(np.float64)


def direction(cos_t, phi, frame=None) -> np.ndarray:
    """Unit directions of (cos θ, φ) about +z, or about frame = (b1, b2, n)."""
    cos_t = np.asarray(cos_t, dtype=np.float64)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    local = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)
    return local if frame is None else local @ np.stack(frame)


def view(n: np.ndarray, cos_i: float) -> np.ndarray:
    """A unit view at cos θi = cos_i from n (azimuth 0.7 in n's frame)."""
    return direction(cos_i, 0.7, orthonormal_frame(n))


def mirror(n: np.ndarray, wi: np.ndarray) -> np.ndarray:
    return 2.0 * np.dot(n, wi) * n - wi


@wp.kernel(enable_backward=False)
def magnify_kernel(dirs: wp.array(dtype=wp.vec3d), axis: wp.vec3d, side: wp.vec3d, theta_c: wp.float64,
                   forward: wp.int32, out: wp.array(dtype=wp.vec3d), jac: wp.array(dtype=wp.float64)):
    """Magnifier.forward (forward = 1) or .inverse (0); jac: dω'/dω at the original direction."""
    i = wp.tid()
    d = dirs[i]
    pi = wp.float64(3.14159265358979323846)
    one = wp.float64(1.0)
    big_l = wp.log(one + pi / theta_c)
    if wp.length_sq(d) == wp.float64(0.0):
        out[i] = d
        jac[i] = one
        return
    d = wp.normalize(d)
    theta = wp.float64(2.0) * wp.atan2(wp.length(d - axis), wp.length(d + axis))
    perp = d - wp.dot(d, axis) * axis
    unit = side
    if wp.length_sq(perp) > wp.float64(0.0):
        unit = wp.normalize(perp)
    theta_new = wp.float64(0.0)
    if forward == 1:
        theta_new = pi * wp.log(one + theta / theta_c) / big_l
    else:
        theta_new = theta_c * (wp.exp(theta * big_l / pi) - one)
    out[i] = wp.cos(theta_new) * axis + wp.sin(theta_new) * unit
    t0 = wp.where(forward == 1, theta, theta_new)  # the original direction's angle
    t1 = wp.where(forward == 1, theta_new, theta)
    slope = pi / (big_l * (theta_c + t0))
    ratio = slope  # sin θ' / sin θ → g'(0) at the axis
    if t0 > wp.float64(1.0e-8) and t0 < pi - wp.float64(1.0e-8):
        ratio = wp.sin(t1) / wp.sin(t0)
    elif t0 >= pi - wp.float64(1.0e-8):
        ratio = slope  # at the antipode both angles are π and the sines vanish alike
    jac[i] = ratio * slope


class Magnifier:
    """A magnification of the sphere about ``axis``: θ' = π log(1 + θ/θc) / log(1 + π/θc).

    φ about the axis is kept; near the axis angles grow by π/(θc log(1 + π/θc)) (31× for
    θc = 0.02), far from it they shrink only mildly, so a narrow lobe and a broad one
    around it both spread over many cells.  A bijection of the sphere; the solid angle
    scales by J = (sin θ'/sin θ) dθ'/dθ, so a density p becomes p/J.
    """

    def __init__(self, axis: np.ndarray, theta_c: float) -> None:
        frame = orthonormal_frame(axis)
        self.axis = frame[2]
        self.side = frame[0]
        self.theta_c = float(theta_c)

    def _map(self, d: np.ndarray, forward: int) -> tuple[np.ndarray, np.ndarray]:
        d = np.ascontiguousarray(d, dtype=np.float64)
        out = wp.zeros(len(d), dtype=wp.vec3d, device="cpu")
        jac = wp.zeros(len(d), dtype=wp.float64, device="cpu")
        wp.launch(magnify_kernel, dim=len(d), device="cpu",
                  inputs=[wp.array(d, dtype=wp.vec3d, device="cpu"), wp.vec3d(*self.axis), wp.vec3d(*self.side),
                          wp.float64(self.theta_c), forward, out, jac])
        return out.numpy(), jac.numpy()

    def forward(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Magnified directions, and the Jacobian dω'/dω at d."""
        return self._map(d, 1)

    def inverse(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Original directions of magnified ones, and the Jacobian dω'/dω at them."""
        return self._map(d, 0)

    def wrap(self, sample_func, pdf_func):
        """(sample_func, pdf_func) on the magnified sphere, for ChiSquareTest."""

        def magnified_sample(count: int, seed: int):
            d, p = sample_func(count, seed)
            ok = p > 0.0
            out = np.zeros_like(d)
            p_out = np.zeros_like(p)
            out[ok], jac = self.forward(d[ok])
            p_out[ok] = p[ok] / jac
            return out, p_out

        def magnified_pdf(d: np.ndarray) -> np.ndarray:
            orig, jac = self.inverse(d)
            return pdf_func(orig) / jac

        return magnified_sample, magnified_pdf


def magnifier_for(alpha: float, n: np.ndarray, wi: np.ndarray) -> Magnifier:
    """Magnification about the mirror direction on the scale of the lobe's narrow side.

    Tilting the normal by δ moves the reflection by 2δ within the plane of incidence and
    by 2δ cos θi across it, so the lobe is about 2α by 2α cos θi: θc = 2α cos θi.
    """
    return Magnifier(mirror(n, wi), 2.0 * alpha * float(np.dot(n, wi)))


def sphere_quadrature(magnifier: Magnifier, func, res: tuple[int, int] = (1024, 512)) -> float:
    """∫ func dω over the sphere: the midpoint rule in (θ', φ') of the magnified sphere,
    dω = sin θ' dθ' dφ' / J (θ' rather than cos θ': the magnification is smooth in θ')."""
    nt, nphi = res
    theta_new = (np.arange(nt) + 0.5) * (math.pi / nt)
    phi = (np.arange(nphi) + 0.5) * (2.0 * math.pi / nphi)
    big_l = math.log1p(math.pi / magnifier.theta_c)
    theta = magnifier.theta_c * np.expm1(theta_new * big_l / math.pi)
    jac = np.sin(theta_new) / np.sin(theta) * math.pi / (big_l * (magnifier.theta_c + theta))
    b1, b2, axis = orthonormal_frame(magnifier.axis)
    around = np.cos(phi)[:, None] * b1 + np.sin(phi)[:, None] * b2  # (nphi, 3)
    d = np.cos(theta)[:, None, None] * axis + np.sin(theta)[:, None, None] * around[None, :, :]
    weight = np.sin(theta_new) * (math.pi / nt) * (2.0 * math.pi / nphi) / jac
    values = np.asarray(func(d.reshape(-1, 3)), dtype=np.float64).reshape(nt, nphi)
    return float(np.sum(values.sum(axis=1) * weight))


def estimator_values(material: int, prm: Params, table: np.ndarray, n, wi, u) -> np.ndarray:
    """ρ cos θo / pdf at the samples of u (k, 2), 0 for a failed sample: one-sample
    estimates of ∫ ρ cos θo dωo."""
    dirs, pdf = sample(material, prm, table, n, wi, u)
    valid = pdf > 0.0
    rho, _ = view_eval(material, prm, table, n, wi, dirs[valid])
    out = np.zeros(len(pdf))
    out[valid] = rho * (dirs[valid] @ np.asarray(n, dtype=np.float64)) / pdf[valid]
    return out


def u_grid(res: int) -> np.ndarray:
    """Midpoints of a res × res grid on the unit square."""
    x = (np.arange(res) + 0.5) / res
    a, b = np.meshgrid(x, x, indexing="ij")
    return np.stack([a.ravel(), b.ravel()], axis=1)


# --------------------------------------------------------------------------- Mitsuba


def _mitsuba():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    return mi


def mitsuba_conductor(mi, dist: str, alpha: float, visible: bool, material: str | None = None):
    spec = {"type": "roughconductor", "distribution": dist, "alpha": alpha, "sample_visible": visible}
    if material is None:
        spec |= {"eta": 1.5, "k": 2.0}
    else:
        spec["material"] = material
    return mi.load_dict(spec)


def mitsuba_plastic(mi, dist: str, alpha: float, visible: bool, specular: float = 1.0):
    return mi.load_dict({"type": "roughplastic", "distribution": dist, "alpha": alpha, "sample_visible": visible,
                         "int_ior": PLASTIC_ETA, "ext_ior": 1.0, "diffuse_reflectance": PLASTIC_ALBEDO,
                         "specular_reflectance": specular})


def mitsuba_eval(mi, bsdf, wi: np.ndarray, wo: np.ndarray, weights=(1 / 3, 1 / 3, 1 / 3)):
    """(Σ_c weights_c eval_c / cos θo, pdf) of a Mitsuba BSDF at local float32 directions."""
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    rho = np.empty(len(wi))
    pdf = np.empty(len(wi))
    for i, (a, b) in enumerate(zip(wi.tolist(), wo.tolist())):
        si.wi = mi.Vector3f(*a)
        w = mi.Vector3f(*b)
        v = bsdf.eval(ctx, si, w)
        rho[i] = (weights[0] * v[0] + weights[1] * v[1] + weights[2] * v[2]) / b[2]
        pdf[i] = bsdf.pdf(ctx, si, w)
    return rho, pdf


def random_pairs(seed: int, alpha: float, count: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """float32 local (wi, wo): a quarter of the views at cos θi < 0.1; every other wo the
    reflection of wi about a normal of slopes α·N(0, 1) (kept where cos θo > 0.01), the
    rest uniform in cos θo ∈ [0.01, 1]."""
    rng = np.random.default_rng(seed)
    cos_i = np.concatenate([rng.uniform(0.01, 0.1, count // 4), rng.uniform(0.1, 1.0, count - count // 4)])
    wi = direction(cos_i, rng.uniform(0.0, 2.0 * math.pi, count))
    wi[-1] = (0.0, 0.0, 1.0)  # normal incidence
    wo = direction(rng.uniform(0.01, 1.0, count), rng.uniform(0.0, 2.0 * math.pi, count))
    slopes = alpha * rng.normal(size=(count, 2))
    m = np.stack([-slopes[:, 0], -slopes[:, 1], np.ones(count)], axis=1)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    refl = 2.0 * np.sum(wi * m, axis=1)[:, None] * m - wi
    use = (np.arange(count) % 2 == 1) & (refl[:, 2] > 0.01)
    wo[use] = refl[use]
    return wi.astype(np.float32), wo.astype(np.float32)


def relative_error(mine: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|mine − ref| / |ref|; 0 where both are 0, inf where only ref is."""
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(mine - ref) / np.abs(ref)
    return np.where((mine == 0.0) & (ref == 0.0), 0.0, rel)


def exact_over_fit_g1(alpha: float, wi: np.ndarray) -> np.ndarray:
    """Smith's exact G1 of Beckmann, 1/(1 + Λ(a)), over Mitsuba's rational fit of it, for
    local views wi (k, 3) (normal +z), a = 1/(α tan θi): 0.99688–1.00296, 1 at normal
    incidence.  warpis's visible-normal pdf is Mitsuba's times this factor."""
    wi = np.asarray(wi, dtype=np.float64)
    xy = np.hypot(wi[:, 0], wi[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        a = wi[:, 2] / (alpha * xy)
        lam = 0.5 * (erf(a) - 1.0) + np.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
        fit = np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a))
    return np.where(xy == 0.0, 1.0, 1.0 / (1.0 + lam) / fit)


def check_against(mine: np.ndarray, ref: np.ndarray, wi: np.ndarray, wo: np.ndarray, what: str) -> float:
    """Asserts the stated tolerance; returns the worst relative error."""
    rel = relative_error(mine, ref)
    grazing = np.minimum(wi[:, 2], wo[:, 2]) < 0.1
    tol = np.where(grazing, 1e-3, 1e-4)
    bad = np.flatnonzero(~(rel <= tol))
    assert bad.size == 0, (f"{what}: {bad.size} of {len(rel)} beyond tolerance; worst at wi={wi[bad[0]]}, "
                           f"wo={wo[bad[0]]}: warpis {mine[bad[0]]!r}, Mitsuba {ref[bad[0]]!r}")
    assert np.all(np.isfinite(mine)) and np.count_nonzero(ref) > len(ref) // 3, what
    return float(np.max(rel))


# --------------------------------------------------------------------------- against Mitsuba

VARIANTS = [(visible, alpha) for visible in (True, False) for alpha in ALPHAS]


def au_channels(mi) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Mitsuba's RGB (eta, k) of its "Au" material."""
    params = mi.traverse(mitsuba_conductor(mi, "ggx", 0.1, True, "Au"))
    return tuple(params["eta.value"]), tuple(params["k.value"])


FIT_ERROR = 3.5e-3  # Walter's rational fit of Beckmann's G1: relative error < 0.35 %


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_conductor_matches_mitsuba(dist):
    """roughconductor's ρ and pdf equal Mitsuba's eval/cos θo and pdf: scalar (eta, k) =
    (1.5, 2) over α × visible/full, and "Au" weighted by luminance at α = 0.1 and 0.3, to
    1e-4 relative (1e-3 where a cosine is < 0.1).  Save the pdf of Beckmann's visible
    normals: warpis's has the exact G1(wi) of the density that the sampler draws where
    Mitsuba's has Walter's rational fit of it, so it is Mitsuba's times exact/fit G1(wi)
    (:func:`exact_over_fit_g1`) to that tolerance, within the fit's 0.35 % of Mitsuba's,
    and the factor is exercised (it departs from 1 by > 2e-3 on some pairs).
    Deterministic."""
    mi = _mitsuba()
    cases = [(visible, alpha, None) for visible, alpha in VARIANTS] + [(True, 0.1, "Au"), (False, 0.3, "Au")]
    for seed, (visible, alpha, material) in enumerate(cases):
        wi, wo = random_pairs(100 + seed, alpha)
        if material is None:
            prm, weights = conductor_params(dist, alpha, visible), (1 / 3, 1 / 3, 1 / 3)
        else:
            eta, k = au_channels(mi)
            prm, weights = conductor_params(dist, alpha, visible, eta, k, LUMINANCE), LUMINANCE
        rho, pdf = evaluate(CONDUCTOR, prm, NO_TABLE, Z, wi, wo)
        ref_rho, ref_pdf = mitsuba_eval(mi, mitsuba_conductor(mi, dist, alpha, visible, material), wi, wo, weights)
        what = f"roughconductor {dist} visible={visible} alpha={alpha} {material or 'eta=1.5 k=2'}"
        check_against(rho, ref_rho, wi, wo, what + " rho")
        if dist == "beckmann" and visible:
            factor = exact_over_fit_g1(alpha, wi)
            assert np.max(np.abs(factor - 1.0)) > 2e-3, what
            assert np.max(relative_error(pdf, ref_pdf)) <= FIT_ERROR, what
            ref_pdf = ref_pdf * factor
        check_against(pdf, ref_pdf, wi, wo, what + " pdf")


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_plastic_matches_mitsuba(dist):
    """roughplastic's ρ and pdf equal Mitsuba's eval/cos θo and pdf (int_ior 1.5, diffuse
    0.5, specular 1; and specular 0.3 at α = 0.3, which moves the sampling weight), to
    1e-4 relative (1e-3 where a cosine is < 0.1).  Save the pdf of Beckmann's visible
    normals, within 0.35 % of Mitsuba's: its specular lobe has the exact G1(wi) of the
    density that the sampler draws, Mitsuba's Walter's rational fit of it (relative error
    < 0.35 %), and the diffuse lobe is the same.  Deterministic."""
    mi = _mitsuba()
    cases = [(visible, alpha, 1.0) for visible, alpha in VARIANTS] + [(True, 0.3, 0.3)]
    for seed, (visible, alpha, specular) in enumerate(cases):
        wi, wo = random_pairs(200 + seed, alpha)
        prm, table = plastic_params(dist, alpha, visible, specular=specular)
        rho, pdf = evaluate(PLASTIC, prm, table, Z, wi, wo)
        ref_rho, ref_pdf = mitsuba_eval(mi, mitsuba_plastic(mi, dist, alpha, visible, specular), wi, wo)
        what = f"roughplastic {dist} visible={visible} alpha={alpha} specular={specular}"
        check_against(rho, ref_rho, wi, wo, what + " rho")
        if dist == "beckmann" and visible:
            assert np.max(relative_error(pdf, ref_pdf)) <= FIT_ERROR, what
            assert np.all(np.isfinite(pdf)) and np.count_nonzero(ref_pdf) > len(ref_pdf) // 3, what
        else:
            check_against(pdf, ref_pdf, wi, wo, what + " pdf")


def test_any_normal_matches_mitsuba():
    """With a tilted normal (warpis's frame is then not the identity) ρ and pdf still equal
    Mitsuba's at the local directions, to 3e-4 relative at α = 0.1 (measured ≤ 1e-4: the
    float32 rotation moves the directions by ~1e-7, which the lobe's slope amplifies).
    Deterministic."""
    mi = _mitsuba()
    frame = np.stack(orthonormal_frame(TILTED))
    for material, dist, visible in ((CONDUCTOR, "ggx", True), (PLASTIC, "beckmann", False)):
        wi, wo = random_pairs(300 + material, 0.1, 1000)
        wi64, wo64 = wi.astype(np.float64) @ frame, wo.astype(np.float64) @ frame
        if material == CONDUCTOR:
            prm, table, bsdf = conductor_params(dist, 0.1, visible), NO_TABLE, mitsuba_conductor(mi, dist, 0.1, visible)
        else:
            (prm, table), bsdf = plastic_params(dist, 0.1, visible), mitsuba_plastic(mi, dist, 0.1, visible)
        rho, pdf = evaluate(material, prm, table, TILTED, wi64, wo64)
        ref_rho, ref_pdf = mitsuba_eval(mi, bsdf, wi, wo)
        assert np.max(relative_error(rho, ref_rho)) < 3e-4
        assert np.max(relative_error(pdf, ref_pdf)) < 3e-4


def mitsuba_sample(mi, bsdf, wi: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Mitsuba's sampled directions (zero where its sample fails)."""
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*map(float, wi))
    out = np.zeros((len(s1), 3))
    for i, (a, b) in enumerate(zip(s1.tolist(), s2.tolist())):
        bs, weight = bsdf.sample(ctx, si, a, mi.Point2f(*b))
        if bs.pdf > 0.0 and bs.wo[2] > 0.0 and max(weight) > 0.0:
            out[i] = bs.wo
    return out


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_samplers_are_mitsubas_maps(dist):
    """The samplers map u to Mitsuba's directions, not only to its density: at 500 u and
    views at cos θi 0.9 and 0.15, both BSDFs, visible and full sampling, α 0.05 and 0.5,
    warpis's direction is Mitsuba's bsdf.sample(u.x, (u.x, u.y)) (roughconductor) or
    bsdf.sample(u.x, (u.x', u.y)) with u.x' the rescaled u.x (roughplastic) to 1e-4 (the
    two differ in their float32 erf/erfinv), and both fail on the same samples, save
    0.5 % at most whose u.x lies within rounding of the lobe boundary or whose direction
    grazes the horizon. Deterministic."""
    mi = _mitsuba()
    u = np.random.default_rng(7).random((500, 2)).astype(np.float32)
    for visible in (True, False):
        for alpha in (0.05, 0.5):
            for cos_i in (0.9, 0.15):
                wi = view(Z, cos_i).astype(np.float32)
                for material in (CONDUCTOR, PLASTIC):
                    if material == CONDUCTOR:
                        prm, table = conductor_params(dist, alpha, visible), NO_TABLE
                        bsdf = mitsuba_conductor(mi, dist, alpha, visible)
                        s1, s2 = u[:, 0], u
                    else:
                        prm, table = plastic_params(dist, alpha, visible)
                        bsdf = mitsuba_plastic(mi, dist, alpha, visible)
                        p_spec = np.float32(specular_probability(prm, table, wi[2]))
                        spec = u[:, 0] < p_spec
                        ux = np.where(spec, u[:, 0] / p_spec, (u[:, 0] - p_spec) / (np.float32(1) - p_spec))
                        s1, s2 = u[:, 0], np.stack([np.minimum(ux, np.float32(0.99999994)), u[:, 1]], axis=1)
                    dirs, _ = sample(material, prm, table, Z, wi, u)
                    ref = mitsuba_sample(mi, bsdf, wi, s1, s2)
                    ok, ref_ok = np.any(dirs != 0.0, axis=1), np.any(ref != 0.0, axis=1)
                    what = f"material {material} {dist} visible={visible} alpha={alpha} cos_i={cos_i}"
                    assert np.count_nonzero(ok != ref_ok) <= 2, what
                    both = ok & ref_ok
                    assert np.count_nonzero(both) > 250, what
                    assert np.max(np.abs(dirs[both] - ref[both])) < 1e-4, what


def test_plastic_table_matches_mitsuba():
    """plastic_table reproduces the table behind Mitsuba's diffuse component: with
    specular_reflectance 0, Mitsuba's eval at cos θi = μ_j (a node of the table) and
    wo = n is d/(1 − R_int) (1/π) (1/η²) T(μ_j) T(1); warpis's table gives the same to
    1e-5 relative at every node but the first, for both distributions, α ∈ {0.01, 0.1,
    0.3, 1} at int_ior 1.5 and α = 0.1 at 1.33.  The first node (μ = 1e-6, a view
    0.00006° above the horizon) to 2e-4: there Mitsuba's float32 quadrature itself has
    that error.  Deterministic."""
    mi = _mitsuba()
    res = mf.ROUGH_TRANSMITTANCE_RES
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    cases = [(dist, alpha, 1.5) for dist in DIST for alpha in ALPHAS] + [(dist, 0.1, 1.33) for dist in DIST]
    for dist, alpha, eta in cases:
        bsdf = mi.load_dict({"type": "roughplastic", "distribution": dist, "alpha": alpha, "int_ior": eta,
                             "ext_ior": 1.0, "specular_reflectance": 0.0, "diffuse_reflectance": 0.5})
        table = one_row_table(dist, alpha, eta)[0]
        assert table.shape == (mf.PLASTIC_TABLE_WIDTH,) and table.dtype == np.float32
        ref = np.empty(res)
        for j in range(res):
            mu = max(float(np.float32(j) * np.float32(1.0 / (res - 1))), 1e-6)
            si.wi = mi.Vector3f(math.sqrt(1.0 - mu * mu), 0.0, mu)
            ref[j] = bsdf.eval(ctx, si, mi.Vector3f(0.0, 0.0, 1.0))[0]
        eta32 = float(np.float32(eta))
        mine = 0.5 / (1.0 - table[res]) / math.pi / eta32 ** 2 * table[:res] * table[res - 1]
        rel = relative_error(mine, ref)
        assert rel[0] < 2e-4 and np.max(rel[1:]) < 1e-5, (dist, alpha, eta, rel[0], np.max(rel[1:]))


def test_plastic_table_arguments():
    """plastic_table rejects what Mitsuba rejects (eta 1, ≤ 0 or not finite; an unknown
    distribution), clamps α to 1e-4 as Mitsuba does, and holds transmittances in [0, 1]
    that grow towards normal incidence, then R_int in [0, 1).  Its rows are cached by the
    float32 parameters, and each call returns a copy that the caller may change.
    Deterministic."""
    for bad in ({"eta": 1.0}, {"eta": 0.0}, {"eta": -1.5}, {"eta": math.nan}, {"distribution": 2},
                {"alpha": math.inf}):
        args = {"distribution": 1, "alpha": 0.1, "eta": 1.5} | bad
        with pytest.raises(ValueError):
            mf.plastic_table(**args)
    np.testing.assert_array_equal(mf.plastic_table(1, 0.0, 1.5), mf.plastic_table(1, 1e-4, 1.5))
    row = mf.plastic_table(0, 0.3, PLASTIC_ETA)
    row[:] = -1.0
    again = mf.plastic_table(0, np.float32(0.3), np.float32(PLASTIC_ETA))
    assert again is not row and again.flags.writeable
    np.testing.assert_array_equal(again, one_row_table("beckmann", 0.3, PLASTIC_ETA)[0])
    for dist in DIST:
        table = one_row_table(dist, 0.3, PLASTIC_ETA)[0]
        t, r_int = table[:-1], table[-1]
        assert np.all((t >= 0.0) & (t <= 1.0)) and 0.0 <= r_int < 1.0
        assert t[-1] > 0.9 and t[-1] > t[10] > t[1]


# --------------------------------------------------------------------------- chi-square

FAMILY_ALPHA = 1e-3
SAMPLES = 500_000
VIEWS = {"normal": 1.0, "grazing": 0.1}
# roughconductor: every combination.  roughplastic's specular lobe is the same sampler, so
# its runs test what it adds (the lobe choice from u.x, the cosine lobe, the mixture pdf):
# every α and view, the four (distribution, sampling) pairs in turn.
COMBOS = [(dist, visible) for dist in DIST for visible in (True, False)]
CHI2_CASES = ([("roughconductor", dist, visible, alpha, v) for dist, visible in COMBOS
               for alpha in (0.01, 0.1, 0.5, 1.0) for v in VIEWS]
              + [("roughplastic", *COMBOS[(i + j) % 4], alpha, v) for i, alpha in enumerate((0.01, 0.1, 0.5, 1.0))
                 for j, v in enumerate(VIEWS)])
CHI2_RUNS = len(CHI2_CASES)


def bsdf_case(name: str, dist: str, visible: bool, alpha: float, view_name: str):
    """(material, Params, table, n, wi) of a test case; the normal is tilted, so warpis's
    frame is exercised."""
    wi = TILTED if VIEWS[view_name] == 1.0 else view(TILTED, VIEWS[view_name])
    if name == "roughconductor":
        return CONDUCTOR, conductor_params(dist, alpha, visible), NO_TABLE, TILTED, wi
    prm, table = plastic_params(dist, alpha, visible)
    return PLASTIC, prm, table, TILTED, wi


def specular_probability(prm: Params, table: np.ndarray, cos_i: float) -> float:
    """roughplastic's probability of the specular lobe, as the kernel computes it (float32)."""
    res = mf.ROUGH_TRANSMITTANCE_RES
    x = np.float32(np.float32(cos_i) * np.float32(res - 1))
    j = min(int(x), res - 2)
    w1 = np.float32(x - np.float32(j))
    t_i = (np.float32(1) - w1) * table[0, j] + w1 * table[0, j + 1]
    ps = np.float32((np.float32(1) - t_i) * np.float32(prm.specular_weight))
    pd = np.float32(t_i * (np.float32(1) - np.float32(prm.specular_weight)))
    return float(np.float32(ps / (ps + pd)))


def sampler_and_pdf(material, prm, table, n, wi):
    """(sample_func, pdf_func) for ChiSquareTest."""

    def pdf_func(d: np.ndarray) -> np.ndarray:
        return view_pdf(material, prm, table, n, wi, d)

    def sample_func(count: int, seed: int):
        return sample(material, prm, table, n, wi, np.random.default_rng(seed).random((count, 2)))

    return sample_func, pdf_func


@pytest.mark.parametrize("case", CHI2_CASES, ids=["-".join(map(str, c)) for c in CHI2_CASES])
def test_sampler_chi2(case):
    """Each sampler draws the density its pdf claims (chi-square on the magnified sphere,
    5·10⁵ samples, failed samples as one bin): passes at the family's Šidák threshold
    (false-failure probability ≤ 1e-3 for the whole family of CHI2_RUNS runs)."""
    material, prm, table, n, wi = bsdf_case(*case)
    sample_func, pdf_func = sampler_and_pdf(material, prm, table, n, wi)
    magnifier = magnifier_for(case[3], n, wi)
    sf, pf = magnifier.wrap(sample_func, pdf_func)
    seed = 1000 + CHI2_CASES.index(case)
    test = ChiSquareTest(sf, pf, magnifier.axis, sample_count=SAMPLES, seed=seed, allow_invalid=True)
    assert test.run(FAMILY_ALPHA, CHI2_RUNS), test.messages


# --------------------------------------------------------------------------- samples and pdf


CONSISTENCY_CASES = ([("roughconductor", dist, visible, alpha, "grazing") for dist, visible in COMBOS
                      for alpha in (0.01, 0.1, 0.5, 1.0)]
                     + [("roughconductor", dist, visible, 0.5, "normal") for dist, visible in COMBOS]
                     + [("roughplastic", dist, visible, 0.5, "grazing") for dist, visible in COMBOS])


@pytest.mark.parametrize("case", CONSISTENCY_CASES, ids=["-".join(map(str, c)) for c in CONSISTENCY_CASES])
def test_pdf_integrates_to_valid_probability(case):
    """Samples on a 1024² grid of u: each is either the zero vector with pdf 0 (failed) or a
    unit vector with a finite pdf > 0; the pdf, integrated over the sphere by quadrature
    (magnified (θ', φ') midpoint rule, error ≤ 3e-4), equals the probability of a valid
    sample (the u grid's valid fraction, error ≤ 5e-4) to 1e-3: the pdf of the valid
    directions is not renormalised, and it is ≤ 1.  Beckmann's visible-normal pdf included:
    it has the exact G1(wi) of the density the sampler draws (Mitsuba's pdf, with the
    rational G1, integrates to P(valid) × fit/exact G1(wi), up to 1.0031 P(valid)).
    Deterministic."""
    material, prm, table, n, wi = bsdf_case(*case)
    dirs, pdf = sample(material, prm, table, n, wi, u_grid(1024))
    assert np.all(np.isfinite(dirs)) and np.all(np.isfinite(pdf))
    valid = np.any(dirs != 0.0, axis=1)
    assert np.all(pdf[~valid] == 0.0)
    assert np.all(pdf[valid] > 0.0)
    np.testing.assert_allclose(np.linalg.norm(dirs[valid], axis=1), 1.0, atol=1e-6)
    p_valid = float(np.mean(valid))
    _, pdf_func = sampler_and_pdf(material, prm, table, n, wi)
    mass = sphere_quadrature(magnifier_for(prm.alpha, n, wi), pdf_func)
    assert mass == pytest.approx(p_valid, abs=1e-3), (mass, p_valid)
    assert mass <= 1.0 + 3e-4, mass
    if case[4] == "grazing" and prm.alpha >= 0.1 and not prm.sample_visible:
        assert p_valid < 0.9  # the full distribution sends many samples below the horizon there


UNBIASED_CASES = [("roughconductor", 1.0, "grazing"), ("roughconductor", 0.5, "normal"), ("roughplastic", 1.0, "grazing")]
UNBIASED_SAMPLES = 1_000_000


@pytest.mark.parametrize("case", UNBIASED_CASES, ids=["-".join(map(str, c)) for c in UNBIASED_CASES])
def test_beckmann_visible_estimator_is_unbiased(case):
    """Beckmann with visible-normal sampling: the mean of ρ cos θo / pdf over 10⁶ samples
    equals ∫ ρ cos θo dωo by quadrature (the magnified midpoint rule at 1024 × 512, which
    agrees with 4096 × 2048 to 2e-6) within 4 standard errors plus 1e-5 (false-failure
    probability ≈ 6e-5 per case): ρ (Mitsuba's, rational G1) and the pdf (the sampler's,
    exact G1) form an unbiased pair, at a grazing view (cos θi = 0.1, α = 1: a = 0.1,
    where Mitsuba's pdf would bias the mean by fit/exact − 1 = 0.29 %, ≈ 18 standard
    errors, which the tolerance resolves) and at normal incidence (where the two G1
    agree).  roughconductor (eta 1.5, k 2) and roughplastic.  Fixed seeds."""
    name, alpha, view_name = case
    material, prm, table, n, wi = bsdf_case(name, "beckmann", True, alpha, view_name)

    def rho_cos(d):
        rho, _ = view_eval(material, prm, table, n, wi, d)
        return rho * np.maximum(d @ n, 0.0)

    e = sphere_quadrature(magnifier_for(alpha, n, wi), rho_cos)
    seed = 31 + UNBIASED_CASES.index(case)
    values = estimator_values(material, prm, table, n, wi,
                              np.random.default_rng(seed).random((UNBIASED_SAMPLES, 2)))
    mc, err = values.mean(), values.std() / math.sqrt(len(values))
    tol = 4.0 * err + 1e-5
    assert abs(mc - e) <= tol, (case, mc, e, err)
    if material == CONDUCTOR and view_name == "grazing":
        cos_i = float(np.float32(np.dot(n, wi)))
        factor = exact_over_fit_g1(alpha, np.array([[math.sqrt(1.0 - cos_i * cos_i), 0.0, cos_i]]))[0]
        assert abs(factor - 1.0) * e > 2.0 * tol, (case, factor, e, tol)  # Mitsuba's pdf: mean e × factor


def test_grazing_and_tiny_alpha_stay_finite():
    """At views 1e-6, 1e-4, 0.01 and 1 in cosine from the normal and α = 1e-4 (Mitsuba's
    floor), 0.01 and 1: samples, ρ and pdf are finite and ≥ 0 everywhere (no NaN from a
    grazing tan θ, a 0/0 in D, or erfinv at ±1); a failed sample is the zero vector with
    pdf 0, a returned direction whose density rounds to 0 (D's 1e-20 floor) is failed by
    its pdf 0 (``techniques.sample_technique``), and ρ ≥ 0.  Deterministic."""
    u = np.random.default_rng(11).random((4096, 2))
    u[:4] = [[0.0, 0.0], [0.0, 0.99999994], [0.99999994, 0.0], [0.99999994, 0.99999994]]
    wo = direction(np.random.default_rng(12).uniform(-1.0, 1.0, 4096),
                   np.random.default_rng(13).uniform(0.0, 2.0 * math.pi, 4096), orthonormal_frame(TILTED))
    for name in ("roughconductor", "roughplastic"):
        for dist, visible in COMBOS:
            for alpha in (1e-4, 0.01, 1.0):
                for cos_i in (1e-6, 1e-4, 0.01, 1.0):
                    wi = view(TILTED, cos_i)
                    if name == "roughconductor":
                        material, prm, table = CONDUCTOR, conductor_params(dist, alpha, visible), NO_TABLE
                    else:
                        material, (prm, table) = PLASTIC, plastic_params(dist, alpha, visible)
                    what = (name, dist, visible, alpha, cos_i)
                    dirs, pdf = sample(material, prm, table, TILTED, wi, u)
                    assert np.all(np.isfinite(dirs)) and np.all(np.isfinite(pdf)), what
                    returned = np.any(dirs != 0.0, axis=1)
                    assert np.all(pdf[~returned] == 0.0), what
                    assert np.allclose(np.linalg.norm(dirs[returned], axis=1), 1.0, atol=1e-5), what
                    valid = returned & (pdf > 0.0)
                    if cos_i >= 0.01 and alpha >= 0.01:  # away from the floors: every direction has a density
                        assert np.all(valid == returned), what
                    for targets in (wo, dirs[valid]):
                        rho, p = view_eval(material, prm, table, TILTED, wi, targets)
                        assert np.all(np.isfinite(rho)) and np.all(rho >= 0.0), what
                        assert np.all(np.isfinite(p)) and np.all(p >= 0.0), what


# --------------------------------------------------------------------------- white furnace


def normal_incidence_albedo(dist: str, alpha: float) -> float:
    """E(n) with F ≡ 1 as a 1-D integral: at normal incidence G1(wi) = 1 and the visible
    normals are D(m) cos θm, whose inverse CDF gives tan²θm; wo lies at 2θm, above the
    horizon while θm < 45°, and E = ∫ G1(wo) du over those u (scipy's adaptive quadrature)."""
    from scipy.integrate import quad

    def g1(u: float) -> float:
        tan2 = alpha * alpha * u / (1.0 - u) if dist == "ggx" else -alpha * alpha * math.log1p(-u)
        t = math.tan(2.0 * math.atan(math.sqrt(tan2)))  # tan θo
        if dist == "ggx":
            return 2.0 / (1.0 + math.sqrt(1.0 + alpha * alpha * t * t))
        a = 1.0 / (alpha * t) if t > 0.0 else math.inf
        return 1.0 if a >= 1.6 else (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)

    u_max = 1.0 / (1.0 + alpha * alpha) if dist == "ggx" else -math.expm1(-1.0 / (alpha * alpha))
    return quad(g1, 0.0, u_max, epsabs=1e-10, epsrel=1e-10, limit=200)[0]


def test_white_furnace():
    """With F ≡ 1 (eta = 0, k = 1: Mitsuba's material "none") the conductor's albedo
    E(wi) = ∫ ρ cos θo dωo, by quadrature, is ≤ 1, 1 to 1e-3 at α = 0.01, and falls as α
    grows: single scattering loses the light that would meet a second microfacet, and
    reflections below the horizon.  At normal incidence it equals the 1-D integral of
    :func:`normal_incidence_albedo` to 2e-4 (GGX at α = 1: E = 0.307, a loss of 69 %;
    Beckmann: 0.463).  And E is the mean of ρ cos θo / pdf over 2·10⁵ samples from
    conductor_sample (for GGX, ρ cos θo / pdf = G1(wo, m); for Beckmann G1(wo, m) times
    Mitsuba's fit of G1(wi) over the exact G1(wi)), within 4 standard errors plus the
    quadrature's 3e-4 (false-failure probability ≈ 6e-5 per comparison, 16 comparisons:
    ≈ 1e-3)."""
    u = np.random.default_rng(21).random((200_000, 2)).astype(np.float32)
    for dist in DIST:
        for cos_i in (1.0, 0.5):
            wi = view(Z, cos_i)
            albedo = []
            for alpha in (0.01, 0.1, 0.3, 0.5, 1.0):
                prm = conductor_params(dist, alpha, True, eta=(0.0,) * 3, k=(1.0,) * 3)

                def rho_cos(d, prm=prm, wi=wi):
                    rho, _ = view_eval(CONDUCTOR, prm, NO_TABLE, Z, wi, d)
                    return rho * np.maximum(d[:, 2], 0.0)

                e = sphere_quadrature(magnifier_for(alpha, Z, wi), rho_cos)
                albedo.append(e)
                what = (dist, cos_i, alpha, e)
                if cos_i == 1.0:
                    assert e == pytest.approx(normal_incidence_albedo(dist, alpha), abs=2e-4), what
                if alpha == 0.01:
                    assert e == pytest.approx(1.0, abs=1e-3), what
                    continue
                values = estimator_values(CONDUCTOR, prm, NO_TABLE, Z, wi, u)
                mc, err = values.mean(), values.std() / math.sqrt(len(values))
                assert abs(e - mc) <= 4.0 * err + 3e-4, what + (mc, err)
            assert all(a <= 1.0 + 3e-4 for a in albedo), (dist, cos_i, albedo)
            assert all(a > b for a, b in zip(albedo, albedo[1:])), (dist, cos_i, albedo)
