"""warpis's camera image against a Mitsuba 3 render of the same XML scene.

The scene is the bundled ``mitsuba-veach-plates`` (four aluminium roughconductor plates,
four sphere lights, a diffuse floor and backdrop, a ``perspective`` sensor with a box
filter), at W × H = 48 × 27 pixels (the film's 16:9; Mitsuba's x_fov kept).  Channel y,
the luminance of linear sRGB: the lights are white, so warpis's y is the luminance of
Mitsuba's RGB.

What is compared, per pixel: the reflected direct radiance averaged over the pixel's area.

* Mitsuba: its ``direct`` integrator (one emitter and one BSDF sample per pass, MIS) in
  ``scalar_rgb``, ``RENDERS`` = 32 independent renders (seeds 0..31) of ``SPP`` = 256
  samples per pixel; the box filter makes each pixel the mean over its area.  A pixel's
  value is the mean of the renders, its standard error their spread / √32 (31 degrees
  of freedom; each render's pixel is a mean of 256 bounded MIS samples, normal to a
  good approximation).
* warpis: the camera resized to K·W × K·H with K = 3, whose sub-pixel centres are the
  receivers; each receiver's F by the quadrature of warpis's fixed-mode reference
  (``quadrature_estimator``: light solid angle for diffuse receivers, power-heuristic
  MIS with the BSDF for glossy ones), ``SAMPLES`` = 16 jittered samples × 32 replicas.
  A pixel's value is the mean of its K × K sub-pixels (the midpoint rule for the box
  average), its standard error √(Σ se²) / K² (independent quadratures; ≥ 31 degrees of
  freedom by Welch–Satterthwaite).  ``reference()`` itself is not called: it first
  evaluates the closed form and its occlusion test for every receiver (even with
  ``closed_form=False``), which these 11k sub-pixels do not need.

The midpoint rule's residual: where F is twice differentiable over the pixel, the K × K
mean differs from the area mean by (h²/24)·⟨F_xx + F_yy⟩ + O(h⁴), h = 1/K pixel, which
the sub-pixels' second differences D estimate as ê = ⟨D_xx + D_yy⟩ / 24; across a jump
in F the rule errs by up to |jump| / (2K).  So the mask keeps only pixels whose second
differences are all small (step 5), and the test asserts that the estimated residual
is a small fraction of the noise at every compared pixel (|ê| ≤ ``RESIDUAL_SHARE`` = ¼
of se; observed: max 0.10, mean 0.013).

The mask.  A pixel is compared when all of these hold (the printed table counts the
pixels each step removes, in this order):

1. border: it is not on the image's border (its ring of neighbouring sub-pixels, used
   below, is complete);
2. coverage: Mitsuba's own rays through a (2K+1) × (2K+1) grid spanning the pixel,
   edges and corners included (every point of the pixel is within 1/(2K)·√2/2 pixel of
   a grid point), all meet the same shape, and not an emitter: no silhouette crosses
   the pixel (bar slivers thinner than 1/(2K) pixel);
3. emitters: no grid ray passes within r + d·δ of a sphere light's centre (r its radius,
   d its distance from the ray's origin, δ the widest angle of a grid cell's diagonal),
   so no part of a light is seen anywhere in the pixel, however small (light-1 spans a
   quarter of a pixel).  The ``direct`` integrator adds the emission it sees directly,
   which warpis leaves out; a render of that emission alone (``path``, max_depth 1) is
   asserted to be 0 at every compared pixel;
4. sub-pixels: all (K+2)² sub-pixels of the pixel and its ring are warpis receivers
   (seen code 0) on that same shape (the mesh of the triangle ``first_hits`` finds);
5. smoothness: every second difference of warpis's F along a row or a column of that
   stencil, centred on one of the pixel's K × K sub-pixels, is at most ``TAU`` = 5% of
   the pixel's value: no shadow edge, highlight edge or sharp peak of F there (the
   glossy plates' highlights, the plates' shadows on the floor).

Of the 1296 pixels this leaves 529: 496 on the backdrop, lit smoothly by the four
lights, 30 on the floor, 3 on plates (at this size a plate is two pixels tall, and its
F is rarely smooth over one); the glossy BSDFs are checked pointwise against Mitsuba in
test_against_mitsuba.py.

The statistic: z = (F_m − F_w) / se, se = √(se_m² + se_w²), over the N compared pixels.

* Per pixel: |F_m − F_w| ≤ t·se, t the quantile of Student's t with 31 dof (a lower
  bound on every pixel's Welch–Satterthwaite dof, so conservative) at Šidák's per-pixel
  level for a family-wise false-failure rate ``ALPHA`` = 1e-3 over the N pixels (t = 5.85
  for N = 529).  warpis reads the scene as Mitsuba holds it (its sphere lights are
  analytic spheres), so there is no systematic term.
* Calibration, so that a systematic error too small for any one pixel still fails:
  |mean z| ≤ 4·s/√N (s = √(31/29), the sd of a t with 31 dof: 4 standard errors of the
  mean of N independent z's: false failure
  ≤ 6.3e-5); and ``SD_BOUNDS`` = (0.85, 1.25) on their standard deviation (s ≈ 1.03
  scatters by ≈ 0.032 for N = 529: both bounds are more than 5 of those away).

Power: ``test_a_small_scaling_is_rejected`` multiplies warpis's image by 1 ± 2% and
1 ± 0.5% and asserts that the calibration rejects each, and that ± 0.5% passes the
per-pixel bound (worst |Δ| / allowance 0.65 and 0.76; mean z +0.96 and −0.75 against a
bound of ±0.18): only the calibration catches it.
``test_a_third_of_a_pixel_shift_is_rejected`` takes warpis's pixels from the sub-pixel
grid shifted by one sub-pixel (a pixel centre misplaced by 1/K pixel) along each axis:
rejected each time (sd z 2.8–4.1, max |z| 6.7–16).

The seeds are fixed, so every run draws the same numbers: the false-failure rates above
are over the choice of seeds.

Also, ``test_pixel_centres_see_what_mitsuba_sees``, at W × H, for the XML's own view and
for one from under the floor (``VIEWS``: it sees the back of the floor's one-sided BSDF,
nothing past the floor's edge, lights and the backdrop, so every seen code occurs):
Mitsuba's own ray through each pixel centre (``sensor.sample_ray``) has warpis's
direction (``Camera.directions()``; ≤ 1e-6, observed 1.6e-7), and ``scene.ray_intersect``
classifies the pixel as warpis's ``seen`` does (nothing / emitter / back of a one-sided
BSDF / receiver, on the same shape).  They may disagree only where the ray grazes a
sphere light's outline (within ``SILHOUETTE`` of its radius: Mitsuba intersects in float32,
warpis in float64) or passes within
``EDGE_GRAZE`` × the scene's diagonal of a triangle edge (float32 ray tests may go
either way there), at most ``GRAZING`` = 2 pixels per view (observed: none).  At
receivers, warpis's hit point is Mitsuba's (≤ 1e-5 of the diagonal, 37.5; observed
5.7e-6) and its normal is Mitsuba's geometric normal turned towards the camera.

Timings on the 2-core machine: 13 s for the file when it is idle (warpis's sub-pixel
quadrature 8 s, Mitsuba's renders 3 s, its grid and pixel-centre rays < 1 s), 23 s when
other work shares the cores (15 s and 7 s).
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from numpy.lib.stride_tricks import sliding_window_view  # noqa: E402
from scipy.special import stdtrit  # noqa: E402

import warpis  # noqa: E402
from warpis.analysis.reference import REFERENCE_SEED, quadrature, quadrature_estimator  # noqa: E402
from warpis.stats import sidak_threshold  # noqa: E402
from warpis.kernels.camera import first_hits  # noqa: E402
from warpis.scenes.camera import PIXEL_BACK, PIXEL_EMITTER, PIXEL_NOTHING, PIXEL_RECEIVER  # noqa: E402
from warpis.scenes.mitsuba import CHANNELS  # noqa: E402

SCENE = "mitsuba-veach-plates"
W, H = 48, 27  # the image
K = 3  # sub-pixels per pixel side (odd: the centre sub-pixel is the pixel centre)
RENDERS, SPP = 32, 256  # Mitsuba: independent renders × samples per pixel
SAMPLES, REPLICAS = 16, 32  # warpis: jittered samples per replica × replicas, per sub-pixel
DOF = min(RENDERS, REPLICAS) - 1  # a lower bound on every pixel's Welch–Satterthwaite dof
ALPHA = 1e-3  # family-wise false-failure rate of the per-pixel bound
TAU = 0.05  # the largest second difference of F, relative to the pixel's value
RESIDUAL_SHARE = 0.25  # the midpoint rule's estimated residual, at most this × se
MEAN_SIGMAS = 4.0  # the mean z's allowance, in its standard errors
SD_BOUNDS = (0.85, 1.25)  # bounds on the standard deviation of the z's
MIN_PIXELS = 400  # the mask must leave at least this many pixels
SUBTLE = 0.005  # a scaling this small passes the per-pixel bound and fails the calibration
GRAZING = 2  # pixel centres per view whose class may differ, each grazing a light's outline or an edge
SILHOUETTE = 1e-5  # relative to a sphere's radius: float32 intersection on Mitsuba's side
Y = np.array(CHANNELS["y"])
MASK_STEPS = ("border", "coverage", "emitters", "sub-pixels", "smoothness")


def mitsuba_scene(path) -> object:
    """Mitsuba's scene at W × H, shapes kept apart (optimize=False: ids survive)."""
    mi.set_variant("scalar_rgb")
    return mi.load_file(str(path), optimize=False, width=W, height=H, spp=SPP, emitter_samples=1, bsdf_samples=1)


