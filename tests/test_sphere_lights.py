"""Analytic spheres: exact densities, exact irradiance, and penumbrae as Mitsuba renders them.

A sphere is a shape of its own (scenes/spheres.py, kernels/spheres.py): rays meet it
exactly, ``light-solid-angle`` samples the cone it subtends, ``light-area`` and
``light-power`` its surface.  What is held here:

* *Densities* (a lone sphere light of radius 1 seen from d = 1.001 … 10⁴ radii above a
  receiver, its cone tilted 20° off the normal): each light technique's samples pass the
  windowed chi-square test of tests/test_techniques.py (the cap around the cone stretched
  onto the sphere), family-wise false-failure rate ``FAMILY_ALPHA`` (Šidák over the
  cases); their pdf integrates to 1 by deterministic quadrature (the cone's own frame for
  light-solid-angle; over the sphere's surface, both crossings of each ray, for
  light-area), within ``PDF_TOL`` (float32 directions: measured ≤ 2e-6); and no sample
  is lost to float32 rounding at the silhouette (every one of ``LOST_SAMPLES`` has pdf > 0
  and meets the sphere), which at 10⁴ radii, where the cone is 10⁻⁴ rad wide, the rim of
  rounding would otherwise cost 10⁻³ of the samples.
* *Irradiance*: at receivers that see a sphere light whole, cut by their horizon, or from
  inside an inward sphere, every light technique and their MIS with the cosine agree with
  the closed form (scenes/lambert.py ``sphere_irradiance``) within ``Z`` = 4 standard
  errors (normal means of ≥ 4000 bounded trials: 6.3e-5 per comparison, < 3e-3 over the
  ≤ 40 comparisons by Bonferroni); and a sphere occluder in front of a large quad light
  removes exactly the light of its cone.
* *Penumbrae against Mitsuba* (the reason spheres are analytic): fourteen floor points
  under the edge of a plate that hides 4% to 99% of a sphere light; warpis's reference
  agrees with Mitsuba 3's own emitter sampling and visibility (``llvm_ad_rgb``, 2^21
  samples a point) within Z = 4 combined standard errors (Mitsuba's samples are bounded,
  L·Ω·ρ cos, so their mean of 2^21 is normal; 14 comparisons: ≤ 8.9e-4 by Bonferroni).
  Its resolution, 4 combined standard errors, is printed per point: 0.1% to 3% of F,
  below 0.5% wherever a quarter of the light or more shows.
* The loaders: Mitsuba's ``sphere`` and TOML's ``[[sphere]]`` are analytic (receivers and
  camera pixels lie on the exact surface, with its exact normal); bad input is one line.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import floor_entry, needs_llvm, one_error_line, quad, write_scene
from test_techniques import Window

import warpis
from warpis.analysis.reference import reference
from warpis.kernels.engine import run_trials
from warpis.kernels.techniques import direction_pdf, sample_directions
from warpis.scenes.lambert import sphere_irradiance
from warpis.scenes.spheres import Spheres
from warpis.stats import sidak_threshold
from warpis.testing import ChiSquareTest, orthonormal_frame

Z = 4.0
FAMILY_ALPHA = 1e-3
RATIOS = (1.001, 1.1, 4.0, 100.0, 1e4)
LIGHT_TECHNIQUES = ("light-solid-angle", "light-area")
# light-area's density grows as 1/√δ at angular distance δ from the silhouette, so the
# share of its mass within float32's resolution of it (~1e-7 rad) is √(1e-7/θmax): 3e-4
# at 4 radii, 3e-2 at 10⁴ radii, where no float32 direction can tell which side of the
# rim it lies on.  Its pdf is therefore checked where float32 resolves it; the cone
# technique (uniform density, no rim mass) everywhere.
AREA_RATIOS = (1.1, 4.0)
CHI2_CASES = [("light-solid-angle", d) for d in RATIOS] + [("light-area", d) for d in AREA_RATIOS]
CHI2_SAMPLES = 400_000
LOST_SAMPLES = 200_000
PDF_TOL = 1e-4
AXIS = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])  # 20.4° off the normal


def lone_sphere(ratio: float, radiance: float = 1.0) -> warpis.Scene:
    """A receiver at the origin (normal +z) and a unit sphere light ``ratio`` radii away
    along AXIS; a small floor far below it (a scene needs a triangle) blocks nothing."""
    v, f = quad((0.0, 0.0, -50.0), 0.5, "up")
    spheres = Spheres(centers=(ratio * AXIS)[None], radii=np.array([1.0]), emission=np.array([radiance]),
                      inward=np.zeros(1, np.int32), owner=np.zeros(1, np.int32))
    return warpis.Scene.from_arrays(v, f, np.zeros(2), [[0.0, 0.0, 0.0]], (0.0, 0.0, 1.0), spheres=spheres,
                                    name=f"sphere-at-{ratio:g}")


def cone_h(ratio: float) -> float:
    """1 − cos θmax of the unit sphere's cone at ``ratio`` radii, in float64's stable form."""
    sin2 = 1.0 / ratio**2
    return sin2 / (1.0 + math.sqrt((ratio - 1.0) * (ratio + 1.0)) / ratio)


# --------------------------------------------------------------------------- densities


@pytest.mark.parametrize("technique,ratio", CHI2_CASES, ids=[f"{t}-{d:g}" for t, d in CHI2_CASES])
def test_cone_and_surface_sampling_chi2(technique, ratio):
    """The samples follow the pdf (windowed chi-square), and the pdf carries their mass."""
    scene = lone_sphere(ratio)
    window = Window(AXIS, min(2.0, 1.25 * cone_h(ratio)))

    def sample(count: int, seed: int):
        u = np.random.default_rng(seed).random((count, 2), dtype=np.float32)
        return sample_directions(scene, 0, technique, u)

    sample_func, pdf_func = window.wrap(sample, lambda d: direction_pdf(scene, 0, technique, d))
    # Every sample is valid (the whole cone lies in the window).  light-area: a sample
    # within an ulp of the silhouette may land outside it when the window's map is undone
    # for pdf_func (its density is 1/√δ there), hence a looser pdf-agreement share.
    area = technique == "light-area"
    test = ChiSquareTest(sample_func, pdf_func, window.axis, sample_count=CHI2_SAMPLES, res=(30, 60), ires=24,
                         seed=int(ratio * 1000) + len(technique), pdf_mismatch_fraction=2e-3 if area else 1e-4)
    assert test.run(FAMILY_ALPHA, len(CHI2_CASES)), test.messages
    assert test.p_value >= sidak_threshold(FAMILY_ALPHA, len(CHI2_CASES))
    # The harness's jittered quadrature of a 1/√δ density loses a little at the rim.
    assert abs(test.pdf_integral - 1.0) <= (2e-3 if area else 2e-4), test.messages


def _gauss(n: int, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (a + b), 0.5 * (b - a) * w


def _cone_directions(h: np.ndarray, phi: np.ndarray) -> np.ndarray:
    b1, b2, a = orthonormal_frame(AXIS)
    hh, pp = np.meshgrid(h, phi, indexing="ij")
    s = np.sqrt(hh * (2.0 - hh))
    return (s * np.cos(pp))[..., None] * b1 + (s * np.sin(pp))[..., None] * b2 + (1.0 - hh)[..., None] * a


@pytest.mark.parametrize("ratio", RATIOS)
def test_cone_pdf_integrates_to_one(ratio):
    """∫ g dω = 1 for light-solid-angle: Gauss–Legendre in h = 1 − cos θ about the cone's
    axis on [0, h_max] (where g is constant) times the trapezoid rule in φ; g = 0 just
    outside the cone."""
    scene = lone_sphere(ratio)
    h_max = cone_h(ratio)
    h, wh = _gauss(16, 0.0, h_max)
    phi = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    d = _cone_directions(h, phi).reshape(-1, 3)
    pdf = direction_pdf(scene, 0, "light-solid-angle", d).reshape(len(h), len(phi))
    integral = float((wh @ pdf).sum() * (2 * np.pi / len(phi)))
    assert abs(integral - 1.0) <= PDF_TOL, integral
    outside = _cone_directions(np.array([h_max * 1.01, h_max * 2.0, 1.5]), phi).reshape(-1, 3)
    assert (direction_pdf(scene, 0, "light-solid-angle", outside) == 0.0).all()


@pytest.mark.parametrize("ratio", AREA_RATIOS)
def test_surface_pdf_integrates_to_one(ratio):
    """∫ g dω = 1 for light-area, over the sphere's surface: each direction in the cone
    crosses it twice, so ∫ g dω = ½ ∫ g(ω(y)) |cos θ_y| / t² dA, Gauss–Legendre in the
    height z of y along the axis towards the receiver, split at the silhouette
    (z = 1/ratio), times the trapezoid rule in φ."""
    scene = lone_sphere(ratio)
    c = ratio * AXIS
    b1, b2, a = orthonormal_frame(-AXIS)  # a: from the centre towards the receiver
    parts = [_gauss(48, -1.0, 1.0 / ratio), _gauss(48, 1.0 / ratio, 1.0)]
    phi = np.linspace(0.0, 2 * np.pi, 96, endpoint=False)
    total = 0.0
    for z, wz in parts:
        zz, pp = np.meshgrid(z, phi, indexing="ij")
        rho = np.sqrt(1.0 - zz**2)
        n = (rho * np.cos(pp))[..., None] * b1 + (rho * np.sin(pp))[..., None] * b2 + zz[..., None] * a
        y = c + n
        t = np.linalg.norm(y, axis=-1)
        w = (y / t[..., None]).reshape(-1, 3)
        g = direction_pdf(scene, 0, "light-area", w).reshape(zz.shape)
        cos_y = np.abs(np.einsum("...j,...j->...", n, y / t[..., None]))
        total += float((wz @ (0.5 * g * cos_y / t**2)).sum() * (2 * np.pi / len(phi)))
    assert abs(total - 1.0) <= PDF_TOL, total


@pytest.mark.parametrize("ratio", RATIOS)
@pytest.mark.parametrize("technique", LIGHT_TECHNIQUES)
def test_no_sample_is_lost_at_the_silhouette(technique, ratio):
    """Every sample has pdf > 0 and meets the sphere (float64 from its float32 direction):
    none is carried off the silhouette by rounding."""
    scene = lone_sphere(ratio)
    u = np.random.default_rng(7).random((LOST_SAMPLES, 2), dtype=np.float32)
    d, pdf = sample_directions(scene, 0, technique, u)
    assert (pdf > 0).all(), f"{int((pdf <= 0).sum())} of {LOST_SAMPLES} samples lost"
    w = d.astype(np.float64)
    c = ratio * AXIS
    tc = w @ c / np.einsum("ij,ij->i", w, w)
    q = np.linalg.norm(tc[:, None] * w - c, axis=1)
    assert (tc > 0).all() and (q <= 1.0).all()


# --------------------------------------------------------------------------- irradiance


def _lights_scene(inward: bool = False) -> warpis.Scene:
    """Receivers around a sphere light of radius 0.5 at (0, 0, 1): facing it, tilted so
    that their horizon cuts it, beside it; or, ``inward``, inside a sphere of radius 3
    that emits on its inside."""
    v, f = quad((0.0, 0.0, -20.0), 0.5, "up")
    if inward:
        spheres = Spheres(centers=np.zeros((1, 3)), radii=np.array([3.0]), emission=np.array([2.0]),
                          inward=np.ones(1, np.int32), owner=np.zeros(1, np.int32))
        points = [[0.0, 0.0, 0.0], [1.0, 0.5, -2.0], [0.0, 2.5, 0.5]]
        normals = [[0.0, 0.0, 1.0], [0.3, -0.2, 1.0], [0.0, -1.0, 0.2]]
    else:
        spheres = Spheres(centers=np.array([[0.0, 0.0, 1.0]]), radii=np.array([0.5]), emission=np.array([3.0]),
                          inward=np.zeros(1, np.int32), owner=np.zeros(1, np.int32))
        points = [[0.0, 0.0, 0.0], [0.6, 0.1, 0.2], [1.2, 0.0, 1.0], [0.0, -0.7, 1.3], [0.2, 0.3, -0.4]]
        normals = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.2], [-1.0, 0.0, 0.1], [0.0, 1.0, -0.5], [0.8, 0.0, 0.1]]
    return warpis.Scene.from_arrays(v, f, np.zeros(2), points, np.array(normals, float), spheres=spheres,
                                    name="inward" if inward else "sphere-light")


def _closed_form(scene: warpis.Scene) -> np.ndarray:
    s, rx = scene.spheres, scene.receivers
    return sphere_irradiance(rx.positions, rx.normals, s.centers, s.radii, s.emission, s.inward)


@pytest.mark.parametrize("inward", [False, True], ids=["outside", "inward"])
def test_estimators_match_the_closed_form(inward):
    scene = _lights_scene(inward)
    exact = _closed_form(scene)
    assert (exact > 0).all()
    for spec in ("independent:single:light-solid-angle", "independent:single:light-area",
                 "independent:single:light-power", "jittered:single:cosine",
                 "jittered:balance:light-solid-angle+cosine", "independent:power:light-area+cosine"):
        x = run_trials(scene, spec, 16, 4000, seed=3)
        mean, se = x.mean(axis=1), x.std(axis=1, ddof=1) / math.sqrt(x.shape[1])
        z = (mean - exact) / np.maximum(se, 1e-7 * exact)
        assert (np.abs(z) <= Z).all(), (spec, mean, exact, z)


def test_reference_matches_the_closed_form():
    """The reference takes the closed form where nothing can block a sphere light (every
    receiver here), and its quadrature agrees with it."""
    scene = _lights_scene()
    exact = _closed_form(scene)
    for r in reference(scene, rel_error=1e-4):
        assert r.method == "closed-form" and r.value == pytest.approx(exact[r.index], rel=1e-12)
    for r in reference(scene, rel_error=1e-4, closed_form=False):
        assert abs(r.value - exact[r.index]) <= Z * r.stderr + 2e-7 * exact[r.index], (r, exact[r.index])


def test_what_may_block_a_sphere_light_sends_the_reference_to_the_quadrature():
    """A small plate between a receiver and the sphere light, a sphere in its cone, a
    triangle inside the light's cube: the closed form is not taken (it would be wrong)."""
    base = _lights_scene()
    v, f = quad((0.0, 0.0, -20.0), 0.5, "up")
    plate_v, plate_f = quad((0.0, 0.0, 0.3), 0.05, "up")
    spheres = base.spheres
    blockers = {
        "plate": (np.vstack([v, plate_v]), np.vstack([f, plate_f + 4]), spheres),
        "ball": (v, f, Spheres(centers=np.vstack([spheres.centers, [[0.0, 0.0, 0.3]]]), radii=np.array([0.5, 0.05]),
                               emission=np.array([3.0, 0.0]), inward=np.zeros(2, np.int32),
                               owner=np.zeros(2, np.int32))),
        "in-cube": (np.vstack([v, quad((0.45, 0.45, 1.45), 0.02, "up")[0]]), np.vstack([f, plate_f + 4]), spheres),
    }
    for name, (vv, ff, ss) in blockers.items():
        scene = warpis.Scene.from_arrays(vv, ff, np.zeros(len(ff)), base.receivers.positions[:1], (0.0, 0.0, 1.0),
                                         spheres=ss, name=name)
        (r,) = reference(scene, rel_error=1e-3)
        assert r.method == "quadrature", name


