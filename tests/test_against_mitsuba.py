"""warpis against Mitsuba 3 itself: direct illumination at the receivers of one XML scene.

The scene (``tests/data/against_mitsuba/scene.xml`` and its receivers file): two glossy
plates over a diffuse floor — ``plate-ggx``, a GGX roughconductor (α 0.2, eta and k
different in each channel), and ``plate-beckmann``, a Beckmann roughplastic (α 0.25,
coloured base), both sampling visible normals — lit by an analytic ``sphere`` light and
a ``rectangle`` light, each on the camera's mirror ray at one plate's centre, with a
``cube`` between the sphere and ``plate-ggx`` casting a partial shadow there.  Eight
receivers: the sphere's highlight and two points in the cube's penumbra on
``plate-ggx``; the square light's highlight, a point beside it and one away from it on
``plate-beckmann``; a lit point on the floor and one in the penumbra of ``plate-ggx``.
Radiances and reflectances differ per channel and both sides read channel g, which
warpis represents exactly (docs/mitsuba-scenes.md).

Each receiver's F = ∫ Le(ω) ρ(ω) cos θ dω, the direct radiance reflected towards the
camera, is computed twice:

* warpis: ``reference(scene, rel_error=5e-4)`` (single-technique jittered quadrature,
  32 replicas; the lit floor point by its closed form), on warpis's own reading of the
  XML (the sphere analytic, as Mitsuba's; everything exact);
* Mitsuba (``llvm_ad_rgb``, every sample of a receiver in one array; the other tests
  here use ``scalar_rgb``): at the receivers file's points, seen from the XML's camera,
  the surface interaction of a short ray cast at the point along the view, then
  ``SAMPLES`` = 2^19 independent uniform samples (numpy, fixed seed) of Mitsuba's own
  emitter sampling (``scene.sample_emitter_direction``: it picks one of the two emitters,
  samples the sphere uniformly over the cone it subtends and the rectangle by area, and
  returns Le/pdf) times its ``bsdf.eval`` (which includes cos θo), times visibility along
  the segment from the receiver to the light sample; mean and standard error.

Visibility: Mitsuba's own shadow ray (``test_visibility=True``, ``si.spawn_ray_to``)
starts (1 + max|p|) · RayEpsilon ≈ 2e-4 off the surface along the normal and runs
parallel to the segment, so near an occluder's edge the two can disagree: in the floor's
penumbra, under the edge of ``plate-ggx``, Mitsuba's own rays let through 0.45% more
light than the segment (the paired difference, printed per receiver as "offset effect";
about 3σ of that receiver's estimate; elsewhere < 0.01%).  warpis's shadow ray is the segment from the receiver itself
(integrand.py), so the comparison tests visibility along the segment (``segment_ray``:
``ray_test`` from EPS along it to EPS short of the light) and prints the estimate with
Mitsuba's own shadow rays beside it.

Tolerance: |F_warpis − F_Mitsuba| ≤ 4 sqrt(se_w² + se_m²): warpis reads the scene
exactly as Mitsuba holds it (its sphere light is an analytic sphere), so a comparison
fails by chance with the two-sided tail at 4 of the difference over its estimated
stderr.  Mitsuba's
samples are bounded (Le/pdf is constant on the sphere's cone and bounded on the
rectangle, ρ cos θ is bounded), so their mean over 2^19 samples is normal to high
accuracy; warpis's stderr comes from 32 replicas (Student's t, 31 degrees of freedom)
and is asserted to be at most half of Mitsuba's, so by Welch–Satterthwaite the ratio has
at least 31 (1 + 2²)² = 775 degrees of freedom: a tail of ≤ 6.9e-5 at 4 (the normal's is
6.3e-5).  Over the eight receivers the false-failure probability is ≤ 8 × 6.9e-5 = 5.6e-4
(Bonferroni), over the choice of seeds: the seeds are fixed, so every run draws the same
numbers.  The worst |z| over the receivers is in the printed table (``pytest -s``) and in
any failure's message.

Also at the same receivers (deterministic, each kept small):

* the receivers themselves: warpis's positions, normals (the plates' and floor's front,
  as Mitsuba's shading frame) and view directions are Mitsuba's, and each receiver has
  the material of the shape it lies on;
* f: ``evaluate_integrand`` (Le × ρ × cos θ × visibility) against Mitsuba's Le ×
  ``bsdf.eval``, visibility along the segment, in directions Mitsuba's emitter sampling
  draws: those towards the rectangle and those within 0.98 of the sphere's angular
  radius (a float32 direction at the very outline may meet the sphere on one side and
  miss it on the other): relative error
  ≤ 1e-4 and the same samples shadowed on both sides (and, on the way, Mitsuba's own
  ``test_visibility=True`` is its spawn_ray_to shadow ray, as the estimate assumes);
* the pdf of warpis's ``bsdf`` technique (``direction_pdf``) against ``bsdf.pdf``, in
  directions uniform over the hemisphere and reflected about normals of slopes α·N(0, 1):
  relative error ≤ 1e-4, except for Beckmann with visible normals, where warpis's pdf is
  the exact density of its sampler (Smith's G1 with erf) and Mitsuba's pdf carries
  Walter's rational fit of G1, which differs from it by < 0.35%: there ≤ 3.5e-3 + 1e-4.
"""