def centre_ray(sensor, x: float, y: float):
    """Mitsuba's camera ray through the film point (x, y) in [0, 1]², no time or lens jitter."""
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
    return ray


def stencils(image: np.ndarray, fill) -> np.ndarray:
    """(H, W, K+2, K+2): each pixel's K × K sub-pixels of a (K·H, K·W) image with their
    ring of neighbours (``fill`` beyond the image)."""
    padded = np.pad(image, 1, constant_values=fill)
    return sliding_window_view(padded, (K + 2, K + 2))[::K, ::K]


def sub_pixel_quadrature(scene: warpis.Scene) -> tuple[np.ndarray, np.ndarray]:
    """(K·H, K·W) F and its standard error at every sub-pixel receiver (NaN elsewhere):
    warpis's fixed-mode reference quadrature, every receiver by quadrature."""
    n = len(scene.receivers)
    value, stderr = np.empty(n), np.empty(n)
    groups: dict[str, list[int]] = {}
    for r in range(n):
        groups.setdefault(quadrature_estimator(scene, r), []).append(r)
    for spec, receivers in groups.items():
        for r, (mean, se) in quadrature(scene, receivers, spec, SAMPLES, REPLICAS, REFERENCE_SEED).items():
            value[r], stderr[r] = mean, se
    image = scene.receivers.image
    return image.to_image(value), image.to_image(stderr)