def test_a_sphere_occluder_removes_its_cone():
    """Under a quad light that fills its view, a sphere removes exactly L ∫_cone cos dω."""
    lv, lf = quad((0.0, 0.0, 3.0), 3.0, "down")
    fv, ff = quad((0.0, 0.0, -1.0), 3.0, "up")
    v = np.vstack([lv, fv])
    f = np.vstack([lf, ff + 4])
    emission = np.array([2.0, 2.0, 0.0, 0.0])
    ball = Spheres(centers=np.array([[0.1, 0.0, 1.5]]), radii=np.array([0.3]), emission=np.zeros(1),
                   inward=np.zeros(1, np.int32), owner=np.zeros(1, np.int32))
    points = np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 0.0]])
    with_ball = warpis.Scene.from_arrays(v, f, emission, points, (0.0, 0.0, 1.0), spheres=ball, name="ball")
    without = warpis.Scene.from_arrays(v, f, emission, points, (0.0, 0.0, 1.0), name="no-ball")
    open_sky = np.array([r.value for r in reference(without)])  # Lambert's closed form
    cone = sphere_irradiance(points, np.tile([0.0, 0.0, 1.0], (2, 1)), ball.centers, ball.radii, [2.0], [0])
    for spec in ("independent:single:light-area", "jittered:single:light-solid-angle", "jittered:single:cosine"):
        x = run_trials(with_ball, spec, 16, 4000, seed=5)
        mean, se = x.mean(axis=1), x.std(axis=1, ddof=1) / math.sqrt(x.shape[1])
        assert (np.abs(mean - (open_sky - cone)) <= Z * se).all(), (spec, mean, open_sky - cone, se)