from __future__ import annotations

import math
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

import warpis  # noqa: E402
from warpis.analysis.reference import reference  # noqa: E402
from warpis.kernels.integrand import evaluate_integrand  # noqa: E402
from warpis.kernels.techniques import direction_pdf  # noqa: E402

# Mitsuba's LLVM variant runs the estimates (scripts/mitsuba_baseline.py holds its loader).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from conftest import needs_llvm

DATA = Path(__file__).parent / "data" / "against_mitsuba"
SCENE = DATA / "scene.xml"
RECEIVERS = DATA / "scene.receivers.toml"
CHANNEL = 1  # g, the receivers file's channel, as an index into Mitsuba's RGB

SAMPLES = 1 << 19  # Mitsuba's emitter samples per receiver
REL_ERROR = 5e-4  # warpis's reference target
Z = 4.0  # the band, in combined standard errors
SE_SHARE = 0.5  # warpis's stderr at most this fraction of Mitsuba's (see the docstring)
SEED = 0x417A  # numpy seeds: SEED + receiver (estimates), + 100 (f), + 200 (pdf)

# The material each receiver group lies on (the groups are named after the shapes).
MATERIAL = {"plate-ggx": "roughconductor", "plate-beckmann": "roughplastic", "floor": "lambert"}

F_SAMPLES = 512  # emitter samples per receiver for the f comparison
PDF_DIRECTIONS = 512  # directions per receiver for the pdf comparison
F_RTOL = 1e-4
PDF_RTOL = 1e-4
BECKMANN_G1_FIT = 3.5e-3  # Walter's rational G1 against the erf form (microfacet.py)
INSIDE_SPHERE = 0.98  # of its angular radius: directions clear of the outline's rounding
EPS = 1e-3  # the segment to a light sample: this much off its start, this fraction off its end


@dataclass
class Receiver:
    """One receiver as Mitsuba sees it."""

    group: str  # the id of the shape it lies on
    point: np.ndarray
    view: np.ndarray  # towards the camera, world
    si: object  # Mitsuba's SurfaceInteraction3f at the point (scalar_rgb), wi = the view
    bsdf: object
    ray: tuple[np.ndarray, np.ndarray]  # origin and direction of the short ray that found si


@dataclass
class Pair:
    scene: warpis.Scene
    ms: object  # Mitsuba's scene
    receivers: list[Receiver]
    sphere: tuple[np.ndarray, float]  # the sphere light's centre and radius