def sub_pixel_shapes(scene: warpis.Scene) -> np.ndarray:
    """(K·H, K·W) name of the shape each sub-pixel receiver lies on ("" where masked)."""
    image = scene.receivers.image
    camera = image.camera
    face = first_hits(scene.vertices, scene.triangles, camera.position, camera.directions(), "cpu")
    names = np.array([*scene.mesh_names, ""], dtype=object)
    mesh = np.where(face >= 0, scene.triangle_mesh[np.maximum(face, 0)], len(scene.mesh_names))
    return np.where(image.seen.ravel() == PIXEL_RECEIVER, names[mesh], "").reshape(image.shape)


def sphere_lights(ms) -> list[tuple[np.ndarray, float, str]]:
    """(centre, radius, id) of every emitter, all spheres in this scene (from their bounding boxes)."""
    out = []
    for shape in ms.shapes():
        if shape.is_emitter():
            assert shape.class_name() == "Sphere", shape.id()
            box = shape.bbox()
            out.append((np.array(box.center(), np.float64), float(box.extents()[0]) / 2.0, shape.id()))
    return out


@dataclass
class Coverage:
    """What Mitsuba's grid of rays over each pixel sees."""

    shape: np.ndarray  # (H, W) the one shape id the whole grid meets, "" if not one non-emitter shape
    near_light: np.ndarray  # (H, W) bool: some grid ray passes within r + d·δ of a light's centre