# --------------------------------------------------------------------------- Mitsuba


PENUMBRA_XML = """<scene version="3.0.0">
  <shape type="rectangle" id="floor"><transform name="to_world"><scale x="4" y="4"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
  <shape type="rectangle" id="plate">
    <transform name="to_world"><scale x="2" y="3"/><translate x="-2" y="0" z="1"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.2"/></bsdf></shape>
  <shape type="sphere" id="light"><point name="center" x="0" y="0" z="2"/><float name="radius" value="0.3"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
    <emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>
</scene>
"""
# Under the plate's edge: 2% to 95% of the light in view.  Where only a sliver shows, the
# tessellated sphere's facets move its outline by a visible share of the sliver (−4.5% at
# 2%, +2% at 7%, within 0.5% beyond 10%: measured against the analytic sphere).
PENUMBRA_X = np.concatenate([[-0.2955, -0.2747], np.linspace(-0.255, 0.255, 12)])
MITSUBA_CHUNK = 1 << 20
MITSUBA_CHUNKS = 2


def _penumbra_files(folder: Path, tessellate: bool) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    xml = folder / "scene.xml"
    xml.write_text(PENUMBRA_XML)
    points = ", ".join(f"[{x:.6f}, 0.1, 0.0]" for x in PENUMBRA_X)
    (folder / "scene.receivers.toml").write_text(
        f'name = "penumbra"\nchannel = "g"\nview = [0.0, -3.0, 5.0]\ntessellate = {str(tessellate).lower()}\n'
        f"[[receivers]]\npoints = [{points}]\n")
    return xml