@pytest.fixture(scope="module")
def pair() -> Pair:
    scene = warpis.load_scene(SCENE)
    mi.set_variant("scalar_rgb")
    ms = mi.load_file(str(SCENE), parallel=False, optimize=False)
    camera = np.array(ms.sensors()[0].world_transform().matrix, dtype=np.float64)[:3, 3]
    with open(RECEIVERS, "rb") as fh:
        groups = tomllib.load(fh)["receivers"]
    receivers = []
    for group in groups:
        for point in np.array(group["points"], dtype=np.float64):
            view = (camera - point) / np.linalg.norm(camera - point)
            # A short ray at the point along the view: it meets the point's surface only.
            ray = (point + 0.01 * view, -view)
            si = ms.ray_intersect(mi.Ray3f(mi.Point3f(*ray[0]), mi.Vector3f(*ray[1])))
            assert si.is_valid() and si.shape.id() == group["name"], (group["name"], point)
            receivers.append(Receiver(group["name"], point, view, si, si.bsdf(), ray))
    (sphere,) = [s for s in ms.shapes() if s.id() == "sphere-light"]
    box = sphere.bbox()
    return Pair(scene, ms, receivers, (np.array(box.center(), np.float64), float(box.extents()[0]) / 2.0))


def segment_ray(rx: Receiver, ds) -> object:
    """The segment from the receiver to Mitsuba's emitter sample ``ds``, less EPS at each
    end: the line warpis's shadow ray follows (Mitsuba's own starts off the surface)."""
    length = ds.dist * (1.0 - EPS) - EPS
    return mi.Ray3f(rx.si.p + EPS * ds.d, ds.d, length, 0.0, mi.Color0f())


@dataclass
class Estimate:
    """Mitsuba's emitter-sampling estimate of F at one receiver: mean and standard error
    with visibility along the segment, with Mitsuba's own shadow ray, and their paired
    difference (own − segment)."""

    mean: float
    se: float
    own: float
    own_se: float
    offset: float
    offset_se: float


def mitsuba_estimates(xml: Path, receivers: list[Receiver], count: int, seeds: list[int]) -> list[Estimate]:
    """F (channel g) at each receiver by Mitsuba's emitter sampling and BSDF, ``count``
    samples each (numpy seed ``seeds[i]`` for receiver i), as whole arrays in Mitsuba's
    ``llvm_ad_rgb`` variant: the receiver's surface interaction (its short ray cast
    ``count`` times, wi = the view), ``sample_emitter_direction`` without its own
    visibility test, ``bsdf.eval``, and both shadow rays (the segment and
    ``spawn_ray_to``) for every sample at once; float32 throughout, as in ``scalar_rgb``."""
    from mitsuba_baseline import llvm_variant, load_mitsuba

    load_mitsuba()
    estimates = []
    with llvm_variant(mi):
        import drjit as dr

        ms = mi.load_file(str(xml), optimize=False)
        bsdfs = {shape.id(): shape.bsdf() for shape in ms.shapes()}
        ctx = mi.BSDFContext()

        def spread(v: np.ndarray):
            return [mi.Float(np.full(count, c, dtype=np.float32)) for c in v]

        def mean_se(x: np.ndarray) -> tuple[float, float]:
            return float(x.mean()), float(x.std(ddof=1) / math.sqrt(count))

        for rx, seed in zip(receivers, seeds, strict=True):
            si = ms.ray_intersect(mi.Ray3f(mi.Point3f(*spread(rx.ray[0])), mi.Vector3f(*spread(rx.ray[1]))))
            assert dr.all(si.is_valid()), rx.group
            si.wi = si.to_local(mi.Vector3f(*spread(rx.view)))
            u = np.random.default_rng(seed).random((count, 2)).astype(np.float32)
            ds, spec = ms.sample_emitter_direction(si, mi.Point2f(mi.Float(u[:, 0]), mi.Float(u[:, 1])), False)
            weight = spec[CHANNEL]  # Le / pdf, unoccluded
            lit = weight > 0.0
            value = dr.select(lit, weight * bsdfs[rx.group].eval(ctx, si, si.to_local(ds.d))[CHANNEL], 0.0)
            length = ds.dist * (1.0 - EPS) - EPS  # segment_ray's, for every sample
            along = ms.ray_test(mi.Ray3f(si.p + EPS * ds.d, ds.d, length, 0.0, mi.Color0f()), lit)
            spawned = ms.ray_test(si.spawn_ray_to(ds.p), lit)  # what test_visibility=True does
            segment = np.array(dr.select(along, 0.0, value), dtype=np.float64)
            own = np.array(dr.select(spawned, 0.0, value), dtype=np.float64)
            # The receiver's point as the scalar variant finds it (the fixture's si), in every lane.
            np.testing.assert_array_equal(np.array(si.p).T, np.broadcast_to(np.array(rx.si.p), (count, 3)))

            estimates.append(Estimate(*mean_se(segment), *mean_se(own), *mean_se(own - segment)))
    return estimates