def pixel_coverage(ms) -> Coverage:
    """Cast Mitsuba's rays through the (2K·W + 1) × (2K·H + 1) film grid (spacing 1/(2K) pixel)."""
    sensor = ms.sensors()[0]
    n, m = 2 * K * W + 1, 2 * K * H + 1
    ids = np.empty((m, n), dtype=object)
    origins, directions = np.empty((m, n, 3)), np.empty((m, n, 3))
    for i in range(m):
        for j in range(n):
            ray = centre_ray(sensor, j / (n - 1), i / (m - 1))
            si = ms.ray_intersect(ray)
            ids[i, j] = "" if not si.is_valid() or si.shape.is_emitter() else si.shape.id()
            origins[i, j], directions[i, j] = np.array(ray.o), np.array(ray.d)
    # δ: the widest angle a grid cell's diagonal subtends (its corners' directions).
    delta = max(float(np.max(np.arccos(np.clip(np.einsum("ijk,ijk->ij", directions[1:, 1:], directions[:-1, :-1]),
                                                    -1, 1)))),
                float(np.max(np.arccos(np.clip(np.einsum("ijk,ijk->ij", directions[1:, :-1], directions[:-1, 1:]),
                                                    -1, 1)))))
    near = np.zeros((m, n), bool)
    for centre, radius, _ in sphere_lights(ms):
        to = centre - origins
        along = np.einsum("ijk,ijk->ij", to, directions)
        miss = np.linalg.norm(to - along[..., None] * directions, axis=-1)  # the ray's distance from the centre
        # Within δ of the light's cone: sin(asin(r/d) + δ) ≤ r/d + δ; 1% slack for float32 directions.
        near |= (along > 0) & (miss <= radius + 1.01 * delta * np.linalg.norm(to, axis=-1))
    shape = np.empty((H, W), dtype=object)
    close = np.zeros((H, W), bool)
    for i in range(H):
        for j in range(W):
            cell = ids[2 * K * i:2 * K * (i + 1) + 1, 2 * K * j:2 * K * (j + 1) + 1]
            shape[i, j] = cell[0, 0] if np.all(cell == cell[0, 0]) else ""
            close[i, j] = near[2 * K * i:2 * K * (i + 1) + 1, 2 * K * j:2 * K * (j + 1) + 1].any()
    return Coverage(shape, close)


@dataclass
class Comparison:
    """Per-pixel values and errors of both sides, and the mask."""

    mitsuba: np.ndarray  # (H, W) mean of the renders
    mitsuba_se: np.ndarray
    warpis: np.ndarray  # (H, W) mean of the K × K sub-pixels
    warpis_se: np.ndarray
    residual: np.ndarray  # (H, W) ê, the midpoint rule's estimated residual
    stencil: np.ndarray  # (H, W, K+2, K+2) warpis's sub-pixels of each pixel and its ring
    compared: np.ndarray  # (H, W) bool
    removed: dict[str, int]  # pixels each mask step removes, in MASK_STEPS order
    emission: np.ndarray  # (H, W) Mitsuba's directly visible emission (luminance)
    shape: np.ndarray  # (H, W) the shape each pixel covers ("" where it covers none alone)
    seconds: dict[str, float]

    @property
    def se(self) -> np.ndarray:
        return np.hypot(self.mitsuba_se, self.warpis_se)