def _mitsuba_direct(xml: Path, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's emitter-sampling estimate of F (channel g) at floor points (normal +z):
    ``sample_emitter_direction`` with its own visibility test × the floor's BSDF, vectorised."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    from mitsuba_baseline import llvm_variant, load_mitsuba

    mi = load_mitsuba()
    with llvm_variant(mi):
        import drjit as dr

        ms = mi.load_file(str(xml))
        bsdf = [s for s in ms.shapes() if s.id() == "floor"][0].bsdf()
        count = len(points)
        total, total2 = np.zeros(count), np.zeros(count)
        rng = np.random.default_rng(11)
        for _ in range(MITSUBA_CHUNKS):
            si = dr.zeros(mi.SurfaceInteraction3f, count * MITSUBA_CHUNK)
            si.p = mi.Point3f(*[mi.Float(np.repeat(points[:, k], MITSUBA_CHUNK)) for k in range(3)])
            si.n = mi.Normal3f(0.0, 0.0, 1.0)
            si.sh_frame = mi.Frame3f(si.n)
            si.wi = mi.Vector3f(0.0, 0.0, 1.0)
            u = rng.random((2, count * MITSUBA_CHUNK), dtype=np.float32)
            ds, weight = ms.sample_emitter_direction(si, mi.Point2f(mi.Float(u[0]), mi.Float(u[1])), True)
            value = bsdf.eval(mi.BSDFContext(), si, si.to_local(ds.d)) * weight
            g = np.array(value.y, np.float64).reshape(count, MITSUBA_CHUNK)
            total += g.sum(axis=1)
            total2 += (g**2).sum(axis=1)
    n = MITSUBA_CHUNKS * MITSUBA_CHUNK
    mean = total / n
    return mean, np.sqrt(np.maximum(total2 / n - mean**2, 0.0) / n)


@needs_llvm
def test_penumbrae_match_mitsuba(tmp_path):
    pytest.importorskip("mitsuba")
    scene = warpis.load_scene(_penumbra_files(tmp_path, False))
    assert scene.spheres is not None and scene.emitter_count == 0
    rx, s = scene.receivers, scene.spheres
    open_light = sphere_irradiance(rx.positions, rx.normals, s.centers, s.radii, s.emission, s.inward) * 0.5 / math.pi
    mean, se = _mitsuba_direct(tmp_path / "scene.xml", rx.positions)
    fraction = mean / open_light
    assert fraction.min() < 0.03 and fraction.max() > 0.95, fraction  # the points span the penumbra
    rows, zs = [], []
    for i, r in enumerate(reference(scene, rel_error=3e-4)):
        sigma = math.hypot(r.stderr, se[i])
        zs.append((r.value - mean[i]) / sigma)
        rows.append(f"{i:2d} visible {fraction[i]:.3f}  warpis {r.value:.6f} ± {r.stderr:.1e}  mitsuba {mean[i]:.6f} "
                    f"± {se[i]:.1e}  z {zs[-1]:+.2f}  resolves {Z * sigma / mean[i]:.2%}")
    print("\n" + "\n".join(rows))
    assert max(abs(z) for z in zs) <= Z, "\n".join(rows)


# --------------------------------------------------------------------------- loaders


def test_mitsuba_spheres_are_analytic():
    pytest.importorskip("mitsuba")
    scene = warpis.load_scene("mitsuba-veach-plates")
    assert scene.spheres is not None and len(scene.spheres) == 4
    assert scene.emitter_count == 0 and len(scene.sphere_lights) == 4
    np.testing.assert_allclose(scene.spheres.radii, [0.0333, 0.1, 0.3, 0.9])
    assert not any("tessellated" in n for n in scene.notes)


def test_mitsuba_receivers_lie_on_the_exact_sphere(tmp_path):
    pytest.importorskip("mitsuba")
    xml = tmp_path / "scene.xml"
    xml.write_text(PENUMBRA_XML.replace("</scene>", """  <shape type="sphere" id="ball"><point name="center" x="1" y="1" z="0.5"/>
    <float name="radius" value="0.4"/><bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
</scene>"""))
    c = np.array([1.0, 1.0, 0.5])
    on = c + 0.4 * np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.8, 0.6]])
    near = on * (1 + 1e-7)  # as written with a few digits
    (tmp_path / "scene.receivers.toml").write_text(
        "view = [1.0, 1.0, 5.0]\n[[receivers]]\npoints = [" + ", ".join(f"[{p[0]:.9f}, {p[1]:.9f}, {p[2]:.9f}]" for p in near)
        + "]\n")
    scene = warpis.load_scene(xml)
    rx = scene.receivers
    (ball,) = np.flatnonzero(scene.spheres.emission == 0)
    c, r = scene.spheres.centers[ball], scene.spheres.radii[ball]  # Mitsuba's, in float32
    assert abs(r - 0.4) < 1e-7 and np.allclose(c, [1.0, 1.0, 0.5], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(rx.positions - c, axis=1), r, rtol=1e-12)
    np.testing.assert_allclose(rx.normals, (rx.positions - c) / r, atol=1e-12)
    np.testing.assert_allclose(rx.geometric_normals, rx.normals, atol=1e-12)