def relative_error(mine: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|mine − ref| / |ref|; 0 where both are 0, inf where only ref is."""
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(mine - ref) / np.abs(ref)
    return np.where((mine == 0.0) & (ref == 0.0), 0.0, rel)


def test_receivers_are_mitsubas(pair):
    """Positions, normals, views and materials of warpis's receivers are Mitsuba's."""
    rx = pair.scene.receivers
    assert len(rx) == len(pair.receivers) == 8
    for i, r in enumerate(pair.receivers):
        np.testing.assert_allclose(rx.positions[i], np.array(r.si.p), atol=1e-6, err_msg=f"receiver {i}")
        np.testing.assert_allclose(rx.normals[i], np.array(r.si.sh_frame.n), atol=1e-6, err_msg=f"receiver {i}")
        np.testing.assert_allclose(rx.view[i], r.view, atol=1e-6, err_msg=f"receiver {i}")
        np.testing.assert_allclose(np.array(r.si.to_world(r.si.wi)), r.view, atol=1e-6)
        assert rx.material_name(i) == MATERIAL[r.group], (i, r.group)
    assert pair.scene.spheres is not None and len(pair.scene.sphere_lights) == 1  # analytic, as Mitsuba's
    assert not any("tessellated" in n for n in pair.scene.notes), pair.scene.notes


@needs_llvm
def test_direct_radiance_matches_mitsuba(pair):
    """F per receiver within 4 combined standard errors (see the docstring)."""
    refs = reference(pair.scene, rel_error=REL_ERROR)
    rows, bad, zs = [], [], []
    estimates = mitsuba_estimates(SCENE, pair.receivers, SAMPLES, [SEED + i for i in range(len(pair.receivers))])
    for i, (ref, r, m) in enumerate(zip(refs, pair.receivers, estimates)):
        sigma = math.hypot(ref.stderr, m.se)
        z = (ref.value - m.mean) / sigma
        zs.append(z)
        tolerance = Z * sigma
        own_z = (ref.value - m.own) / math.hypot(ref.stderr, m.own_se)
        rows.append(f"  {i} {r.group:<14} warpis {ref.value:.6f} ± {ref.stderr:.1e}  mitsuba {m.mean:.6f} ± "
                    f"{m.se:.1e}  z {z:+.2f}  |Δ|/tol {abs(ref.value - m.mean) / tolerance:.2f}  "
                    f"(own shadow rays: {m.own:.6f}, z {own_z:+.2f}, offset effect "
                    f"{m.offset / m.mean:+.2%} ± {m.offset_se / m.mean:.2%})")
        if not (abs(ref.value - m.mean) <= tolerance and ref.stderr <= SE_SHARE * m.se and m.mean > 0.0):
            bad.append(i)
    table = "\n".join(rows) + f"\n  worst |z| = {max(abs(z) for z in zs):.2f}"
    print("\nF (channel g), warpis vs Mitsuba:\n" + table)
    assert not bad, f"receivers {bad} disagree (or warpis's stderr exceeds {SE_SHARE} × Mitsuba's):\n{table}"


def test_integrand_matches_mitsuba_towards_lights(pair):
    """f = Le ρ cos θ V against Mitsuba's Le × bsdf.eval, visible along the same segment,
    in Mitsuba's own emitter samples."""
    centre, radius = pair.sphere
    ctx = mi.BSDFContext()
    worst, shadowed, lit = 0.0, 0, 0
    for i, r in enumerate(pair.receivers):
        dirs, ref = [], []
        to_centre = centre - r.point
        limit = math.asin(INSIDE_SPHERE * radius / np.linalg.norm(to_centre))
        for a, b in np.random.default_rng(SEED + 100 + i).random((F_SAMPLES, 2)).tolist():
            ds, spec = pair.ms.sample_emitter_direction(r.si, mi.Point2f(a, b), False)
            # The estimate's own visibility is test_visibility=True's.
            _, seen = pair.ms.sample_emitter_direction(r.si, mi.Point2f(a, b), True)
            assert seen[CHANNEL] == (0.0 if pair.ms.ray_test(r.si.spawn_ray_to(ds.p)) else spec[CHANNEL])
            d = np.array(ds.d, dtype=np.float64)
            on_sphere = abs(np.linalg.norm(np.array(ds.p) - centre) - radius) < 1e-4 * radius
            if on_sphere and math.acos(min(1.0, d @ to_centre / np.linalg.norm(to_centre))) > limit:
                continue
            le = 0.0 if pair.ms.ray_test(segment_ray(r, ds)) else spec[CHANNEL] * ds.pdf  # Le × visibility
            dirs.append(d)
            ref.append(le * r.bsdf.eval(ctx, r.si, r.si.to_local(ds.d))[CHANNEL] if le > 0.0 else 0.0)
        dirs, ref = np.array(dirs), np.array(ref)
        assert len(dirs) > F_SAMPLES // 2
        f = evaluate_integrand(pair.scene, i, dirs)
        np.testing.assert_array_equal(f > 0.0, ref > 0.0, err_msg=f"receiver {i}: visibility")
        rel = relative_error(f, ref)
        assert rel.max() <= F_RTOL, (i, r.group, float(rel.max()), dirs[np.argmax(rel)])
        worst = max(worst, float(rel.max()))
        shadowed, lit = shadowed + int((ref == 0.0).sum()), lit + int((ref > 0.0).sum())
    assert shadowed > 100 and lit > 2000  # the penumbra receivers put samples on both sides
    print(f"\nf towards the lights: worst relative error {worst:.2e} ({lit} lit, {shadowed} shadowed samples)")


def test_bsdf_pdf_matches_mitsuba(pair):
    """The pdf of warpis's bsdf technique against Mitsuba's bsdf.pdf."""
    ctx = mi.BSDFContext()
    rx = pair.scene.receivers
    worst = {}
    for i, r in enumerate(pair.receivers):
        rng = np.random.default_rng(SEED + 200 + i)
        half = PDF_DIRECTIONS // 2
        cos_t, phi = rng.uniform(0.02, 1.0, half), rng.uniform(0.0, 2.0 * math.pi, half)
        sin_t = np.sqrt(1.0 - cos_t**2)
        uniform = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
        alpha = float(rx.alpha[i]) if rx.material_name(i) != "lambert" else 0.5
        slopes = alpha * rng.normal(size=(half, 2))
        m = np.stack([-slopes[:, 0], -slopes[:, 1], np.ones(half)], axis=1)
        m /= np.linalg.norm(m, axis=1, keepdims=True)
        wi = np.array(r.si.wi, dtype=np.float64)
        lobe = 2.0 * (m @ wi)[:, None] * m - wi
        local = np.vstack([uniform, lobe[lobe[:, 2] > 0.02]])
        world = np.array([list(r.si.to_world(mi.Vector3f(*d))) for d in local.tolist()], dtype=np.float32)
        ref = np.array([r.bsdf.pdf(ctx, r.si, r.si.to_local(mi.Vector3f(*d))) for d in world.tolist()])
        pdf = direction_pdf(pair.scene, i, "bsdf", world)
        assert np.all(ref > 0.0), (i, r.group)
        rel = relative_error(pdf, ref)
        beckmann_visible = rx.material_name(i) != "lambert" and rx.distribution[i] == 0 and rx.sample_visible[i]
        tol = BECKMANN_G1_FIT + PDF_RTOL if beckmann_visible else PDF_RTOL
        assert rel.max() <= tol, (i, r.group, float(rel.max()), world[np.argmax(rel)])
        key = "beckmann (visible normals)" if beckmann_visible else rx.material_name(i)
        worst[key] = max(worst.get(key, 0.0), float(rel.max()))
    print("\nbsdf pdf, worst relative error: " + ", ".join(f"{k} {v:.2e}" for k, v in worst.items()))