@pytest.fixture(scope="module")
def comparison() -> Comparison:
    """Both images, their errors and the mask (module docstring), with timings."""
    seconds = {}
    t = time.perf_counter()
    fine = warpis.load_scene(SCENE, camera=True, width=K * W, height=K * H)
    ms = mitsuba_scene(fine.path)
    seconds["load"] = time.perf_counter() - t

    t = time.perf_counter()
    renders = np.array([np.asarray(mi.render(ms, seed=s, spp=SPP), np.float64) @ Y for s in range(RENDERS)])
    emission_only = mi.load_dict({"type": "path", "max_depth": 1})  # what the camera sees directly
    emission = np.asarray(mi.render(ms, integrator=emission_only, seed=RENDERS, spp=SPP), np.float64) @ Y
    seconds["mitsuba renders"] = time.perf_counter() - t

    t = time.perf_counter()
    coverage = pixel_coverage(ms)
    seconds["mitsuba grid rays"] = time.perf_counter() - t

    t = time.perf_counter()
    value, stderr = sub_pixel_quadrature(fine)
    seconds["warpis quadrature"] = time.perf_counter() - t

    shapes = stencils(sub_pixel_shapes(fine), "")
    v = stencils(value, np.nan)
    block = v[..., 1:-1, 1:-1]
    warpis_mean = block.mean(axis=(2, 3))
    warpis_se = np.sqrt((stencils(stderr, np.nan)[..., 1:-1, 1:-1] ** 2).sum(axis=(2, 3))) / K**2
    d_xx = v[..., 1:-1, 2:] - 2 * block + v[..., 1:-1, :-2]
    d_yy = v[..., 2:, 1:-1] - 2 * block + v[..., :-2, 1:-1]
    residual = (d_xx.mean(axis=(2, 3)) + d_yy.mean(axis=(2, 3))) / 24
    with np.errstate(invalid="ignore"):
        rough = np.maximum(np.abs(d_xx).max(axis=(2, 3)), np.abs(d_yy).max(axis=(2, 3))) / np.abs(warpis_mean)

    border = np.zeros((H, W), bool)
    border[1:-1, 1:-1] = True
    steps = {
        "border": border,
        "coverage": coverage.shape != "",
        "emitters": ~coverage.near_light,
        "sub-pixels": np.all(shapes == coverage.shape[..., None, None], axis=(2, 3)),
        "smoothness": rough <= TAU,
    }
    compared = np.ones((H, W), bool)
    removed = {}
    for name in MASK_STEPS:
        removed[name] = int((compared & ~steps[name]).sum())
        compared &= steps[name]
    return Comparison(renders.mean(axis=0), renders.std(axis=0, ddof=1) / math.sqrt(RENDERS), warpis_mean,
                      warpis_se, residual, v, compared, removed, emission, coverage.shape, seconds)


@dataclass
class Verdict:
    """The statistics of one comparison and whether each check passes."""

    n: int
    z: np.ndarray  # (N,) over the compared pixels
    threshold: float  # t at Šidák's per-pixel level
    worst: float  # max over pixels of |Δ| / (t·se)
    mean_bound: float
    sd: float

    @property
    def pixels_ok(self) -> bool:
        return self.worst <= 1.0

    @property
    def mean_ok(self) -> bool:
        return abs(float(self.z.mean())) <= self.mean_bound

    @property
    def sd_ok(self) -> bool:
        return SD_BOUNDS[0] <= self.sd <= SD_BOUNDS[1]

    @property
    def calibrated(self) -> bool:
        return self.mean_ok and self.sd_ok

    def describe(self) -> str:
        return (f"N = {self.n} pixels: max |z| = {np.abs(self.z).max():.2f} (t threshold {self.threshold:.2f}; "
                f"worst |Δ| / allowance {self.worst:.2f}), mean z = {self.z.mean():+.3f} "
                f"(bound ±{self.mean_bound:.3f}), sd z = {self.sd:.3f} (bounds {SD_BOUNDS})")