def test_toml_camera_pixels_lie_on_the_exact_sphere(tmp_path):
    c = np.array([0.0, 0.0, 0.6])
    path = write_scene(
        tmp_path, meshes=[floor_entry(material={"type": "lambert", "albedo": 0.5})],
        spheres=[{"center": c.tolist(), "radius": 0.5, "material": {"type": "lambert", "albedo": 0.7}, "name": "ball"},
                 {"center": [0.8, 0.5, 1.5], "radius": 0.2, "emission": 20.0}],
        receivers={"camera": {"position": [0.0, -4.0, 2.0], "target": [0.0, 0.0, 0.5], "fov": 40.0, "width": 48,
                              "height": 36}}, material=None)
    scene = warpis.load_scene(path)
    rx = scene.receivers
    on_ball = np.abs(np.linalg.norm(rx.positions - c, axis=1) - 0.5) < 1e-9
    assert on_ball.sum() > 100
    np.testing.assert_allclose(rx.normals[on_ball], (rx.positions[on_ball] - c) / 0.5, atol=1e-9)
    assert (rx.albedo[on_ball] == 0.7).all()
    assert scene.receivers.image.masked_counts()["emitter"] > 0  # the light's pixels


def test_tessellate_keeps_the_old_triangles(tmp_path):
    entry = {"center": [0.0, 0.0, 2.0], "radius": 0.3, "emission": 5.0}
    analytic = warpis.load_scene(write_scene(tmp_path / "a", meshes=[floor_entry()], spheres=[entry]))
    tess = warpis.load_scene(write_scene(tmp_path / "t", meshes=[floor_entry()], spheres=[entry | {"tessellate": True}]))
    assert analytic.spheres is not None and analytic.triangle_count == 2
    assert tess.spheres is None and tess.emitter_count == 1280
    assert abs(tess.total_emitter_area / analytic.total_emitter_area - 1) < 1e-12  # pushed out to keep the area