def verdict(c: Comparison, scale: float = 1.0, image: np.ndarray | None = None) -> Verdict:
    """The checks of the module docstring, with warpis's image (or ``image``) multiplied by ``scale``."""
    mask = c.compared
    mitsuba, warpis_value = c.mitsuba[mask], scale * (c.warpis if image is None else image)[mask]
    se = np.hypot(c.mitsuba_se[mask], scale * c.warpis_se[mask])
    n = int(mask.sum())
    z = (mitsuba - warpis_value) / se
    t = float(stdtrit(DOF, 1.0 - sidak_threshold(ALPHA, n) / 2.0))
    worst = float(np.max(np.abs(mitsuba - warpis_value) / (t * se)))
    s = math.sqrt(DOF / (DOF - 2))
    mean_bound = MEAN_SIGMAS * s / math.sqrt(n)
    return Verdict(n, z, t, worst, mean_bound, float(z.std(ddof=1)))


def table(c: Comparison, v: Verdict) -> str:
    shapes = {}
    for name in np.unique(c.shape[c.compared]):
        mine = c.compared & (c.shape == name)
        z = (c.mitsuba[mine] - c.warpis[mine]) / c.se[mine]
        rel = np.mean((c.mitsuba[mine] - c.warpis[mine]) / c.warpis[mine])
        shapes[name] = f"{int(mine.sum())} px, mean z {z.mean():+.2f}, mean (m − w)/w {rel:+.3%}"
    share = np.abs(c.residual[c.compared]) / c.se[c.compared]
    return "\n".join([
        f"  {v.describe()}",
        f"  masked: {W * H - v.n} of {W * H}: " + ", ".join(f"{k} {n}" for k, n in c.removed.items()),
        "  by shape: " + "; ".join(f"{k}: {s}" for k, s in shapes.items()),
        f"  noise: median se/F mitsuba {np.median(c.mitsuba_se[c.compared] / c.mitsuba[c.compared]):.2%}, warpis "
        f"{np.median(c.warpis_se[c.compared] / c.warpis[c.compared]):.2%}",
        f"  midpoint residual |ê|/se: max {share.max():.3f}, mean {share.mean():.3f}",
        "  seconds: " + ", ".join(f"{k} {s:.1f}" for k, s in c.seconds.items()),
    ])


def test_image_matches_mitsuba(comparison):
    """Mitsuba's render and warpis's supersampled reference agree within noise at every
    compared pixel (Šidák, family-wise 1e-3) and their z's are calibrated (module docstring)."""
    c = comparison
    v = verdict(c)
    text = table(c, v)
    print("\nimage, mitsuba vs warpis:\n" + text)
    assert v.n >= MIN_PIXELS, text
    assert np.all(c.emission[c.compared] == 0.0), "a compared pixel sees emission in Mitsuba\n" + text
    assert np.all(np.abs(c.residual[c.compared]) <= RESIDUAL_SHARE * c.se[c.compared]), text
    bad = np.argwhere(c.compared & (np.abs(c.mitsuba - c.warpis) > v.threshold * c.se))
    assert v.pixels_ok, f"pixels (row, col) {bad.tolist()} disagree:\n{text}"
    assert v.mean_ok, f"the mean z is off:\n{text}"
    assert v.sd_ok, f"the spread of z is off:\n{text}"