BAD_SPHERES = [
    ({"radius": 1.0}, "missing key 'center'"),
    ({"center": [0, 0, 2]}, "missing key 'radius'"),
    ({"center": [0, 0, 2], "radius": 0.0}, "radius must be > 0"),
    ({"center": [0, 0, 2], "radius": -1.0}, "radius must be > 0"),
    ({"center": [0, 0, 2], "radius": float("nan")}, "radius must be finite"),
    ({"center": [0, 0], "radius": 1.0}, "center must be a list of 3 numbers"),
    ({"center": [0, 0, 2], "radius": 1.0, "emission": True}, "emission must be a finite number"),
    ({"center": [0, 0, 2], "radius": 1.0, "emission": -1.0}, "emission"),
    ({"center": [0, 0, 2], "radius": 1.0, "inward": 1}, "inward must be true or false"),
    ({"center": [0, 0, 2], "radius": 1.0, "tessellate": "yes"}, "tessellate must be true or false"),
    ({"center": [0, 0, 2], "radius": 1.0, "colour": 1}, "unknown key 'colour'"),
    ({"center": [1e15, 0, 2], "radius": 1e-6}, "below float32's resolution"),
    ({"center": [0, 0, 2], "radius": 1.0, "material": {"type": "glass"}}, "is not one of"),
]


@pytest.mark.parametrize("entry,words", BAD_SPHERES, ids=[w for _, w in BAD_SPHERES])
def test_bad_spheres_are_one_line(tmp_path, cli, entry, words):
    path = write_scene(tmp_path, meshes=[floor_entry()], spheres=[entry])
    line = one_error_line(cli("info", path))
    assert str(path) in line and words in line, line


def test_bad_tessellate_in_a_receivers_file_is_one_line(tmp_path, cli):
    pytest.importorskip("mitsuba")
    xml = _penumbra_files(tmp_path, False)
    side = tmp_path / "scene.receivers.toml"
    side.write_text(side.read_text().replace("tessellate = false", "tessellate = 1"))
    line = one_error_line(cli("info", xml))
    assert "scene.receivers.toml" in line and "tessellate must be true or false" in line, line