@pytest.mark.parametrize("scale", [0.98, 0.995, 1.005, 1.02])
def test_a_small_scaling_is_rejected(comparison, scale):
    """warpis's image × (1 ± 2%) or × (1 ± 0.5%) fails the calibration check; at ± 0.5% no
    single pixel exceeds its bound: the mean z is what catches a small systematic error."""
    v = verdict(comparison, scale)
    print(f"\nwarpis × {scale}: {v.describe()}")
    assert not v.calibrated, v.describe()
    if abs(scale - 1.0) <= SUBTLE:
        assert v.pixels_ok, v.describe()


@pytest.mark.parametrize("shift", [(0, 1), (1, 0), (0, -1), (-1, 0)])
def test_a_third_of_a_pixel_shift_is_rejected(comparison, shift):
    """warpis's image taken from sub-pixels shifted by one (1/K pixel) along a row or a
    column, as a misplaced pixel centre would, fails the comparison."""
    di, dj = shift
    shifted = comparison.stencil[..., 1 + di:K + 1 + di, 1 + dj:K + 1 + dj].mean(axis=(2, 3))
    v = verdict(comparison, image=shifted)
    print(f"\nwarpis shifted by {shift} sub-pixels: {v.describe()}")
    assert not (v.pixels_ok and v.calibrated), v.describe()


def classify(si, d: np.ndarray) -> int:
    """warpis's seen code of a Mitsuba primary hit along ``d``."""
    if not si.is_valid():
        return PIXEL_NOTHING
    if si.shape.is_emitter():
        return PIXEL_EMITTER
    two_sided = mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.BackSide)
    if float(np.dot(np.array(si.n), d)) > 0 and not two_sided:
        return PIXEL_BACK
    return PIXEL_RECEIVER


def edge_distance(scene: warpis.Scene, meshes: list[int], o: np.ndarray, d: np.ndarray) -> float:
    """The least distance between the ray (o, d) and an edge of a triangle of ``meshes``."""
    tris = scene.vertices[scene.triangles[np.isin(scene.triangle_mesh, meshes)]]
    a = tris.reshape(-1, 3)
    b = tris[:, [1, 2, 0]].reshape(-1, 3)
    e = b - a
    # The segment's point nearest the line: minimise |(a + s e − o) × d| over s ∈ [0, 1].
    w = a - o
    ed, wd = e @ d, w @ d
    ee, we = np.einsum("ij,ij->i", e, e), np.einsum("ij,ij->i", w, e)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.clip(-(we - wd * ed) / (ee - ed**2), 0.0, 1.0)
    s = np.nan_to_num(s)
    p = w + s[:, None] * e
    return float(np.linalg.norm(p - (p @ d)[:, None] * d, axis=1).min())


# The views of test_pixel_centres_see_what_mitsuba_sees: the XML's own lookat, and one from
# under the floor (the back of its one-sided BSDF), past its edge (nothing), towards the
# lights and the backdrop: every seen code occurs in one of them.
VIEWS = {"own": None, "below": 'origin="0, -20, -1" target="0, 4, 4"'}
OWN_LOOKAT = 'origin="0, -15, 6.5" target="0, -1.5, 2.1"'
EDGE_GRAZE = 1e-5  # a ray this close to an edge (× the scene's diagonal) may go either way in float32


def scene_file(view: str, tmp_path) -> Path:
    """The bundled XML, or a copy of it (with its meshes) whose camera looks the ``view`` way."""
    path = warpis.load_scene(SCENE, camera=True, width=W, height=H).path
    if VIEWS[view] is None:
        return path
    text = path.read_text()
    assert OWN_LOOKAT in text
    for ply in path.parent.glob("*.ply"):
        shutil.copy(ply, tmp_path / ply.name)
    (tmp_path / path.name).write_text(text.replace(OWN_LOOKAT, VIEWS[view]))
    return tmp_path / path.name


@pytest.mark.parametrize("view", list(VIEWS))
def test_pixel_centres_see_what_mitsuba_sees(view, tmp_path):
    """At a W × H camera, Mitsuba's pixel-centre rays have warpis's directions and meet
    what warpis's seen codes say, at warpis's receiver points and normals (module docstring)."""
    scene = warpis.load_scene(scene_file(view, tmp_path), camera=True, width=W, height=H)
    ms = mitsuba_scene(scene.path)
    sensor = ms.sensors()[0]
    image = scene.receivers.image
    directions = image.camera.directions().reshape(H, W, 3)
    faces = first_hits(scene.vertices, scene.triangles, image.camera.position, directions.reshape(-1, 3),
                       "cpu", scene.spheres).reshape(H, W)
    receiver = np.full(H * W, -1)
    receiver[image.pixel] = np.arange(len(image.pixel))
    receiver = receiver.reshape(H, W)
    lights = sphere_lights(ms)
    bands = [(r * (1 - SILHOUETTE), r * (1 + SILHOUETTE)) for _, r, _ in lights]
    flat = [m for m, name in enumerate(scene.mesh_names) if name not in {name for _, _, name in lights}]
    diagonal = float(np.linalg.norm(scene.vertices.max(axis=0) - scene.vertices.min(axis=0)))
    seen = np.empty((H, W), np.int8)
    grazing, worst_p, worst_d, worst_n = [], 0.0, 0.0, 0.0
    for i in range(H):
        for j in range(W):
            ray = centre_ray(sensor, (j + 0.5) / W, (i + 0.5) / H)
            d = np.array(ray.d, np.float64)
            worst_d = max(worst_d, float(np.abs(d - directions[i, j]).max()))
            si = ms.ray_intersect(ray)
            seen[i, j] = classify(si, d)
            if seen[i, j] != image.seen[i, j]:
                o = np.array(ray.o, np.float64)
                miss = [float(np.linalg.norm(np.cross(c - o, d))) for c, _, _ in lights]
                edge = edge_distance(scene, flat, o, d)
                assert any(lo <= m <= hi for m, (lo, hi) in zip(miss, bands)) or edge <= EDGE_GRAZE * diagonal, \
                    (f"pixel ({i}, {j}): mitsuba {seen[i, j]}, warpis {image.seen[i, j]}; the ray passes "
                     f"{miss} from the lights' centres, outside their outlines' bands {bands}, and "
                     f"{edge:.3g} from the nearest edge")
                grazing.append((i, j))
            elif seen[i, j] == PIXEL_RECEIVER:
                r = receiver[i, j]
                assert scene.mesh_names[scene.triangle_mesh[faces[i, j]]] == si.shape.id(), (i, j)
                worst_p = max(worst_p, float(np.linalg.norm(scene.receivers.positions[r] - np.array(si.p))))
                n = np.array(si.n, np.float64)
                n = -n if n @ d > 0 else n
                worst_n = max(worst_n, float(np.abs(scene.receivers.normals[r] - n).max()))
    counts = {code: int((seen == code).sum()) for code in (PIXEL_RECEIVER, PIXEL_NOTHING, PIXEL_EMITTER, PIXEL_BACK)}
    print(f"\n{view}: pixel centres {counts} (mitsuba), {len(grazing)} grazing {grazing}; max |Δd| {worst_d:.1e}, "
          f"max |Δp| {worst_p:.1e} (diagonal {diagonal:.3g}), max |Δn| {worst_n:.1e}")
    assert worst_d <= 1e-6
    assert worst_p <= 1e-5 * diagonal
    assert worst_n <= 1e-5
    assert len(grazing) <= GRAZING, grazing
    assert counts[PIXEL_RECEIVER] > 0 and counts[PIXEL_EMITTER] > 0
    if view == "below":
        assert counts[PIXEL_NOTHING] > 0 and counts[PIXEL_BACK] > 0
